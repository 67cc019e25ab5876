"""Solve a space-time edit of the active body and bake it into shape keys."""
import bpy

from ..bridge import bake, jobs, preview, scene, spacetime_inputs, writes
from ..bridge.scene import InputError


class RS_ELASTIC_OT_solve_spacetime(jobs.JobOperator, bpy.types.Operator):
    """Find the motion with the least control force that meets the handles and pose keys, and
    bake it (replacing the previous bake)"""
    bl_idname = "rs_elastic.solve_spacetime"
    bl_label = "Solve and Bake"
    bl_options = {'REGISTER', 'UNDO'}

    def make_work(self, context):
        inputs = spacetime_inputs.gather(scene.acted_on(context), context.scene)
        self._inputs = inputs
        return lambda job: spacetime_inputs.solve(inputs, job)

    def apply(self, context, output, job):
        result, poses = output
        inputs = self._inputs
        obj = bpy.data.objects[inputs.object_name]
        settings = obj.rs_elastic
        for message in inputs.warnings:
            self.report({'WARNING'}, message)
        try:
            with writes.transaction(f"Baking '{obj.name}'") as transaction:
                active = bake.write_bake(obj, inputs.frames, poses)
                _record_solve(obj, inputs, result, transaction)
        except InputError as exc:
            self.report({'ERROR'}, str(exc))
            return {'CANCELLED'}
        if active:
            self.report({'WARNING'}, f"Shape keys {', '.join(active)} are not at 0 and add on "
                                     "top of the bake")
        if not obj.rs_elastic.live:     # the mode preview would add to the bake: it steps aside
            preview.refresh(obj)
        worst = max((h.residual for h in settings.handles), default=-1.0)
        self.report({'INFO'}, f"'{obj.name}': baked frames {inputs.frames[0]}–{inputs.frames[-1]}"
                              f" in {result.iterations} iterations"
                              + (f", largest handle miss {worst:.2g} m" if worst >= 0 else ""))
        return {'FINISHED'}


def _record_solve(obj, inputs, result, transaction):
    """Each handle's residual and the objective's history, for the panel (undone with the bake)."""
    settings = obj.rs_elastic
    forget_solve(obj, transaction)
    scale = inputs.world_scale          # positive, a mirrored object's too
    for index, rows in inputs.track_slices:
        settings.handles[index].residual = scale * float(result.handle_residuals[rows].max())
    for _, _, objective in result.history:
        settings.solve_history.add().value = float(objective)


CLASSES = (RS_ELASTIC_OT_solve_spacetime,)


def forget_solve(obj, transaction):
    """Clear the last solve's residuals and objectives (kept for `transaction`'s undo): the
    panel shows them only while that solve's bake is in place."""
    settings = obj.rs_elastic
    for handle in settings.handles:
        writes.keep_values(transaction, handle, ["residual"])
    history = [item.value for item in settings.solve_history]

    def undo():
        settings.solve_history.clear()
        for value in history:
            settings.solve_history.add().value = value
    transaction.undo(undo)
    for handle in settings.handles:
        handle.residual = -1.0
    settings.solve_history.clear()
