"""RS Elastic: elastic motion in rotation-strain coordinates. This module only registers."""
import bpy

from . import operators, panels
from .bridge import cli, farm, handlers, properties, tet_overlay


def register():
    properties.register()
    farm.register()
    for cls in operators.CLASSES + panels.CLASSES:
        bpy.utils.register_class(cls)
    tet_overlay.register()
    handlers.register()
    cli.register()


def unregister():
    cli.unregister()
    handlers.unregister()
    tet_overlay.unregister()
    for cls in reversed(operators.CLASSES + panels.CLASSES):
        bpy.utils.unregister_class(cls)
    farm.unregister()
    properties.unregister()
