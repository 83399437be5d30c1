"""The add-on's operators: check the kpcn executable, denoise the last render (a modal operator from the
button: progress in the status bar, Esc cancels; run from a script it waits), and the render handlers that
denoise after every render and every frame of an animation written."""

import os
import tempfile

import bpy

from . import passes
from .exr_colour import ExrError
from .runner import AddonError, Job, denoise_command, find_kpcn, version


def prefs(context=None):
    return (context or bpy.context).preferences.addons[__package__].preferences


def start_job(context, scene) -> Job:
    """The Render Result written to a fresh temporary folder and ``kpcn denoise`` started on it. AddonError in one
    line where kpcn is not there or nothing was rendered."""
    p = prefs(context)
    kpcn = find_kpcn(p.kpcn_path)
    image = passes.render_result()
    if image is None:
        raise AddonError("no render to denoise: render a frame first (F12)")
    folder = tempfile.mkdtemp(prefix="kpcn-")
    src, out = os.path.join(folder, "render.exr"), os.path.join(folder, "denoised.exr")
    passes.save_render_result(scene, image, src)
    if not os.path.isfile(src):
        raise AddonError(f"Blender wrote no {src}")
    quality = "" if p.quality == "MODEL" else p.quality
    label = passes.image_name(scene, scene.frame_current)
    return Job(denoise_command(kpcn, src, out, quality, p.ensemble), out, label)


def finish_job(job: Job):
    """The denoised image loaded and shown (AddonError with kpcn's error line where it failed)."""
    try:
        image = passes.load_result(job.result(), job.label)
    except ExrError as exc:
        raise AddonError(str(exc)) from None
    prefs().last_message = f"denoised into image '{image.name}'"
    return image


class KPCN_OT_check(bpy.types.Operator):
    """Run the kpcn executable with --version: its version and the model it serves"""

    bl_idname = "kpcn.check"
    bl_label = "Check kpcn"

    def execute(self, context):
        p = prefs(context)
        try:
            p.found = version(find_kpcn(p.kpcn_path)).replace("\n", "; ")
        except AddonError as exc:
            p.found = ""
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, p.found)
        return {"FINISHED"}


class KPCN_OT_denoise_render(bpy.types.Operator):
    """Denoise the last render with kpcn: the result is an image named after the scene and frame"""

    bl_idname = "kpcn.denoise_render"
    bl_label = "Denoise Last Render"

    _job = None
    _timer = None

    def execute(self, context):
        """From a script: wait for kpcn, then load its output."""
        try:
            job = start_job(context, context.scene)
            job.wait()
            image = finish_job(job)
        except AddonError as exc:
            return self._fail(exc)
        self.report({"INFO"}, f"kpcn: denoised into image '{image.name}'")
        return {"FINISHED"}

    def invoke(self, context, event):
        """From the button: kpcn runs while Blender stays responsive; the status bar shows its progress."""
        try:
            self._job = start_job(context, context.scene)
        except AddonError as exc:
            return self._fail(exc)
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.25, window=context.window)
        wm.modal_handler_add(self)
        context.workspace.status_text_set(self._job.status())
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type == "ESC":
            self._job.cancel()
            self._end(context)
            self.report({"WARNING"}, "kpcn: cancelled")
            return {"CANCELLED"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        if not self._job.poll():
            context.workspace.status_text_set(self._job.status())
            return {"RUNNING_MODAL"}
        self._end(context)
        try:
            image = finish_job(self._job)
        except AddonError as exc:
            return self._fail(exc)
        self.report({"INFO"}, f"kpcn: denoised into image '{image.name}'")
        return {"FINISHED"}

    def _end(self, context):
        context.window_manager.event_timer_remove(self._timer)
        context.workspace.status_text_set(None)

    def _fail(self, exc):
        prefs().last_message = f"error: {exc}"
        self.report({"ERROR"}, str(exc))
        return {"CANCELLED"}


# Handlers: jobs started by a render run one after another, polled by a timer (no operator owns them)
QUEUE = []


def _pump():
    """Poll the first queued job; None (the timer ends) once the queue is empty."""
    if not QUEUE:
        return None
    job, load = QUEUE[0]
    if not job.poll():
        return 0.5
    QUEUE.pop(0)
    try:
        if load:
            finish_job(job)
        else:
            prefs().last_message = f"denoised {job.result()}"
    except AddonError as exc:
        prefs().last_message = f"error: {exc}"
        print(f"kpcn: {exc}")
    return 0.5 if QUEUE else None


def _queue(job: Job, load: bool) -> None:
    QUEUE.append((job, load))
    if not bpy.app.timers.is_registered(_pump):
        bpy.app.timers.register(_pump, first_interval=0.5)


def _handler_error(exc) -> None:
    prefs().last_message = f"error: {exc}"
    print(f"kpcn: {exc}")


@bpy.app.handlers.persistent
def after_render(scene, *_):
    """After a render (preference): the Render Result denoised and loaded, as the button does."""
    if not prefs().after_render or bpy.app.background:  # a headless render script calls the operator itself
        return
    try:
        _queue(start_job(bpy.context, scene), load=True)
    except AddonError as exc:
        _handler_error(exc)


@bpy.app.handlers.persistent
def after_frame_written(scene, *_):
    """Each frame of an animation written (preference): a multilayer EXR frame denoised beside it."""
    if not prefs().each_frame:
        return
    path = bpy.path.abspath(scene.render.frame_path(frame=scene.frame_current))
    if scene.render.image_settings.file_format != "OPEN_EXR_MULTILAYER" or not os.path.isfile(path):
        _handler_error(f"frame {scene.frame_current} not denoised: the output format is not OpenEXR MultiLayer")
        return
    p = prefs()
    try:
        quality = "" if p.quality == "MODEL" else p.quality
        out = passes.denoised_path(path)
        _queue(Job(denoise_command(find_kpcn(p.kpcn_path), path, out, quality, p.ensemble), out, out), load=False)
    except AddonError as exc:
        _handler_error(exc)


CLASSES = (KPCN_OT_check, KPCN_OT_denoise_render)
HANDLERS = ((bpy.app.handlers.render_complete, after_render), (bpy.app.handlers.render_write, after_frame_written))
