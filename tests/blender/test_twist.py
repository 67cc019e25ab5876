"""Rotation handles end to end (issue 12 item 3): an Empty keyed 0 -> 360 deg about the bar's axis
with Orientation on twists the bar's end a full turn, winding included.

Oracle: the keyed (linear) Euler F-curve, 6 deg per frame, against the twist of the baked end
measured from its vertices (least-squares angle about the bar's axis, unwrapped over frames).
"""
import numpy as np
import bpy

from blender_helpers import add_tip_handle, evaluated_vertices, make_bar, vertices


def end_angles(obj, tip, frames):
    """(n,) unwrapped twist [deg] about the body's x axis of the tip vertices on `frames`."""
    rest = vertices(obj)[tip]
    rest = rest - rest.mean(axis=0)
    angles = []
    for frame in frames:
        bpy.context.scene.frame_set(frame)
        now = evaluated_vertices(obj)[tip]
        now = now - now.mean(axis=0)
        cross = np.sum(rest[:, 1] * now[:, 2] - rest[:, 2] * now[:, 1])
        angles.append(np.arctan2(cross, np.sum(rest[:, 1:] * now[:, 1:])))
    return np.degrees(np.unwrap(angles))


def test_keyed_full_turn_of_an_orientation_handle_is_baked_with_its_winding(ext):
    obj = make_bar(cuts=3)
    obj.rotation_euler = (0.0, 0.0, 0.4)     # the body's frame is not the world's
    obj.rs_elastic.edge_length = 0.08
    obj.rs_elastic.num_modes = 10
    bpy.context.view_layer.update()
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    tip_world = tuple((np.array(obj.matrix_world) @ np.r_[4.0, 0.5, 0.5, 1.0])[:3])
    empty, tip = add_tip_handle(obj, {0: tip_world, 60: tip_world})
    handle = obj.rs_elastic.handles[0]
    assert handle.orientation is False             # existing scenes are unchanged
    handle.orientation = True
    empty.rotation_mode = 'XYZ'                   # R = Rz(0.4) Rx(theta): about the bar's axis
    for frame, turn in ((0, 0.0), (60, 2.0 * np.pi)):
        empty.rotation_euler = (turn, 0.0, 0.4)
        empty.keyframe_insert("rotation_euler", frame=frame)
    for curve in ext.bridge.animation.fcurves(empty):
        for point in curve.keyframe_points:
            point.interpolation = 'LINEAR'
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 0, 60
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    frames = np.arange(0, 61)
    angles = end_angles(obj, tip, frames)
    error = angles - 6.0 * frames
    checked = [15, 30, 45, 60]
    print(f"baked end twist at frames {checked}: {np.round(angles[checked], 3).tolist()} deg "
          f"(keyed {[6 * f for f in checked]}), max error over frames 2-60 "
          f"{np.abs(error[2:]).max():.3f} deg, handle residual {handle.residual:.2g} m")
    assert np.abs(error[checked]).max() <= 1.0
    assert np.abs(error[2:]).max() <= 1.0       # frames 0 and 1 are held at rest


def test_orientation_targets_every_frame_of_the_keyed_span_and_warns_of_fast_turns(ext):
    """Read back without a solve. Oracle: the keyed linear Euler angle about the bar's axis
    (rotation from the range's first frame, in the body's frame), and the 90 deg/frame limit."""
    obj = make_bar()
    obj.rotation_euler = (0.0, 0.0, 0.4)
    bpy.context.view_layer.update()
    empty, _ = add_tip_handle(obj, {2: (0.0, 0.0, 0.0)})
    empty.rotation_mode = 'XYZ'
    read = ext.bridge.constraints.read_handles
    frames = list(range(0, 11))
    for frame, turn in ((0, 0.0), (8, 2.0 * np.pi)):
        empty.rotation_euler = (turn, 0.0, 0.4)
        empty.keyframe_insert("rotation_euler", frame=frame)
    for curve in ext.bridge.animation.fcurves(empty):
        for point in curve.keyframe_points:
            point.interpolation = 'LINEAR'
    (track,), warnings = read(obj, bpy.context.scene, frames)
    assert track.rotations is None and track.frames.tolist() == [2] and not warnings
    obj.rs_elastic.handles[0].orientation = True
    (track,), warnings = read(obj, bpy.context.scene, frames)
    assert track.frames.tolist() == [2] and track.rotation_frames.tolist() == list(range(9))
    angle = np.radians(45.0) * track.rotation_frames          # 360 deg over 8 frames
    c, s = np.cos(angle), np.sin(angle)
    np.testing.assert_allclose(track.rotations[:, 1:, 1:],
                               np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2),
                               atol=1e-6)
    np.testing.assert_allclose(track.rotations[:, 0, 0], 1.0, atol=1e-6)
    assert not warnings
    empty.keyframe_delete("rotation_euler", frame=8)
    empty.rotation_euler = (2.0 * np.pi, 0.0, 0.4)           # 360 deg in 3 frames: 120/frame
    empty.keyframe_insert("rotation_euler", frame=3)
    for curve in ext.bridge.animation.fcurves(empty):
        for point in curve.keyframe_points:
            point.interpolation = 'LINEAR'
    (track,), warnings = read(obj, bpy.context.scene, frames)
    assert track.rotation_frames.tolist() == [0, 1, 2, 3]
    assert len(warnings) == 1 and "more than 90°" in warnings[0]
