"""Tet mesh settings and the Tetrahedralize operator."""
import bpy

from ..bridge import estimates
from .body import RSElasticPanel


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
        layout.prop(settings, "mesher_time_limit")
        obj = context.active_object
        if obj.data.polygons:
            text, over = estimates.mesher_line(obj, settings)
            layout.label(text=text, icon='ERROR' if over else 'TIME')
            if over:
                layout.label(text="Over the Time Limit: a new tet mesh is refused")
        layout.operator("rs_elastic.tetrahedralize", icon='MESH_ICOSPHERE')
        if settings.tets_key:
            col = layout.column(align=True)
            col.label(text=f"{settings.tet_node_count:,} nodes, {settings.tet_count:,} tets")
            col.prop(settings, "show_tets")


CLASSES = (RS_ELASTIC_PT_tet_mesh,)
