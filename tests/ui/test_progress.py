"""Long operators in the real window: while Prepare Body or Simulate and Bake runs modal, its panel
draws a progress bar (Blender's `layout.progress`) at the job's fraction, with its words fitting
the sidebar (a slow simulation's note under the bar), and a real Esc key ends Simulate and Bake
within a substep's work, with nothing changed."""
import time

from body_state import body_state
from panel_fit import MEASURER, cut_labels
from panel_items import RECORDER
from sidebar import drawn_panels, scroll

QUICK_BAR = """
import sys, threading, time, blender_helpers as h
with override():
    obj = h.make_bar(cuts=3)
obj.rs_elastic.edge_length = 0.1
obj.rs_elastic.num_modes = 3
with override():
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
"""

# A finer tet mesh, more modes and a larger training than QUICK_BAR: Prepare runs long enough
# to look at its progress.
SLOW_PREPARE = """
s = bpy.data.objects["Bar"].rs_elastic
s.edge_length, s.num_modes, s.basis_size, s.cubature_tets, s.training_poses = 0.04, 20, 0, 150, 80
"""

# Many substeps per frame: each frame takes long enough that stopping only between frames shows.
SLOW_SIMULATION = """
s = bpy.data.objects["Bar"].rs_elastic
s.material_model, s.substeps = 'LINEAR', 1000
bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 200
"""

OPERATOR = """
ops = [op for op in bpy.context.window_manager.windows[0].modal_operators
       if op.bl_idname in OPERATOR_NAMES]
"""

# The panel's draw code, recorded with the real context while the job runs; the job's fraction
# read just before and just after the draw bounds the fraction the bar must show.
PANEL_PROGRESS = RECORDER + OPERATOR + """
job = ops[0]._job if ops else None
before = job.fraction if job else None
items = panel_items([PANEL])[PANEL]
result = [before, job.fraction if job else None, [i for i in items if i[0] == "progress"]]
"""


def _operator(idname, panel=None):
    """Code that sets OPERATOR_NAMES (how modal_operators may name operator `idname`) and PANEL."""
    name = idname.split(".")[1]
    return f"OPERATOR_NAMES = ({f'RS_ELASTIC_OT_{name}'!r}, {idname!r})\nPANEL = {panel!r}\n"


def _wait_for_progress(gui, idname, panel, least, timeout=180, measure=False):
    """Poll until the running job is past `least`; return (before, after, progress items) of
    its panel's draw then, and with `measure` the panel's texts that do not fit the sidebar,
    measured in the same call (``panel_fit``)."""
    code = _operator(idname, panel) + PANEL_PROGRESS
    if measure:
        code = MEASURER + code + "result.append(cut_labels([PANEL])[PANEL])\n"
    x, y = gui.point("view", 0.5, 0.5)
    deadline = time.monotonic() + timeout
    while True:
        gui.mouse_move(x, y + (time.monotonic() % 2))   # events keep the modal timer going
        before, after, bars, *cut = gui.run(code)
        assert before is not None, f"{idname} is not running as a modal operator"
        if before >= least:
            return (before, after, bars, *cut)
        assert time.monotonic() < deadline, f"{idname}: no progress in {timeout} s"
        time.sleep(0.2)


def _check_bar(before, after, bars):
    assert len(bars) == 1, f"the panel draws no progress bar while the job runs: {bars}"
    _, text, factor = bars[0]
    assert before <= factor <= after, (before, factor, after)
    percent = f"{100 * factor:.0f} %"      # a message too long for the bar goes under it
    assert text == percent or text.endswith(f"({percent})"), text


def _wait_until_ended(gui, idname, timeout=300):
    deadline = time.monotonic() + timeout
    code = _operator(idname) + OPERATOR + "result = len(ops)"
    while gui.run(code):
        assert time.monotonic() < deadline, f"Esc did not end {idname} in {timeout} s"
        gui.settle(0.1)


