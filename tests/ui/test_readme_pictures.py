"""The README's pictures, taken in the real window by this test and written into docs/images/
on every run, so that the README shows the panels as they are: the sidebar's panels for a
prepared and solved body (top and bottom of the RS Elastic tab), the Physics tab, and a handle
edit (the handle's Empty active at a keyed frame, the body bent to it by the solve's bake, the
panels showing its body). Each picture is cropped to the part an artist looks at and kept
small; the test checks that each shows what it should (the panels drew for the body, the body
and the handle are in the picture, the picture is not blank) and that the README shows it."""
import re

from blender_gui import PROJECT
from sidebar import drawn_panels, scroll
from test_panel_words import SOLVE, SOLVED

PICTURES = PROJECT / "docs" / "images"
README = PROJECT / "README.md"
MAX_BYTES = 200_000

# The window's Properties editor on its Physics tab: its rectangle in window pixels.
PROPERTIES = """
window = bpy.context.window_manager.windows[0]
area = next(a for a in window.screen.areas if a.type == 'PROPERTIES')
area.spaces.active.context = 'PHYSICS'
result = [area.x, window.height - area.y - area.height, area.width, area.height]
"""


def _picture(gui, name, rect):
    """Crop window rectangle `rect` (x, y, w, h) of the screen into docs/images/<name>.png
    (a 256-colour PNG: the UI's flat colours need no more); returns its (width, height,
    standard deviation of its grey levels)."""
    x, y, w, h = [round(v) for v in rect]
    sx, sy = gui.screen_xy(x, y)
    inside = f"{gui.run_in}/files/{name}.png"
    gui.x_client("import", "-window", "root", "-crop", f"{w}x{h}+{sx}+{sy}", "+repage",
                 "-colors", "256", "-define", "png:compression-level=9", f"png8:{inside}")
    PICTURES.mkdir(parents=True, exist_ok=True)
    path = PICTURES / f"{name}.png"
    path.write_bytes((gui.run_dir / "files" / f"{name}.png").read_bytes())
    out = gui.x_client("identify", "-format", "%w %h %[fx:standard_deviation]", inside,
                       text=True).stdout.split()
    size = path.stat().st_size
    assert size < MAX_BYTES, f"{path.name} is {size} bytes"
    return int(out[0]), int(out[1]), float(out[2])


def _check(gui, name, rect, panels, obj="Bar"):
    """Draw the sidebar, check `panels` drew for `obj`, and take picture `name` of `rect`."""
    drawn = drawn_panels(gui)
    missing = {(panel, obj) for panel in panels} - drawn
    assert not missing, f"{name}: not drawn: {missing}"
    width, height, spread = _picture(gui, name, rect)
    assert (width, height) == (round(rect[2]), round(rect[3])), (name, width, height, rect)
    assert spread > 0.02, f"{name} is blank (grey-level spread {spread:.3f})"
    return name


def test_the_readme_pictures_show_the_panels_as_they_are(gui):
    gui.run(SOLVED, timeout=300)
    gui.run(SOLVE, timeout=300)
    gui.run("bpy.context.scene.frame_set(8); watch_panels()")
    taken = []
    sidebar = gui.rects()["sidebar"]
    try:
        # The sidebar for the prepared, solved body: its top, then scrolled to its end.
        scroll(gui, "VIEW_3D", "UI", -5)
        taken.append(_check(gui, "sidebar_body", sidebar,
                            ["RS_ELASTIC_PT_body", "RS_ELASTIC_PT_tet_mesh"]))
        scroll(gui, "VIEW_3D", "UI", 5)
        taken.append(_check(gui, "sidebar_spacetime_simulation", sidebar,
                            ["RS_ELASTIC_PT_spacetime", "RS_ELASTIC_PT_simulate"]))

        # The Physics tab, scrolled to its RS Elastic panels.
        properties = gui.run(PROPERTIES)
        scroll(gui, "PROPERTIES", "WINDOW", 5)
        taken.append(_check(gui, "physics_tab", properties, []))
        scroll(gui, "PROPERTIES", "WINDOW", -5)

        # A handle edit: the handle's Empty active at its key, the view framed on the body.
        gui.run("""
obj = bpy.data.objects["Bar"]
empty = obj.rs_elastic.handles[0].empty
h.make_active(empty)
obj.select_set(True)
with override():
    bpy.ops.view3d.view_selected()
    bpy.ops.view3d.zoom(delta=-1)
empty.select_set(True)
obj.select_set(False)
""")
        view = gui.rects()["view"]
        scroll(gui, "VIEW_3D", "UI", 5, pixels=700)   # the sidebar at the handles and the solve
        gui.settle(0.5)
        x, y, w, h = sidebar
        edit = [max(view[0], x + w - 1100), view[1], min(1100, x + w - view[0]), view[3]]
        handle = gui.run("result = to_screen(empty.matrix_world.translation)")
        middle = gui.run("import mathutils\n"
                         "result = to_screen(obj.matrix_world @ mathutils.Vector((2, 0.5, 0.5)))")
        for point in (handle, middle):
            assert point and edit[0] < point[0] < x and edit[1] < point[1] < edit[1] + edit[3], \
                (point, edit)
        taken.append(_check(gui, "handle_edit", edit, ["RS_ELASTIC_PT_body",
                                                       "RS_ELASTIC_PT_spacetime"],
                            obj=gui.run("result = empty.name")))
    finally:
        scroll(gui, "VIEW_3D", "UI", -5)
    # The README shows every picture the tier takes.
    shown = set(re.findall(r"!\[[^\]]*\]\(docs/images/([\w.-]+)\.png\)", README.read_text()))
    assert set(taken) <= shown, f"not in the README: {set(taken) - shown}"
