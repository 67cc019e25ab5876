"""Handles, pose keys, takes and the bake's bookkeeping (no solve needed)."""
import numpy as np
import pytest
import bpy
from mathutils import Matrix

from blender_helpers import make_bar, vertices


def tip_group(obj):
    group = obj.vertex_groups.new(name="Tip")
    group.add([int(i) for i in np.flatnonzero(vertices(obj)[:, 0] > 4.0 - 1e-9)], 1.0, 'REPLACE')
    return group


def test_handle_from_a_vertex_group_sits_at_its_world_centroid(ext):
    obj = make_bar()
    obj.location = (1.0, 2.0, 3.0)
    obj.rotation_euler = (0.0, 0.0, 0.5)
    bpy.context.view_layer.update()
    tip_group(obj)
    assert bpy.ops.rs_elastic.add_handle(vertex_group="Tip") == {'FINISHED'}
    handle = obj.rs_elastic.handles[0]
    assert handle.vertex_group == "Tip" and handle.empty.type == 'EMPTY'
    rest = vertices(obj)
    centroid = rest[rest[:, 0] > 4.0 - 1e-9].mean(axis=0)
    expected = np.array(obj.matrix_world @ Matrix.Translation(centroid).to_translation())
    np.testing.assert_allclose(np.array(handle.empty.location), expected, atol=1e-6)


def test_handle_from_the_edit_mode_selection(ext):
    obj = make_bar()
    bpy.ops.object.mode_set(mode='EDIT')
    bpy.ops.mesh.select_all(action='DESELECT')
    bpy.ops.object.mode_set(mode='OBJECT')
    tip = vertices(obj)[:, 0] > 4.0 - 1e-9
    obj.data.vertices.foreach_set("select", tip)
    bpy.ops.object.mode_set(mode='EDIT')
    assert bpy.ops.rs_elastic.add_handle() == {'FINISHED'}
    assert obj.mode == 'EDIT'
    bpy.ops.object.mode_set(mode='OBJECT')
    group = obj.vertex_groups[obj.rs_elastic.handles[0].vertex_group]
    members = {v.index for v in obj.data.vertices for g in v.groups if g.group == group.index}
    assert members == set(np.flatnonzero(tip))


def test_add_handle_refuses_an_empty_selection_and_no_group(ext):
    obj = make_bar()
    names = sorted(o.name for o in bpy.data.objects)
    with pytest.raises(RuntimeError, match="Edit Mode"):
        bpy.ops.rs_elastic.add_handle()
    with pytest.raises(RuntimeError, match="does not exist"):
        bpy.ops.rs_elastic.add_handle(vertex_group="Nope")
    bpy.ops.object.mode_set(mode='EDIT')
    bpy.ops.mesh.select_all(action='DESELECT')
    with pytest.raises(RuntimeError, match="No vertices are selected"):
        bpy.ops.rs_elastic.add_handle()
    bpy.ops.object.mode_set(mode='OBJECT')
    assert sorted(o.name for o in bpy.data.objects) == names
    assert len(obj.rs_elastic.handles) == 0


def test_keyed_empty_locations_become_targets_in_the_body_frame(ext):
    obj = make_bar()
    obj.location = (0.5, -1.0, 2.0)
    obj.rotation_euler = (0.3, 0.0, 1.0)
    obj.scale = (2.0, 2.0, 2.0)
    tip_group(obj)
    bpy.ops.rs_elastic.add_handle(vertex_group="Tip")
    empty = obj.rs_elastic.handles[0].empty
    keyed = {10: (3.0, 1.0, 2.0), 25: (-1.0, 4.0, 0.0)}
    for frame, location in keyed.items():
        empty.location = location
        empty.keyframe_insert("location", frame=frame)
    tracks, warnings = ext.bridge.constraints.read_handles(obj, bpy.context.scene, range(1, 101))
    assert warnings == [] and len(tracks) == 1
    assert list(tracks[0].frames) == [10, 25]
    to_body = np.array(obj.matrix_world.inverted())
    for frame, target in zip(tracks[0].frames, tracks[0].targets):
        expected = (to_body @ np.r_[keyed[int(frame)], 1.0])[:3]
        np.testing.assert_allclose(target, expected, atol=1e-6)
    obj.rs_elastic.handles[0].follow = True
    tracks, _ = ext.bridge.constraints.read_handles(obj, bpy.context.scene, range(5, 15))
    assert list(tracks[0].frames) == list(range(5, 15))


def _evaluated_x(obj, frame):
    bpy.context.scene.frame_set(frame)
    return obj.matrix_world.translation.x