def test_a_modal_prepare_draws_a_progress_bar_at_its_fraction(gui):
    gui.run(QUICK_BAR, timeout=300)
    gui.run(SLOW_PREPARE)
    gui.run("watch_panels()")
    assert gui.run("with override():\n"
                   "    result = sorted(bpy.ops.rs_elastic.prepare('INVOKE_DEFAULT'))") == \
        ["RUNNING_MODAL"]
    # The bar at the job's fraction, and every word of the panel fits the sidebar (fTetWild's
    # estimate, the first message, is too long for the bar: it goes under it).
    *progress, cut = _wait_for_progress(gui, "rs_elastic.prepare", "RS_ELASTIC_PT_modes", 0.05,
                                        measure=True)
    _check_bar(*progress)
    # The real sidebar draws the Modes panel with the bar (Blender's own layout.progress).
    assert ("RS_ELASTIC_PT_modes", "Bar") in drawn_panels(gui)
    gui.screenshot("progress")
    assert cut == [], cut
    gui.key("Escape")
    _wait_until_ended(gui, "rs_elastic.prepare")
    # Once it ended, no bar.
    bars = gui.run(RECORDER + "result = panel_items(['RS_ELASTIC_PT_modes'])"
                   "['RS_ELASTIC_PT_modes']")
    assert not [item for item in bars if item[0] == "progress"], bars


# Inside Blender, on the running simulation: the worker's frames and substeps timed (wrapped on
# the instance; the worker looks them up there), and when the operator heard Esc (the job's
# cancel) and ended (its cleanup), wrapped on the job and the operator. No polling timer: one
# would compete with the worker for Python's lock and slow down the very thing measured.
WATCH = OPERATOR + """
operator, job = ops[0], ops[0]._job
sim = operator._inputs.simulation
TIMES = {"frames": [], "substeps": [], "cancel": [], "cleanup": []}
def timed(function, key):
    def wrapper(*args, **kwargs):
        start = time.monotonic()
        try:
            return function(*args, **kwargs)
        finally:
            TIMES[key].append([start, time.monotonic() - start])
    return wrapper
sim.step = timed(sim.step, "frames")
sim._checked_step = timed(sim._checked_step, "substeps")
job.cancel = timed(job.cancel, "cancel")
operator._cleanup = timed(operator._cleanup, "cleanup")
"""


def test_esc_stops_a_simulation_within_a_substep_with_nothing_changed(gui):
    gui.run(QUICK_BAR, timeout=300)
    gui.run(SLOW_SIMULATION)
    before = body_state(gui)
    before_keys = gui.run("o = bpy.data.objects['Bar']; result = [o.data.shape_keys is None, "
                          "[m.name for m in o.modifiers]]")
    gui.run("watch_panels()")
    assert gui.run("with override():\n"
                   "    result = sorted(bpy.ops.rs_elastic.simulate('INVOKE_DEFAULT'))") == \
        ["RUNNING_MODAL"]
    gui.run(_operator("rs_elastic.simulate") + WATCH)
    _check_bar(*_wait_for_progress(gui, "rs_elastic.simulate", "RS_ELASTIC_PT_simulate", 0.0))

    # Press Esc just after a frame started: stopping only between frames would wait for all of it.
    gui.wait_for("len(TIMES['frames']) >= 2", timeout=300)
    done = gui.run("result = len(TIMES['frames'])")
    gui.wait_for(f"len(TIMES['frames']) > {done}", timeout=120, interval=0.005)
    pressed = time.monotonic()
    gui.key("Escape")
    delivered = time.monotonic() - pressed      # the key has reached X by the time xdotool returns
    _wait_until_ended(gui, "rs_elastic.simulate")
    times = gui.run("result = TIMES")
    assert times["cleanup"] and times["cleanup"][0][0] > pressed, \
        "the solve ended before Esc was pressed: make its iterations longer"
    assert len(times["cancel"]) == 1 and len(times["cleanup"]) == 1, times
    latency = sum(times["cleanup"][0]) - pressed
    heard = times["cancel"][0][0] - pressed               # the modal operator got the Esc
    stopped = sum(times["frames"][-1]) - pressed          # the worker's interrupted frame ended
    frame = max(duration for _, duration in times["frames"])
    substep = max(duration for _, duration in times["substeps"])
    poll = gui.run("result = sys.modules['bl_ext.user_default.rs_elastic.bridge.jobs'].POLL")
    # Bound: the key's delivery, then at most the substep running when the flag was set and one
    # more (the check is before each), then one modal timer period to notice the ended worker.
    bound = delivered + 2 * substep + poll
    print(f"\nEsc latency {1000 * latency:.0f} ms: heard after {1000 * heard:.0f} ms, worker "
          f"stopped after {1000 * stopped:.0f} ms (key delivery {1000 * delivered:.0f} ms; longest "
          f"frame {1000 * frame:.0f} ms, longest substep {1000 * substep:.1f} ms over "
          f"{len(times['substeps'])} substeps; bound {1000 * bound:.0f} ms)")
    assert frame > 2 * bound, f"frames too short ({frame:.3f} s) to tell a substep's stop"
    assert latency < bound, f"Esc took {latency:.3f} s to end the simulation (bound {bound:.3f} s)"

    reports = gui.run("result = reports()")
    assert any("Simulate and Bake: cancelled, nothing was changed" in line
               for line in reports), reports
    after = body_state(gui)
    assert {k: v for k, v in after.items() if k != "cache"} == \
        {k: v for k, v in before.items() if k != "cache"}
    assert gui.run("o = bpy.data.objects['Bar']; result = [o.data.shape_keys is None, "
                   "[m.name for m in o.modifiers]]") == before_keys


