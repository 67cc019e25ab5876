"""Take from Animation, Fit Material and Continue: the take, the material fitted to it, and
the motion continued with it."""
import bpy

from ..bridge import take
from .body import RSElasticPanel, drawn_body, draw_progress


class RS_ELASTIC_PT_take(RSElasticPanel, bpy.types.Panel):
    bl_label = "Take and Fitted Material"
    bl_parent_id = "RS_ELASTIC_PT_body"
    bl_options = {'DEFAULT_CLOSED'}

    def draw(self, context):
        obj = drawn_body(self.layout, context)
        settings = obj.rs_elastic
        layout = self.layout
        layout.prop(settings, "take_source")
        layout.operator("rs_elastic.take_from_animation", icon='IMPORT')
        draw_progress(layout, obj, "rs_elastic.take_from_animation")
        row = layout.row(align=True)
        row.prop(settings, "fit_frame_start")
        row.prop(settings, "fit_frame_end")
        layout.operator("rs_elastic.fit_material", icon='MOD_PHYSICS')
        draw_progress(layout, obj, "rs_elastic.fit_material")
        fitted = take.fitted_material(obj)
        if fitted is None:
            layout.label(text="No fitted material yet")
            return
        layout.prop(settings, "use_fitted_material")
        draw_fitted(layout.box(), fitted)
        layout.operator("rs_elastic.continue_motion", icon='FF')


def draw_fitted(layout, fitted):
    """Per mode: the prepared and the fitted frequency [Hz] and damping [1/s]; the residual."""
    layout.label(text=f"Fit of frames {fitted.first_frame}–{fitted.last_frame}: residual "
                      f"{fitted.residual:.3g} m (worst frame {fitted.worst_frame})"
                      + ("" if fitted.converged else ", not converged"))
    layout.label(text="Mode: frequency prepared → fitted, damping prepared → fitted")
    for k, (f0, f1, d0, d1) in enumerate(zip(fitted.prepared_frequencies, fitted.frequencies,
                                             fitted.prepared_damping, fitted.damping)):
        layout.label(text=f"{k + 1}: {f0:.3f} → {f1:.3f} Hz, {d0:.3f} → {d1:.3f} /s")


CLASSES = (RS_ELASTIC_PT_take,)
