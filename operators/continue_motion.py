"""Continue: play the take on past the fit with the fitted material, baked after it."""
import bpy

from ..bridge import scene, take
from ..bridge.scene import InputError


class RS_ELASTIC_OT_continue_motion(bpy.types.Operator):
    """Simulate on from the fit's last frame with the fitted material, from the take's position
    and velocity there, and bake the frames after it (the take is untouched)"""
    bl_idname = "rs_elastic.continue_motion"
    bl_label = "Continue"
    bl_options = {'REGISTER', 'UNDO'}

    frame_end: bpy.props.IntProperty(name="End", default=0,
                                     description="Last frame baked (0: the scene's end frame)")

    def execute(self, context):
        obj = scene.active_mesh_or_report(self, context)
        if obj is None:
            return {'CANCELLED'}
        try:
            frames = take.continue_motion(obj, self.frame_end or context.scene.frame_end)
        except InputError as exc:
            self.report({'ERROR'}, str(exc))
            return {'CANCELLED'}
        self.report({'INFO'}, f"Continued '{obj.name}' with its fitted material over frames "
                              f"{frames[0]}–{frames[-1]}")
        return {'FINISHED'}


CLASSES = (RS_ELASTIC_OT_continue_motion,)
