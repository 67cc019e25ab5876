"""Simulation end to end in the installed extension, and its command line."""
import time

import numpy as np
import pytest
import bpy

from blender_helpers import diagonal, evaluated_vertices, fingerprint, make_bar, vertices
from test_spacetime import run_cli


def prepared(obj, num_modes=6, edge_length=0.08):
    obj.rs_elastic.edge_length = edge_length
    obj.rs_elastic.num_modes = num_modes
    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    return obj


def baked_positions(obj, frames):
    out = []
    for frame in frames:
        bpy.context.scene.frame_set(frame)
        out.append(evaluated_vertices(obj))
    return np.array(out)


def test_a_keyed_prop_lags_swings_and_settles(ext):
    scene = bpy.context.scene
    scene.use_gravity = False
    scene.frame_start, scene.frame_end = 1, 120
    obj = prepared(make_bar(name="Prop", cuts=3))
    obj.rs_elastic.damping_mass = 1.0
    # The prop is carried sideways (along +y) between frames 1 and 12, then held.
    obj.keyframe_insert("location", frame=1)
    obj.location = (0.0, 3.0, 0.0)
    obj.keyframe_insert("location", frame=12)
    before = fingerprint(obj)
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    assert ext.bridge.bake.bake_frames(obj) == list(range(1, 121))
    rest = vertices(obj)
    tip, pinned = rest[:, 0] > 4.0 - 1e-9, rest[:, 0] < 1e-9
    local = baked_positions(obj, range(1, 121))                  # object space: the body frame
    sway = local[:, tip, 1].mean(axis=1) - rest[tip, 1].mean()
    assert sway[:6].min() < -0.05 * diagonal(rest)               # lags behind while speeding up
    assert sway[10:30].max() > 0.05 * diagonal(rest)             # swings past when stopped
    assert abs(sway[-1]) < 0.2 * np.abs(sway).max()              # and settles
    assert np.abs(local[:, pinned] - rest[pinned]).max() < 1e-6  # pins follow the keys exactly
    # The bake replaced nothing of the user's: clearing it restores the object.
    assert bpy.ops.rs_elastic.clear_bake() == {'FINISHED'}
    assert fingerprint(obj) == before


def test_a_free_body_falls_with_gravity_and_does_not_spin(ext):
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 25
    bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=2, radius=0.5)
    obj = prepared(bpy.context.active_object, num_modes=4, edge_length=0.15)
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    positions = baked_positions(obj, range(1, 26))
    h = 1.0 / scene.render.fps
    t = np.arange(25) * h
    drop = positions.mean(axis=1)[:, 2] - vertices(obj).mean(axis=0)[2]
    expected = -0.5 * 9.81 * t ** 2
    assert np.abs(drop - expected).max() < 0.05 * abs(expected[-1])
    horizontal = positions.mean(axis=1)[:, :2] - vertices(obj).mean(axis=0)[:2]
    assert np.abs(horizontal).max() < 1e-3


def test_simulate_refuses_bad_input_and_changes_nothing(ext):
    obj = make_bar(pin_end=False)
    before = fingerprint(obj)
    with pytest.raises(RuntimeError, match="not prepared"):
        bpy.ops.rs_elastic.simulate()
    prepared(obj, num_modes=3, edge_length=0.12)
    obj.keyframe_insert("location", frame=1)
    obj.location = (1.0, 0.0, 0.0)
    obj.keyframe_insert("location", frame=10)
    before = fingerprint(obj)
    with pytest.raises(RuntimeError, match="no pins"):
        bpy.ops.rs_elastic.simulate()
    assert fingerprint(obj) == before


def test_command_line_simulates_a_saved_file(ext, tmp_path):
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 24
    prepared(make_bar(cuts=3))
    blend = tmp_path / "jelly.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    result = run_cli(blend, ["bake", "--mode", "simulate", "--object", "Bar"])
    assert result.returncode == 0, result.stdout + result.stderr
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    obj = bpy.data.objects["Bar"]
    assert ext.bridge.bake.bake_frames(obj) == list(range(1, 25))
    bpy.context.scene.frame_set(24)
    sag = vertices(obj)[:, 2].min() - evaluated_vertices(obj)[:, 2].min()
    assert sag > 0.01                                            # gravity pulled the tip down


