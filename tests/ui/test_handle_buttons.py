"""A handle's Empty active, in the real window: the sidebar shows its body's panels, and their
buttons act on the body. A real click on Solve and Bake in the handle's panel bakes the body
(not the Empty), and the Empty stays active, where it was keyed."""
import time

from sidebar import find_button, scroll
from test_panel_words import SOLVED

SOLVE = "rs_elastic.solve_spacetime"

STATE = """
import sys
bridge = sys.modules["bl_ext.user_default.rs_elastic.bridge"]
obj = bpy.data.objects["Bar"]
empty = obj.rs_elastic.handles[0].empty
curves = bridge.animation.fcurves(empty)
result = {"active": bpy.context.active_object.name, "baked": bridge.bake.bake_frames(obj),
          "empty_keys": [[list(k.co) for k in c.keyframe_points] for c in curves],
          "residuals": [h.residual for h in obj.rs_elastic.handles]}
"""

RUNNING = ("result = [op.bl_idname for op in bpy.context.window_manager.windows[0].modal_operators"
           " if op.bl_idname in ('RS_ELASTIC_OT_solve_spacetime', 'rs_elastic.solve_spacetime')]")


def test_solve_and_bake_clicked_in_a_handles_panel_bakes_its_body(gui):
    gui.run(SOLVED, timeout=300)
    empty = gui.run("empty = obj.rs_elastic.handles[0].empty; h.make_active(empty); "
                    "result = empty.name")
    before = gui.run(STATE)
    assert before["active"] == empty and before["baked"] == [], before
    assert before["residuals"] == [-1.0], before       # not solved yet
    start = len(gui.log_text())

    try:
        gui.click(*find_button(gui, SOLVE))
    finally:
        scroll(gui, "VIEW_3D", "UI", -5)        # the sidebar back at its top, for later tests
    deadline = time.monotonic() + 120
    while gui.run(RUNNING):
        assert time.monotonic() < deadline, "Solve and Bake did not finish in 120 s"
        gui.settle(0.1)
    gui.screenshot("solved_from_the_handle")
    after = gui.run(STATE)
    reports = gui.run("result = reports()")
    assert any("'Bar': baked frames 1–8" in line for line in reports), \
        (reports, gui.log_text()[start:])
    assert after["baked"] == list(range(1, 9)), after
    assert after["residuals"][0] >= 0.0, after                # the solve's handle miss is shown
    assert after["active"] == empty, after                    # the handle stays the active object
    assert after["empty_keys"] == before["empty_keys"], after
