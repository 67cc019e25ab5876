"""The panels' layout in the real window: the rows a space-time solve and a simulation share are
drawn once, every handle option has a label, and a handle's Empty, made active, shows its
body's panels."""
from panel_items import panel_items
from panel_sources import PANELS
from panel_text import labels
from sidebar import drawn_panels
from test_panel_words import SOLVED

OPEN = {name for name, closed in PANELS.items() if not closed}
# What a solve and a simulation share: the frame range, the damping, where the bake goes and
# what to do with it.
SHARED = {("prop", "use_scene_range"), ("prop", "damping_mass"), ("prop", "damping_stiffness"),
          ("prop", "bake_to"), ("operator", "rs_elastic.keep_take"),
          ("operator", "rs_elastic.clear_bake")}


def _all_items(gui):
    return [item for items in panel_items(gui, PANELS).values() for item in items]


def test_the_rows_a_solve_and_a_simulation_share_are_drawn_once(gui):
    gui.run(SOLVED, timeout=300)
    gui.run("bpy.context.active_object.rs_elastic.use_scene_range = False")
    drawn = [(kind, name) for kind, name, _ in _all_items(gui)]
    counts = {row: drawn.count(row) for row in SHARED}
    assert counts == {row: 1 for row in SHARED}, counts
    gui.screenshot("panels")


def test_every_handle_option_has_a_label(gui):
    gui.run(SOLVED, timeout=300)
    handle_options = gui.run("result = list(bpy.context.active_object.rs_elastic.handles[0]"
                             ".bl_rna.properties.keys())")
    shown = [(name, text) for kind, name, text in _all_items(gui)
             if kind == "prop" and name in handle_options]
    assert "orientation" in {name for name, _ in shown}, shown
    unlabelled = [name for name, text in shown if not text]
    assert not unlabelled, f"drawn without a label (an icon only): {unlabelled}"


def test_a_handles_empty_active_shows_its_bodys_panels(gui):
    gui.run(SOLVED, timeout=300)
    body, empty = gui.run("""
obj = bpy.context.active_object
empty = obj.rs_elastic.handles[0].empty
h.make_active(empty)
result = [obj.name, bpy.context.active_object.name]
""")
    assert body != empty
    drawn = drawn_panels(gui)
    gui.screenshot("empty_active")
    assert {name for name, _ in drawn} == OPEN, f"not drawn: {OPEN - {n for n, _ in drawn}}"
    said = labels(gui, "RS_ELASTIC_PT_body")
    assert "Select a mesh object" not in said, said
    assert body in said and f"Handle of {body}" in said, said
    # The panels show the body's own settings: its handles, its vertex groups.
    items = panel_items(gui, ["RS_ELASTIC_PT_spacetime"])["RS_ELASTIC_PT_spacetime"]
    assert ["label", empty, empty] in items, items
