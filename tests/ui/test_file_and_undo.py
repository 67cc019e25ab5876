"""Save, reopen and undo in the real Blender: a prepared body saved and opened again is still
prepared, and ctrl+z / ctrl+shift+z (real key presses over the viewport) undo and redo the
extension's operators."""
import time

from body_state import body_state
from sidebar import drawn_panels
from test_modal import QUICK_BAR

RUNNING = ("result = [op.bl_idname for op in bpy.context.window_manager.windows[0].modal_operators"
           " if 'rs_elastic' in op.bl_idname.lower()]")


def press(gui, keys):
    """Real key presses with the pointer over the 3D viewport (where Blender sends them)."""
    gui.mouse_move(*gui.point("view", 0.4, 0.5))
    gui.key(keys)
    gui.settle()


def test_save_reopen_keeps_the_body_prepared_and_ctrl_z_undoes_its_operators(gui):
    gui.run(QUICK_BAR, timeout=300)
    path = gui.run_in + "/files/shot.blend"
    gui.run(f"with override():\n    bpy.ops.wm.save_as_mainfile(filepath={path!r})")
    saved = body_state(gui)
    assert saved["prepared"] and not saved["stale"] and saved["cache"], saved
    assert (gui.run_dir / "files" / "blendcache_shot").is_dir()

    # Reopen: a new file is loaded (the extension's memory of the body goes too).
    gui.run("""
with override():
    bpy.ops.wm.read_homefile(use_empty=True, load_ui=False)
assert "Bar" not in bpy.data.objects
""")
    gui.run(f"with override():\n    bpy.ops.wm.open_mainfile(filepath={path!r}, load_ui=False)")
    reopened = body_state(gui)
    assert reopened == saved
    gui.run("h.make_active(bpy.data.objects['Bar'])")
    assert ("RS_ELASTIC_PT_modes", "Bar") in drawn_panels(gui)
    gui.screenshot("reopened")

    # Operators run as from their buttons: 'INVOKE_DEFAULT' with an undo step (the second
    # argument; a script's call pushes none).
    # An operator, then ctrl+z: the material preset is undone, the body is current again.
    gui.run("with override():\n"
            "    assert bpy.ops.rs_elastic.apply_material_preset('INVOKE_DEFAULT', True, preset='STEEL')"
            " == {'FINISHED'}")
    steel = body_state(gui)
    assert steel["youngs"] > 1e10 and steel["stale"], steel
    press(gui, "ctrl+z")
    assert body_state(gui) == saved
    press(gui, "ctrl+shift+z")
    assert body_state(gui)["youngs"] == steel["youngs"]

    # A modal Prepare run to its end, then ctrl+z: the preparation is undone (the old keys
    # are back and the body is stale again), and redo brings the new one back.
    gui.run("with override():\n    bpy.ops.rs_elastic.prepare('INVOKE_DEFAULT', True)")
    deadline = time.monotonic() + 300
    while gui.run(RUNNING):
        assert time.monotonic() < deadline, "Prepare Body did not finish in 300 s"
        gui.settle(0.2)
    prepared = body_state(gui)
    assert prepared["prepared"] and not prepared["stale"], prepared
    assert prepared["keys"][1] != saved["keys"][1]
    gui.screenshot("prepared-steel")
    press(gui, "ctrl+z")
    undone = body_state(gui)
    assert undone["keys"] == saved["keys"] and undone["stale"], undone
    press(gui, "ctrl+shift+z")
    assert body_state(gui)["keys"] == prepared["keys"]
    gui.screenshot("redone")
