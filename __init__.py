"""RS Elastic: elastic motion in rotation-strain coordinates. This module only registers."""
import bpy

try:
    import numpy  # noqa: F401  (the whole extension computes with it)
except ImportError:             # a distribution's Blender may run without it
    numpy = None
else:
    from . import operators, panels
    from .bridge import cli, farm, handlers, properties, tet_overlay

NO_NUMPY = ("RS Elastic needs numpy, which this Blender's Python lacks: install your system's "
            "python3-numpy, or use Blender from blender.org (it includes numpy)")


def register():
    if numpy is None:
        print(NO_NUMPY)
        raise ImportError(NO_NUMPY)
    properties.register()
    farm.register()
    for cls in operators.CLASSES + panels.CLASSES:
        bpy.utils.register_class(cls)
    tet_overlay.register()
    handlers.register()
    cli.register()


def unregister():
    if numpy is None:
        return
    cli.unregister()
    handlers.unregister()
    tet_overlay.unregister()
    for cls in reversed(operators.CLASSES + panels.CLASSES):
        bpy.utils.unregister_class(cls)
    farm.unregister()
    properties.unregister()
