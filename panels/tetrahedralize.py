"""Tet mesh settings and the Tetrahedralize operator."""
import bpy
import numpy as np

from ..solver import proxy
from .body import RSElasticPanel

_ESTIMATES = {}    # (mesh pointer, polygons, edge length, budget) -> (triangles, proxy triangles)


def mesh_estimate(obj, settings):
    """(triangles, triangles fTetWild will mesh) of the object's own mesh, from its polygons'
    areas and the bounding box, without triangulating (cheap enough for draw; cached)."""
    mesh = obj.data
    key = (mesh.as_pointer(), len(mesh.polygons), settings.edge_length, settings.proxy_triangles)
    if key not in _ESTIMATES:
        sizes = np.empty(len(mesh.polygons), dtype=np.int32)
        areas = np.empty(len(mesh.polygons), dtype=np.float32)
        mesh.polygons.foreach_get("loop_total", sizes)
        mesh.polygons.foreach_get("area", areas)
        triangles = int(np.maximum(sizes - 2, 0).sum())
        corners = np.array(obj.bound_box)
        diagonal = float(np.linalg.norm(corners.max(axis=0) - corners.min(axis=0)))
        budget = settings.proxy_triangles or proxy.budget_for(float(areas.sum()), diagonal,
                                                              settings.edge_length)
        if len(_ESTIMATES) > 64:
            _ESTIMATES.clear()
        _ESTIMATES[key] = (triangles, min(triangles, budget))
    return _ESTIMATES[key]


class RS_ELASTIC_PT_tet_mesh(RSElasticPanel, bpy.types.Panel):
    bl_label = "Tet Mesh"
    bl_parent_id = "RS_ELASTIC_PT_body"

    def draw(self, context):
        settings = context.active_object.rs_elastic
        layout = self.layout
        layout.use_property_split = True
        layout.prop(settings, "edge_length")
        layout.prop(settings, "envelope")
        layout.prop(settings, "proxy_triangles")
        obj = context.active_object
        if obj.data.polygons:
            triangles, meshed = mesh_estimate(obj, settings)
            what = (f"a {meshed:,}-triangle proxy of {triangles:,}" if meshed < triangles
                    else f"{triangles:,} triangles")
            layout.label(text=f"fTetWild meshes {what}: roughly "
                              f"{proxy.tetwild_seconds(meshed):.0f} s", icon='TIME')
        layout.operator("rs_elastic.tetrahedralize", icon='MESH_ICOSPHERE')
        if settings.tets_key:
            col = layout.column(align=True)
            col.label(text=f"{settings.tet_node_count:,} nodes, {settings.tet_count:,} tets")
            col.prop(settings, "show_tets")


CLASSES = (RS_ELASTIC_PT_tet_mesh,)
