"""The long operators test_progress does not run, in the real window: Tetrahedralize and Fit
Material invoked as from their buttons run modal, draw their bar in the panel of their button
(at the job's fraction, every word fitting the sidebar), and a real Esc ends them with nothing
changed. (Fit Material's panel, closed by default, is drawn by the test with the real context,
not seen in the sidebar.)"""
from body_state import body_state
from sidebar import drawn_panels
from test_progress import (OPERATOR, QUICK_BAR, _check_bar, _operator, _wait_for_progress,
                           _wait_until_ended)

# A finer tet mesh than QUICK_BAR's (and than any other GUI test's, so the stage cache holds
# none): fTetWild runs for seconds. While the test runs, the job waits after its progress
# reached 5 % (just before fTetWild starts) until the test has looked at its bar (GATE), so Esc
# comes while fTetWild runs.
SLOW_TETS = """
import sys, threading
bpy.data.objects["Bar"].rs_elastic.edge_length = 0.035
JOB = sys.modules[bpy.types.RS_ELASTIC_OT_tetrahedralize.__module__].jobs.Job
JOB_STEP = JOB.step
GATE = threading.Event()
def gated_step(self, *args, **kwargs):
    JOB_STEP(self, *args, **kwargs)
    if (self.idname == "rs_elastic.tetrahedralize" and self.fraction >= 0.05
            and threading.current_thread() is self._thread):
        GATE.wait(60.0)
JOB.step = gated_step
"""
RESTORE_TETS = "GATE.set()\nJOB.step = JOB_STEP"


def test_tetrahedralize_draws_its_bar_in_the_tet_mesh_panel_and_esc_cancels_it(gui):
    gui.run(QUICK_BAR, timeout=300)
    gui.run(SLOW_TETS)
    try:
        _tetrahedralize_and_cancel(gui)
    finally:
        gui.run(RESTORE_TETS)


def _tetrahedralize_and_cancel(gui):
    before = body_state(gui)
    gui.run("watch_panels()")
    assert gui.run("with override():\n    result = sorted("
                   "bpy.ops.rs_elastic.tetrahedralize('INVOKE_DEFAULT'))") == ["RUNNING_MODAL"]
    *progress, cut = _wait_for_progress(gui, "rs_elastic.tetrahedralize",
                                        "RS_ELASTIC_PT_tet_mesh", 0.05, measure=True)
    _check_bar(*progress)
    assert "fTetWild" in progress[2][0][1] or progress[2][0][1] == "5 %", progress
    assert ("RS_ELASTIC_PT_tet_mesh", "Bar") in drawn_panels(gui)
    gui.screenshot("progress")
    assert cut == [], cut
    _look_around_while_it_runs(gui, "rs_elastic.tetrahedralize")
    gui.run("GATE.set()")
    gui.key("Escape")
    _wait_until_ended(gui, "rs_elastic.tetrahedralize")
    reports = gui.run("result = reports()")
    assert any("Tetrahedralize: cancelled, nothing was changed" in line for line in reports), \
        reports[-5:]
    after = body_state(gui)
    assert {k: v for k, v in after.items() if k != "cache"} == \
        {k: v for k, v in before.items() if k != "cache"}


VIEW_DISTANCE = "result = view3d()[1].spaces.active.region_3d.view_distance"
SELECTED = "result = sorted(o.name for o in bpy.context.selected_objects)"


def _look_around_while_it_runs(gui, idname):
    """While the job runs, the wheel zooms the viewport (looking around changes nothing), and a
    click on empty space, which would deselect the body, does not reach the scene."""
    running = _operator(idname) + OPERATOR + "result = len(ops)"
    selected, distance = gui.run(SELECTED), gui.run(VIEW_DISTANCE)
    x, y = gui.point("view", 0.15, 0.8)
    for _ in range(3):
        gui.click(x, y, button=5)               # the wheel, down: zoom out
    gui.settle(0.5, at=(x, y))
    zoomed = gui.run(VIEW_DISTANCE)
    assert zoomed > 1.2 * distance, (distance, zoomed)
    gui.click(x, y)
    gui.settle(0.5, at=(x, y))
    assert gui.run(SELECTED) == selected == ["Bar"], selected
    assert gui.run(running) == 1, f"{idname} ended before Esc"
    print(f"\nWhile {idname} ran: the wheel zoomed the view from {distance:.2f} to "
          f"{zoomed:.2f}; a click on empty space left {selected} selected")


