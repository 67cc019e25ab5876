"""Fit Material: recover the body's modal material from the take's frames."""
import bpy

from ..bridge import jobs, scene, take


class RS_ELASTIC_OT_fit_material(jobs.JobOperator, bpy.types.Operator):
    """Recover each mode's frequency and damping from the take's frames in the fit range (the
    frames are keyframes of a space-time solve that also optimises the material)"""
    bl_idname = "rs_elastic.fit_material"
    bl_label = "Fit Material"
    bl_options = {'REGISTER', 'UNDO'}

    def make_work(self, context):
        obj = scene.require_mesh_object(scene.acted_on(context))
        inputs = take.gather_fit(obj, context.scene)
        self._object_name = inputs.object_name
        return lambda job: take.fit_work(inputs, job)

    def apply(self, context, fitted, job):
        obj = bpy.data.objects[self._object_name]
        take.keep_fitted(obj, fitted)
        said = "" if fitted.converged else f" (not converged: {fitted.reason})"
        self.report({'WARNING'} if said else {'INFO'},
                    f"Fitted the material of '{obj.name}' to frames {fitted.first_frame}–"
                    f"{fitted.last_frame}: residual {fitted.residual:.3g} m RMS, worst on frame "
                    f"{fitted.worst_frame}{said}")
        return {'FINISHED'}


CLASSES = (RS_ELASTIC_OT_fit_material,)
