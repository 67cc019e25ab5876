"""Undo of Take from Animation and Fit Material (issue 28, item 3: the fitted material survives
undo). The UI pushes an undo step after every operator flagged UNDO; background mode does not,
so the test pushes them as the UI would. Oracle: the state before each operator, recorded here
(the take's positions, the fitted material's arrays, the panel's lines), comes back exactly.
"""
import numpy as np
import bpy

from blender_helpers import make_active
from test_panels import draw_all
from test_take_sources import body, copy_of, hooked, prepared_file  # noqa: F401 (fixtures)


def fitted_lines():
    """What the take panel shows of the fitted material (its residual and per-mode lines)."""
    return [text for kind, text in draw_all()
            if kind == "label" and ("Hz," in text or text.startswith("Fit of frames"))]


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
