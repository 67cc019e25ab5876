"""The zip installs through Blender's own installer into the real Blender and its panels register
and show in the sidebar's RS Elastic tab."""
from panel_sources import PANELS, PHYSICS_PANELS


def test_the_zip_installs_enables_and_registers_its_panels(gui):
    assert gui.install_result == ['FINISHED'], gui.install_result
    found = gui.tracebacks(since=0)[:1]
    assert not found, f"the install printed a traceback:\n{found[0]}"
    state = gui.run("""
import addon_utils, importlib, sys
module = "bl_ext.user_default.rs_elastic"
ext = importlib.import_module(module)
panels = {name: getattr(bpy.types, name) for name in dir(bpy.types)
          if name.startswith("RS_ELASTIC_PT_")}
result = {
    "enabled": module in bpy.context.preferences.addons,
    "loaded": addon_utils.check(module),
    "file": ext.__file__,
    "operators": sorted(dir(bpy.ops.rs_elastic)),
    "panels": {name: [cls.bl_space_type, cls.bl_region_type, getattr(cls, "bl_category", ""),
                      getattr(cls, "bl_parent_id", "")] for name, cls in panels.items()},
    "scipy": sys.modules["scipy"].__version__ if "scipy" in sys.modules else None,
}
""")
    assert state["enabled"] and state["loaded"] == [True, True], state
    # Installed into the throw-away user folder's extension repository, not loaded from elsewhere.
    assert state["file"].startswith(gui.run_in + "/user/extensions/user_default/rs_elastic/")
    assert {"prepare", "simulate", "solve_spacetime", "add_handle"} <= set(state["operators"])
    assert set(state["panels"]) == set(PANELS) | set(PHYSICS_PANELS), state["panels"]
    for name in PHYSICS_PANELS:
        space, region, _, parent = state["panels"].pop(name)
        assert (space, region) == ('PROPERTIES', 'WINDOW'), name
        assert parent == ("" if name == "RS_ELASTIC_PT_physics" else "RS_ELASTIC_PT_physics")
    for name, (space, region, category, parent) in state["panels"].items():
        assert (space, region, category) == ('VIEW_3D', 'UI', "RS Elastic"), name
        assert parent == ("" if name == "RS_ELASTIC_PT_body" else "RS_ELASTIC_PT_body"), name

    # The sidebar shows the tab: its parent panel draws there (and so the others can).
    drawn = gui.run("""
watch_panels()
DRAWN.clear()
view3d()[1].tag_redraw()
""")
    gui.mouse_move(*gui.point("view", 0.5, 0.5))
    gui.wait_for("any(name == 'RS_ELASTIC_PT_body' for name, _ in DRAWN)", timeout=30)
    assert "sidebar" in gui.rects()
    gui.screenshot("installed")
