"""Long operators in the real window: Prepare Body invoked as from its button runs modal, shows
its progress, and a real Esc key cancels it with nothing changed."""
import time

from body_state import body_state

QUICK_BAR = """
import blender_helpers as h
with override():
    obj = h.make_bar(cuts=3)
obj.rs_elastic.edge_length = 0.1
obj.rs_elastic.num_modes = 3
with override():
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
"""

# Settings that make the next Prepare take long (a finer tet mesh, 20 modes and the automatic,
# larger reduced basis and training), so there is time to see its progress and press Esc.
SLOW_SETTINGS = """
s = bpy.data.objects["Bar"].rs_elastic
s.edge_length, s.num_modes, s.basis_size, s.cubature_tets, s.training_poses = 0.04, 20, 0, 150, 80
"""

RUNNING = """
ops = [op for op in bpy.context.window_manager.windows[0].modal_operators
       if op.bl_idname in ("RS_ELASTIC_OT_prepare", "rs_elastic.prepare")]
result = [[op._job.fraction, op._job.message] for op in ops]
"""


def test_a_modal_prepare_shows_progress_and_esc_cancels_it_with_nothing_changed(gui):
    gui.run(QUICK_BAR, timeout=300)
    gui.run(SLOW_SETTINGS)
    before = body_state(gui)
    assert before["prepared"] and before["stale"] and before["cache"], before

    assert gui.run("with override():\n"
                   "    result = sorted(bpy.ops.rs_elastic.prepare('INVOKE_DEFAULT'))") == \
        ["RUNNING_MODAL"]
    # Progress: the running operator's job moves past its first stages, and the status bar says so.
    x, y = gui.point("view", 0.5, 0.5)
    deadline = time.monotonic() + 120
    while True:
        gui.mouse_move(x, y)                   # events keep the modal operator's timer going
        running = gui.run(RUNNING)
        assert running, "Prepare Body is not running as a modal operator"
        fraction, message = running[0]
        if fraction >= 0.05:
            break
        assert time.monotonic() < deadline, f"no progress in 120 s: {running}"
        time.sleep(0.3)
    gui.screenshot("progress")
    assert message != "Starting", message

    gui.key("Escape")                          # the pointer is over the viewport
    deadline = time.monotonic() + 300
    while gui.run(RUNNING):
        assert time.monotonic() < deadline, "Esc did not end Prepare Body in 300 s"
        gui.mouse_move(x, y + (time.monotonic() % 2))
        time.sleep(0.3)
    gui.settle()
    gui.screenshot("cancelled")

    reports = gui.run("result = reports()")
    assert any("Prepare Body: cancelled, nothing was changed" in line for line in reports), reports
    after = body_state(gui)
    assert {k: v for k, v in after.items() if k != "cache"} == \
        {k: v for k, v in before.items() if k != "cache"}
    # The previous preparation's cache files are all still there (new stage files may remain
    # beside them: a later Prepare reuses them).
    assert set(before["cache"]) <= set(after["cache"]), (before["cache"], after["cache"])
