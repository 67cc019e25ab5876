"""Simulation: material model, damping, time integration and the Simulate operator."""
import bpy

from ..bridge import bodies, colliders, estimates
from .body import RSElasticPanel, draw_bake_buttons, draw_frame_range, frame_count


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
        if settings.is_prepared and settings.material_model != 'LINEAR':
            layout.label(text=energy_label(context.active_object))
        layout.prop(settings, "damping_mass")
        layout.prop(settings, "damping_stiffness")
        frequencies = settings.frequencies
        if frequencies and frequencies[0] > 0.0:
            layout.label(text=damping_label(settings, frequencies[0]))
        layout.prop(settings, "integrator")
        layout.prop(settings, "substeps")
        layout.prop(settings, "start_settled")
        draw_collisions(layout, context, settings)
        draw_frame_range(layout, settings)
        layout.use_property_split = False
        layout.operator("rs_elastic.simulate", icon='PHYSICS')
        draw_bake_buttons(layout, context.active_object,
                          frame_count(context.scene, context.active_object.rs_elastic))


def energy_label(obj):
    """Whether the next simulation trains the material's energy cubature (StVK / Fung)."""
    if bodies.energy_ready(obj):
        return "Energy cubature: cached with the body"
    return "Energy cubature: trained when you simulate (Esc cancels)"


def draw_collisions(layout, context, settings):
    """The collision settings and the colliders the next simulation will see."""
    layout.prop(settings, "use_collisions")
    if not settings.use_collisions:
        return
    layout.prop(settings, "collider_collection")
    layout.prop(settings, "contact_samples")
    names = [obj.name for obj in colliders.collider_objects(context.active_object, context.scene)]
    text = f"Colliders: {', '.join(names)}" if names else "No object with a Collision modifier"
    layout.label(text=text, icon='MOD_PHYSICS')


def damping_label(settings, frequency_hz):
    """The Rayleigh damping as a damping ratio at the first mode (frequency in Hz)."""
    zeta = estimates.first_mode_damping_ratio(settings, frequency_hz)
    return f"Damping ratio at mode 1 ({frequency_hz:.3g} Hz): {100.0 * zeta:.3g} %"


CLASSES = (RS_ELASTIC_PT_simulate,)
