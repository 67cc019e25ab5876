"""The RS Elastic tab of the 3D viewport's sidebar, opened with real clicks."""
import time

CATEGORY = ("result = next(r for r in view3d()[1].regions if r.type == 'UI')"
            ".active_panel_category")


def open_sidebar(gui):
    """Show the 3D viewport's sidebar and pick its RS Elastic tab the way a user does, with a
    click on the tab (Python may read the active tab but not set it): the tabs stand in a
    column at the sidebar's right edge, so click down that column until it is picked."""
    gui.run("view3d()[1].spaces.active.show_region_ui = True")
    x, y, width, height = gui.rects()["sidebar"]
    for tab_y in range(y + 8, y + min(height, 600), 12):
        if gui.run(CATEGORY) == "RS Elastic":
            return
        gui.click(x + width - 12, tab_y)
    assert gui.run(CATEGORY) == "RS Elastic", "no RS Elastic tab in the sidebar"


def drawn_panels(gui, draws=2, timeout=30.0):
    """Redraw the sidebar `draws` times (panels that changed size settle on the next redraw);
    return the RS Elastic panels whose draw ran to the end, with the active object's name they
    drew for: {(idname, object name)} (ui_server.DRAWN)."""
    count = gui.run("DRAWN.clear(); view3d()[1].tag_redraw(); result = SIDEBAR_DRAWS[0]")
    deadline = time.monotonic() + timeout
    while gui.run("view3d()[1].tag_redraw(); result = SIDEBAR_DRAWS[0]") < count + draws:
        if time.monotonic() > deadline:
            raise TimeoutError(f"the sidebar did not redraw in {timeout:.0f} s")
        gui.settle(0.05)
    return {tuple(item) for item in gui.run("result = DRAWN")}
