"""Tet mesh settings and the Tetrahedralize operator."""
import bpy

from ..bridge import estimates
from .body import RSElasticPanel, drawn_body, draw_lines, draw_progress


class RS_ELASTIC_PT_tet_mesh(RSElasticPanel, bpy.types.Panel):
    bl_label = "Tet Mesh"
    bl_parent_id = "RS_ELASTIC_PT_body"

    def draw(self, context):
        obj = drawn_body(self.layout, context)
        settings = obj.rs_elastic
        layout = self.layout
        col = layout.column(align=True)     # 'Name: value' fields: the names fit the sidebar
        col.prop(settings, "edge_length")
        col.prop(settings, "envelope")
        col.prop(settings, "proxy_triangles")
        col.prop(settings, "mesher_time_limit")
        if obj.data.polygons:
            text, over = estimates.mesher_line(obj, settings)
            draw_lines(layout, text, 'ERROR' if over else 'TIME')
            if over:
                draw_lines(layout, "Over the Time Limit: a new tet mesh is refused")
        layout.operator("rs_elastic.tetrahedralize", icon='MESH_ICOSPHERE')
        draw_progress(layout, obj, "rs_elastic.tetrahedralize")
        if settings.tets_key:
            col = layout.column(align=True)
            col.label(text=f"{settings.tet_node_count:,} nodes, {settings.tet_count:,} tets")
            col.prop(settings, "show_tets")


CLASSES = (RS_ELASTIC_PT_tet_mesh,)
