"""Bakes to a Mesh Cache (issue 14 item 3): a .pc2 next to the saved .blend, played by a Mesh
Cache modifier at the top of the stack.

Oracles: the same simulation baked to shape keys (the form tested everywhere else) gives the
positions the modifier must play, frame by frame, within 1e-6 of the diagonal; the .pc2 holds
exactly those float32 poses; ownership (re-bake replaces, Clear Bake and switching back to keys
remove the modifier and its file, the user's fingerprint is restored); an unsaved file is
refused with nothing changed; the .blend does not grow with the frames.
"""
import os

import numpy as np
import pytest
import bpy

from blender_helpers import diagonal, evaluated_vertices, fingerprint, make_bar, preview_pose, \
    user_fingerprint, vertices
from test_spacetime import run_cli

FRAMES = list(range(1, 41))


def saved_bar(tmp_path):
    obj = make_bar(cuts=3)
    obj.rs_elastic.edge_length, obj.rs_elastic.num_modes = 0.08, 6
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = FRAMES[0], FRAMES[-1]
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "shot.blend"))
    obj = bpy.data.objects["Bar"]
    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    return obj


def played(obj, frames):
    out = []
    for frame in frames:
        bpy.context.scene.frame_set(frame)
        out.append(evaluated_vertices(obj))
    return np.array(out)


def test_a_cache_bake_plays_the_simulation_and_owns_only_its_modifier_and_file(ext, tmp_path):
    obj = saved_bar(tmp_path)
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}              # shape keys first
    expected = played(obj, FRAMES)
    bpy.ops.rs_elastic.clear_bake()
    obj.rs_elastic.bake_to = 'CACHE'
    user = user_fingerprint()
    for _ in range(2):                                                # a re-bake replaces
        assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    owned = [m for m in obj.modifiers if m.type == 'MESH_CACHE']
    assert len(owned) == 1 and obj.modifiers[0] == owned[0]
    assert ext.bridge.bake.owned_keys(obj, "bake") == []             # the key bake went
    path = bpy.path.abspath(obj.rs_elastic.cache_bake_file)
    assert os.path.dirname(path) == str(tmp_path / "blendcache_shot" / "bakes")
    samples, header = ext.bridge.mesh_cache.read_pc2(path)
    assert samples.shape == (len(FRAMES), len(obj.data.vertices), 3)
    assert ext.bridge.bake.bake_frames(obj) == FRAMES
    got = played(obj, FRAMES)
    error = np.abs(got - expected).max() / diagonal(vertices(obj))
    print(f"Mesh Cache against the shape-key bake: {error:.2e} of the diagonal")
    assert error < 1e-6
    np.testing.assert_allclose(samples, expected, atol=1e-6 * diagonal(vertices(obj)))
    assert user_fingerprint() == user
    # The mode preview shows over the cache bake, and the bake plays again once it is off.
    bpy.context.scene.frame_set(FRAMES[-1])
    previewed = preview_pose(obj, 'LINEAR', 0.2)
    assert np.abs(previewed - got[-1]).max() > 0.1
    assert np.abs(evaluated_vertices(obj) - got[-1]).max() < 1e-6
    obj.rs_elastic.bake_to = 'KEYS'                                  # back to keys: file goes
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    assert not any(m.type == 'MESH_CACHE' for m in obj.modifiers)
    bpy.ops.wm.save_mainfile()                   # what nothing plays goes at the save
    assert not os.path.exists(path)
    obj.rs_elastic.bake_to = 'CACHE'
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    path = ext.bridge.mesh_cache.bake_file(obj)
    assert bpy.ops.rs_elastic.clear_bake() == {'FINISHED'}
    bpy.ops.wm.save_mainfile()
    assert not any(m.type == 'MESH_CACHE' for m in obj.modifiers) and not os.path.exists(path)
    assert ext.bridge.bake.bake_frames(obj) == []


def test_an_unsaved_file_cannot_bake_to_a_cache_and_nothing_changes(ext):
    obj = make_bar(cuts=3)
    obj.rs_elastic.edge_length, obj.rs_elastic.num_modes = 0.08, 4
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 10
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    obj.rs_elastic.bake_to = 'CACHE'
    before = fingerprint(obj)
    with pytest.raises(RuntimeError, match="Save the .blend first"):
        bpy.ops.rs_elastic.simulate()
    assert fingerprint(obj) == before and len(obj.modifiers) == 0


def test_the_blend_does_not_grow_with_a_cache_bake(ext, tmp_path):
    obj = saved_bar(tmp_path)
    bpy.ops.wm.save_mainfile()
    empty = os.path.getsize(tmp_path / "shot.blend")
    obj.rs_elastic.bake_to = 'CACHE'
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    bpy.ops.wm.save_mainfile()
    grown = os.path.getsize(tmp_path / "shot.blend") - empty
    keys_bytes = len(FRAMES) * len(obj.data.vertices) * 12
    print(f".blend grew by {grown} bytes (a shape-key bake holds {keys_bytes} bytes of positions)")
    assert grown < 20_000


def test_command_line_bakes_to_a_cache(ext, tmp_path):
    obj = saved_bar(tmp_path)
    bpy.ops.wm.save_mainfile()
    blend = tmp_path / "shot.blend"
    result = run_cli(blend, ["bake", "--mode", "simulate", "--object", "Bar", "--bake-to", "cache"])
    assert result.returncode == 0, result.stdout + result.stderr
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    obj = bpy.data.objects["Bar"]
    assert obj.modifiers[0].type == 'MESH_CACHE'
    assert os.path.isfile(bpy.path.abspath(obj.rs_elastic.cache_bake_file))
    assert ext.bridge.bake.bake_frames(obj) == FRAMES
