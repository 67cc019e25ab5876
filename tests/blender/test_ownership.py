"""Mesh Cache bakes own what they write (issue 26, item 2).

A bake's file is named by an identity stored with the object's bake, not by the object's name;
the extension's modifier is the Mesh Cache modifier that plays that file, whatever it is called;
a file is deleted only from the .blend's own bakes folder and only when no modifier plays it any
more; a save under another folder or name gives the new .blend its own copy.

Each test bakes through the extension's own writer (`bake.write_bake`, what every operator calls)
a known motion, and checks what the modifier plays frame by frame against that motion (played
positions are the evaluated mesh: the oracle is independent of how the bake is found), which
files exist, and that the user's own modifier and file are untouched.
"""
import os
import shutil

import numpy as np
import bpy

from blender_helpers import evaluated_vertices, make_active, make_bar, vertices

FRAMES = list(range(1, 9))


def motion(obj, amplitude):
    """(F, n, 3) poses: the bar bends upward, more on every frame (distinct per amplitude)."""
    rest = vertices(obj)
    bend = np.zeros_like(rest)
    bend[:, 2] = (rest[:, 0] / 4.0) ** 2
    return np.stack([rest + amplitude * (k + 1) * bend for k in range(len(FRAMES))])


def cache_bake(ext, obj, amplitude):
    obj.rs_elastic.bake_to = 'CACHE'
    poses = motion(obj, amplitude)
    ext.bridge.bake.write_bake(obj, FRAMES, poses)
    return poses


def played(obj):
    out = []
    for frame in FRAMES:
        bpy.context.scene.frame_set(frame)
        out.append(evaluated_vertices(obj))
    return np.array(out)


def plays(obj, poses):
    np.testing.assert_allclose(played(obj), poses, atol=1e-6)


def cache_modifiers(obj):
    return [m for m in obj.modifiers if m.type == 'MESH_CACHE']


def played_file(obj):
    """The file the object's one Mesh Cache modifier plays, as Blender resolves its path."""
    modifier, = cache_modifiers(obj)
    return os.path.normpath(bpy.path.abspath(modifier.filepath))


PLAYER = ("cache_format", "filepath", "deform_mode", "interpolation", "time_mode", "play_mode",
          "frame_start", "frame_scale", "show_viewport")


def clear(obj):
    make_active(obj)
    return bpy.ops.rs_elastic.clear_bake()


def files(folder):
    return sorted(os.listdir(folder)) if os.path.isdir(folder) else []


def saved(path):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(path))


def test_bodies_whose_names_read_alike_in_a_file_name_own_separate_bakes(ext, tmp_path):
    first, second = make_bar("Bar.001"), make_bar("Bar_001")
    second.location.y = 3.0
    saved(tmp_path / "shot.blend")
    first_poses = cache_bake(ext, first, 0.1)
    cache_bake(ext, second, 0.3)
    plays(first, first_poses)                  # the second bake did not write over the first
    assert played_file(first) != played_file(second)
    assert clear(second) == {'FINISHED'}
    assert os.path.isfile(played_file(first))
    plays(first, first_poses)


def test_a_duplicate_gets_its_own_bake_and_never_deletes_the_originals(ext, tmp_path):
    obj = make_bar()
    saved(tmp_path / "shot.blend")
    poses = cache_bake(ext, obj, 0.2)
    copy = obj.copy()                          # Shift+D: the object and its mesh copied
    copy.data = obj.data.copy()
    copy.location.y = 3.0
    bpy.context.scene.collection.objects.link(copy)
    original_file = played_file(obj)
    assert played_file(copy) == original_file     # the duplicate plays it too
    assert clear(copy) == {'FINISHED'}
    assert cache_modifiers(copy) == []
    assert os.path.isfile(original_file)       # the original still plays it
    plays(obj, poses)
    copy_poses = cache_bake(ext, copy, 0.5)    # its first bake: a file of its own
    assert played_file(copy) != original_file
    plays(obj, poses)
    plays(copy, copy_poses)
    copy_file = played_file(copy)
    assert clear(obj) == {'FINISHED'}
    assert os.path.isfile(original_file)       # until the save: undo may bring its bake back
    bpy.ops.wm.save_mainfile()
    assert not os.path.exists(original_file)   # nothing plays it any more
    assert os.path.isfile(copy_file)
    plays(copy, copy_poses)


