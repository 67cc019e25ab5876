"""Simulate the active body in RS coordinates and bake the motion into shape keys.

A StVK or Fung body needs its energy cubature: Prepare makes it, but a material model chosen
after Prepare (or a new session without the cache in memory) needs it loaded or trained first.
That runs as a first job on the worker thread (progress, Esc), then the simulation is gathered
on the main thread and run as a second job, within the same operator.
"""
import bpy
import numpy as np

from ..bridge import bake, jobs, preview, scene, simulation_inputs, stage_cache, writes
from ..bridge.scene import InputError
from .solve_spacetime import forget_solve

ENERGY, SIMULATE = "energy", "simulate"
MAX_ENERGY_JOBS = 3     # the material may change during a training: retrain, but not forever


class RS_ELASTIC_OT_simulate(jobs.JobOperator, bpy.types.Operator):
    """Simulate the body over the frame range (gravity, pins, its keyed motion) and bake it,
    replacing the previous bake"""
    bl_idname = "rs_elastic.simulate"
    bl_label = "Simulate and Bake"
    bl_options = {'REGISTER', 'UNDO'}

    _modal = False
    _energy_jobs = 0

    def make_work(self, context):
        obj = scene.acted_on(context)
        bake.require_target(scene.require_body(obj))     # before any training
        work = None
        if self._energy_jobs < MAX_ENERGY_JOBS:
            work = simulation_inputs.energy_work(obj)
        if work is not None:
            self._phase, self._object_name = ENERGY, obj.name
            self._energy_jobs += 1
            return work
        inputs = simulation_inputs.gather(obj, context.scene)
        self._phase, self._inputs = SIMULATE, inputs
        return lambda job: simulation_inputs.run(inputs, job)

    def invoke(self, context, event):
        self._modal = not bpy.app.background
        return super().invoke(context, event)

    def _then_simulate(self, context):
        """After the energy job: gather and run the simulation (as the first job ran)."""
        obj = bpy.data.objects.get(self._object_name)
        if obj is None or context.view_layer.objects.active != obj:
            self.report({'ERROR'}, f"'{self._object_name}' is no longer the active object: "
                                   "its energy cubature is ready, simulate it again")
            return {'CANCELLED'}
        simulation_inputs.record_energy(obj)
        job = self._start(context)
        if job is None:
            return {'CANCELLED'}
        if not self._modal:
            try:
                job.run_here()
            except Exception as exc:
                return self._fail(exc)
            return self._finish(context, job)
        self._run_modal(context, job)
        return {'RUNNING_MODAL'}     # the modal handler added by invoke carries on

    def apply(self, context, poses, job):
        if self._phase == ENERGY:
            return self._then_simulate(context)
        inputs = self._inputs
        obj = bpy.data.objects[inputs.object_name]
        for message in inputs.warnings:
            self.report({'WARNING'}, message)
        if not np.all(np.isfinite(poses)):
            self.report({'ERROR'}, f"The simulation of '{obj.name}' blew up; try more damping "
                                   "or a higher frame rate. Nothing was baked")
            return {'CANCELLED'}
        try:
            with writes.transaction(f"Baking '{obj.name}'") as transaction:
                writes.keep_id_properties(transaction, obj.rs_elastic, [stage_cache.ENERGY_RECORD])
                active = bake.write_bake(obj, inputs.frames, poses)
                forget_solve(obj, transaction)      # its words were about the bake replaced
                simulation_inputs.record_energy(obj)
        except InputError as exc:
            self.report({'ERROR'}, str(exc))
            return {'CANCELLED'}
        if active:
            self.report({'WARNING'}, f"Shape keys {', '.join(active)} are not at 0 and add on "
                                     "top of the bake")
        if not obj.rs_elastic.live:     # the mode preview would add to the bake: it steps aside
            preview.refresh(obj)
        self.report({'INFO'}, f"'{obj.name}': simulated and baked frames "
                              f"{inputs.frames[0]}–{inputs.frames[-1]}")
        return {'FINISHED'}


CLASSES = (RS_ELASTIC_OT_simulate,)
