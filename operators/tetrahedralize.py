"""Tetrahedralise the active mesh with fTetWild and embed its vertices in the tets."""
import bpy

from ..bridge import bodies, jobs, scene, stage_cache, tet_overlay


class RS_ELASTIC_OT_tetrahedralize(jobs.JobOperator, bpy.types.Operator):
    """Build the tet mesh of the active object (its evaluated mesh, in object space)"""
    bl_idname = "rs_elastic.tetrahedralize"
    bl_label = "Tetrahedralize"
    bl_options = {'REGISTER', 'UNDO'}

    def make_work(self, context):
        inputs = bodies.read_inputs(scene.acted_on(context), context.evaluated_depsgraph_get(),
                                    with_material=False)
        self._object_name = inputs.object_name
        self._key = inputs.tets_key
        return lambda job: bodies.tet_stage(inputs, job)

    def apply(self, context, tet_body, job):
        obj = bpy.data.objects[self._object_name]
        settings = obj.rs_elastic
        if settings.tets_key != self._key:
            settings.prepared_key = ""   # the modes belong to the old tet mesh
            settings.reduced_key = ""
            settings.mode_results.clear()
            settings.mnf = 0.0
            stage_cache.forget_prepared(obj)
        settings.tets_key = self._key
        stage_cache.store_tet_mesh(obj, self._key, tet_body)
        settings.tet_node_count = len(tet_body.nodes)
        settings.tet_count = len(tet_body.tets)
        stage_cache.persist(obj)
        stage_cache.prune(obj)
        tet_overlay.tag_redraw(context)
        self.report({'INFO'}, f"'{obj.name}': {settings.tet_node_count} nodes, "
                              f"{settings.tet_count} tets")
        return {'FINISHED'}


CLASSES = (RS_ELASTIC_OT_tetrahedralize,)