def test_a_duplicate_rebaked_without_clearing_leaves_the_originals_file(ext, tmp_path):
    obj = make_bar()
    saved(tmp_path / "shot.blend")
    poses = cache_bake(ext, obj, 0.2)
    copy = obj.copy()
    copy.data = obj.data.copy()
    bpy.context.scene.collection.objects.link(copy)
    cache_bake(ext, copy, 0.4)
    assert played_file(copy) != played_file(obj)
    plays(obj, poses)


def test_a_users_mesh_cache_named_like_the_extensions_is_never_touched(ext, tmp_path):
    obj = make_bar()
    saved(tmp_path / "shot.blend")
    mine = tmp_path / "mine" / "wave.pc2"
    mine.parent.mkdir()
    ext.bridge.mesh_cache.write_pc2(str(mine), motion(obj, 0.7)[:3])
    modifier = obj.modifiers.new("RS Elastic Bake", 'MESH_CACHE')
    modifier.cache_format, modifier.filepath, modifier.frame_start = 'PC2', str(mine), 5.0
    modifier.show_viewport = False
    settings = [(p, getattr(modifier, p)) for p in PLAYER]
    content = mine.read_bytes()
    assert clear(obj) == {'CANCELLED'}                      # no bake of ours: nothing to clear
    for amplitude in (0.1, 0.2):                            # a re-bake replaces our own only
        cache_bake(ext, obj, amplitude)
    assert clear(obj) == {'FINISHED'}
    kept = cache_modifiers(obj)
    assert [m.name for m in kept] == ["RS Elastic Bake"]
    assert [(p, getattr(kept[0], p)) for p in PLAYER] == settings
    assert mine.read_bytes() == content
    bpy.ops.wm.save_mainfile()
    assert mine.read_bytes() == content
    assert files(tmp_path / "blendcache_shot" / "bakes") == []


def test_a_save_as_to_another_folder_keeps_the_bake_playing_and_clearable(ext, tmp_path):
    obj = make_bar()
    saved(tmp_path / "a" / "shot.blend")
    poses = cache_bake(ext, obj, 0.2)
    bpy.ops.wm.save_mainfile()
    saved(tmp_path / "b" / "take2.blend")
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "b" / "take2.blend"))
    obj = bpy.data.objects["Bar"]
    assert ext.bridge.bake.bake_frames(obj) == FRAMES
    plays(obj, poses)
    own = tmp_path / "b" / "blendcache_take2" / "bakes"
    assert os.path.dirname(played_file(obj)) == str(own)
    assert clear(obj) == {'FINISHED'}
    bpy.ops.wm.save_mainfile()
    assert cache_modifiers(obj) == [] and files(own) == []
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "a" / "shot.blend"))
    obj = bpy.data.objects["Bar"]                      # the first .blend kept its own bake
    plays(obj, poses)
    assert clear(obj) == {'FINISHED'}
    bpy.ops.wm.save_mainfile()
    assert files(tmp_path / "a" / "blendcache_shot" / "bakes") == []


def test_a_saved_copy_gets_its_own_bake_and_the_open_file_keeps_its_own(ext, tmp_path):
    obj = make_bar()
    saved(tmp_path / "a" / "shot.blend")
    poses = cache_bake(ext, obj, 0.2)
    path, record = obj.modifiers[0].filepath, obj.rs_elastic.cache_bake_file
    os.makedirs(tmp_path / "c")
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "c" / "copy.blend"), copy=True)
    assert (obj.modifiers[0].filepath, obj.rs_elastic.cache_bake_file) == (path, record)
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "c" / "copy.blend"))
    obj = bpy.data.objects["Bar"]
    assert ext.bridge.bake.bake_frames(obj) == FRAMES
    assert os.path.dirname(played_file(obj)) == \
        str(tmp_path / "c" / "blendcache_copy" / "bakes")
    plays(obj, poses)


def test_a_renamed_body_in_a_moved_folder_keeps_its_bake_playing_and_clearable(ext, tmp_path):
    obj = make_bar()
    saved(tmp_path / "a" / "shot.blend")
    poses = cache_bake(ext, obj, 0.2)
    obj.name = "Renamed"
    bpy.ops.wm.save_mainfile()
    bpy.ops.wm.read_homefile(use_empty=True)
    shutil.move(tmp_path / "a", tmp_path / "moved")
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "moved" / "shot.blend"))
    obj = bpy.data.objects["Renamed"]
    assert ext.bridge.bake.bake_frames(obj) == FRAMES
    plays(obj, poses)
    assert clear(obj) == {'FINISHED'}
    bpy.ops.wm.save_mainfile()
    assert files(tmp_path / "moved" / "blendcache_shot" / "bakes") == []


