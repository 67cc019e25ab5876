"""Fit Material: recover the body's modal material from the take's frames."""
import bpy

from ..bridge import scene, take
from ..bridge.scene import InputError


class RS_ELASTIC_OT_fit_material(bpy.types.Operator):
    """Recover each mode's frequency and damping from the take's frames in the fit range (the
    frames are keyframes of a space-time solve that also optimises the material)"""
    bl_idname = "rs_elastic.fit_material"
    bl_label = "Fit Material"
    bl_options = {'REGISTER', 'UNDO'}

    def execute(self, context):
        obj = scene.active_mesh_or_report(self, context)
        if obj is None:
            return {'CANCELLED'}
        try:
            fitted = take.fit_material(obj, context.scene)
        except (InputError, ValueError) as exc:
            self.report({'ERROR'}, str(exc))
            return {'CANCELLED'}
        said = "" if fitted.converged else f" (not converged: {fitted.reason})"
        self.report({'WARNING'} if said else {'INFO'},
                    f"Fitted the material of '{obj.name}' to frames {fitted.first_frame}–"
                    f"{fitted.last_frame}: residual {fitted.residual:.3g} m RMS, worst on frame "
                    f"{fitted.worst_frame}{said}")
        return {'FINISHED'}


CLASSES = (RS_ELASTIC_OT_fit_material,)
