"""Space-time editing end to end in the installed extension, and its command line."""
import subprocess
import sys

import numpy as np
import pytest
import bpy

from blender_helpers import add_tip_handle, diagonal, evaluated_vertices, fingerprint, make_bar, vertices
from conftest import ROOT, USER_DIR


def prepared_bar_with_tip_handle(keys):
    """A pinned bar, moved and turned in the world, whose tip handle is keyed at `keys`
    {frame: world location}. Returns (bar, empty, tip mask)."""
    obj = make_bar(cuts=3)
    obj.location = (1.0, 2.0, 0.5)
    obj.rotation_euler = (0.0, 0.0, 0.4)
    obj.rs_elastic.edge_length = 0.08
    obj.rs_elastic.num_modes = 6
    bpy.context.view_layer.update()
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    empty, tip = add_tip_handle(obj, keys)
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 60
    return obj, empty, tip


def world_tip(obj, tip):
    local = evaluated_vertices(obj)[tip].mean(axis=0)
    return np.array(obj.matrix_world) @ np.r_[local, 1.0]


def lifted(obj, height):
    """World location of the bar's rest tip centroid raised by `height` in the bar's frame."""
    return tuple((np.array(obj.matrix_world) @ np.r_[4.0, 0.5, 0.5 + height, 1.0])[:3])


def test_solve_puts_the_handle_on_its_empty_on_every_keyed_frame(ext):
    obj = make_bar()   # only to compute targets in the bar's frame before the real one
    obj.location = (1.0, 2.0, 0.5)
    obj.rotation_euler = (0.0, 0.0, 0.4)
    bpy.context.view_layer.update()
    keys = {20: lifted(obj, 1.5), 40: lifted(obj, -1.0)}
    bpy.data.objects.remove(obj)
    obj, empty, tip = prepared_bar_with_tip_handle(keys)
    user = fingerprint(obj)
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    assert ext.bridge.bake.bake_frames(obj) == list(range(1, 61))
    for frame, target in keys.items():
        bpy.context.scene.frame_set(frame)
        miss = np.linalg.norm(world_tip(obj, tip)[:3] - np.array(target))
        assert miss < 1e-3 * diagonal(vertices(obj)), (frame, miss)
    assert 0 <= obj.rs_elastic.handles[0].residual < 1e-3 * diagonal(vertices(obj))
    assert len(obj.rs_elastic.solve_history) > 1
    history = [item.value for item in obj.rs_elastic.solve_history]
    assert all(b <= a * (1 + 1e-12) for a, b in zip(history, history[1:]))
    # Between and after the keys the body moves freely: frame 50 is neither rest nor a target.
    bpy.context.scene.frame_set(50)
    assert np.abs(evaluated_vertices(obj) - vertices(obj)).max() > 1e-3
    # Re-solving replaces the bake; clearing it restores the user's object exactly.
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    assert ext.bridge.bake.bake_frames(obj) == list(range(1, 61))
    assert bpy.ops.rs_elastic.clear_bake() == {'FINISHED'}
    bpy.context.scene.frame_set(1)
    assert fingerprint(obj) == user


def test_iterations_zero_runs_the_solver_to_its_own_limits_and_a_number_caps_it(ext):
    """The Iterations setting defaults to 0 (automatic): the operator's solve is then the
    solver's with its own step limits (the same objective after every step); a number caps the
    Gauss-Newton steps, and a solve cut short says so."""
    obj, empty, tip = prepared_bar_with_tip_handle({20: (3.0, 3.5, 2.5), 40: (2.0, 3.0, 3.0)})
    assert obj.rs_elastic.iterations == 0
    inputs = ext.bridge.spacetime_inputs
    job = inputs.gather(obj, bpy.context.scene)
    assert job.iterations is None
    reference = ext.solver.spacetime.solve(job.problem)
    assert reference.converged and len(reference.history) > 4, reference.reason
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    assert inputs.LAST_STATUS[obj.name] == (True, "Solve converged")
    history = [item.value for item in obj.rs_elastic.solve_history]
    np.testing.assert_allclose(history, [value for _, _, value in reference.history], rtol=1e-6)
    obj.rs_elastic.iterations = 2
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    assert inputs.LAST_STATUS[obj.name] == (
        False, "Solve did not converge: Gauss-Newton did not converge in 2 steps")
    assert len(obj.rs_elastic.solve_history) < len(history)