def test_a_simulated_take_is_the_input_of_a_space_time_edit(ext):
    """Simulate, keep the bake as the take, then edit it with one handle key: the edit meets the
    handle and follows the take away from it."""
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 48
    obj = prepared(make_bar(cuts=3))
    obj.rs_elastic.youngs_modulus = 2e6
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    assert bpy.ops.rs_elastic.keep_take() == {'FINISHED'}
    frames, take = ext.bridge.bake.take_poses(obj)
    assert frames == list(range(1, 49)) and obj.rs_elastic.use_take
    rest = vertices(obj)
    tip = rest[:, 0] > 4.0 - 1e-9
    obj.vertex_groups.new(name="Tip").add([int(i) for i in np.flatnonzero(tip)], 1.0, 'REPLACE')
    assert bpy.ops.rs_elastic.add_handle(vertex_group="Tip") == {'FINISHED'}
    empty = obj.rs_elastic.handles[0].empty
    target = take[29][tip].mean(axis=0) + np.array([0.0, 0.8, 0.0])   # push the tip sideways
    empty.location = tuple(np.array(obj.matrix_world) @ np.r_[target, 1.0])[:3]
    empty.keyframe_insert("location", frame=30)
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    edited = baked_positions(obj, range(1, 49))
    assert np.linalg.norm(edited[29][tip].mean(axis=0) - target) < 1e-2 * diagonal(rest)
    # Far from the edit (the first frames) the result stays with the take; at the edit it leaves it.
    early = np.abs(edited[:8] - take[:8]).max()
    at_edit = np.abs(edited[29] - take[29]).max()
    print(f"take followed to {early:.3g} m early on; moved {at_edit:.3g} m at the edit")
    assert early < 0.1 * at_edit


