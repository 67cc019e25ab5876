"""Writing outside Object Mode (issue 26, item 3): Edit Mode keeps its own copy of the mesh and
its shape keys and writes it back when it is left, so whatever an operator wrote to the keys
meanwhile is lost (a bake became the rest pose; cleared keys came back untagged). Every operator
that writes keys or modifiers refuses outside Object Mode with one line and changes nothing;
the mode preview and Live write nothing there and show once the body is back in Object Mode.
Prepare (it only reads the mesh) and Add Handle (it reads the selection) keep working in Edit
Mode.

Oracles: `state_fingerprint` (every key with its data and tags, F-curves, modifiers, results)
before the refusal, and again after leaving the mode; the preview's pose computed in Object Mode;
the live solution's own pose.
"""
import numpy as np
import pytest
import bpy

import creature
from blender_helpers import add_tip_handle, evaluated_vertices, make_active, make_bar, \
    preview_pose, state_fingerprint, vertices

FRAMES = (1, 6)


def prepared_bar(mode='OBJECT'):
    """A coarse pinned bar prepared in `mode` (Prepare only reads the mesh: it works there)."""
    obj = make_bar()
    settings = obj.rs_elastic
    settings.edge_length, settings.num_modes = 0.15, 6
    settings.use_scene_range = False
    settings.frame_start, settings.frame_end = FRAMES
    bpy.ops.object.mode_set(mode=mode)
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert obj.mode == mode and settings.is_prepared
    bpy.ops.object.mode_set(mode='OBJECT')
    return obj


def refused(operator, **arguments):
    """The operator's one error line; it must raise and change nothing."""
    before = state_fingerprint()
    with pytest.raises(RuntimeError) as info:
        operator(**arguments)
    assert state_fingerprint() == before
    lines = [line.removeprefix("Error: ") for line in str(info.value).strip().splitlines()]
    assert len(lines) == 1, lines
    return lines[0]


def user_key(obj, name="Smile"):
    if obj.data.shape_keys is None:
        obj.shape_key_add(name="Basis", from_mix=False)
    block = obj.shape_key_add(name=name, from_mix=False)
    block.data.foreach_set("co", (vertices(obj) + 0.01).astype(np.float32).ravel())
    return block


def test_prepare_works_in_edit_mode(ext):
    prepared_bar(mode='EDIT')


@pytest.mark.parametrize("bake_to", ['KEYS', 'CACHE'])
def test_simulate_and_bake_in_edit_mode_is_refused_and_the_old_bake_survives(ext, tmp_path,
                                                                             bake_to):
    obj = prepared_bar()
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "shot.blend"))
    obj = bpy.data.objects["Bar"]
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}            # the bake to keep
    obj.rs_elastic.bake_to = bake_to
    bpy.ops.object.mode_set(mode='EDIT')
    before = state_fingerprint(tmp_path)
    assert refused(bpy.ops.rs_elastic.simulate) == \
        "'Bar' is in Edit Mode: switch to Object Mode (Tab) to bake"
    bpy.ops.object.mode_set(mode='OBJECT')          # Edit Mode writes its copy back
    assert state_fingerprint(tmp_path) == before
    assert ext.bridge.bake.bake_frames(obj) == list(range(FRAMES[0], FRAMES[1] + 1))


def test_clear_bake_in_edit_mode_is_refused_and_the_bake_stays_clearable(ext):
    obj = prepared_bar()
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    bpy.ops.object.mode_set(mode='EDIT')
    before = state_fingerprint()
    assert refused(bpy.ops.rs_elastic.clear_bake) == \
        "'Bar' is in Edit Mode: switch to Object Mode (Tab) to clear its bake"
    bpy.ops.object.mode_set(mode='OBJECT')
    assert state_fingerprint() == before
    assert bpy.ops.rs_elastic.clear_bake() == {'FINISHED'}
    assert obj.data.shape_keys is None                               # all of it went


