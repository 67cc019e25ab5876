"""Simulation: material model, damping and the Simulate operator."""
import bpy

from .body import RSElasticPanel


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
        layout.prop(settings, "use_scene_range")
        if not settings.use_scene_range:
            row = layout.row(align=True)
            row.prop(settings, "frame_start")
            row.prop(settings, "frame_end")
        layout.use_property_split = False
        layout.operator("rs_elastic.simulate", icon='PHYSICS')
        row = layout.row(align=True)
        row.operator("rs_elastic.keep_take", icon='PINNED')
        row.operator("rs_elastic.clear_bake", icon='TRASH')


CLASSES = (RS_ELASTIC_PT_simulate,)
