"""RS preview and RS interpolation of shape keys in the installed extension."""
import numpy as np
import pytest
import bpy
from scipy.spatial.transform import Rotation

from blender_helpers import (closed_volume, diagonal, evaluated_vertices, fingerprint, make_bar,
                             preview_pose, vertices)


def prepared_bar(pin_end=True, cuts=7, edge_length=0.06, num_modes=4):
    obj = make_bar(pin_end=pin_end, cuts=cuts)
    obj.rs_elastic.edge_length = edge_length
    obj.rs_elastic.num_modes = num_modes
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    return obj


def test_rs_preview_curls_the_bar_where_the_linear_one_stretches_it(ext):
    obj = prepared_bar()
    rest = vertices(obj)
    # Amplitude: the linear tip displacement is 4× the bar's thickness (1 m).
    amplitude = 4.0 / diagonal(rest)
    linear, warped = preview_pose(obj, 'LINEAR', amplitude), preview_pose(obj, 'RS', amplitude)
    root, tip = rest[:, 0] < 1e-9, rest[:, 0] > 4.0 - 1e-9
    reach = lambda pose: np.linalg.norm(pose[tip].mean(axis=0) - pose[root].mean(axis=0))
    assert np.linalg.norm(linear[tip].mean(axis=0) - rest[tip].mean(axis=0)) == pytest.approx(4.0, rel=0.05)
    assert reach(linear) > 1.3 * 4.0          # the linear mode stretches the bar
    assert reach(warped) < 1.02 * 4.0         # the RS mode bends it
    v0 = closed_volume(obj, rest)
    print(f"volume / rest: linear {closed_volume(obj, linear) / v0:.3f}, "
          f"RS {closed_volume(obj, warped) / v0:.3f}")
    assert abs(closed_volume(obj, warped) / v0 - 1.0) < 0.05
    assert abs(closed_volume(obj, linear) / v0 - 1.0) > 0.3
    np.testing.assert_array_equal(vertices(obj), rest)
    assert obj.data.shape_keys is None


def rotated_keys(obj):
    """Keys 'Bent' (a smooth bend) and 'Turned' (the bend rotated 120° about the bar's centre)."""
    rest = vertices(obj)
    obj.shape_key_add(name="Basis")
    bent = rest + np.column_stack([np.zeros(len(rest)), np.zeros(len(rest)),
                                   0.08 * rest[:, 0] ** 2])
    centre = bent.mean(axis=0)
    turned = (bent - centre) @ Rotation.from_euler("z", 120, degrees=True).as_matrix().T + centre
    for name, pose in (("Bent", bent), ("Turned", turned)):
        key = obj.shape_key_add(name=name)
        key.data.foreach_set("co", pose.astype(np.float32).ravel())
        key.value = 0.0       # the bake plays on the Basis; active user keys would add to it
    return bent, turned


def key_co(obj, name):
    block = obj.data.shape_keys.key_blocks[name]
    co = np.empty(len(block.data) * 3, dtype=np.float32)
    block.data.foreach_get("co", co)
    return co.reshape(-1, 3).astype(float)


def test_interpolated_keys_keep_their_volume_where_a_linear_blend_collapses(ext):
    obj = prepared_bar(pin_end=False)
    bent, turned = rotated_keys(obj)
    v0 = closed_volume(obj, vertices(obj))
    user_keys = fingerprint(obj)
    assert bpy.ops.rs_elastic.interpolate_shape_keys(key_from="Bent", key_to="Turned", count=3) \
        == {'FINISHED'}
    names = [k.name for k in obj.data.shape_keys.key_blocks]
    made = [n for n in names if n.startswith("RS Bent")]
    assert len(made) == 3
    ratios = [closed_volume(obj, key_co(obj, n)) / v0 for n in made]
    linear = closed_volume(obj, 0.5 * (bent + turned)) / v0
    print(f"volume / rest: RS {np.round(ratios, 4)}, linear blend at t=0.5 {linear:.3f}")
    assert max(abs(r - 1.0) for r in ratios) < 0.02
    assert linear < 0.8
    # The middle key is the bend turned by 60°: its centre stays, its ends swing.
    middle = key_co(obj, made[1])
    expected = (bent - bent.mean(axis=0)) @ Rotation.from_euler("z", 60, degrees=True).as_matrix().T \
        + bent.mean(axis=0)
    assert np.abs(middle - expected).max() < 0.02 * diagonal(bent)
    # Running again replaces the in-betweens; the user's keys are untouched throughout.
    assert bpy.ops.rs_elastic.interpolate_shape_keys(key_from="Bent", key_to="Turned", count=2) \
        == {'FINISHED'}
    assert len([k for k in obj.data.shape_keys.key_blocks if k.name.startswith("RS Bent")]) == 2
    for name in made:
        if name in obj.data.shape_keys.key_blocks:
            obj.shape_key_remove(obj.data.shape_keys.key_blocks[name])
    assert fingerprint(obj) == user_keys