def test_keys_in_nla_strips_count_on_the_frames_the_strips_play_them(ext):
    """An Empty whose keys were pushed down to NLA strips: each key counts on every scene frame
    where a playing strip plays it (start, scale, repeats, reversal), a muted track's never."""
    obj = make_bar()
    tip_group(obj)
    bpy.ops.rs_elastic.add_handle(vertex_group="Tip")
    empty = obj.rs_elastic.handles[0].empty
    values = {1: 0.0, 5: 2.0, 11: 7.0}              # distinct: a frame's value names its key
    for frame, x in values.items():
        empty.location = (x, 0.5, 0.5)
        empty.keyframe_insert("location", frame=frame)
    anim = empty.animation_data
    action = anim.action
    stretched = anim.nla_tracks.new().strips.new("Stretched", 20, action)
    stretched.scale, stretched.repeat = 2.0, 2.0     # plays 20-60: keys at 20, 28, 40 | 40, 48, 60
    backwards = anim.nla_tracks.new().strips.new("Backwards", 100, action)
    backwards.use_reverse = True                     # plays 100-110: keys 11, 5, 1 at 100, 106, 110
    muted = anim.nla_tracks.new()
    muted.strips.new("Muted", 200, action)
    muted.mute = True
    anim.action = None
    for strip in (stretched, backwards):
        strip.extrapolation = 'NOTHING'              # no hold over the other strip's frames
    tracks, warnings = ext.bridge.constraints.read_handles(obj, bpy.context.scene, range(1, 251))
    assert warnings == [] and len(tracks) == 1
    assert list(tracks[0].frames) == [20, 28, 40, 48, 60, 100, 106, 110]
    # Blender's own evaluation puts that key's value there (the next repeat's first key where
    # two repeats meet), and each target is where the Empty is on its frame
    played = [1, 5, 1, 5, 11, 11, 5, 1]
    for frame, key, target in zip(tracks[0].frames, played, tracks[0].targets):
        assert _evaluated_x(empty, int(frame)) == pytest.approx(values[key]), frame
        np.testing.assert_allclose(target, np.array(obj.matrix_world.inverted()
                                                     @ empty.matrix_world.translation), atol=1e-6)
    bpy.context.scene.frame_set(1)
    backwards.use_animated_time = True               # its own time curve: every frame it plays
    tracks, _ = ext.bridge.constraints.read_handles(obj, bpy.context.scene, range(1, 251))
    assert list(tracks[0].frames) == [20, 28, 40, 48, 60] + list(range(100, 111))


def test_an_empty_without_keys_says_how_to_follow_it(ext):
    obj = make_bar()
    tip_group(obj)
    bpy.ops.rs_elastic.add_handle(vertex_group="Tip")
    handle = obj.rs_elastic.handles[0]
    mover = bpy.data.objects.new("Mover", None)
    bpy.context.scene.collection.objects.link(mover)
    handle.empty.parent = mover                      # moved by its parent, not by its own keys
    for frame, x in ((1, 0.0), (10, 1.0)):
        mover.location = (x, 0.0, 0.0)
        mover.keyframe_insert("location", frame=frame)
    tracks, warnings = ext.bridge.constraints.read_handles(obj, bpy.context.scene, range(1, 11))
    assert tracks == [] and "Follow Every Frame" in warnings[0]
    handle.follow = True
    tracks, warnings = ext.bridge.constraints.read_handles(obj, bpy.context.scene, range(1, 11))
    assert warnings == [] and list(tracks[0].frames) == list(range(1, 11))
    assert tracks[0].targets[-1] - tracks[0].targets[0] == pytest.approx([1.0, 0.0, 0.0])


def test_a_deleted_empty_is_reported_and_ignored(ext):
    obj = make_bar()
    tip_group(obj)
    bpy.ops.rs_elastic.add_handle(vertex_group="Tip")
    empty = obj.rs_elastic.handles[0].empty
    empty.keyframe_insert("location", frame=5)
    bpy.data.objects.remove(empty)
    tracks, warnings = ext.bridge.constraints.read_handles(obj, bpy.context.scene, range(1, 11))
    assert tracks == [] and "Empty was deleted" in warnings[0]


def test_pose_keys_keyed_to_one_are_full_pose_constraints(ext):
    obj = make_bar()
    obj.shape_key_add(name="Basis")
    pose = obj.shape_key_add(name="Pose")
    for frame, value in ((20, 0.0), (30, 1.0), (40, 0.0)):
        pose.value = value
        pose.keyframe_insert("value", frame=frame)
    other = obj.shape_key_add(name="Half")
    other.value = 0.5
    other.keyframe_insert("value", frame=30)
    assert ext.bridge.constraints.read_pose_keys(obj, range(1, 101)) == [(30, "Pose")]
    assert ext.bridge.constraints.read_pose_keys(obj, range(1, 25)) == []
    # pushed down to an NLA strip that starts 50 frames later: the key plays on frame 80
    anim = obj.data.shape_keys.animation_data
    strip = anim.nla_tracks.new().strips.new("Later", 70, anim.action)
    anim.action = None
    assert strip.frame_start == 70 and strip.action_frame_start == 20
    assert ext.bridge.constraints.read_pose_keys(obj, range(1, 101)) == [(80, "Pose")]