def test_material_optimisation_bakes_and_lowers_nothing_it_should_not(ext):
    obj, empty, tip = prepared_bar_with_tip_handle({15: (3.0, 3.5, 2.5), 35: (2.0, 3.0, 3.0)})
    obj.rs_elastic.optimize_material = True
    obj.rs_elastic.iterations = 4
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    history = [item.value for item in obj.rs_elastic.solve_history]
    assert all(b <= a * (1 + 1e-12) for a, b in zip(history, history[1:]))
    assert ext.bridge.bake.bake_frames(obj) == list(range(1, 61))


def test_undo_restores_the_state_before_the_solve(ext):
    obj, empty, tip = prepared_bar_with_tip_handle({20: (3.0, 3.5, 2.5)})
    assert 'UNDO' in ext.operators.solve_spacetime.RS_ELASTIC_OT_solve_spacetime.bl_options
    bpy.ops.ed.undo_push(message="before")
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    bpy.ops.ed.undo_push(message="Solve and Bake")       # what the UI pushes after the operator
    bpy.ops.ed.undo()
    assert ext.bridge.bake.bake_frames(bpy.data.objects["Bar"]) == []


def test_a_deleted_empty_is_reported_and_the_other_handles_still_solve(ext, capfd):
    obj, empty, tip = prepared_bar_with_tip_handle({20: (3.0, 3.5, 2.5)})
    root_group = obj.vertex_groups.new(name="Middle")
    middle = np.flatnonzero(np.abs(vertices(obj)[:, 0] - 2.0) < 1e-9)
    root_group.add([int(i) for i in middle], 1.0, 'REPLACE')
    bpy.ops.rs_elastic.add_handle(vertex_group="Middle")
    second = obj.rs_elastic.handles[1].empty
    second.keyframe_insert("location", frame=30)
    bpy.data.objects.remove(empty)
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    assert "Empty was deleted" in capfd.readouterr().out
    assert obj.rs_elastic.handles[0].residual == -1.0
    assert obj.rs_elastic.handles[1].residual >= 0.0


def test_a_pose_key_is_met_on_its_frame(ext):
    obj = make_bar(cuts=3)
    obj.rs_elastic.edge_length = 0.08
    obj.rs_elastic.num_modes = 6
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    rest = vertices(obj)
    # The sculpted pose: the bar curled along its first mode (the RS preview's shape).
    obj.rs_elastic.preview_method = 'RS'
    obj.rs_elastic.preview_amplitude = 0.25
    obj.rs_elastic.preview_enabled = True
    drooped = evaluated_vertices(obj)
    obj.rs_elastic.preview_enabled = False
    obj.shape_key_add(name="Basis")
    pose = obj.shape_key_add(name="Droop")
    pose.data.foreach_set("co", drooped.astype(np.float32).ravel())
    pose.value = 1.0
    pose.keyframe_insert("value", frame=30)
    pose.value = 0.0
    pose.keyframe_insert("value", frame=29)
    pose.keyframe_insert("value", frame=31)
    bpy.context.scene.frame_end = 50
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    baked = ext.bridge.bake
    block = obj.data.shape_keys.key_blocks[baked.bake_key_name(30)]
    co = np.empty(len(block.data) * 3, dtype=np.float32)
    block.data.foreach_get("co", co)
    # The pose is met through the reduced model: within 5 % of its size.
    error = np.abs(co.reshape(-1, 3) - drooped).max()
    print(f"pose key miss {error:.4f} m of a {np.abs(drooped - rest).max():.3f} m pose")
    assert error < 0.05 * np.abs(drooped - rest).max()


def test_solve_refuses_bad_input_and_changes_nothing(ext):
    obj = make_bar()
    before = fingerprint(obj)
    with pytest.raises(RuntimeError, match="not prepared"):
        bpy.ops.rs_elastic.solve_spacetime()
    assert fingerprint(obj) == before
    obj.rs_elastic.edge_length = 0.1
    obj.rs_elastic.num_modes = 3
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    before = fingerprint(obj)
    with pytest.raises(RuntimeError, match="Nothing to solve"):
        bpy.ops.rs_elastic.solve_spacetime()
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 5, 6
    with pytest.raises(RuntimeError, match="fewer than 3 frames"):
        bpy.ops.rs_elastic.solve_spacetime()
    assert fingerprint(obj) == before