def test_interpolation_bakes_an_animation_that_plays_when_scrubbed(ext):
    obj = prepared_bar(pin_end=False)
    bent, turned = rotated_keys(obj)
    assert bpy.ops.rs_elastic.interpolate_shape_keys(
        key_from="Bent", key_to="Turned", output='ANIMATION', frame_start=1, frame_end=10) \
        == {'FINISHED'}
    assert ext.bridge.bake.bake_frames(obj) == list(range(1, 11))
    scene = bpy.context.scene
    for frame in (1, 4, 10):
        scene.frame_set(frame)
        np.testing.assert_allclose(evaluated_vertices(obj), key_co(obj, f"RS Bake {frame:04d}"),
                                   atol=1e-5)
    scene.frame_set(1)
    np.testing.assert_allclose(evaluated_vertices(obj), bent, atol=1e-5)
    scene.frame_set(10)
    np.testing.assert_allclose(evaluated_vertices(obj), turned, atol=1e-5)
    # Re-running replaces the bake: keys and their F-curves, no leftovers.
    assert bpy.ops.rs_elastic.interpolate_shape_keys(
        key_from="Bent", key_to="Turned", output='ANIMATION', frame_start=3, frame_end=7) \
        == {'FINISHED'}
    assert ext.bridge.bake.bake_frames(obj) == list(range(3, 8))
    curves = ext.bridge.animation.fcurves(obj.data.shape_keys)
    assert sorted(c.data_path for c in curves) == sorted(
        f'key_blocks["RS Bake {f:04d}"].value' for f in range(3, 8))


def test_interpolation_refuses_bad_input_and_changes_nothing(ext):
    obj = make_bar(pin_end=False)
    rotated_keys(obj)
    before = fingerprint(obj)
    with pytest.raises(RuntimeError, match="not prepared"):
        bpy.ops.rs_elastic.interpolate_shape_keys(key_from="Bent", key_to="Turned")
    obj.rs_elastic.edge_length = 0.1
    obj.rs_elastic.num_modes = 3
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    before = fingerprint(obj)
    for kwargs, match in (({"key_from": "Bent", "key_to": "Smile"}, "'Smile' is not a shape key"),
                          ({"key_from": "Bent", "key_to": "Bent"}, "two different"),
                          ({"key_from": "Bent", "key_to": "Turned", "output": 'ANIMATION',
                            "frame_start": 5, "frame_end": 5}, "empty")):
        with pytest.raises(RuntimeError, match=match):
            bpy.ops.rs_elastic.interpolate_shape_keys(**kwargs)
        assert fingerprint(obj) == before


def test_inverted_input_is_flagged_and_gives_finite_poses(ext, capfd):
    obj = prepared_bar(pin_end=False, cuts=3, edge_length=0.1, num_modes=3)
    rest = vertices(obj)
    obj.shape_key_add(name="Basis")
    squashed = rest.copy()
    squashed[:, 2] = 1.0 - squashed[:, 2]        # mirrored through z = 0.5: every tet inverts
    key = obj.shape_key_add(name="Mirrored")
    key.data.foreach_set("co", squashed.astype(np.float32).ravel())
    key.value = 0.0
    assert bpy.ops.rs_elastic.interpolate_shape_keys(key_from="Basis", key_to="Mirrored", count=2) \
        == {'FINISHED'}
    assert "tets are inverted" in capfd.readouterr().out
    for name in ("RS Basis → Mirrored 01", "RS Basis → Mirrored 02"):
        assert np.all(np.isfinite(key_co(obj, name)))