def legacy_bake(ext, obj, poses, blend_folder):
    """A bake as the extension wrote it before identities: `<object>.pc2`, a modifier named
    "RS Elastic Bake", the path recorded in cache_bake_file."""
    path = os.path.join(blend_folder, "blendcache_shot", "bakes", "Bar.pc2")
    os.makedirs(os.path.dirname(path))
    ext.bridge.mesh_cache.write_pc2(path, poses)
    modifier = obj.modifiers.new("RS Elastic Bake", 'MESH_CACHE')
    modifier.cache_format, modifier.deform_mode = 'PC2', 'OVERWRITE'
    modifier.filepath, modifier.frame_start = bpy.path.relpath(path), float(FRAMES[0])
    obj.rs_elastic.cache_bake_file = modifier.filepath
    return path


def test_a_bake_from_before_identities_is_recognised_and_cleared(ext, tmp_path):
    obj = make_bar()
    saved(tmp_path / "shot.blend")
    poses = motion(obj, 0.2)
    path = legacy_bake(ext, obj, poses, str(tmp_path))
    assert ext.bridge.bake.bake_frames(obj) == FRAMES
    plays(obj, poses)
    assert clear(obj) == {'FINISHED'}
    bpy.ops.wm.save_mainfile()
    assert cache_modifiers(obj) == [] and not os.path.exists(path)


def test_a_bake_from_before_identities_saved_elsewhere_by_the_old_extension(ext, tmp_path):
    # The old extension left the record as it was (Blender remaps only the modifier's path), so
    # the record no longer says where the file is: the modifier does. The file belongs to the
    # first .blend: clearing the bake in the second removes its modifier and leaves the file.
    obj = make_bar()
    saved(tmp_path / "a" / "shot.blend")
    poses = motion(obj, 0.2)
    path = legacy_bake(ext, obj, poses, str(tmp_path / "a"))
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "take2.blend"))
    obj = bpy.data.objects["Bar"]
    obj.modifiers[0].filepath = bpy.path.relpath(path)      # as Blender remapped it
    obj.rs_elastic.cache_bake_file = "//blendcache_shot/bakes/Bar.pc2"
    assert ext.bridge.bake.bake_frames(obj) == FRAMES
    plays(obj, poses)
    assert clear(obj) == {'FINISHED'}
    bpy.ops.wm.save_mainfile()
    assert cache_modifiers(obj) == [] and os.path.isfile(path)


def test_the_command_line_saving_elsewhere_gives_the_output_its_own_bake(ext, tmp_path):
    from test_mesh_cache import FRAMES as SHOT_FRAMES, saved_bar
    from test_spacetime import run_cli
    saved_bar(tmp_path)
    bpy.ops.wm.save_mainfile()
    out = tmp_path / "other" / "out.blend"
    out.parent.mkdir()
    result = run_cli(tmp_path / "shot.blend", ["bake", "--mode", "simulate", "--object", "Bar",
                                               "--bake-to", "cache", "--output", str(out)])
    assert result.returncode == 0, result.stdout + result.stderr
    bpy.ops.wm.open_mainfile(filepath=str(out))
    obj = bpy.data.objects["Bar"]
    assert ext.bridge.bake.bake_frames(obj) == SHOT_FRAMES
    assert os.path.dirname(played_file(obj)) == str(out.parent / "blendcache_out" / "bakes")
    assert clear(obj) == {'FINISHED'}
    bpy.ops.wm.save_mainfile()
    assert files(out.parent / "blendcache_out" / "bakes") == []
    # The bake the command line wrote beside the opened file is played by no saved .blend.
    assert files(tmp_path / "blendcache_shot" / "bakes") == []


def test_undo_brings_back_a_cleared_or_replaced_bake_with_its_file(ext, tmp_path):
    """Clear Bake and a re-bake leave the old file until the save; undo plays it again; the save
    deletes only what nothing plays."""
    obj = make_bar()
    saved(tmp_path / "shot.blend")
    poses = cache_bake(ext, obj, 0.2)
    first = played_file(obj)
    bpy.ops.ed.undo_push(message="baked")
    assert clear(obj) == {'FINISHED'}
    bpy.ops.ed.undo_push(message="cleared")
    bpy.ops.ed.undo()
    obj = bpy.data.objects["Bar"]
    assert played_file(obj) == first
    plays(obj, poses)
    again = cache_bake(ext, obj, 0.5)                     # a re-bake: a new file
    assert played_file(obj) != first and os.path.isfile(first)
    bpy.ops.wm.save_mainfile()
    assert files(tmp_path / "blendcache_shot" / "bakes") == [os.path.basename(played_file(obj))]
    plays(obj, again)