CLI_SCRIPT = """
import sys
sys.path.insert(0, {tools!r})
import blender_session
ext = blender_session.start(user_dir={user_dir!r})
import bpy
bpy.ops.wm.open_mainfile(filepath={blend!r})
blender_session.exit_child(ext.bridge.cli.main({argv!r}))
"""


def run_cli(blend, argv):
    """The command-line handler in a fresh Blender process, as `blender -b FILE -c rs_elastic`."""
    script = CLI_SCRIPT.format(tools=str(ROOT / "tools"), user_dir=USER_DIR, blend=str(blend),
                               argv=argv)
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=600)


def test_command_line_bakes_a_saved_file_and_returns_exit_codes(ext, tmp_path):
    obj, empty, tip = prepared_bar_with_tip_handle({20: (3.0, 3.5, 2.5)})
    blend, out = tmp_path / "shot.blend", tmp_path / "baked.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))

    good = run_cli(blend, ["bake", "--object", "Bar", "--frames", "1-30", "--output", str(out)])
    assert good.returncode == 0, good.stdout + good.stderr
    assert "rs_elastic: baked frames 1-30 of 'Bar'" in good.stdout
    assert ("rs_elastic: Solve converged" in good.stdout
            or "rs_elastic: Solve did not converge: " in good.stdout), good.stdout
    bpy.ops.wm.open_mainfile(filepath=str(out))
    assert ext.bridge.bake.bake_frames(bpy.data.objects["Bar"]) == list(range(1, 31))

    bad = run_cli(blend, ["bake", "--object", "Nobody"])
    assert bad.returncode == 2                                          # a bad argument
    errors = [l for l in bad.stderr.splitlines() if l.startswith("rs_elastic: error:")]
    assert errors == ["rs_elastic: error: no object named 'Nobody' in " + str(blend)]
    assert run_cli(blend, ["bake"]).returncode == 2                    # --object is required
    assert run_cli(blend, ["bake", "--object", "Bar", "--frames", "9-3"]).returncode == 2


class _QuietJob:
    """The worker's job interface without a thread: progress ignored, never cancelled."""

    def step(self, fraction, text):
        pass

    def is_cancelled(self):
        return False


def test_material_optimisation_chooses_modes_and_stays_within_material_freedom(ext):
    """Optimize Material solves with more candidate modes than optimised ones ([L14]'s S), keeps
    every frequency and damping within Material Freedom of the prepared body's, and leaves the
    convergence verdict for the panel and the command line."""
    obj, empty, tip = prepared_bar_with_tip_handle({15: (3.0, 3.5, 2.5), 35: (2.0, 3.0, 3.0)})
    settings = obj.rs_elastic
    settings.optimize_material = True
    settings.material_freedom = 1.2
    inputs = ext.bridge.spacetime_inputs
    job_inputs = inputs.gather(obj, bpy.context.scene)
    problem = job_inputs.problem
    m, r = problem.sampling.shape
    assert m == job_inputs.body.deformer.num_coords and r == ext.solver.problems.optimised_modes(m) < m
    assert problem.material_freedom == pytest.approx(1.2)
    result, poses = inputs.solve(job_inputs, _QuietJob())
    frequency = np.sqrt(result.eigenvalues / problem.eigenvalues)
    damping = result.damping / problem.damping
    print(f"Blender material solve: {m} candidate modes, {r} optimised; converged "
          f"{result.converged} ({result.reason}); frequency ratios [{frequency.min():.3f}, "
          f"{frequency.max():.3f}], damping ratios [{damping.min():.3f}, {damping.max():.3f}]")
    f = problem.material_freedom            # 1.2 as Blender's float32 stores it
    for ratios in (frequency, damping):
        assert np.all(ratios >= (1 - 1e-12) / f) and np.all(ratios <= f * (1 + 1e-12))
    history = result.objective_history
    assert np.all(np.diff(history) <= 1e-12 * history[0])
    assert inputs.LAST_STATUS[obj.name] == inputs.status_sentence(result)
    assert inputs.LAST_STATUS[obj.name][0] == result.converged
    assert poses.shape == (len(job_inputs.frames), len(vertices(obj)), 3)
