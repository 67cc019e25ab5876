"""Undo and Esc of Take from Animation and Fit Material (issue 28, item 3: the fitted material
survives undo; long operators run as jobs with progress and Esc). The UI pushes an undo step
after every operator flagged UNDO; background mode does not, so the test pushes them as the UI
would. Oracle: the state before each operator, recorded here
(the take's positions, the fitted material's arrays, the panel's lines), comes back exactly;
a fit cancelled on its worker thread keeps nothing.
"""
import time

import numpy as np
import bpy

from blender_helpers import make_active
from test_panels import draw_all, draw_each, fitted_table
from test_take_sources import body, copy_of, hooked, prepared_file  # noqa: F401 (fixtures)


def fitted_lines():
    """What the take panel shows of the fitted material (its residual and per-mode values)."""
    return [text for kind, text in draw_all()
            if kind == "label" and ("→" in text or text.endswith(" m"))]


def state(ext):
    obj = bpy.data.objects["Body"]
    frames, take = ext.bridge.bake.take_poses(obj)
    return frames, take, ext.bridge.take.fitted_material(obj), fitted_lines()


def test_undo_brings_back_the_previous_fit_then_the_previous_take(ext, body):
    source = copy_of(body)
    hooked(source)
    body.rs_elastic.take_source = source
    make_active(body)
    for operator in ("take_from_animation", "fit_material"):
        assert 'UNDO' in getattr(ext.operators, operator).__dict__[
            "RS_ELASTIC_OT_" + operator].bl_options
    assert bpy.ops.rs_elastic.take_from_animation() == {'FINISHED'}
    assert bpy.ops.rs_elastic.fit_material() == {'FINISHED'}
    bpy.ops.ed.undo_push(message="first take and fit")
    frames_a, take_a, fit_a, lines_a = state(ext)
    assert fit_a is not None and lines_a

    source.modifiers["Hook"].strength = 0.5                 # the source now moves half as far
    assert bpy.ops.rs_elastic.take_from_animation() == {'FINISHED'}
    bpy.ops.ed.undo_push(message="Take from Animation")
    _, take_b, fit_after_take, _ = state(ext)
    assert bpy.ops.rs_elastic.fit_material() == {'FINISHED'}
    bpy.ops.ed.undo_push(message="Fit Material")
    _, _, fit_b, lines_b = state(ext)
    assert np.abs(take_b - take_a).max() > 0.05
    assert not np.allclose(fit_b.eigenvalues, fit_a.eigenvalues, rtol=1e-6)
    assert lines_b != lines_a

    bpy.ops.ed.undo()                                       # the fit of the second take goes
    frames, take, fit, lines = state(ext)
    np.testing.assert_array_equal(take, take_b)
    np.testing.assert_array_equal(fit.eigenvalues, fit_after_take.eigenvalues)
    np.testing.assert_array_equal(fit.damping, fit_after_take.damping)
    np.testing.assert_array_equal(fit.sampling, fit_after_take.sampling)
    assert lines == lines_a                                 # fit_after_take is fit_a

    bpy.ops.ed.undo()                                       # and then the second take
    frames, take, fit, lines = state(ext)
    assert frames == frames_a
    np.testing.assert_array_equal(take, take_a)
    np.testing.assert_array_equal(fit.eigenvalues, fit_a.eigenvalues)
    assert lines == lines_a


def test_the_take_panel_shows_each_modes_prepared_and_fitted_values(ext, body):
    """The fitted material as the Take panel draws it, read back from its labels: the frames,
    the residual and, per mode in order, the prepared and fitted frequency [Hz] and damping
    [1/s] agree with the fitted material's own arrays to the three digits shown."""
    source = copy_of(body)
    hooked(source)
    body.rs_elastic.take_source = source
    make_active(body)
    assert bpy.ops.rs_elastic.take_from_animation() == {'FINISHED'}
    assert bpy.ops.rs_elastic.fit_material() == {'FINISHED'}
    fit = ext.bridge.take.fitted_material(body)
    facts, rows = fitted_table(draw_each()["RS_ELASTIC_PT_take"])
    assert facts == {"Frames": f"{fit.first_frame}–{fit.last_frame}",
                     "Residual": f"{fit.residual:.3g} m", "Worst frame": f"{fit.worst_frame}"}
    assert [number for number, _, _ in rows] == [str(k + 1) for k in range(len(fit.frequencies))]
    for k, (_, frequency, damping) in enumerate(rows):
        np.testing.assert_allclose(frequency, (fit.prepared_frequencies[k], fit.frequencies[k]),
                                   rtol=5e-3, atol=5e-4)
        np.testing.assert_allclose(damping, (fit.prepared_damping[k], fit.damping[k]),
                                   rtol=5e-3, atol=5e-4)


def test_a_fit_cancelled_on_its_worker_thread_keeps_nothing(ext, body):
    """The fit as the UI runs it (the operator's modal Job; Esc calls job.cancel()): its
    progress goes through the take's frames, then the solve's rounds; cancelled in the solve,
    it raises Cancelled and the body keeps no fitted material, so Continue still refuses."""
    source = copy_of(body)
    hooked(source)
    body.rs_elastic.take_source = source
    make_active(body)
    assert bpy.ops.rs_elastic.take_from_animation() == {'FINISHED'}
    take, jobs = ext.bridge.take, ext.bridge.jobs
    inputs = take.gather_fit(body, bpy.context.scene)
    seen = []

    def work(job):
        step = job.step

        def recorded(fraction, message):
            seen.append((fraction, message))
            step(fraction, message)
        job.step = recorded
        return take.fit_work(inputs, job)

    job = jobs.Job(work)
    job.start()
    deadline = time.monotonic() + 120
    while not job.message.startswith("round") and not job.done and time.monotonic() < deadline:
        time.sleep(0.005)
    job.cancel()
    while not job.done:
        time.sleep(0.01)
    assert isinstance(job.error, jobs.Cancelled), job.error
    assert take.fitted_material(body) is None
    fractions = [fraction for fraction, _ in seen]
    assert fractions == sorted(fractions) and 0.0 < fractions[0] and fractions[-1] < 1.0
    assert seen[len(inputs.frames) - 1] == (take.FIT_READING,
                                           f"reading the take's frame {len(inputs.frames)} of "
                                           f"{len(inputs.frames)}")
    assert seen[-1][1].startswith("round")