def test_bake_take_and_clear_keep_the_users_keys_and_keyframes(ext):
    obj = make_bar()
    obj.shape_key_add(name="Basis")
    smile = obj.shape_key_add(name="Smile")
    smile.keyframe_insert("value", frame=3)
    bake = ext.bridge.bake
    rest = vertices(obj)
    poses = np.stack([rest + 0.01 * f for f in range(1, 6)])
    bake.write_bake(obj, range(1, 6), poses)
    assert bake.bake_frames(obj) == [1, 2, 3, 4, 5]
    assert bpy.ops.rs_elastic.keep_take() == {'FINISHED'}
    frames, take = bake.take_poses(obj)
    assert frames == [1, 2, 3, 4, 5] and bake.bake_frames(obj) == []
    np.testing.assert_allclose(take, poses, atol=1e-6)
    curves = ext.bridge.animation.fcurves(obj.data.shape_keys)
    assert [c.data_path for c in curves] == ['key_blocks["Smile"].value']
    bake.write_bake(obj, range(1, 3), poses[:2])
    assert bpy.ops.rs_elastic.clear_bake() == {'FINISHED'}
    assert bpy.ops.rs_elastic.clear_bake() == {'CANCELLED'}
    assert [c.data_path for c in curves] == ['key_blocks["Smile"].value']
    assert [k.name for k in obj.data.shape_keys.key_blocks][:2] == ["Basis", "Smile"]


def test_clear_bake_can_be_undone(ext):
    """The UI pushes an undo step after every operator flagged UNDO; background mode does not,
    so the test pushes the two steps the UI would."""
    assert 'UNDO' in ext.operators.clear_bake.RS_ELASTIC_OT_clear_bake.bl_options
    obj = make_bar()
    rest = vertices(obj)
    ext.bridge.bake.write_bake(obj, range(1, 4), np.stack([rest] * 3))
    bpy.ops.ed.undo_push(message="baked")
    assert bpy.ops.rs_elastic.clear_bake() == {'FINISHED'}
    bpy.ops.ed.undo_push(message="Clear Bake")
    assert ext.bridge.bake.bake_frames(bpy.data.objects["Bar"]) == []
    bpy.ops.ed.undo()
    assert ext.bridge.bake.bake_frames(bpy.data.objects["Bar"]) == [1, 2, 3]


def test_with_a_handle_active_the_operators_act_on_its_body(ext):
    """F3, a shortcut or a script with a handle's Empty active: the operators work on the body
    the sidebar shows for it, as its buttons do, and leave the Empty's own settings alone; an
    Empty that is no handle is refused in one line."""
    from blender_helpers import add_tip_handle, make_active
    from test_faults import refusal
    obj = make_bar(cuts=3)
    obj.rs_elastic.edge_length, obj.rs_elastic.num_modes = 0.1, 3
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 8
    empty, _ = add_tip_handle(obj, {1: (4.0, 0.5, 0.5), 8: (4.0, 0.5, 1.0)})
    make_active(empty)
    untouched = {name: getattr(empty.rs_elastic, name)
                 for name in ("youngs_modulus", "density", "tets_key", "prepared_key")}

    assert bpy.ops.rs_elastic.apply_material_preset(preset="SILICONE") == {'FINISHED'}
    assert (obj.rs_elastic.youngs_modulus, obj.rs_elastic.density) == (3.0e5, 1100.0)
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert obj.rs_elastic.is_prepared
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    assert ext.bridge.bake.bake_frames(obj) == list(range(1, 9))
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    assert ext.bridge.bake.bake_frames(obj) == list(range(1, 9))
    assert bpy.ops.rs_elastic.remove_handle() == {'FINISHED'}
    assert len(obj.rs_elastic.handles) == 0
    assert bpy.context.active_object == empty
    assert {name: getattr(empty.rs_elastic, name) for name in untouched} == untouched

    loose = bpy.data.objects.new("Loose", None)
    bpy.context.scene.collection.objects.link(loose)
    make_active(loose)
    assert refusal(bpy.ops.rs_elastic.prepare) == "'Loose' is an empty, not a mesh"
