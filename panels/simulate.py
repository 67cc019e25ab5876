"""Simulation: material model, damping and the Simulate operator."""
import bpy

from .body import RSElasticPanel, draw_bake_buttons, draw_frame_range


class RS_ELASTIC_PT_simulate(RSElasticPanel, bpy.types.Panel):
    bl_label = "Simulation"
    bl_parent_id = "RS_ELASTIC_PT_body"

    def draw(self, context):
        settings = context.active_object.rs_elastic
        layout = self.layout
        layout.use_property_split = True
        layout.prop(settings, "material_model")
        if settings.material_model == 'FUNG':
            layout.prop(settings, "fung_stiffening")
        layout.prop(settings, "damping_mass")
        layout.prop(settings, "damping_stiffness")
        draw_frame_range(layout, settings)
        layout.use_property_split = False
        layout.operator("rs_elastic.simulate", icon='PHYSICS')
        draw_bake_buttons(layout)


CLASSES = (RS_ELASTIC_PT_simulate,)
