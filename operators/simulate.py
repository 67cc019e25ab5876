"""Simulate the active body in RS coordinates and bake the motion into shape keys."""
import bpy
import numpy as np

from ..bridge import bake, jobs, simulation_inputs


class RS_ELASTIC_OT_simulate(jobs.JobOperator, bpy.types.Operator):
    """Simulate the body over the frame range (gravity, pins, its keyed motion) and bake it,
    replacing the previous bake"""
    bl_idname = "rs_elastic.simulate"
    bl_label = "Simulate and Bake"
    bl_options = {'REGISTER', 'UNDO'}

    def make_work(self, context):
        inputs = simulation_inputs.gather(context.active_object, context.scene)
        self._inputs = inputs
        return lambda job: simulation_inputs.run(inputs, job)

    def apply(self, context, poses, job):
        inputs = self._inputs
        obj = bpy.data.objects[inputs.object_name]
        for message in inputs.warnings:
            self.report({'WARNING'}, message)
        if not np.all(np.isfinite(poses)):
            self.report({'ERROR'}, f"The simulation of '{obj.name}' blew up; try more damping "
                                   "or a higher frame rate. Nothing was baked")
            return {'CANCELLED'}
        active = bake.write_bake(obj, inputs.frames, poses)
        if active:
            self.report({'WARNING'}, f"Shape keys {', '.join(active)} are not at 0 and add on "
                                     "top of the bake")
        self.report({'INFO'}, f"'{obj.name}': simulated and baked frames "
                              f"{inputs.frames[0]}–{inputs.frames[-1]}")
        return {'FINISHED'}


CLASSES = (RS_ELASTIC_OT_simulate,)
