"""At the sidebar's default width every label every panel draws fits, for an unprepared, a
prepared and solved, and a stale body, with a handle's Empty active, and for a body with a take
and a material fitted to it (see panel_fit for how a label is measured)."""
from panel_fit import cut_labels
from panel_text import labels
from panel_sources import PANELS
from test_panel_words import SOLVE, SOLVED
from test_progress_tets_and_fit import BENDING_SOURCE

BAR = """
import blender_helpers as h
with override():
    obj = h.make_bar(cuts=3)
obj.rs_elastic.edge_length = 0.1
obj.rs_elastic.num_modes = 3
"""
# Every optional row shown: a non-linear material, collisions, the preview, Live.
EVERYTHING_ON = """
s = bpy.context.active_object.rs_elastic
s.material_model, s.use_collisions, s.use_take, s.optimize_material = 'FUNG', True, True, True
s.use_scene_range = False
"""
# The bar prepared, a take of it bending (BENDING_SOURCE) and the material fitted to it: the
# Take panel's table of prepared and fitted values.
TAKE_AND_FIT = BAR + """
with override():
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
""" + BENDING_SOURCE + """
with override():
    h.make_active(obj)
    assert bpy.ops.rs_elastic.take_from_animation() == {'FINISHED'}
    assert bpy.ops.rs_elastic.fit_material() == {'FINISHED'}
"""
DEFAULT_WIDTH = 291            # Blender 4.3's sidebar at ui_scale 1.04 (this window's)


def _check(gui, state):
    width = gui.run("_, a, _ = view3d(); result = next(r for r in a.regions "
                    "if r.type == 'UI').width")
    assert width == DEFAULT_WIDTH, f"the sidebar is {width} px wide, not Blender's default"
    cut = {panel: texts for panel, texts in cut_labels(gui, PANELS).items() if texts}
    gui.screenshot(state)
    return {state: cut} if cut else {}


def test_every_label_fits_at_the_default_sidebar_width(gui):
    gui.run(BAR)
    cut = _check(gui, "unprepared")
    gui.run("with override():\n    bpy.ops.wm.read_homefile(use_empty=True, load_ui=False)")
    gui.run(SOLVED, timeout=300)
    gui.run(SOLVE, timeout=300)
    gui.run(EVERYTHING_ON)
    cut |= _check(gui, "prepared")
    gui.run("bpy.context.active_object.rs_elastic.youngs_modulus *= 2.0")
    cut |= _check(gui, "stale")
    gui.run("h.make_active(bpy.context.active_object.rs_elastic.handles[0].empty)")
    cut |= _check(gui, "handle's Empty active")
    gui.run("with override():\n    bpy.ops.wm.read_homefile(use_empty=True, load_ui=False)")
    gui.run(TAKE_AND_FIT, timeout=300)
    said = labels(gui, "RS_ELASTIC_PT_take")
    assert any("→" in line for line in said), said              # the fitted table is drawn
    cut |= _check(gui, "take and fitted material")
    assert not cut, f"labels cut at the default sidebar width: {cut}"