def test_simulation_follows_the_integrator_and_substeps_settings(ext):
    """The object's integrator and substeps reach the solver; 0 substeps is the automatic rule
    (dt w_max <= 1), and a bake at 48 fps repeats the 24 fps bake on their common frames (the
    motion does not depend on the frame rate beyond sampling)."""
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 25
    obj = prepared(make_bar(cuts=3))
    dynamics = ext.solver.dynamics
    sim = ext.bridge.simulation_inputs.gather(obj, scene).simulation
    assert sim.integrator == "newmark" and obj.rs_elastic.substeps == 0
    assert sim.substeps == dynamics.automatic_substeps(1.0 / scene.render.fps, sim.omega[-1])
    assert sim.dt * sim.omega[-1] <= 1.0 + 1e-12
    obj.rs_elastic.integrator, obj.rs_elastic.substeps = 'IMPLICIT_EULER', 3
    sim = ext.bridge.simulation_inputs.gather(obj, scene).simulation
    assert sim.integrator == "implicit_euler" and sim.substeps == 3
    assert sim.dt == pytest.approx(1.0 / (3 * scene.render.fps))
    obj.rs_elastic.integrator, obj.rs_elastic.substeps = 'NEWMARK', 0
    tips = []
    for fps, end in ((24, 25), (48, 49)):
        scene.render.fps, scene.frame_end = fps, end
        assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
        tips.append(baked_positions(obj, range(1, end + 1, fps // 24))[:, :, 2].min(axis=1))
    sag = np.abs(tips[0] - tips[0][0]).max()
    print(f"tip at 24 and 48 fps over 1 s: largest difference {np.abs(tips[0] - tips[1]).max():.2e}"
          f" m, sag {sag:.3f} m")
    assert sag > 0.01
    assert np.abs(tips[0] - tips[1]).max() <= 0.02 * sag


def test_start_settled_begins_at_rest_in_the_sag_it_keeps(ext):
    """Start Settled: a pinned bar under gravity starts in its static equilibrium, so with no
    damping every baked frame is that first sagged pose (a fixed point of the dynamics); from
    the undeformed shape (the default) the same bar sags and bounces about it."""
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 24
    obj = make_bar(name="Shelf", cuts=3)
    obj.rs_elastic.youngs_modulus = 1e7          # sags about 0.4 m (Euler-Bernoulli)
    prepared(obj)
    obj.rs_elastic.damping_mass = obj.rs_elastic.damping_stiffness = 0.0
    rest = vertices(obj)
    tip = rest[:, 0] > 4.0 - 1e-9
    runs = {}
    for settled in (False, True):
        obj.rs_elastic.start_settled = settled
        assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
        runs[settled] = baked_positions(obj, range(1, 25))
    sag = rest[tip, 2].mean() - runs[True][0, tip, 2].mean()
    still = np.abs(runs[True] - runs[True][0]).max() / diagonal(rest)
    bounce = np.abs(runs[False] - runs[False][0]).max() / diagonal(rest)
    print(f"Start Settled: tip sag {sag:.4f} m, frames move {still:.1e} of the diagonal; "
          f"from rest they move {bounce:.1e}")
    assert sag > 1e-3 * diagonal(rest)
    assert still < 1e-6
    assert bounce > 1e-3
    assert np.abs(runs[False][0] - rest).max() < 1e-9        # the default starts undeformed


def test_frames_whose_steps_were_cut_to_the_shortest_are_reported_as_slow(ext, capfd,
                                                                          monkeypatch):
    """A body whose steps must be retaken down to dt / 2^MAX_STEP_SPLITS to keep its tets from
    inverting (a basis far too coarse for a mesh's smallest tets does it frame after frame) bakes
    slowly: one warning names how many frames and the first, and what usually avoids it; the
    bake still lands. Forced here (every check of a longer step fails; the shortest are checked
    for real), and the same body unforced reports nothing."""
    dynamics = ext.solver.dynamics
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 4
    obj = prepared(make_bar())
    obj.rs_elastic.substeps = 1

    def slow_warnings():
        return [line for line in capfd.readouterr().out.splitlines()
                if line.startswith("Warning: ") and "were slow" in line]

    shown = []                                       # (message, note) of each progress step
    step = ext.bridge.jobs.Job.step

    def recorded(job, fraction, message, note=None):
        shown.append((message, note))
        return step(job, fraction, message, note)

    monkeypatch.setattr(ext.bridge.jobs.Job, "step", recorded)
    capfd.readouterr()
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    assert slow_warnings() == []
    assert [note for message, note in shown if message.startswith("frame ")] == [None] * 3
    shown.clear()
    real_check = dynamics.Simulation._inverted_tets

    def failing_above_the_shortest(sim):
        count, smallest, finite, ratios = real_check(sim)
        if sim.state.dt > 1.5 * sim.h / sim.substeps / 2 ** dynamics.MAX_STEP_SPLITS:
            return 1, -1.0, True, ratios
        return count, smallest, finite, ratios

    monkeypatch.setattr(dynamics.Simulation, "_inverted_tets", failing_above_the_shortest)
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    cut = 2 ** dynamics.MAX_STEP_SPLITS
    assert slow_warnings() == [
        f"Warning: 'Bar': 3 of 3 frames (from frame 2) were slow: their steps were cut to "
        f"1/{cut} to keep every tet from inverting. A larger Basis Size (0 is automatic), more "
        "Substeps or a stiffer material usually avoid it"]
    # While it ran, the progress said so from the first slow frame on.
    slow = "Slow since frame 2: steps are cut to keep tets from inverting"
    assert [(m, n) for m, n in shown if m.startswith("frame ")] == [
        (f"frame {frame} of 4", slow) for frame in (2, 3, 4)]
    assert ext.bridge.bake.bake_frames(obj) == [1, 2, 3, 4]


def test_a_scaled_body_is_simulated_with_one_readable_warning(ext, capfd):
    """A scaled (and mirrored) body: one warning giving the scale as plain numbers (a mirror is
    not a scale), and the bake lands."""
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 3
    obj = prepared(make_bar())
    obj.scale = (1.2, -1.0, 1.1)
    capfd.readouterr()
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    warnings = [line for line in capfd.readouterr().out.splitlines()
                if line.startswith("Warning: ")]
    assert warnings == ["Warning: 'Bar' is scaled by (1.2, 1, 1.1): the simulation treats its "
                        "object space as metres"]
    assert ext.bridge.bake.bake_frames(obj) == [1, 2, 3]


def test_a_job_runs_numpy_blas_on_one_thread_and_gives_back_the_count(ext):
    """While a job's work runs (on its thread or here), numpy's BLAS has one thread; after it,
    also after an error or a second job nested in time, the count it had."""
    controls = ext.solver.threads.numpy_blas_controls()
    if controls is None:
        pytest.skip("numpy here has no OpenBLAS whose threads can be set (e.g. Accelerate)")
    set_threads, get_threads = controls
    original = get_threads()
    set_threads(2)
    try:
        _check_jobs_blas(ext, get_threads)
    finally:
        set_threads(original)


def _check_jobs_blas(ext, get_threads):
    seen = []

    def work(job):
        seen.append(get_threads())
        return "done"

    def failing(job):
        seen.append(get_threads())
        raise ValueError("bad input")

    Job = ext.bridge.jobs.Job
    assert Job(work).run_here() == "done" and get_threads() == 2
    with pytest.raises(ValueError):
        Job(failing).run_here()
    assert get_threads() == 2
    slow = Job(lambda job: time.sleep(0.2) or seen.append(get_threads()))
    slow.start()
    quick = Job(work)
    quick.start()
    while not (slow.done and quick.done):
        time.sleep(0.01)
    assert quick.result == "done" and seen == [1, 1, 1, 1] and get_threads() == 2
