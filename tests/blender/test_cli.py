"""The command line where it failed (issue 26): every failure is one line on stderr and exit 1,
or 2 for a bad argument, and leaves nothing written: the opened file's bytes and time stamp and
every other file in its folders stay as they were, and no output is saved. Saving is the last
step, so what the command reports is read before it.

Each case runs the registered handler in a new Blender process, as `blender -b shot.blend -c
rs_elastic bake …` does (``test_spacetime.run_cli``), so what Blender itself prints is seen too.
"""
import contextlib
import os
import shutil
import subprocess

import bpy
import numpy as np
import pytest

from blender_helpers import add_tip_handle, evaluated_vertices, make_active, vertices
from test_faults import small_bar
from test_spacetime import run_cli

NAN = float("nan")


def saved_shot(tmp_path, keys):
    """A prepared 4 x 1 x 1 bar pinned at x = 0 with a handle on its tip keyed at `keys`
    {frame: location}, saved as shot/shot.blend (its prepared cache beside it)."""
    obj = small_bar()
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    add_tip_handle(obj, keys)
    make_active(obj)
    bpy.context.scene.frame_set(1)
    (tmp_path / "shot").mkdir()
    (tmp_path / "other").mkdir()
    blend = tmp_path / "shot" / "shot.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    return blend


def files(root):
    """{path: (bytes, modification time)} of every file under root."""
    return {str(p.relative_to(root)): (p.read_bytes(), p.stat().st_mtime_ns)
            for p in sorted(root.rglob("*")) if p.is_file()}


def failed(result, code):
    """The one error line of a run that must fail with `code` (and print no traceback)."""
    assert result.returncode == code, result.stdout + result.stderr
    assert "Traceback" not in result.stdout + result.stderr, result.stdout + result.stderr
    errors = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(errors) == 1 and errors[0].startswith("rs_elastic: error: "), result.stderr
    return errors[0].removeprefix("rs_elastic: error: ")


def succeeded(result):
    """The report of a run that must succeed (exit 0, nothing on stderr from the extension)."""
    assert result.returncode == 0, result.stdout + result.stderr
    assert "Traceback" not in result.stdout + result.stderr, result.stdout + result.stderr
    assert "rs_elastic: error" not in result.stderr
    return [line for line in result.stdout.splitlines() if line.startswith("rs_elastic: ")]


def tip_at(obj, frame):
    bpy.context.scene.frame_set(frame)
    return evaluated_vertices(obj)[vertices(obj)[:, 0] > 4.0 - 1e-9].mean(axis=0)


@pytest.fixture
def shot(tmp_path):
    return saved_shot(tmp_path, {12: (3.6, 0.5, 1.6)})


def test_a_mesh_cache_bake_saved_into_another_folder(tmp_path, shot):
    """It saved out.blend, then read the bake back through the saved file: IndexError, exit 1."""
    before = shot.read_bytes(), shot.stat().st_mtime_ns
    out = tmp_path / "other" / "out.blend"
    report = succeeded(run_cli(shot, ["bake", "--object", "Bar", "--frames", "1-12",
                                      "--bake-to", "cache", "--output", str(out)]))
    assert report[0] == f"rs_elastic: baked frames 1-12 of 'Bar' into {out}"
    assert (shot.read_bytes(), shot.stat().st_mtime_ns) == before
    bpy.ops.wm.open_mainfile(filepath=str(out))
    obj = bpy.data.objects["Bar"]
    assert [m.type for m in obj.modifiers][:1] == ['MESH_CACHE']
    rest = vertices(obj)[vertices(obj)[:, 0] > 4.0 - 1e-9].mean(axis=0)
    lift = tip_at(obj, 12)[2] - rest[2]
    print(f"out.blend plays the bake: the tip rises {lift:.3f} m of the keyed 1.1 m")
    assert lift > 0.5


def test_a_failure_after_the_bake_saves_nothing(ext, tmp_path, shot, monkeypatch, capsys):
    """Whatever fails once the bake is made, nothing is saved: the report is read first."""
    bpy.ops.wm.open_mainfile(filepath=str(shot))
    before = files(tmp_path)

    def broken(obj):
        raise IndexError("list index out of range")

    monkeypatch.setattr(ext.bridge.bake, "bake_frames", broken)
    out = tmp_path / "other" / "out.blend"
    capsys.readouterr()
    assert ext.bridge.cli.main(["bake", "--object", "Bar", "--frames", "1-12", "--output",
                                str(out)]) == 1
    assert capsys.readouterr().err.splitlines() == [
        "rs_elastic: error: internal error: IndexError: list index out of range; nothing was "
        "saved"]
    assert not out.exists() and files(tmp_path) == before


