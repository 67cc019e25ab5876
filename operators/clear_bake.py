"""Remove the body's bake (its RS Bake shape keys and their keyframes, or its Mesh Cache)."""
import bpy

from ..bridge import bake, preview, scene
from ..bridge.scene import InputError


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
        try:
            removed = bake.clear_bake(obj)
        except InputError as exc:
            self.report({'ERROR'}, str(exc))
            return {'CANCELLED'}
        if removed is None:
            self.report({'WARNING'}, f"'{obj.name}' has no bake")
            return {'CANCELLED'}
        if not obj.rs_elastic.live:     # the mode preview shows again, on its own
            preview.refresh(obj)
        self.report({'INFO'}, f"Removed {removed} baked frames from '{obj.name}'" if removed
                    else f"Removed the bake of '{obj.name}' (its .pc2 file was missing)")
        return {'FINISHED'}


CLASSES = (RS_ELASTIC_OT_clear_bake,)
