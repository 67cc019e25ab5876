"""Space-time editing: handles, the solve and its words (the bake's rows are in the Bake panel)."""
import bpy

from ..bridge import live, spacetime_inputs
from .body import RSElasticPanel, drawn_body, draw_lines, draw_progress


class RS_ELASTIC_UL_handles(bpy.types.UIList):
    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index):
        empty = item.empty
        deleted = empty is None or context.scene.objects.get(empty.name) is None
        # The Empty and its residual; the vertex group and the options are in the box below.
        row = layout.row(align=True)
        row.label(text=empty.name if empty is not None else "(deleted)",
                  icon='ERROR' if deleted else 'EMPTY_AXIS')
        if item.residual >= 0.0:
            row.label(text=f"{item.residual:.2g} m")


class RS_ELASTIC_PT_spacetime(RSElasticPanel, bpy.types.Panel):
    bl_label = "Space-Time Editing"
    bl_parent_id = "RS_ELASTIC_PT_body"

    def draw(self, context):
        obj = drawn_body(self.layout, context)
        settings = obj.rs_elastic
        layout = self.layout
        row = layout.row()
        row.template_list("RS_ELASTIC_UL_handles", "", settings, "handles", settings,
                          "active_handle", rows=3)
        col = row.column(align=True)
        col.operator("rs_elastic.add_handle", icon='ADD', text="")
        col.operator("rs_elastic.remove_handle", icon='REMOVE', text="")
        if 0 <= settings.active_handle < len(settings.handles):
            handle = settings.handles[settings.active_handle]
            box = layout.box()
            box.prop(handle, "empty")
            box.prop_search(handle, "vertex_group", obj, "vertex_groups", text="Group")
            box.prop(handle, "orientation", icon='ORIENTATION_GIMBAL')
            box.prop(handle, "follow")
            box.prop(handle, "weight")

        col = layout.column(align=True)     # 'Name: value' fields: the names fit the sidebar
        col.prop(settings, "tightness")
        col.prop(settings, "iterations")
        layout.prop(settings, "optimize_material")
        if settings.optimize_material:
            layout.prop(settings, "material_freedom")
        layout.prop(settings, "use_take")
        if settings.use_take:
            layout.prop(settings, "take_weight")
        row = layout.row(align=True)
        row.prop(settings, "live", toggle=True, icon='REC')
        row.operator("rs_elastic.solve_spacetime", icon='PLAY')
        draw_progress(layout, obj, "rs_elastic.solve_spacetime")
        live_status = live.status(obj) if settings.live else None
        if live_status is not None:
            layout.label(text=live_status, icon='PREVIEW_RANGE')
        # The solve's words only while its bake is in place: a simulation's bake or an undo
        # takes its objectives away (they live on the object, undone with the bake).
        status = (spacetime_inputs.LAST_STATUS.get(obj.name) if len(settings.solve_history)
                  else None)
        if status is not None:
            converged, text = status
            for i, line in enumerate(text.split("; ")):
                draw_lines(layout, line, ('CHECKMARK' if converged else 'ERROR') if i == 0
                           else 'BLANK1')
        if len(settings.solve_history):
            draw_objectives(layout, settings.solve_history)


def draw_objectives(layout, history):
    """The solve's objective, first and last, with every step's value in a sub-panel closed
    by default: after the first steps they mostly agree to six digits, and a list of twenty
    equal numbers hid the rest of the panel."""
    first, last = history[0].value, history[-1].value
    layout.label(text=f"Objective {first:.3g} to {last:.3g}")
    header, body = layout.panel("rs_elastic_objective_steps", default_closed=True)
    header.label(text=f"{len(history) - 1} Steps")
    if body is not None:
        col = body.column(align=True)
        for i, item in enumerate(history):
            col.label(text=f"{i:3d}   {item.value:.6g}")


CLASSES = (RS_ELASTIC_UL_handles, RS_ELASTIC_PT_spacetime)
