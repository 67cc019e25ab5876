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
        layout.label(text="Take Source:")      # beside its field it showed as "Take So…"
        layout.prop(settings, "take_source", text="")
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


FACT_SPLIT = 0.4     # width of a fact's name; its value takes the rest
MODE_SPLIT = 0.14    # width of the mode number; frequency and damping share the rest


def draw_fitted(layout, fitted):
    """The fit's frames and residual [m], then per mode the prepared and the fitted frequency
    [Hz] and damping [1/s], in columns narrow enough for the sidebar at its default width."""
    for name, value in (("Frames", f"{fitted.first_frame}–{fitted.last_frame}"),
                        ("Residual", f"{fitted.residual:.3g} m"),
                        ("Worst frame", f"{fitted.worst_frame}")):
        _columns(layout, FACT_SPLIT, name, value)
    if not fitted.converged:
        layout.label(text="The fit did not converge", icon='ERROR')
    layout.label(text="Per mode, prepared → fitted:")
    _columns(layout, MODE_SPLIT, "", "Frequency, Hz", "Damping, 1/s")
    for k, (f0, f1, d0, d1) in enumerate(zip(fitted.prepared_frequencies, fitted.frequencies,
                                             fitted.prepared_damping, fitted.damping)):
        _columns(layout, MODE_SPLIT, f"{k + 1}", f"{_short(f0)} → {_short(f1)}",
                 f"{_short(d0)} → {_short(d1)}")


def _columns(layout, factor, *texts):
    """One row of labels: the first ``factor`` of the width, the others share the rest (the
    same split on every row, so the columns line up)."""
    split = layout.split(factor=factor)
    for text in texts:
        split.label(text=text)


def _short(value):
    """Three significant digits, whole numbers from 100 up (1234, not 1.23e+03)."""
    return f"{value:.0f}" if abs(value) >= 100.0 else f"{value:.3g}"


CLASSES = (RS_ELASTIC_PT_take,)
