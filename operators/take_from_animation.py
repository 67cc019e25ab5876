"""Take from Animation: the evaluated motion of the body (or its Take Source) becomes the take."""
import bpy
import numpy as np

from ..bridge import scene, take
from ..bridge.scene import InputError


class RS_ELASTIC_OT_take_from_animation(bpy.types.Operator):
    """Read the motion of the Take Source (or of this object) over the scene's frame range as
    the take to edit and fit"""
    bl_idname = "rs_elastic.take_from_animation"
    bl_label = "Take from Animation"
    bl_options = {'REGISTER', 'UNDO'}

    def execute(self, context):
        obj = scene.active_mesh_or_report(self, context)
        if obj is None:
            return {'CANCELLED'}
        try:
            frames, residuals = take.take_from_animation(context, obj)
        except InputError as exc:
            self.report({'ERROR'}, str(exc))
            return {'CANCELLED'}
        worst = int(np.argmax(residuals))
        self.report({'INFO'}, f"Took frames {frames[0]}–{frames[-1]} of "
                              f"'{take.take_source(obj).name}' as the take of '{obj.name}'; the "
                              f"modes miss it by {residuals.mean():.3g} m on average, "
                              f"{residuals[worst]:.3g} m on frame {frames[worst]} (worst)")
        return {'FINISHED'}


CLASSES = (RS_ELASTIC_OT_take_from_animation,)
