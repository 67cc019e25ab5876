"""Simulation: material model, time integration, collisions and the Simulate operator (the frame
range, damping and bake it shares with a space-time solve are in the Bake panel)."""
import bpy

from ..bridge import bodies, colliders
from .body import RSElasticPanel, drawn_body, draw_lines, draw_progress


class RS_ELASTIC_PT_simulate(RSElasticPanel, bpy.types.Panel):
    bl_label = "Simulation"
    bl_parent_id = "RS_ELASTIC_PT_body"

    def draw(self, context):
        obj = drawn_body(self.layout, context)
        layout = self.layout
        draw_simulation_settings(layout, context, obj)
        layout.operator("rs_elastic.simulate", icon='PHYSICS')
        draw_progress(layout, obj, "rs_elastic.simulate")


def draw_simulation_settings(layout, context, obj):
    """Material model, time integration and collisions (the sidebar's Simulation panel and the
    Physics tab)."""
    settings = obj.rs_elastic
    col = layout.column()
    col.use_property_split = True
    col.prop(settings, "material_model")
    if settings.material_model == 'FUNG':
        col.prop(settings, "fung_stiffening")
    if settings.is_prepared and settings.material_model != 'LINEAR':
        draw_lines(col, energy_label(obj), 'INFO')
    col.prop(settings, "integrator")
    col.prop(settings, "substeps")
    col.prop(settings, "start_settled")
    draw_collisions(col, context, obj)


def energy_label(obj):
    """Whether the next simulation trains the material's energy cubature (StVK / Fung)."""
    if bodies.energy_ready(obj):
        return "Energy cubature: cached with the body"
    return "Energy cubature: trained when you simulate (Esc cancels)"


def draw_collisions(layout, context, obj):
    """The collision settings and the colliders the next simulation will see."""
    settings = obj.rs_elastic
    layout.prop(settings, "use_collisions")
    if not settings.use_collisions:
        return
    layout.prop(settings, "collider_collection")
    layout.prop(settings, "contact_samples")
    names = [other.name for other in colliders.collider_objects(obj, context.scene)]
    text = f"Colliders: {', '.join(names)}" if names else "No Collision modifier"
    layout.label(text=text, icon='MOD_PHYSICS')


CLASSES = (RS_ELASTIC_PT_simulate,)
