"""The farm's Blender side (bridge/farm.py and the command line's farm options; the farm itself
runs in tests/farm): the plan of a shot (which bodies, how each is baked, whose bakes it reads,
in an order where those come first, and the new bake file each is baked to), and the
command-line steps its tasks run, each in a new Blender process: prepare only, bake only (which
prepares nothing), a bake that writes only the .pc2 its job named while another body's farm bake
plays as that body's bake, and collect.

Oracles: the dependencies the scene sets up by hand, the order that follows from them, the
files each step may and may not write or delete (the .blend's bytes before and after, the bakes
folder's listing), the bake that plays after collect against the .pc2 the bake wrote."""
import json
import pathlib
import re
import shutil

import numpy as np
import bpy

from blender_helpers import make_active, make_bar
from test_spacetime import run_cli

FRAMES = list(range(1, 13))


def tetrahedralized_bar(name, y, **settings):
    obj = make_bar(name=name, length=2.0, width=0.5)
    obj.location.y = y
    obj.rs_elastic.edge_length, obj.rs_elastic.num_modes = 0.3, 3
    for key, value in settings.items():
        setattr(obj.rs_elastic, key, value)
    assert bpy.ops.rs_elastic.tetrahedralize() == {'FINISHED'}
    return obj


def plan(ext):
    return json.loads(ext.bridge.farm.plan_json(bpy.context.scene))


def identity(ext, obj, file_name):
    """The identity of a bake file name of `obj` (an oracle apart from mesh_cache's own parser):
    the object's name with other characters than letters, digits, '_' and '-' made '_', a dot,
    16 hex digits, '.pc2'."""
    readable = re.sub(r"[^A-Za-z0-9_-]", "_", obj.name)
    match = re.fullmatch(re.escape(readable) + r"\.([0-9a-f]{16})\.pc2", file_name)
    assert match is not None, file_name
    assert ext.bridge.mesh_cache.identity_of(obj, file_name) == match.group(1)
    return match.group(1)


def test_the_plan_lists_each_body_after_the_bakes_it_reads(ext):
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 24
    slab = tetrahedralized_bar("Slab", 0.0)
    slab.modifiers.new("Collision", 'COLLISION')
    tetrahedralized_bar("Drop", 2.0)                            # collides with Slab
    whip = tetrahedralized_bar("Whip", 4.0, use_scene_range=False, frame_start=5, frame_end=20)
    whip.vertex_groups.new(name="Tip").add([0], 1.0, 'REPLACE')
    make_active(whip)
    assert bpy.ops.rs_elastic.add_handle(vertex_group="Tip") == {'FINISHED'}
    empty = whip.rs_elastic.handles[0].empty
    empty.parent, empty.parent_type = bpy.data.objects["Drop"], 'VERTEX'   # rides Drop's bake
    tag = tetrahedralized_bar("Tag", 6.0, use_collisions=False)
    follow = tag.constraints.new('COPY_LOCATION')                 # reads Slab's surface
    follow.target, follow.subtarget = slab, "Pin"
    loose = tetrahedralized_bar("Loose", 8.0, use_collisions=False)
    loose.parent = slab                                           # Slab's transform only
    make_bar(name="Plain")                                        # never tetrahedralized
    bodies = plan(ext)["bodies"]
    assert [b["name"] for b in bodies] == ["Loose", "Slab", "Drop", "Tag", "Whip"]
    by_name = {b["name"]: b for b in bodies}
    assert {name: b["after"] for name, b in by_name.items()} == {
        "Loose": [], "Slab": [], "Drop": ["Slab"], "Tag": ["Slab"], "Whip": ["Drop"]}
    assert {name: b["mode"] for name, b in by_name.items()} == {
        "Loose": "simulate", "Slab": "simulate", "Drop": "simulate", "Tag": "simulate",
        "Whip": "spacetime"}
    assert by_name["Whip"]["frames"] == "5-20" and by_name["Slab"]["frames"] == "1-24"
    # Each body gets a new bake file of its own, new again at the next submission.
    first = {name: identity(ext, bpy.data.objects[name], b["bake_file"])
             for name, b in by_name.items()}
    again = json.loads(bpy.context.scene.rs_elastic_farm.plan)["bodies"]
    assert len(set(first.values())) == len(first)
    assert all(identity(ext, bpy.data.objects[b["name"]], b["bake_file"]) != first[b["name"]]
               for b in again)
    # The scene property the job type's `eval` reads is the same plan.
    assert ([{k: v for k, v in b.items() if k != "bake_file"} for b in again]
            == [{k: v for k, v in b.items() if k != "bake_file"} for b in bodies])


