"""Remove the body's bake (its RS Bake shape keys and their keyframes, or its Mesh Cache)."""
import bpy

from ..bridge import bake, scene


class RS_ELASTIC_OT_clear_bake(bpy.types.Operator):
    """Remove the bake: its shape keys and keyframes, or its Mesh Cache modifier and .pc2 file;
    your own keys and modifiers stay"""
    bl_idname = "rs_elastic.clear_bake"
    bl_label = "Clear Bake"
    bl_options = {'REGISTER', 'UNDO'}

    def execute(self, context):
        obj = scene.active_mesh_or_report(self, context)
        if obj is None:
            return {'CANCELLED'}
        removed = bake.clear_bake(obj)
        if removed == 0:
            self.report({'WARNING'}, f"'{obj.name}' has no bake")
            return {'CANCELLED'}
        self.report({'INFO'}, f"Removed {removed} baked frames from '{obj.name}'")
        return {'FINISHED'}


CLASSES = (RS_ELASTIC_OT_clear_bake,)