def test_a_save_that_fails_leaves_the_files_as_they_were(tmp_path, shot):
    out = tmp_path / "other" / "out.blend"
    (tmp_path / "other" / "out.blend@").mkdir()       # where Blender writes before it renames
    before = files(tmp_path)
    message = failed(run_cli(shot, ["bake", "--object", "Bar", "--frames", "1-12", "--output",
                                    str(out)]), 1)
    assert message.startswith(f"could not save {out}: ") and message.endswith("nothing was saved")
    assert not out.exists() and files(tmp_path) == before


@contextlib.contextmanager
def read_only(folder):
    """The folder made read-only: by its mode, or, for root (whom modes do not stop), by the
    immutable attribute."""
    if os.geteuid() != 0:
        mode = folder.stat().st_mode
        folder.chmod(0o555)
        try:
            yield
        finally:
            folder.chmod(mode)
        return
    if shutil.which("chattr") is None or subprocess.run(
            ["chattr", "+i", str(folder)], capture_output=True).returncode != 0:
        pytest.skip("running as root, and this file system cannot make a folder immutable "
                    "(chattr +i), so no folder is read-only for this test")
    try:
        yield
    finally:
        subprocess.run(["chattr", "-i", str(folder)], check=True)


def test_a_read_only_folder_refuses_what_it_cannot_write_and_bakes_the_rest(tmp_path, shot):
    """The opened file's folder is read-only (its cache folder not made yet): a bake that would
    be saved over it, or write a Mesh Cache next to it, is refused before any work; shape keys
    saved elsewhere work."""
    shutil.rmtree(tmp_path / "shot" / "blendcache_shot")
    out = tmp_path / "other" / "out.blend"
    before = files(tmp_path)
    with read_only(tmp_path / "shot"):
        over_it = run_cli(shot, ["bake", "--object", "Bar", "--frames", "1-12"])
        to_cache = run_cli(shot, ["bake", "--object", "Bar", "--frames", "1-12", "--bake-to",
                                  "cache", "--output", str(out)])
        assert files(tmp_path) == before
        elsewhere = run_cli(shot, ["bake", "--object", "Bar", "--frames", "1-12", "--output",
                                   str(out)])
    assert failed(over_it, 2) == (f"cannot save over the open file {shot}: it or its folder is "
                                  "not writable; pass --output FILE.blend")
    cache = tmp_path / "shot" / "blendcache_shot"
    assert failed(to_cache, 2) == (f"'Bar' bakes to a Mesh Cache in {cache / 'bakes'}, and the "
                                   f"folder {tmp_path / 'shot'} is not writable: pass --bake-to "
                                   "keys, or open a copy in a writable folder")
    assert succeeded(elsewhere)[0] == f"rs_elastic: baked frames 1-12 of 'Bar' into {out}"
    assert {name: data for name, data in files(tmp_path).items() if name.startswith("shot")} \
        == {name: data for name, data in before.items() if name.startswith("shot")}


def test_a_file_where_the_cache_folder_goes_refuses_a_mesh_cache_bake(tmp_path, shot):
    """The issue's unwritable bakes folder, which even root cannot write through."""
    cache = tmp_path / "shot" / "blendcache_shot"
    shutil.rmtree(cache)
    cache.write_text("in the way")
    before = files(tmp_path)
    message = failed(run_cli(shot, ["bake", "--object", "Bar", "--frames", "1-12",
                                    "--bake-to", "cache"]), 2)
    assert message == (f"'Bar' bakes to a Mesh Cache in {cache / 'bakes'}, and {cache} is a "
                       "file, not a folder: pass --bake-to keys, or open a copy in a writable "
                       "folder")
    assert files(tmp_path) == before


@pytest.mark.parametrize("argv, frames", [
    (["--frames", "-5-10"], (-5, 10)),
    (["--frames=-5-10"], (-5, 10)),
    (["--frames", "-20--10"], (-20, -10)),
    (["--frames", " -3 - 4 "], (-3, 4)),
    (["--mode", "simulate", "--frames", "-5-10", "--bake-to", "keys"], (-5, 10)),
])
def test_negative_frames_are_a_frame_range(ext, argv, frames):
    args = ext.bridge.cli.parse_arguments(["bake", "--object", "Bar"] + argv)
    assert ext.bridge.cli._frame_range(args.frames) == frames