def test_the_plan_refuses_a_cycle_and_gives_bodies_whose_names_clash_their_own_files(ext):
    one = tetrahedralized_bar("One", 0.0)
    two = tetrahedralized_bar("Two", 2.0)
    for obj in (one, two):
        obj.modifiers.new("Collision", 'COLLISION')
    assert plan(ext) == {"error": "Bodies need each other's bakes in a circle ('One' needs "
                                  "'Two'; 'Two' needs 'One'): break one link (a collider, a "
                                  "vertex parent or a constraint)"}
    two.modifiers.remove(two.modifiers["Collision"])
    # Names that read the same in a file name, and the same on a case-insensitive disk.
    tetrahedralized_bar("one", 4.0, use_collisions=False)
    tetrahedralized_bar("One!", 6.0, use_collisions=False)
    files = [b["bake_file"] for b in plan(ext)["bodies"]]
    assert len({f.lower() for f in files}) == len(files) == 4


def saved_shot(tmp_path, name="shot"):
    """A prepared pinned bar and an unprepared tetrahedralized one (Other), saved."""
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = FRAMES[0], FRAMES[-1]
    tetrahedralized_bar("Other", 3.0)
    bar = tetrahedralized_bar("Bar", 0.0)
    make_active(bar)
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    blend = tmp_path / f"{name}.blend"
    blend.parent.mkdir(parents=True, exist_ok=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    return blend


def error_lines(result):
    return [line for line in result.stderr.splitlines() if line.startswith("rs_elastic: error:")]


def bake_name(ext, name, identity):
    return ext.bridge.mesh_cache.bake_name(bpy.data.objects[name], identity)


def listing(folder):
    return sorted(p.name for p in folder.iterdir()) if folder.exists() else []


def test_prepare_only_then_bake_only_write_the_cache_and_the_pc2_and_leave_the_blend(ext,
                                                                                      tmp_path):
    blend = saved_shot(tmp_path / "elsewhere")
    bar_file, other_file = bake_name(ext, "Bar", "0123456789abcdef"), bake_name(
        ext, "Other", "fedcba9876543210")
    farm = tmp_path / "farm"
    farm.mkdir()
    shutil.copyfile(blend, farm / blend.name)           # the file alone, without its cache
    blend = farm / blend.name
    bakes = farm / "blendcache_shot" / "bakes"
    submitted = blend.read_bytes()
    bake_only = ["bake", "--object", "Bar", "--mode", "simulate", "--bake-to", "cache",
                 "--bake-file", bar_file, "--no-save", "--only", "bake"]
    refused = run_cli(blend, bake_only)
    assert refused.returncode == 1
    assert error_lines(refused) == [
        "rs_elastic: error: 'Bar' is not prepared: its linear modes are not in the cache next "
        "to the .blend, and bake only prepares nothing (prepare it first)"]
    assert not bakes.exists()

    prepared = run_cli(blend, ["bake", "--object", "Bar", "--only", "prepare", "--no-save"])
    assert prepared.returncode == 0, prepared.stderr
    stages = sorted(p.name.split(".")[1] for p in (farm / "blendcache_shot").glob("Bar.*.npz"))
    assert stages == ["modes", "reduced", "tets"]
    baked = run_cli(blend, bake_only)
    assert baked.returncode == 0, baked.stderr
    pc2 = bakes / bar_file
    assert f"baked frames 1-12 of 'Bar' into {pc2}" in baked.stdout
    assert listing(bakes) == [bar_file]                           # the file its job named
    poses, _ = ext.bridge.mesh_cache.read_pc2(str(pc2))
    assert poses.shape == (len(FRAMES), 26, 3) and np.abs(poses - poses[0]).max() > 1e-3
    assert blend.read_bytes() == submitted                          # never saved

    # collect: a body without a farm bake fails and saves nothing; then Bar's bake plays.
    missing = run_cli(blend, ["collect", "--bake", f"Bar={bar_file}", "--bake",
                              f"Other={other_file}"])
    assert missing.returncode == 1
    assert error_lines(missing) == [f"rs_elastic: error: 'Other' has no farm bake: "
                                    f"{bakes / other_file} is missing"]
    assert blend.read_bytes() == submitted and listing(bakes) == [bar_file]
    collected = run_cli(blend, ["collect", "--bake", f"Bar={bar_file}"])
    assert collected.returncode == 0, collected.stderr
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    bar = bpy.data.objects["Bar"]
    assert ext.bridge.bake.bake_frames(bar) == FRAMES                # shape keys (Bake To)
    for frame in (1, 7, 12):
        key = bar.data.shape_keys.key_blocks[ext.bridge.bake.bake_key_name(frame)]
        co = np.empty(len(key.data) * 3, dtype=np.float32)
        key.data.foreach_get("co", co)
        np.testing.assert_array_equal(co.reshape(-1, 3), poses[frame - 1])
    # Nothing plays the farm's file of a shape-key body once the shot is saved: it went.
    assert listing(bakes) == [] and not bar.rs_elastic.cache_bake_file


def test_a_farm_bake_leaves_the_shots_bakes_and_collect_replaces_them(ext, tmp_path):
    """The shot plays an earlier Mesh Cache bake of Bar; a farm task bakes Bar again without
    saving: the earlier file stays (the shot on disk plays it). Collected, the farm's file is
    Bar's bake (its modifier plays it, its record names it) and the earlier file goes."""
    blend = saved_shot(tmp_path)
    bar = bpy.data.objects["Bar"]
    bar.rs_elastic.bake_to = 'CACHE'
    rest = np.array([v.co for v in bar.data.vertices])
    earlier = pathlib.Path(ext.bridge.mesh_cache.write(bar, FRAMES, np.repeat(rest[None], 12, 0)))
    bpy.ops.wm.save_mainfile()
    bakes = earlier.parent
    farm_file = bake_name(ext, "Bar", "00000000000000aa")
    baked = run_cli(blend, ["bake", "--object", "Bar", "--mode", "simulate", "--bake-to",
                            "cache", "--bake-file", farm_file, "--no-save"])
    assert baked.returncode == 0, baked.stderr
    assert listing(bakes) == sorted([earlier.name, farm_file])
    farm_poses, _ = ext.bridge.mesh_cache.read_pc2(str(bakes / farm_file))
    assert np.abs(farm_poses - rest).max() > 1e-3                   # a real bake, not the rest

    collected = run_cli(blend, ["collect", "--bake", f"Bar={farm_file}"])
    assert collected.returncode == 0, collected.stderr
    assert listing(bakes) == [farm_file]
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    bar = bpy.data.objects["Bar"]
    assert ext.bridge.mesh_cache.bake_file(bar) == str(bakes / farm_file)
    assert pathlib.Path(bpy.path.abspath(bar.rs_elastic.cache_bake_file)).name == farm_file
    assert ext.bridge.mesh_cache.owned_modifier(bar) == bar.modifiers[0]
    assert ext.bridge.bake.bake_frames(bar) == FRAMES
    assert ext.bridge.farm.playback_error(bar, bpy.context.scene, FRAMES, farm_poses) <= 1e-6


def test_a_bake_with_another_bodys_farm_bake_playing_and_the_farm_options_checks(ext, tmp_path):
    blend = saved_shot(tmp_path)
    bakes = tmp_path / "blendcache_shot" / "bakes"
    bar_file = bake_name(ext, "Bar", "0123456789abcdef")
    other_file = bake_name(ext, "Other", "0123456789abcdef")
    bar_pc2 = bakes / bar_file
    with_bar = ["bake", "--object", "Other", "--mode", "simulate", "--bake-to", "cache",
                "--bake-file", other_file, "--no-save", "--with-bake", f"Bar={bar_file}"]
    absent = run_cli(blend, with_bar)
    assert absent.returncode == 1
    assert error_lines(absent) == [f"rs_elastic: error: 'Bar' has no farm bake: {bar_pc2} is "
                                   "missing"]
    # A farm bake of Bar one frame short of its range.
    bar_pc2.parent.mkdir(parents=True)
    rest = np.array([v.co for v in bpy.data.objects["Bar"].data.vertices])
    ext.bridge.mesh_cache.write_pc2(str(bar_pc2), np.repeat(rest[None], len(FRAMES) - 1, 0))
    short = run_cli(blend, with_bar)
    assert error_lines(short) == [f"rs_elastic: error: 'Bar': its farm bake {bar_pc2} has 11 "
                                  "frames, its frame range 1-12 has 12"]
    assert short.returncode == 1 and listing(bakes) == [bar_file]
    pattern = "Bar.<16 hex digits>.pc2"
    for argv, message in (
            (["bake", "--object", "Bar", "--no-save"],
             "--no-save keeps a bake only as a Mesh Cache: add --bake-to cache"),
            (["bake", "--object", "Bar", "--bake-to", "cache", "--no-save", "--output",
              str(tmp_path / "out.blend")], "--no-save and --output contradict each other"),
            (["bake", "--object", "Bar", "--bake-to", "cache", "--bake-file", other_file],
             f"--bake-file '{other_file}' is not a bake file name of 'Bar' ({pattern})"),
            (["bake", "--object", "Bar", "--bake-to", "cache", "--bake-file", "../Bar.pc2"],
             f"--bake-file '../Bar.pc2' is not a bake file name of 'Bar' ({pattern})"),
            (["bake", "--object", "Bar", "--bake-file", bar_file],
             "--bake-file names a Mesh Cache bake: add --bake-to cache (and no --only prepare)"),
            (["bake", "--object", "Bar", "--with-bake", f"Bar={bar_file}"],
             "--with-bake 'Bar' is the body being baked"),
            (["bake", "--object", "Other", "--with-bake", "Bar"],
             "--with-bake must be OBJECT=FILE, got 'Bar'"),
            (["bake", "--object", "Other", "--with-bake", f"Bar={other_file}"],
             f"--with-bake Bar={other_file}: '{other_file}' is not a bake file name of 'Bar' "
             f"(expected {pattern})"),
            (["collect", "--bake", f"Nobody={bar_file}"], f"no object named 'Nobody' in {blend}")):
        result = run_cli(blend, argv)
        assert result.returncode == 2 and error_lines(result) == [f"rs_elastic: error: {message}"]