# Every det F check of a step longer than the shortest fails (Simulation._inverted_tets wrapped
# in the class; the shortest are checked for real), so every frame's steps are cut to the
# shortest: each frame is slow. Each check also sleeps a little, so the run lasts long enough
# to look at (about 30 checks a frame).
FORCED_SLOW = """
DYNAMICS = sys.modules["bl_ext.user_default.rs_elastic.solver.dynamics"]
REAL_CHECK = DYNAMICS.Simulation._inverted_tets
def failing_above_the_shortest(sim):
    time.sleep(0.002)
    count, smallest, finite, ratios = REAL_CHECK(sim)
    if sim.state.dt > 1.5 * sim.h / sim.substeps / 2 ** DYNAMICS.MAX_STEP_SPLITS:
        return 1, -1.0, True, ratios
    return count, smallest, finite, ratios
DYNAMICS.Simulation._inverted_tets = failing_above_the_shortest
s = bpy.data.objects["Bar"].rs_elastic
s.material_model, s.substeps = 'LINEAR', 1
bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 100
"""
RESTORE_CHECK = "DYNAMICS.Simulation._inverted_tets = REAL_CHECK"
SLOW_NOTE = "Slow since frame 2: steps are cut to keep tets from inverting"


def test_a_slow_simulation_says_why_under_its_bar_in_words_that_fit(gui):
    """While frames are slow, the Simulate panel says why under its bar (the bar keeps the frame
    and the percentage), every text of it fits the sidebar; the bake lands with one warning in
    the report log."""
    gui.run(QUICK_BAR, timeout=300)
    gui.run(FORCED_SLOW)
    try:
        gui.run("watch_panels()")
        assert gui.run("with override():\n"
                       "    result = sorted(bpy.ops.rs_elastic.simulate('INVOKE_DEFAULT'))") == \
            ["RUNNING_MODAL"]
        code = (_operator("rs_elastic.simulate", "RS_ELASTIC_PT_simulate") + PANEL_PROGRESS
                + "result.append(panel_items([PANEL])[PANEL])")
        deadline = time.monotonic() + 120
        while True:
            before, after, bars, items = gui.run(code)
            assert before is not None, "Simulate and Bake is not running as a modal operator"
            labels = [text for kind, text, _ in items if kind == "label"]
            if SLOW_NOTE.split(":")[0] + ":" in labels:
                break
            assert time.monotonic() < deadline, f"no slow note under the bar: {items}"
            time.sleep(0.2)
        _check_bar(before, after, bars)
        assert bars[0][1].startswith("frame "), bars
        # The note, wrapped as panels wrap a sentence, under the bar.
        assert " ".join(labels[labels.index("Slow since frame 2:"):][:3]).startswith(
            "Slow since frame 2: steps are cut"), labels
        cut = cut_labels(gui, ["RS_ELASTIC_PT_simulate"])
        drawn_panels(gui)            # drawn with the note: the sidebar knows its new length
        scroll(gui, "VIEW_3D", "UI", 5)              # the Simulation panel (at the end) in view
        assert ("RS_ELASTIC_PT_simulate", "Bar") in drawn_panels(gui)
        gui.screenshot("slow")
        assert cut == {"RS_ELASTIC_PT_simulate": []}, cut
        _wait_until_ended(gui, "rs_elastic.simulate")
        reports = gui.run("result = reports()")
        assert any("'Bar': 99 of 99 frames (from frame 2) were slow" in line
                   for line in reports), reports
        assert gui.run("result = sys.modules['bl_ext.user_default.rs_elastic.bridge.bake']"
                       ".bake_frames(bpy.data.objects['Bar'])") == list(range(1, 101))
    finally:
        gui.run(RESTORE_CHECK)
        scroll(gui, "VIEW_3D", "UI", -5)            # the sidebar back at its top, for later tests


