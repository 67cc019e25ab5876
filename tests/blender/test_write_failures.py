"""Never destroy before the new result exists (issue 26, item 1).

Every operator that writes computes its whole result first, then writes the new data, then
removes the old. A failure forced at each step of the write (the bakes folder unwritable, the
disk full part-way through the .pc2 or at its rename, an exception injected into each step)
must leave everything as it was and say so in one line: the oracle is `state_fingerprint` of the
whole file (every shape key with its data and tags, F-curves, modifiers, the results and records
in obj.rs_elastic) and of every file below the .blend's folder, taken before the operator ran.
Each injected failure also asserts it was reached, so a step that is no longer taken fails the
test instead of passing it silently.
"""
import builtins
import errno
import os

import numpy as np
import pytest
import bpy

from blender_helpers import add_tip_handle, make_active, make_bar, state_fingerprint, vertices

FRAMES = (1, 6)


@pytest.fixture(scope="module")
def base_blend(tmp_path_factory):
    """A saved, prepared bar with a keyed tip handle and a keyed key of the user's: each test
    opens it and saves it as its own file (the prepared stages follow the save)."""
    path = tmp_path_factory.mktemp("base") / "base.blend"
    bpy.ops.wm.read_homefile(use_empty=True)
    obj = make_bar()
    settings = obj.rs_elastic
    settings.edge_length, settings.num_modes = 0.15, 6
    settings.use_scene_range = False
    settings.frame_start, settings.frame_end = FRAMES
    obj.shape_key_add(name="Basis", from_mix=False)
    smile = obj.shape_key_add(name="Smile", from_mix=False)
    smile.data.foreach_set("co", (vertices(obj) + 0.01).astype(np.float32).ravel())
    for frame, value in ((1, 0.0), (6, 0.5)):
        smile.value = value
        smile.keyframe_insert("value", frame=frame)
    smile.value = 0.0
    add_tip_handle(obj, {3: (4.0, 0.5, 1.3), 6: (4.0, 0.5, 0.8)})
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    make_active(bpy.data.objects["Bar"])
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    bpy.ops.wm.save_mainfile()
    return path


def opened(base_blend, tmp_path, bake_to=None):
    """The base file saved as this test's own, with a first bake to `bake_to` if given."""
    bpy.ops.wm.open_mainfile(filepath=str(base_blend))
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "shot.blend"))
    obj = bpy.data.objects["Bar"]
    make_active(obj)
    if bake_to is not None:
        obj.rs_elastic.bake_to = bake_to
        assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    return obj


def failing(monkeypatch, owner, name, on_call=1, error=None):
    """Make `owner.name` raise on its `on_call`-th call (earlier calls go through). Returns the
    list of calls, to assert the failure was reached."""
    original = getattr(owner, name)
    calls = []

    def wrapper(*args, **kwargs):
        calls.append(name)
        if len(calls) == on_call:
            raise error or RuntimeError(f"injected failure in {name}")
        return original(*args, **kwargs)
    monkeypatch.setattr(owner, name, wrapper)
    return calls


class _HalfWriter:
    """A file whose first write stores half of its bytes and then finds the disk full."""

    def __init__(self, file):
        self._file = file

    def write(self, data):
        self._file.write(bytes(data)[:len(data) // 2])
        self._file.flush()
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), self._file.name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._file.close()


def disk_full_while_writing(ext, monkeypatch):
    calls = []

    def full_disk_open(path, mode="r", *args, **kwargs):
        file = builtins.open(path, mode, *args, **kwargs)
        if "w" not in mode:
            return file
        calls.append(path)
        return _HalfWriter(file)
    monkeypatch.setattr(ext.bridge.mesh_cache, "open", full_disk_open, raising=False)
    return calls


def disk_full_at_rename(ext, monkeypatch):
    return failing(monkeypatch, os, "replace",
                   error=OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)))


def folder_cannot_be_made(ext, monkeypatch):
    return failing(monkeypatch, os, "makedirs", error=FileExistsError(
        errno.EEXIST, os.strerror(errno.EEXIST), "bakes"))


def modifier_setup_fails(ext, monkeypatch):
    # relpath runs once the modifier is made and moved to the top, before its settings.
    return failing(monkeypatch, bpy.path, "relpath")


def key_positions_fail(ext, monkeypatch):
    return failing(monkeypatch, ext.bridge.bake, "_set_positions", on_call=3)


def keying_fails(ext, monkeypatch):
    return failing(monkeypatch, ext.bridge.animation, "insert_keys", on_call=3)


def tagging_fails(ext, monkeypatch):
    # The first tagging: of the old keys set aside (renamed), or else of the new keys.
    return failing(monkeypatch, ext.bridge.bake, "_tag")


def removing_old_keys_fails(ext, monkeypatch):
    return failing(monkeypatch, ext.bridge.bake, "_remove_named")