# A take of the bar bending up and down: a source copy of it whose shape key is keyed over 24
# frames (the bar "Bar" must exist).
BENDING_SOURCE = """
import numpy as np
obj = bpy.data.objects["Bar"]
source = obj.copy()
source.data = obj.data.copy()
source.name = "Source"
bpy.context.scene.collection.objects.link(source)
source.shape_key_add(name="Basis")
bend = source.shape_key_add(name="Bend")
co = np.empty(3 * len(bend.data))
bend.data.foreach_get("co", co)
co = co.reshape(-1, 3)
co[:, 2] += 0.15 * (co[:, 0] / 4.0) ** 2
bend.data.foreach_set("co", co.ravel())
for frame in range(1, 25, 3):
    bend.value = float(np.sin(frame / 24.0 * 2.0 * np.pi))
    bend.keyframe_insert("value", frame=frame)
bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 24
obj.rs_elastic.take_source = source
"""
# That take read with Take from Animation. While the test runs, each progress step of a Fit
# Material job sleeps STEP seconds after it is taken, and the first one waits until the test
# has seen the bar (GATE): the fit of this small take is otherwise over in a moment.
STEP = 0.3
TAKE_AND_SLOW_FIT = BENDING_SOURCE + f"""
import sys, threading, time
with override():
    h.make_active(obj)
    assert bpy.ops.rs_elastic.take_from_animation() == {{'FINISHED'}}
JOB = sys.modules[bpy.types.RS_ELASTIC_OT_fit_material.__module__].jobs.Job
JOB_STEP = JOB.step
GATE = threading.Event()
def slowed_step(self, *args, **kwargs):
    JOB_STEP(self, *args, **kwargs)
    if self.idname == "rs_elastic.fit_material" and threading.current_thread() is self._thread:
        if not GATE.is_set():
            GATE.wait(60.0)
        time.sleep({STEP})
JOB.step = slowed_step
"""
RESTORE_STEP = "GATE.set()\nJOB.step = JOB_STEP"

FIT_STATE = """
obj = bpy.data.objects["Bar"]
result = {"properties": sorted(obj.keys()), "use_fitted": obj.rs_elastic.use_fitted_material,
          "use_take": obj.rs_elastic.use_take}
"""


def test_fit_material_draws_its_bar_in_the_take_panel_and_esc_cancels_it(gui):
    gui.run(QUICK_BAR, timeout=300)
    gui.run(TAKE_AND_SLOW_FIT, timeout=120)
    try:
        before, before_fit = body_state(gui), gui.run(FIT_STATE)
        assert before_fit["use_take"], before_fit
        gui.run("watch_panels()")
        assert gui.run("with override():\n    result = sorted("
                       "bpy.ops.rs_elastic.fit_material('INVOKE_DEFAULT'))") == ["RUNNING_MODAL"]
        *progress, cut = _wait_for_progress(gui, "rs_elastic.fit_material",
                                            "RS_ELASTIC_PT_take", 0.01, measure=True)
        _check_bar(*progress)
        assert "reading the take's frame" in progress[2][0][1] or \
            progress[2][0][1].endswith(" %"), progress
        # The Take panel is closed by default, and the tests cannot open it (test_panels): its
        # draw is the recorded one above, with the real context.
        gui.screenshot("progress")
        assert cut == [], cut
        gui.run("GATE.set()")
        gui.key("Escape")
        _wait_until_ended(gui, "rs_elastic.fit_material")
        reports = gui.run("result = reports()")
        assert any("Fit Material: cancelled, nothing was changed" in line
                   for line in reports), reports
        assert not any(line.startswith("Fitted the material") for line in reports), reports
        after = body_state(gui)
        assert {k: v for k, v in after.items() if k != "cache"} == \
            {k: v for k, v in before.items() if k != "cache"}
        assert gui.run(FIT_STATE) == before_fit
    finally:
        gui.run(RESTORE_STEP)