# A handle keyed over a long range, many iterations allowed. This bar's solve is over in a
# fraction of a second, too soon to look at its bar or press Esc in it: while this test runs,
# each cancel check of a solve's job (the solver polls it between its steps) first sleeps
# ITERATION seconds (Job.is_cancelled wrapped in the class; the solver, the operator and the
# panel are untouched), and CHECKS records when each returned.
ITERATION = 0.5
SLOW_SOLVE = f"""
obj = bpy.data.objects["Bar"]
with override():
    h.add_tip_handle(obj, {{1: (4.0, 0.5, 0.5), 60: (4.0, 0.5, 1.5), 120: (4.0, 1.0, 0.5)}})
    h.make_active(obj)
s = obj.rs_elastic
s.iterations, s.tightness = 200, 1e6
bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 120
JOB = sys.modules[bpy.types.RS_ELASTIC_OT_solve_spacetime.__module__].jobs.Job   # the operator's
JOB_IS_CANCELLED = JOB.is_cancelled
CHECKS = []
# The worker waits at its first check after its progress moved until the test has seen the bar,
# so a solve that converges in a few steps cannot end before the test has looked; the spacing of
# the checks is measured from the release.
GATE = threading.Event()
def slowed_check(self):
    if self.idname == "rs_elastic.solve_spacetime" and threading.current_thread() is self._thread:
        if self.fraction > 0.0 and not GATE.is_set():
            GATE.wait(60.0)
            CHECKS[:] = [time.monotonic()]
        time.sleep({ITERATION})
        CHECKS.append(time.monotonic())
    return JOB_IS_CANCELLED(self)
JOB.is_cancelled = slowed_check
"""
RESTORE_STEP = "GATE.set()\nJOB.is_cancelled = JOB_IS_CANCELLED"

# What a cancelled solve must leave as it was, beside body_state: the mesh's shape keys, the
# handle's Empty and its keys, and the solve's words on the object.
SOLVE_STATE = """
obj = bpy.data.objects["Bar"]
empty = obj.rs_elastic.handles[0].empty
curves = sys.modules["bl_ext.user_default.rs_elastic.bridge"].animation.fcurves(empty)
result = {"shape_keys": obj.data.shape_keys is not None, "modifiers": [m.name for m in obj.modifiers],
          "empty": list(empty.location), "keys": [[list(k.co) for k in c.keyframe_points]
                                                  for c in curves],
          "residuals": [h.residual for h in obj.rs_elastic.handles],
          "history": len(obj.rs_elastic.solve_history)}
"""

# Esc heard (job.cancel) and the operator's end (its cleanup), timed inside Blender.
WATCH_SOLVE = OPERATOR + """
operator, job = ops[0], ops[0]._job
TIMES = {"cancel": [], "cleanup": []}
def timed(function, key):
    def wrapper(*args, **kwargs):
        start = time.monotonic()
        try:
            return function(*args, **kwargs)
        finally:
            TIMES[key].append([start, time.monotonic() - start])
    return wrapper
job.cancel = timed(job.cancel, "cancel")
operator._cleanup = timed(operator._cleanup, "cleanup")
"""


def test_solve_and_bake_draws_a_progress_bar_and_esc_cancels_it_with_nothing_changed(gui):
    gui.run(QUICK_BAR, timeout=300)
    gui.run(SLOW_SOLVE)
    try:
        _solve_and_cancel(gui)
    finally:
        gui.run(RESTORE_STEP)