def test_every_writing_operator_refuses_outside_object_mode(ext):
    obj = prepared_bar()
    empty, _ = add_tip_handle(obj, {3: (4.0, 0.5, 1.0)})
    user_key(obj)
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    bpy.context.view_layer.objects.active = obj
    bpy.ops.object.mode_set(mode='EDIT')
    tab = "switch to Object Mode (Tab) to"
    assert refused(bpy.ops.rs_elastic.solve_spacetime) == f"'Bar' is in Edit Mode: {tab} bake"
    assert refused(bpy.ops.rs_elastic.keep_take) == f"'Bar' is in Edit Mode: {tab} keep its bake"
    for output in ('KEYS', 'ANIMATION'):
        assert refused(bpy.ops.rs_elastic.interpolate_shape_keys, key_from="Basis",
                       key_to="Smile", output=output, frame_start=1, frame_end=4) == \
            f"'Bar' is in Edit Mode: {tab} write shape keys"
    bpy.ops.object.mode_set(mode='SCULPT')
    assert refused(bpy.ops.rs_elastic.simulate) == \
        "'Bar' is in Sculpt Mode: switch to Object Mode to bake"
    assert refused(bpy.ops.rs_elastic.clear_bake) == \
        "'Bar' is in Sculpt Mode: switch to Object Mode to clear its bake"
    bpy.ops.object.mode_set(mode='WEIGHT_PAINT')
    assert refused(bpy.ops.rs_elastic.simulate) == \
        "'Bar' is in Weight Paint mode: switch to Object Mode to bake"
    bpy.ops.object.mode_set(mode='OBJECT')
    assert bpy.ops.rs_elastic.keep_take() == {'FINISHED'}            # and in Object Mode, all go


def test_the_mode_preview_writes_nothing_in_edit_mode_and_shows_once_back(ext):
    obj = prepared_bar()
    rest = vertices(obj)
    expected = preview_pose(obj, 'LINEAR', 0.2)                      # in Object Mode
    assert np.abs(expected - rest).max() > 0.1
    bpy.ops.object.mode_set(mode='EDIT')
    obj.rs_elastic.preview_enabled = True
    written_in_edit_mode = obj.data.shape_keys is not None
    bpy.ops.object.mode_set(mode='OBJECT')
    np.testing.assert_allclose(evaluated_vertices(obj), expected, atol=1e-5)
    assert not written_in_edit_mode               # leaving Edit Mode would overwrite a key
    bpy.ops.object.mode_set(mode='EDIT')
    obj.rs_elastic.preview_enabled = False
    bpy.ops.object.mode_set(mode='OBJECT')
    assert obj.data.shape_keys is None            # gone, not back as an untagged key
    np.testing.assert_array_equal(evaluated_vertices(obj), rest)


def test_live_writes_nothing_in_edit_mode_and_shows_its_pose_once_back(ext):
    live = ext.bridge.live
    obj = prepared_bar()
    obj.rs_elastic.use_scene_range = True
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 12
    add_tip_handle(obj, {6: (4.0, 0.5, 1.2), 12: (4.0, 0.5, 0.3)})
    bpy.context.view_layer.objects.active = obj
    bpy.context.scene.frame_set(6)
    bpy.ops.object.mode_set(mode='EDIT')
    obj.rs_elastic.live = True
    assert live.flush() == [obj.name]
    written_in_edit_mode = obj.data.shape_keys is not None
    bpy.ops.object.mode_set(mode='OBJECT')
    live.flush()                                   # asked again once back in Object Mode
    solution = live.SOLUTIONS[obj.name]
    pose = solution.pose(6 - solution.frames[0])
    assert np.abs(pose - vertices(obj)).max() > 0.05              # the pose is not the rest
    np.testing.assert_allclose(evaluated_vertices(obj), pose, atol=1e-5)
    assert not written_in_edit_mode
    live.stop(obj)


def test_follow_selected_bones_is_refused_in_edit_mode_and_works_in_weight_paint(ext):
    obj, rig = creature.build(bpy, np)
    make_active(obj)
    ext.bridge.armature.select_bones(rig, ["Body"])
    bpy.ops.object.mode_set(mode='EDIT')
    assert refused(bpy.ops.rs_elastic.follow_bones) == \
        f"'{obj.name}' is in Edit Mode: switch to Object Mode (Tab) to set Follow Rig"
    bpy.ops.object.mode_set(mode='WEIGHT_PAINT')          # where weights are painted
    assert bpy.ops.rs_elastic.follow_bones() == {'FINISHED'}
    bpy.ops.object.mode_set(mode='OBJECT')
    np.testing.assert_array_equal(ext.bridge.scene.group_weights(obj, "Follow Rig"),
                                  ext.bridge.scene.group_weights(obj, "Body"))
