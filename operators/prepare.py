"""Prepare the active body: tet mesh (if missing), stiffness, mass and linear modes, the reduced
RS deformer, and the energy cubature of a StVK or Fung material (so its first simulation is
fast)."""
import bpy

from ..bridge import bodies, jobs, preview, scene, stage_cache, staleness, tet_overlay, writes
from ..bridge.scene import InputError

# What Prepare records in the object (settings, then ID properties), undone together on failure.
RECORDED = ("tets_key", "prepared_key", "reduced_key", "reduced_basis_count", "cubature_count",
            "tet_node_count", "tet_count", "mnf")
RECORDED_ID_PROPERTIES = (stage_cache.TET_MESH, stage_cache.PREPARED_INPUTS,
                          stage_cache.ENERGY_RECORD)


class RS_ELASTIC_OT_prepare(jobs.JobOperator, bpy.types.Operator):
    """Compute the active body's elastic modes (cached next to the .blend)"""
    bl_idname = "rs_elastic.prepare"
    bl_label = "Prepare Body"
    bl_options = {'REGISTER', 'UNDO'}

    cached_only: bpy.props.BoolProperty(
        name="Cached Only", default=False, options={'HIDDEN', 'SKIP_SAVE'},
        description="Only load what the .blend and its cache hold; a stage that would have to "
                    "be computed is refused (the command line's --only bake)")

    def make_work(self, context):
        obj = scene.acted_on(context)
        inputs = bodies.read_inputs(obj, context.evaluated_depsgraph_get())
        inputs.energy = bodies.energy_inputs(obj)
        inputs.cached_only = self.cached_only
        self._inputs = inputs
        return lambda job: bodies.prepare(inputs, job)

    def apply(self, context, body, job):
        obj = bpy.data.objects[self._inputs.object_name]
        settings = obj.rs_elastic
        try:
            with writes.transaction(f"Recording the preparation of '{obj.name}'") as transaction:
                self._record(obj, body, transaction)
                if settings.preview_enabled:
                    preview.show(obj)
        except InputError as exc:
            self.report({'ERROR'}, str(exc))
            return {'CANCELLED'}
        stage_cache.persist(obj)
        stage_cache.prune(obj)          # the old preparation's files go once the new one is in
        tet_overlay.tag_redraw(context)
        f = body.linear_modes.frequencies_hz
        energy = "" if body.energy is None else (
            f"; {self._inputs.energy.label} energy cubature {len(body.energy.tets)} tets")
        self.report({'INFO'}, f"'{obj.name}': {len(f)} modes, {f[0]:.3g} to {f[-1]:.3g} Hz; "
                              f"reduced basis {settings.reduced_basis_count}, cubature "
                              f"{settings.cubature_count} tets{energy}")
        return {'FINISHED'}

    def _record(self, obj, body, transaction):
        settings = obj.rs_elastic
        writes.keep_values(transaction, settings, RECORDED)
        writes.keep_id_properties(transaction, settings, RECORDED_ID_PROPERTIES)
        frequencies = [mode.frequency_hz for mode in settings.mode_results]

        def undo():
            settings.mode_results.clear()
            for f in frequencies:
                settings.mode_results.add().frequency_hz = f
        transaction.undo(undo)
        settings.tets_key, settings.prepared_key, settings.reduced_key = body.keys
        stage_cache.store_tet_mesh(obj, settings.tets_key, body.tet_body)
        staleness.record_prepared(obj, self._inputs.fingerprint)
        stage_cache.record_energy(obj, bodies.energy_parent(body), body.energy_key)
        settings.reduced_basis_count = body.deformer.basis_size
        settings.cubature_count = len(body.deformer.cubature_tets)
        settings.tet_node_count = len(body.tet_body.nodes)
        settings.tet_count = len(body.tet_body.tets)
        settings.mode_results.clear()
        for f in body.linear_modes.frequencies_hz:
            settings.mode_results.add().frequency_hz = float(f)
        settings.mnf = float(body.linear_modes.mnf)


CLASSES = (RS_ELASTIC_OT_prepare,)
