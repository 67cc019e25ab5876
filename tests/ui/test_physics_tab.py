"""The body's physical settings in the Properties editor's Physics tab: its RS Elastic panels draw
in the real editor, without a draw error, for an unprepared and a prepared body, and they hold the
same material, pin and simulation rows as the sidebar (drawn by the same functions)."""
import time

from panel_items import RECORDER
from panel_sources import PHYSICS_PANELS

BAR = """
import blender_helpers as h
with override():
    obj = h.make_bar()
obj.rs_elastic.edge_length = 0.1
obj.rs_elastic.num_modes = 3
"""

# The window's Properties editor, on its Physics tab.
PROPERTIES = """
window = bpy.context.window_manager.windows[0]
area = next(a for a in window.screen.areas if a.type == 'PROPERTIES')
area.spaces.active.context = 'PHYSICS'
region = next(r for r in area.regions if r.type == 'WINDOW')
"""

# Each panel's items drawn with the Properties editor's context (its `object`), the Physics tab's
# and the sidebar's panels side by side.
ITEMS = PROPERTIES + RECORDER + """
with bpy.context.temp_override(window=window, screen=window.screen, area=area, region=region):
    result = panel_items(["RS_ELASTIC_PT_physics_material", "RS_ELASTIC_PT_material",
                          "RS_ELASTIC_PT_physics_simulation", "RS_ELASTIC_PT_simulate"])
"""


def _drawn_in_properties(gui, timeout=30.0):
    """Redraw the Properties editor until the Physics tab's panels have drawn; return
    {(panel, object)} of those that drew to the end."""
    x, y, w, h = gui.run(PROPERTIES + "result = [area.x, window.height - area.y - area.height, "
                                      "area.width, area.height]")
    gui.run(PROPERTIES + "DRAWN.clear(); area.tag_redraw()")
    deadline = time.monotonic() + timeout
    while True:
        drawn = {tuple(item) for item in gui.run("result = DRAWN")
                 if item[0] in PHYSICS_PANELS}
        if {name for name, _ in drawn} == set(PHYSICS_PANELS) or time.monotonic() > deadline:
            return drawn
        gui.mouse_move(x + w / 2, y + h / 2 + (time.monotonic() % 2))   # Blender redraws on events
        time.sleep(0.1)


def test_the_physics_tab_draws_the_body_settings_with_the_sidebar_rows(gui):
    assert PHYSICS_PANELS, "no Physics tab panel in panels/"
    gui.run(BAR)
    gui.run("watch_panels()")
    for state, change in {"unprepared": "",
                          "prepared": "with override():\n"
                                      "    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}"
                          }.items():
        start = len(gui.log_text())
        gui.run(change, timeout=300)
        drawn = _drawn_in_properties(gui)
        gui.screenshot(f"physics_{state}")
        found = gui.tracebacks(since=start)
        assert not found, f"{state} body: a Physics tab panel raised while drawing:\n{found[0]}"
        assert drawn == {(name, "Bar") for name in PHYSICS_PANELS}, (state, drawn)

        items = gui.run(ITEMS)
        material = items["RS_ELASTIC_PT_physics_material"]
        names = {name for kind, name, _ in material if kind == "prop"}
        assert {"youngs_modulus", "poisson_ratio", "density", "stiffness_group", "pin_group"} \
            <= names, material
        # The same rows as the sidebar's (one draw function, not a copy).
        assert material == items["RS_ELASTIC_PT_material"]
        simulation = items["RS_ELASTIC_PT_physics_simulation"]
        assert simulation == [item for item in items["RS_ELASTIC_PT_simulate"]
                              if item[0] != "operator"], (simulation, items["RS_ELASTIC_PT_simulate"])
        assert {"material_model", "integrator", "substeps"} <= \
            {name for kind, name, _ in simulation if kind == "prop"}
