"""Mode preview controls."""
import bpy

from ..bridge import preview
from .body import RSElasticPanel, drawn_body


class RS_ELASTIC_PT_preview(RSElasticPanel, bpy.types.Panel):
    bl_label = "Mode Preview"
    bl_parent_id = "RS_ELASTIC_PT_body"

    def draw_header(self, context):
        self.layout.prop(drawn_body(self.layout, context).rs_elastic, "preview_enabled", text="")

    def draw(self, context):
        obj = drawn_body(self.layout, context)
        settings = obj.rs_elastic
        layout = self.layout
        layout.use_property_split = True
        layout.active = settings.preview_enabled
        layout.prop(settings, "preview_method")
        layout.prop(settings, "preview_mode")
        layout.prop(settings, "preview_amplitude", slider=True)
        if settings.preview_enabled and not settings.live and preview.under_bake(obj):
            layout.label(text="Clear Bake to preview", icon='INFO')
        elif settings.preview_enabled and not preview.is_shown(obj):
            layout.label(text="Prepare to preview the modes", icon='ERROR')


CLASSES = (RS_ELASTIC_PT_preview,)
