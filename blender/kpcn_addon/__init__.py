"""kpcn for Blender: denoise Cycles renders with the kpcn executable (docs/blender.md).

It runs inside Blender's own Python and imports nothing of kpcn: kpcn stays in its own environment and is run as
a program, so the add-on adds no package to Blender and downloads nothing."""

import bpy

from . import operators, ui


def register():
    for cls in ui.CLASSES + operators.CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.kpcn = bpy.props.PointerProperty(type=ui.KpcnSceneSettings)
    for handlers, handler in operators.HANDLERS:
        handlers.append(handler)


def unregister():
    for handlers, handler in operators.HANDLERS:
        if handler in handlers:
            handlers.remove(handler)
    for job, _ in operators.QUEUE:
        job.cancel()
    operators.QUEUE.clear()
    del bpy.types.Scene.kpcn
    for cls in reversed(ui.CLASSES + operators.CLASSES):
        bpy.utils.unregister_class(cls)
