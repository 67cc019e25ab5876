"""Take from Animation: the evaluated motion of the body (or its Take Source) becomes the take."""
import bpy
import numpy as np

from ..bridge import jobs, scene, take


class RS_ELASTIC_OT_take_from_animation(jobs.JobOperator, bpy.types.Operator):
    """Read the motion of the Take Source (or of this object) over the scene's frame range as
    the take to edit and fit"""
    bl_idname = "rs_elastic.take_from_animation"
    bl_label = "Take from Animation"
    bl_options = {'REGISTER', 'UNDO'}

    def make_work(self, context):
        obj = scene.require_mesh_object(scene.acted_on(context))
        return self._work_after(take.gather_take(context, obj))

    def _work_after(self, reading):
        """The reading of the frames (a generator, ``jobs``), then the fit's work."""
        inputs = yield from reading
        self._inputs = inputs
        return lambda job: take.take_residuals(inputs, job)

    def apply(self, context, residuals, job):
        inputs = self._inputs
        obj = bpy.data.objects[inputs.object_name]
        take.store_take(obj, inputs)
        frames, worst = inputs.frames, int(np.argmax(residuals))
        self.report({'INFO'}, f"Took frames {frames[0]}–{frames[-1]} of '{inputs.source_name}' "
                              f"as the take of '{obj.name}'; the modes miss it by "
                              f"{residuals.mean():.3g} m on average, {residuals[worst]:.3g} m on "
                              f"frame {frames[worst]} (worst)")
        return {'FINISHED'}


CLASSES = (RS_ELASTIC_OT_take_from_animation,)