def removing_old_modifier_fails(ext, monkeypatch):
    return failing(monkeypatch, ext.bridge.mesh_cache, "_remove_modifier")


def recording_fails(ext, monkeypatch):
    # After the bake is written: the operator's own record of the simulation.
    return failing(monkeypatch, ext.bridge.simulation_inputs, "record_energy")


# (the bake there is, Bake To for the new one): the failures each step of that write can meet.
SIMULATE_FAULTS = [
    ('KEYS', 'CACHE', folder_cannot_be_made), ('KEYS', 'CACHE', disk_full_while_writing),
    ('KEYS', 'CACHE', disk_full_at_rename), ('KEYS', 'CACHE', modifier_setup_fails),
    ('KEYS', 'CACHE', removing_old_keys_fails), ('KEYS', 'CACHE', recording_fails),
    ('CACHE', 'CACHE', disk_full_while_writing), ('CACHE', 'CACHE', disk_full_at_rename),
    ('CACHE', 'CACHE', modifier_setup_fails), ('CACHE', 'CACHE', recording_fails),
    ('CACHE', 'KEYS', key_positions_fail), ('CACHE', 'KEYS', keying_fails),
    ('CACHE', 'KEYS', tagging_fails), ('CACHE', 'KEYS', removing_old_modifier_fails),
    ('KEYS', 'KEYS', key_positions_fail), ('KEYS', 'KEYS', keying_fails),
    ('KEYS', 'KEYS', tagging_fails), ('KEYS', 'KEYS', removing_old_keys_fails),
    ('KEYS', 'KEYS', recording_fails),
]


def failed_without_a_trace(operator, folder, **arguments):
    """Run the operator, which must fail with one line and change nothing. Returns the line."""
    before = state_fingerprint(folder)
    with pytest.raises(RuntimeError) as info:
        operator(**arguments)
    assert state_fingerprint(folder) == before
    lines = [line.removeprefix("Error: ") for line in str(info.value).strip().splitlines()]
    assert len(lines) == 1, lines
    return lines[0]


@pytest.mark.parametrize("old, new, fault", [
    pytest.param(old, new, fault, id=f"{old.lower()}-to-{new.lower()}-{fault.__name__}")
    for old, new, fault in SIMULATE_FAULTS])
def test_a_failed_simulate_and_bake_leaves_everything_as_it_was(ext, base_blend, tmp_path,
                                                                monkeypatch, old, new, fault):
    obj = opened(base_blend, tmp_path, bake_to=old)
    obj.rs_elastic.bake_to = new
    calls = fault(ext, monkeypatch)
    line = failed_without_a_trace(bpy.ops.rs_elastic.simulate, tmp_path)
    assert calls, f"{fault.__name__} was never reached"
    assert "nothing was changed" in line, line
    monkeypatch.undo()                                    # and the next try bakes
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}


def test_an_unwritable_bakes_folder_keeps_the_shape_key_bake(ext, base_blend, tmp_path):
    # The reported case: the key bake was deleted first, then the bake died with a traceback.
    obj = opened(base_blend, tmp_path, bake_to='KEYS')
    folder = tmp_path / "blendcache_shot" / "bakes"
    folder.parent.mkdir(exist_ok=True)
    folder.write_text("a file where the bakes folder goes")
    obj.rs_elastic.bake_to = 'CACHE'
    line = failed_without_a_trace(bpy.ops.rs_elastic.simulate, tmp_path)
    assert line == f"'Bar' cannot be baked to a Mesh Cache: {folder} is a file, not a folder"
    assert ext.bridge.bake.bake_frames(obj) == list(range(FRAMES[0], FRAMES[1] + 1))


@pytest.mark.parametrize("bake_to, fault", [('KEYS', removing_old_keys_fails),
                                            ('CACHE', removing_old_modifier_fails)])
def test_a_failed_clear_bake_leaves_the_bake(ext, base_blend, tmp_path, monkeypatch, bake_to,
                                             fault):
    opened(base_blend, tmp_path, bake_to=bake_to)
    calls = fault(ext, monkeypatch)
    failed_without_a_trace(bpy.ops.rs_elastic.clear_bake, tmp_path)
    assert calls


def take_renaming_fails(ext, monkeypatch):
    # _tag: the old take set aside (1), then the bake keys renamed into the take (2).
    return failing(monkeypatch, ext.bridge.bake, "_tag", on_call=2)


@pytest.mark.parametrize("bake_to, fault", [
    ('KEYS', take_renaming_fails), ('KEYS', removing_old_keys_fails),
    ('CACHE', key_positions_fail), ('CACHE', removing_old_modifier_fails)])
def test_a_failed_keep_take_leaves_the_bake_and_the_old_take(ext, base_blend, tmp_path,
                                                            monkeypatch, bake_to, fault):
    obj = opened(base_blend, tmp_path, bake_to='KEYS')
    assert bpy.ops.rs_elastic.keep_take() == {'FINISHED'}           # the take to replace
    obj.rs_elastic.bake_to = bake_to
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    calls = fault(ext, monkeypatch)
    failed_without_a_trace(bpy.ops.rs_elastic.keep_take, tmp_path)
    assert calls


