"""Material, pins and modes, and the Prepare operator with its results."""
import bpy

from ..bridge import armature
from .body import RSElasticPanel, drawn_body, draw_lines, draw_progress


class RS_ELASTIC_UL_modes(bpy.types.UIList):
    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index):
        layout.label(text=f"Mode {index + 1}")
        layout.label(text=f"{item.frequency_hz:.4g} Hz")


class RS_ELASTIC_MT_material_presets(bpy.types.Menu):
    bl_label = "Material Presets"

    def draw(self, context):
        self.layout.operator_enum("rs_elastic.apply_material_preset", "preset")


class RS_ELASTIC_PT_material(RSElasticPanel, bpy.types.Panel):
    bl_label = "Material and Pins"
    bl_parent_id = "RS_ELASTIC_PT_body"

    def draw(self, context):
        draw_material(self.layout, drawn_body(self.layout, context))


def draw_material(layout, obj):
    """The body's material and pins (the sidebar's Material and Pins panel and the Physics tab)."""
    settings = obj.rs_elastic
    layout.menu("RS_ELASTIC_MT_material_presets", icon='PRESET')
    # 'Name: value' fields and labels above the group fields: the names fit the sidebar
    # (the units are in the tooltips).
    col = layout.column(align=True)
    col.prop(settings, "youngs_modulus")
    col.prop(settings, "poisson_ratio")
    col.prop(settings, "density")
    col = layout.column(align=True)
    col.label(text="Stiffness Group:")
    col.prop_search(settings, "stiffness_group", obj, "vertex_groups", text="")
    col.prop(settings, "stiffness_ratio")
    rigged = armature.is_rigged(obj)  # on a rig the pins are what follows the bones
    col = layout.column(align=True)
    col.label(text="Follow Rig:" if rigged else "Pin Group:")
    col.prop_search(settings, "pin_group", obj, "vertex_groups", text="")
    if rigged:
        layout.operator("rs_elastic.follow_bones", icon='BONE_DATA')
        draw_lines(layout, f"Rigged by '{armature.armature_modifier(obj).object.name}': "
                           "the rest is free flesh", 'ARMATURE_DATA')


class RS_ELASTIC_PT_modes(RSElasticPanel, bpy.types.Panel):
    bl_label = "Modes"
    bl_parent_id = "RS_ELASTIC_PT_body"

    def draw(self, context):
        obj = drawn_body(self.layout, context)
        settings = obj.rs_elastic
        layout = self.layout
        row = layout.row()
        row.prop(settings, "num_modes")
        layout.operator("rs_elastic.prepare", icon='PLAY')
        draw_progress(layout, obj, "rs_elastic.prepare")
        col = layout.column(align=True)     # 'Name: value' fields: the names fit the sidebar
        col.prop(settings, "basis_size")
        col.prop(settings, "cubature_tets")
        col.prop(settings, "cubature_tolerance")
        col.prop(settings, "training_poses")
        if settings.is_prepared:
            layout.label(text=f"MNF {settings.mnf:.4g} rad/s")
            if settings.reduced_key:
                col = layout.column(align=True)
                col.label(text=f"Reduced basis {settings.reduced_basis_count}")
                col.label(text=f"Cubature {settings.cubature_count} tets")
            layout.template_list("RS_ELASTIC_UL_modes", "", settings, "mode_results",
                                 settings, "preview_mode", rows=4)


CLASSES = (RS_ELASTIC_UL_modes, RS_ELASTIC_MT_material_presets, RS_ELASTIC_PT_material,
           RS_ELASTIC_PT_modes)
