"""Keep the current bake as the take: the input motion that space-time edits start from."""
import bpy

from ..bridge import bake, scene
from ..bridge.scene import InputError


class RS_ELASTIC_OT_keep_take(bpy.types.Operator):
    """Store the current bake (a simulation or an earlier edit) as the take to edit"""
    bl_idname = "rs_elastic.keep_take"
    bl_label = "Keep Bake as Take"
    bl_options = {'REGISTER', 'UNDO'}

    def execute(self, context):
        obj = scene.active_mesh_or_report(self, context)
        if obj is None:
            return {'CANCELLED'}
        try:
            frames = bake.keep_bake_as_take(obj)
        except InputError as exc:
            self.report({'ERROR'}, str(exc))
            return {'CANCELLED'}
        if not frames:
            self.report({'ERROR'}, f"'{obj.name}' has no bake to keep")
            return {'CANCELLED'}
        obj.rs_elastic.use_take = True
        self.report({'INFO'}, f"Kept frames {frames[0]}–{frames[-1]} of '{obj.name}' as the take")
        return {'FINISHED'}


CLASSES = (RS_ELASTIC_OT_keep_take,)
