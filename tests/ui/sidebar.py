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


COPY_COMMAND = """
try:
    with override('UI'):
        bpy.ops.ui.copy_python_command_button()
    result = bpy.context.window_manager.clipboard
except RuntimeError:            # no operator button under the pointer
    result = None
"""


def find_button(gui, idname, fx=0.75, step=10):
    """Window pixel (x, y) of operator `idname`'s button in the sidebar, found the way a user
    sees what a button does: the sidebar is scrolled to its end, then the pointer
    goes up the column at fraction `fx` of its width and, at each stop, Blender's own Copy Python
    Command says which operator button is under it (a button lights up under the pointer)."""
    x, y, width, height = gui.rects()["sidebar"]
    scroll(gui, "VIEW_3D", "UI", 5)                           # to the end
    gui.settle(0.1, at=(x + fx * width, y + height / 2))
    for button_y in range(y + height - step, y, -step):
        gui.mouse_move(x + fx * width, button_y)
        if gui.run(COPY_COMMAND) == f"bpy.ops.{idname}()":
            return x + fx * width, button_y
    raise AssertionError(f"no {idname} button in the sidebar")


SCROLL = """
window = bpy.context.window_manager.windows[0]
area = max((a for a in window.screen.areas if a.type == {area!r}), key=lambda a: a.width * a.height)
region = next(r for r in area.regions if r.type == {region!r})
with bpy.context.temp_override(window=window, screen=window.screen, area=area, region=region):
    for _ in range({times}):
        if {pages} > 0:
            bpy.ops.view2d.scroll_down(page=True)
        elif {pages} < 0:
            bpy.ops.view2d.scroll_up(page=True)
    if {pixels}:
        bpy.ops.view2d.scroll_up(deltay={pixels})
"""


def scroll(gui, area, region, pages, pixels=0):
    """Scroll a panel region (the sidebar: VIEW_3D, UI; the Properties editor: PROPERTIES,
    WINDOW) by whole `pages` (down for pages > 0; it stops at either end) with Blender's own
    View2D scrolling (Page Down / Page Up), then `pixels` up."""
    gui.run(SCROLL.format(area=area, region=region, times=abs(pages), pages=pages,
                          pixels=int(pixels)))


def open_panel(gui, idname, below, fx=0.3, reach=80, step=4):
    """Open the closed sub-panel `idname` with a click on its header, the way a user does. Its
    header stands below the button of operator `below` (the last button of the panel drawn
    before it): the pointer goes down from that button `step` px at a time, clicking until the
    panel draws (a click between two panels changes nothing; the first header below the
    button is the panel's). Returns the window pixel clicked."""
    _, y = find_button(gui, below)
    left, _, width, _ = gui.rects()["sidebar"]
    x = left + fx * width
    for header_y in range(int(y) + step, int(y) + reach, step):
        gui.click(x, header_y)
        if any(name == idname for name, _ in drawn_panels(gui)):
            return x, header_y
    raise AssertionError(f"no header of {idname} under the {below} button")
