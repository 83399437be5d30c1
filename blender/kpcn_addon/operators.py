"""The add-on's operators: check the kpcn executable, denoise the last render, render the frame as a pair and
denoise it adapting (modal operators from the button: progress in the status bar, Esc cancels; run from a script
they wait), and the render handlers that denoise after every render and every frame of an animation written."""

import os
import tempfile

import bpy

from . import passes
from .exr_colour import ExrError
from .runner import AddonError, Job, denoise_command, find_kpcn, version


def prefs(context=None):
    return (context or bpy.context).preferences.addons[__package__].preferences


def command(p, kpcn: str, src: str, out: str, pair: str = "", adapt_steps: int = 0) -> list[str]:
    """``runner.denoise_command`` with the preferences ``p`` (quality, ensemble, Adaptation Seconds)."""
    quality = "" if p.quality == "MODEL" else p.quality
    return denoise_command(kpcn, src, out, quality, p.ensemble, pair, p.adapt_seconds, adapt_steps)


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
    return Job(command(p, kpcn, src, out), out, passes.image_name(scene, scene.frame_current))


def start_pair_job(context, scene, adapt_steps: int = 0) -> Job:
    """The current frame rendered as two halves into a fresh temporary folder (``passes.render_halves``) and
    ``kpcn denoise A --pair B`` started on them, adapting for the preferences' Adaptation Seconds (or exactly
    ``adapt_steps`` steps where > 0). AddonError in one line where kpcn is not there (before any render) or the
    halves cannot be rendered."""
    p = prefs(context)
    kpcn = find_kpcn(p.kpcn_path)
    folder = tempfile.mkdtemp(prefix="kpcn-")
    half_a, half_b = passes.render_halves(scene, folder)
    out = os.path.join(folder, "denoised.exr")
    label = passes.image_name(scene, scene.frame_current, "kpcn pair")
    return Job(command(p, kpcn, half_a, out, half_b, adapt_steps), out, label)


def finish_job(job: Job):
    """The denoised image loaded and shown (AddonError with kpcn's error line where it failed); the panel's last
    message names it, with what kpcn's adaptation decided where it adapted."""
    try:
        image = passes.load_result(job.result(), job.label)
    except ExrError as exc:
        raise AddonError(str(exc)) from None
    prefs().last_message = f"denoised into image '{image.name}'" + (f"; {job.adaptation}" if job.adaptation else "")
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


class DenoiseJob:
    """What both denoise operators do with the job their ``start(context)`` starts: from a script, wait for kpcn and
    load its output; from the button, kpcn runs while Blender stays responsive, its progress in the status bar,
    Esc cancelling it."""

    _job = None
    _timer = None

    def execute(self, context):
        """From a script: wait for kpcn, then load its output."""
        try:
            job = self.start(context)
            job.wait()
            finish_job(job)
        except AddonError as exc:
            return self._fail(exc)
        self.report({"INFO"}, f"kpcn: {prefs().last_message}")
        return {"FINISHED"}

    def invoke(self, context, event):
        """From the button: kpcn runs while Blender stays responsive; the status bar shows its progress."""
        try:
            self._job = self.start(context)
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
            finish_job(self._job)
        except AddonError as exc:
            return self._fail(exc)
        self.report({"INFO"}, f"kpcn: {prefs().last_message}")
        return {"FINISHED"}

    def _end(self, context):
        context.window_manager.event_timer_remove(self._timer)
        context.workspace.status_text_set(None)

    def _fail(self, exc):
        prefs().last_message = f"error: {exc}"
        self.report({"ERROR"}, str(exc))
        return {"CANCELLED"}


class KPCN_OT_denoise_render(DenoiseJob, bpy.types.Operator):
    """Denoise the last render with kpcn: the result is an image named after the scene and frame"""

    bl_idname = "kpcn.denoise_render"
    bl_label = "Denoise Last Render"

    def start(self, context) -> Job:
        return start_job(context, context.scene)


class KPCN_OT_denoise_pair(DenoiseJob, bpy.types.Operator):
    """Render the frame twice at half the samples with two seeds, and denoise the pair with kpcn, adapting to it
    for the preferences' Adaptation Seconds: the result is an image named after the scene and frame"""

    bl_idname = "kpcn.denoise_pair"
    bl_label = "Render a Pair and Adapt"

    # a script's (and the tests') reproducible adaptation: exactly this many steps instead of the seconds
    adapt_steps: bpy.props.IntProperty(name="Adaptation Steps", default=0, min=0,
                                       options={"HIDDEN", "SKIP_SAVE"})

    def start(self, context) -> Job:
        return start_pair_job(context, context.scene, self.adapt_steps)


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
    if passes.RENDERING_HALVES[0]:  # a pair's half: the pair operator denoises both
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
        out = passes.denoised_path(path)
        _queue(Job(command(p, find_kpcn(p.kpcn_path), path, out), out, out), load=False)
    except AddonError as exc:
        _handler_error(exc)


CLASSES = (KPCN_OT_check, KPCN_OT_denoise_render, KPCN_OT_denoise_pair)
HANDLERS = ((bpy.app.handlers.render_complete, after_render), (bpy.app.handlers.render_write, after_frame_written))