def _solve_and_cancel(gui):
    before, before_solve = body_state(gui), gui.run(SOLVE_STATE)
    gui.run("watch_panels()")
    assert gui.run("with override():\n"
                   "    result = sorted(bpy.ops.rs_elastic.solve_spacetime('INVOKE_DEFAULT'))") \
        == ["RUNNING_MODAL"]
    gui.run(_operator("rs_elastic.solve_spacetime") + WATCH_SOLVE)
    # The bar in the Space-Time panel, at the job's fraction, once an iteration is done.
    *progress, cut = _wait_for_progress(gui, "rs_elastic.solve_spacetime",
                                        "RS_ELASTIC_PT_spacetime", 0.0, measure=True)
    _check_bar(*progress)
    assert ("RS_ELASTIC_PT_spacetime", "Bar") in drawn_panels(gui)
    gui.screenshot("progress")
    assert cut == [], cut

    # Esc in the middle of the solve, the worker let go just before.
    gui.run("GATE.set()")
    pressed = time.monotonic()
    gui.key("Escape")
    delivered = time.monotonic() - pressed
    _wait_until_ended(gui, "rs_elastic.solve_spacetime")
    times = gui.run("result = TIMES")
    assert times["cleanup"] and times["cleanup"][0][0] > pressed, \
        "the solve ended before Esc was pressed: make its iterations longer"
    assert len(times["cancel"]) == 1 and len(times["cleanup"]) == 1, times
    latency = sum(times["cleanup"][0]) - pressed
    starts = gui.run("result = CHECKS")
    iteration = max(b - a for a, b in zip(starts, starts[1:]))
    poll = gui.run("result = sys.modules['bl_ext.user_default.rs_elastic.bridge.jobs'].POLL")
    bound = delivered + 2 * iteration + poll
    print(f"\nSolve and Bake: Esc latency {1000 * latency:.0f} ms, heard after "
          f"{1000 * (times['cancel'][0][0] - pressed):.0f} ms (key delivery "
          f"{1000 * delivered:.0f} ms; cancel checks at most {1000 * iteration:.0f} ms apart "
          f"over {len(starts)} checks; bound {1000 * bound:.0f} ms)")
    assert latency < bound, f"Esc took {latency:.3f} s to end the solve (bound {bound:.3f} s)"

    reports = gui.run("result = reports()")
    assert any("Solve and Bake: cancelled, nothing was changed" in line for line in reports), \
        reports
    after = body_state(gui)
    assert {k: v for k, v in after.items() if k != "cache"} == \
        {k: v for k, v in before.items() if k != "cache"}
    assert gui.run(SOLVE_STATE) == before_solve
    bars = gui.run(RECORDER + "result = panel_items(['RS_ELASTIC_PT_spacetime'])"
                   "['RS_ELASTIC_PT_spacetime']")
    assert not [item for item in bars if item[0] == "progress"], bars


# A take source with the body's vertices, over a long range, in a scene that takes 20 ms per
# frame to evaluate (a frame-change handler sleeps): reading all its frames takes about 8 s.
SLOW_TAKE = """
obj = bpy.data.objects["Bar"]
source = obj.copy()
source.data = obj.data.copy()
source.name = "Source"
bpy.context.scene.collection.objects.link(source)
obj.rs_elastic.take_source = source
bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 400
bpy.context.scene.frame_set(7)
READ = []
def slow_frame(scene, depsgraph=None):
    time.sleep(0.02)
    READ.append(scene.frame_current)
bpy.app.handlers.frame_change_post.append(slow_frame)
"""
RESTORE_FRAMES = """
bpy.app.handlers.frame_change_post[:] = [f for f in bpy.app.handlers.frame_change_post
                                         if f.__name__ != "slow_frame"]
"""


def test_take_from_animation_reads_frame_by_frame_with_a_bar_and_esc_puts_the_frame_back(gui):
    """The frames are read on the main thread a piece per timer tick: the operator returns at
    once, the Take panel's bar moves while the frames are read, and Esc stops the reading with
    the scene on its frame again and no take."""
    gui.run(QUICK_BAR, timeout=300)
    gui.run(SLOW_TAKE)
    try:
        before = body_state(gui)
        gui.run("watch_panels()")
        assert gui.run("with override():\n    result = sorted("
                       "bpy.ops.rs_elastic.take_from_animation('INVOKE_DEFAULT'))") == \
            ["RUNNING_MODAL"]
        assert gui.run("result = len(READ)") < 400      # invoke did not read them all
        *bar, cut = _wait_for_progress(gui, "rs_elastic.take_from_animation",
                                       "RS_ELASTIC_PT_take", 0.05, measure=True)
        _check_bar(*bar)
        assert "reading frame" in bar[2][0][1], bar
        assert cut == [], cut
        gui.key("Escape")
        _wait_until_ended(gui, "rs_elastic.take_from_animation")
        read, frame = gui.run("result = [len(READ), bpy.context.scene.frame_current]")
        print(f"\nTake from Animation: Esc after {read} of 400 frames read")
        assert read < 400 and frame == 7
        reports = gui.run("result = reports()")
        assert any("Take from Animation: cancelled, nothing was changed" in line
                   for line in reports), reports
        assert gui.run("result = bpy.data.objects['Bar'].rs_elastic.use_take") is False
        after = body_state(gui)
        assert {k: v for k, v in after.items() if k != "cache"} == \
            {k: v for k, v in before.items() if k != "cache"}
    finally:
        gui.run(RESTORE_FRAMES)