def records_fail_half_way(ext, monkeypatch):
    # The operator's records after the bake: its float() calls make the scale, then each
    # handle's residual, so the second comes once the residuals are being written.
    module = ext.operators.solve_spacetime
    monkeypatch.setattr(module, "float", float, raising=False)
    return failing(monkeypatch, module, "float", on_call=2)


@pytest.mark.parametrize("fault", [keying_fails, records_fail_half_way])
def test_a_failed_solve_and_bake_leaves_everything_as_it_was(ext, base_blend, tmp_path,
                                                             monkeypatch, fault):
    opened(base_blend, tmp_path)
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}     # a bake and its records
    calls = fault(ext, monkeypatch)
    failed_without_a_trace(bpy.ops.rs_elastic.solve_spacetime, tmp_path)
    assert calls


@pytest.mark.parametrize("output, fault", [('KEYS', key_positions_fail),
                                           ('ANIMATION', keying_fails)])
def test_a_failed_interpolation_leaves_the_keys(ext, base_blend, tmp_path, monkeypatch, output,
                                                fault):
    opened(base_blend, tmp_path, bake_to='KEYS')
    arguments = dict(key_from="Basis", key_to="Smile", output=output, count=4,
                     frame_start=1, frame_end=5)
    assert bpy.ops.rs_elastic.interpolate_shape_keys(**arguments) == {'FINISHED'}
    calls = fault(ext, monkeypatch)
    failed_without_a_trace(bpy.ops.rs_elastic.interpolate_shape_keys, tmp_path, **arguments)
    assert calls


def showing_over_the_cache_fails(ext, monkeypatch):
    return failing(monkeypatch, ext.bridge.preview, "_show_cache_bake")


@pytest.mark.parametrize("shown", [False, True])
def test_a_failed_preview_leaves_the_keys(ext, base_blend, tmp_path, monkeypatch, shown):
    obj = opened(base_blend, tmp_path, bake_to='CACHE')
    preview = ext.bridge.preview
    if shown:                                  # a preview key there already: its pose stays
        obj.rs_elastic.preview_enabled = True
        assert preview.is_shown(obj)
        obj.rs_elastic.preview_amplitude = 0.3
    before = state_fingerprint(tmp_path)
    calls = showing_over_the_cache_fails(ext, monkeypatch)
    with pytest.raises(ext.bridge.scene.InputError, match="nothing was changed"):
        preview.show(obj)
    assert calls and state_fingerprint(tmp_path) == before


def test_a_failed_live_pose_leaves_the_keys(ext, base_blend, tmp_path, monkeypatch):
    obj = opened(base_blend, tmp_path, bake_to='KEYS')
    live = ext.bridge.live
    bpy.context.scene.frame_set(3)
    obj.rs_elastic.live = True
    assert live.flush() == [obj.name] and live.show(obj, bpy.context.scene)
    bpy.context.scene.frame_set(4)
    before = state_fingerprint(tmp_path)
    calls = showing_over_the_cache_fails(ext, monkeypatch)     # once the key's pose is written
    with pytest.raises(ext.bridge.scene.InputError, match="nothing was changed"):
        live.show(obj, bpy.context.scene)
    assert calls and state_fingerprint(tmp_path) == before


def test_failed_records_of_prepare_leave_the_previous_preparation(ext, base_blend, tmp_path,
                                                                   monkeypatch):
    obj = opened(base_blend, tmp_path)
    obj.rs_elastic.num_modes = 5                           # a new preparation to record
    calls = failing(monkeypatch, ext.bridge.stage_cache, "record_energy")
    # The new preparation's stage files are written beside the old ones (the cache is content
    # addressed): the .blend's records are what must not change.
    before = state_fingerprint()
    with pytest.raises(RuntimeError) as info:
        bpy.ops.rs_elastic.prepare()
    assert calls and state_fingerprint() == before
    assert len(str(info.value).strip().splitlines()) == 1
    obj.rs_elastic.num_modes = 6
    assert ext.bridge.prepared.for_object(obj) is not None         # still prepared as before


def test_a_failed_first_key_bake_leaves_a_mesh_without_keys_or_actions(ext, monkeypatch):
    # No keys, no animation before: the Basis, the Key, its action and F-curves made on the
    # way go again.
    obj = make_bar()
    rest = vertices(obj)
    before = state_fingerprint()
    calls = keying_fails(ext, monkeypatch)
    poses = np.stack([rest + 0.01 * k for k in range(1, 6)])
    with pytest.raises(ext.bridge.scene.InputError, match="nothing was changed"):
        ext.bridge.bake.write_bake(obj, range(1, 6), poses)
    assert calls and obj.data.shape_keys is None and len(bpy.data.actions) == 0
    assert state_fingerprint() == before
