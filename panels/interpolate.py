"""RS interpolation of shape keys."""
import bpy

from .body import RSElasticPanel, drawn_body


class RS_ELASTIC_PT_interpolate(RSElasticPanel, bpy.types.Panel):
    bl_label = "Shape Key Interpolation"
    bl_parent_id = "RS_ELASTIC_PT_body"
    bl_options = {'DEFAULT_CLOSED'}

    def draw(self, context):
        obj = drawn_body(self.layout, context)
        layout = self.layout
        if not obj.rs_elastic.is_prepared:
            layout.label(text="Prepare the body first", icon='INFO')
        elif obj.data.shape_keys is None or len(obj.data.shape_keys.key_blocks) < 2:
            layout.label(text="Needs two shape keys", icon='INFO')
        layout.operator("rs_elastic.interpolate_shape_keys", icon='SHAPEKEY_DATA')


CLASSES = (RS_ELASTIC_PT_interpolate,)
