"""Every RS Elastic panel draws in the real sidebar, for an unprepared, a prepared and a stale body,
without a draw error: the panels' own draw code runs in Blender's real UI layout (the Blender
tests can only draw them into a recording stand-in, since background mode never draws).

A panel closed by default (Take and Fitted Material, Shape Key Interpolation) is not drawn until
it is opened: the Take panel is opened with a click on its header, for a body with a fitted
material, so its own draw runs in Blender's real layout too."""
from sidebar import drawn_panels, open_panel
from panel_sources import PANELS
from panel_text import labels
from test_panel_fit import TAKE_AND_FIT

OPEN = {name for name, closed in PANELS.items() if not closed}

BAR = """
with override():
    obj = h.make_bar()
obj.rs_elastic.edge_length = 0.1
obj.rs_elastic.num_modes = 3
"""

STATE = """
staleness = sys.modules["bl_ext.user_default.rs_elastic.bridge.staleness"]
obj = bpy.context.active_object
result = [obj.rs_elastic.is_prepared, staleness.stale_reason(obj)]
"""


def test_every_panel_draws_for_an_unprepared_a_prepared_and_a_stale_body(gui):
    gui.run("import sys, blender_helpers as h; watch_panels()")
    gui.run(BAR)
    changes = {
        "unprepared": "",
        "prepared": "with override():\n    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}",
        "stale": "bpy.context.active_object.rs_elastic.youngs_modulus *= 2.0",
    }
    for state, change in changes.items():
        start = len(gui.log_text())
        gui.run(change, timeout=300)
        prepared, stale = gui.run(STATE)
        assert (prepared, bool(stale)) == {"unprepared": (False, False), "prepared": (True, False),
                                           "stale": (True, True)}[state], (state, stale)
        drawn = drawn_panels(gui)
        names, objects = {name for name, _ in drawn}, {obj for _, obj in drawn}
        gui.screenshot(state)
        found = gui.tracebacks(since=start)
        assert not found, f"{state} body: a panel raised while drawing:\n{found[0]}"
        assert names == OPEN, f"{state} body: not drawn: {OPEN - names}"
        assert objects == {"Bar"}


def test_the_take_panel_opened_with_a_click_draws_its_fitted_material(gui):
    gui.run("import sys, blender_helpers as h; watch_panels()")
    gui.run(TAKE_AND_FIT, timeout=300)
    assert PANELS["RS_ELASTIC_PT_take"], "the Take panel is no longer closed by default"
    start = len(gui.log_text())
    assert "RS_ELASTIC_PT_take" not in {name for name, _ in drawn_panels(gui)}
    open_panel(gui, "RS_ELASTIC_PT_take", "rs_elastic.solve_spacetime")
    drawn = drawn_panels(gui)
    gui.screenshot("take_open")
    found = gui.tracebacks(since=start)
    assert not found, f"a panel raised while drawing:\n{found[0]}"
    assert ("RS_ELASTIC_PT_take", "Bar") in drawn, drawn
    assert {name for name, _ in drawn} == OPEN | {"RS_ELASTIC_PT_take"}
    said = labels(gui, "RS_ELASTIC_PT_take")
    assert "Per mode, prepared → fitted:" in said and "Damping, 1/s" in said, said
