"""What the user sees: the add-on's preferences (where kpcn is, how it denoises) and the kpcn panel in the
render properties (the passes checkbox, the denoise button and the pair button)."""

import bpy

from . import passes

QUALITY_ITEMS = (("MODEL", "Model's Default", "The model's own networks (kpcn denoise without --quality)"),
                 ("fast", "Fast", "kpcn denoise --quality fast"),
                 ("balanced", "Balanced", "kpcn denoise --quality balanced"),
                 ("high", "High", "kpcn denoise --quality high"))


class KpcnPreferences(bpy.types.AddonPreferences):
    bl_idname = __package__

    kpcn_path: bpy.props.StringProperty(
        name="kpcn Executable", subtype="FILE_PATH", default="",
        description="The kpcn program of kpcn's environment (.venv/bin/kpcn of a kpcn checkout); empty: kpcn on PATH")
    quality: bpy.props.EnumProperty(name="Quality", items=QUALITY_ITEMS, default="MODEL",
                                    description="The model's quality mode (kpcn denoise --quality)")
    ensemble: bpy.props.IntProperty(
        name="Ensemble", default=1, min=1, max=8,
        description="Denoise the frame under this many of the square's 8 symmetries and keep each pixel's median: "
                    "that many times the time, for a lower error (kpcn denoise --ensemble)")
    adapt_seconds: bpy.props.FloatProperty(
        name="Adaptation Seconds", default=60.0, min=0.0, max=86400.0,
        description="Render a Pair and Adapt: seconds at most of adapting to the frame's two halves (kpcn denoise "
                    "--pair --adapt); 0: the pair's mean denoised without adapting")
    after_render: bpy.props.BoolProperty(name="Denoise After Every Render", default=False,
                                         description="Denoise the Render Result when a render finishes")
    each_frame: bpy.props.BoolProperty(
        name="Denoise Every Animation Frame", default=False,
        description="Denoise each frame an animation writes (OpenEXR MultiLayer output) into <frame>-kpcn.exr")
    found: bpy.props.StringProperty(name="Found", default="")
    last_message: bpy.props.StringProperty(name="Last", default="")

    def draw(self, context):
        layout = self.layout
        row = layout.row()
        row.prop(self, "kpcn_path")
        row.operator("kpcn.check", text="Check")
        if self.found:
            for line in self.found.split("; "):
                layout.label(text=line, icon="CHECKMARK")
        layout.prop(self, "quality")
        layout.prop(self, "ensemble")
        layout.prop(self, "adapt_seconds")
        layout.prop(self, "after_render")
        layout.prop(self, "each_frame")


def _use_passes_changed(self, context):
    passes.use_passes(self.id_data, self.use_passes)


class KpcnSceneSettings(bpy.types.PropertyGroup):
    use_passes: bpy.props.BoolProperty(
        name="Passes for kpcn", default=False, update=_use_passes_changed,
        description="Turn on every pass kpcn reads (light passes, Denoising Data, normal) and Blender's own "
                    "denoiser off for the render")
    blender_denoiser: bpy.props.BoolProperty(default=False, options={"HIDDEN"})
    denoiser_saved: bpy.props.BoolProperty(default=False, options={"HIDDEN"})


class RENDER_PT_kpcn(bpy.types.Panel):
    bl_label = "kpcn Denoiser"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "render"
    bl_options = {"DEFAULT_CLOSED"}

    @classmethod
    def poll(cls, context):
        return context.scene.render.engine == "CYCLES"

    def draw(self, context):
        layout = self.layout
        layout.prop(context.scene.kpcn, "use_passes")
        layout.operator("kpcn.denoise_render", icon="IMAGE")
        layout.operator("kpcn.denoise_pair", icon="RENDER_STILL")
        message = context.preferences.addons[__package__].preferences.last_message
        if message:
            layout.label(text=message, icon="ERROR" if message.startswith("error") else "INFO")


CLASSES = (KpcnPreferences, KpcnSceneSettings, RENDER_PT_kpcn)