@pytest.mark.parametrize("argv, message", [
    (["--frames", "-5"], "--frames must look like 1-120, got '-5'"),
    (["--frames", "5--5"], "--frames 5--5 has fewer than 3 frames (start before end)"),
    (["--frames", "-1048580--1048578"],
     "--frames -1048580--1048578 starts before Blender's first frame, -1048574"),
])
def test_bad_negative_frame_ranges_are_refused(ext, argv, message):
    with pytest.raises(ext.bridge.cli.UsageError) as info:
        ext.bridge.cli._frame_range(ext.bridge.cli.parse_arguments(
            ["bake", "--object", "Bar"] + argv).frames)
    assert str(info.value) == message


def test_a_range_of_negative_frames_bakes(ext, tmp_path):
    blend = saved_shot(tmp_path, {5: (3.6, 0.5, 1.6)})
    out = tmp_path / "other" / "out.blend"
    report = succeeded(run_cli(blend, ["bake", "--object", "Bar", "--frames", "-5-10",
                                       "--output", str(out)]))
    assert report[0] == f"rs_elastic: baked frames -5-10 of 'Bar' into {out}"
    bpy.ops.wm.open_mainfile(filepath=str(out))
    obj = bpy.data.objects["Bar"]
    assert obj.rs_elastic.frame_start == -5
    assert ext.bridge.bake.bake_frames(obj) == list(range(-5, 11))
    assert np.linalg.norm(tip_at(obj, 5) - np.array([3.6, 0.5, 1.6])) < 0.02


def test_three_frames_bake_on_the_command_line(tmp_path):
    """Frames 1 and 2 start at rest, frame 3 meets the handle (a traceback before)."""
    blend = saved_shot(tmp_path, {3: (4.0, 0.5, 0.9)})
    out = tmp_path / "other" / "out.blend"
    report = succeeded(run_cli(blend, ["bake", "--object", "Bar", "--frames", "1-3", "--output",
                                       str(out)]))
    assert report[0] == f"rs_elastic: baked frames 1-3 of 'Bar' into {out}"
    bpy.ops.wm.open_mainfile(filepath=str(out))
    assert np.linalg.norm(tip_at(bpy.data.objects["Bar"], 3) - np.array([4.0, 0.5, 0.9])) < 4e-3


def test_a_handle_key_that_is_not_a_number_fails_in_one_line(tmp_path):
    blend = saved_shot(tmp_path, {4: (3.6, 0.5, 1.6), 8: (NAN, 0.5, 0.5)})
    out = tmp_path / "other" / "out.blend"
    before = files(tmp_path)
    message = failed(run_cli(blend, ["bake", "--object", "Bar", "--frames", "1-12", "--output",
                                     str(out)]), 1)
    assert message == ("The transform of handle 'Bar Handle' on frame 8 is not a finite number: "
                       "check the keys, drivers and parents that move it")
    assert not out.exists() and files(tmp_path) == before


@pytest.mark.parametrize("mode", ['EDIT', 'SCULPT', 'WEIGHT_PAINT'])
def test_a_file_saved_in_another_mode_bakes_as_in_object_mode(tmp_path, shot, mode):
    """A file saved mid-edit opens in that mode; on the command line (no one editing) it bakes
    in Object Mode, says so, and bakes what the same file saved in Object Mode bakes."""
    argv = ["bake", "--object", "Bar", "--frames", "1-12", "--bake-to", "keys"]
    in_object = tmp_path / "other" / "object.blend"
    succeeded(run_cli(shot, argv + ["--output", str(in_object)]))
    bpy.ops.wm.open_mainfile(filepath=str(shot))
    make_active(bpy.data.objects["Bar"])
    bpy.ops.object.mode_set(mode=mode)
    bpy.ops.wm.save_mainfile()
    in_mode = tmp_path / "other" / "mode.blend"
    report = succeeded(run_cli(shot, argv + ["--output", str(in_mode)]))
    mode_name = {'EDIT': "Edit Mode", 'SCULPT': "Sculpt Mode",
                 'WEIGHT_PAINT': "Weight Paint mode"}[mode]
    assert report[0] == (f"rs_elastic: baked frames 1-12 of 'Bar' into {in_mode} ('Bar' was "
                         f"saved in {mode_name}: baked in Object Mode)")
    tips = []
    for path in (in_object, in_mode):
        bpy.ops.wm.open_mainfile(filepath=str(path))
        obj = bpy.data.objects["Bar"]
        assert obj.mode == 'OBJECT'
        tips.append([tip_at(obj, frame) for frame in (1, 6, 12)])
    np.testing.assert_allclose(tips[1], tips[0], rtol=0, atol=1e-9)
    assert np.linalg.norm(tips[0][2] - tips[0][0]) > 0.1      # the handle moved the tip
