"""Bakes to a Mesh Cache: a .pc2 file on disk played by Blender's own Mesh Cache modifier.

A shape-key bake costs frames x vertices x 12 bytes inside the .blend (1,000 frames of a
100k-vertex mesh: 1.2 GB) and makes the shape-key list unusable. For long shots the bake is
written instead to ``blendcache_<blend>/bakes/<object>.<identity>.pc2`` next to the saved .blend
(a folder the cache pruning never touches) and played by a Mesh Cache modifier (named
``MODIFIER`` when it is made) at the top of the stack in Overwrite mode: it replaces the base
positions before every other modifier, exactly where shape keys act, so an Armature modifier
still carries the bake.

PC2 layout (little-endian): char[12] "POINTCACHE2\\0", int32 version 1, int32 point count,
float32 start frame, float32 sample rate, int32 sample count, then float32 (samples, points, 3).
The file's start is 0 and its rate 1; the modifier's Frame Start puts sample 0 on the bake's
first scene frame.

Ownership. Every bake gets a new identity (a uuid4: identity, not a result), which is in its
file's name; the object records that file (``rs_elastic.cache_bake_file``), and the extension's
modifier is the Mesh Cache modifier that plays a file of that name, whatever the modifier is
called (modifiers cannot hold ID properties). So a user's own Mesh Cache modifier is never
touched, two objects never share a file by their names, and a duplicate (Shift+D), which copies
the record and the modifier, gets its own file at its first bake. Where the file is comes from
the modifier (Blender remaps its relative path when the .blend is saved elsewhere); the record's
folder is only informative. Bakes made before identities (``<object>.pc2``, a modifier named
``MODIFIER``) are recognised the same way.

A bake's file is never written over: a new bake writes a new file. The files a Clear Bake or a
re-bake stops playing are deleted when the .blend is saved (``after_save``), if nothing plays
them then and they are in its own bakes folder: until then undo can bring their bake back, and
the saved .blend never plays a deleted file. Only files this session wrote or stopped playing are
deleted, never one it does not know (a farm task's, still running). Saving the .blend under
another folder or name gives the new file its own copy (a hard link where the disk allows,
``before_save``), so clearing a bake in one .blend never breaks another's; the files written
since the last save stay only where a saved .blend plays them.

Farm tasks (bridge/farm.py) bake the bodies of one .blend side by side and do not save it. The
job decides each body's file at submission (`new_bake_name`), so that the tasks that play that
body's bake, and the last one that collects every bake into the .blend, know it in advance:
inside `pinned_identities` a new bake of a named object takes its job's identity (a task run
again writes the same file, through a temporary one, so it is whole or absent). A task does not
save, so it deletes nothing; the last one saves the shot, then `discard`s the farm's files the
shot does not play.
"""
import contextlib
import os
import re
import shutil
import uuid

import bpy
import numpy as np

from . import writes
from .scene import InputError

MODIFIER = "RS Elastic Bake"
HEADER = np.dtype([("magic", "S12"), ("version", "<i4"), ("points", "<i4"), ("start", "<f4"),
                   ("rate", "<f4"), ("samples", "<i4")])
SUGGEST_BYTES = 64 * 2 ** 20    # shape keys above this size: the panel suggests a Mesh Cache
IDENTITY = re.compile(r"[0-9a-f]{16}")
# The modifier's settings a bake sets (and a failed bake puts back).
PLAYER_SETTINGS = ("cache_format", "filepath", "deform_mode", "interpolation", "time_mode",
                   "play_mode", "frame_start", "frame_scale")


# --- the .pc2 format ----------------------------------------------------------------------------

def write_pc2(path, positions):
    """Write poses (F, n, 3) [object space] as a .pc2 file (start 0, rate 1). A failed write
    leaves nothing behind (it goes through a temporary file)."""
    positions = np.ascontiguousarray(positions, dtype="<f4")
    header = np.array([(b"POINTCACHE2\0", 1, positions.shape[1], 0.0, 1.0, positions.shape[0])],
                      dtype=HEADER)
    temporary = path + ".part"
    try:
        with open(temporary, "wb") as f:
            f.write(header.tobytes())
            f.write(positions.tobytes())
        os.replace(temporary, path)
    except BaseException:
        writes.remove_file_quietly(temporary)
        raise


def read_pc2_header(path):
    """(samples, points) of a .pc2 file; ValueError if it is not one or is cut short."""
    with open(path, "rb") as f:
        header = np.frombuffer(f.read(HEADER.itemsize), dtype=HEADER)
        size = os.fstat(f.fileno()).st_size
    if len(header) != 1 or header["magic"][0] != b"POINTCACHE2":
        raise ValueError(f"{path} is not a PC2 point cache")
    samples, points = int(header["samples"][0]), int(header["points"][0])
    if size < HEADER.itemsize + samples * points * 12:
        raise ValueError(f"{path} is shorter than its header says")
    return samples, points


def read_pc2(path):
    """(samples (F, n, 3) float32, header record) of a .pc2 file; ValueError if it is not one."""
    with open(path, "rb") as f:
        header = np.frombuffer(f.read(HEADER.itemsize), dtype=HEADER)
        if len(header) != 1 or header["magic"][0] != b"POINTCACHE2":
            raise ValueError(f"{path} is not a PC2 point cache")
        count = int(header["samples"][0]) * int(header["points"][0]) * 3
        data = np.fromfile(f, dtype="<f4", count=count)
    if data.size != count:
        raise ValueError(f"{path} is shorter than its header says")
    return data.reshape(int(header["samples"][0]), int(header["points"][0]), 3), header[0]


def shape_key_bytes(frames, vertex_count):
    """Bytes a shape-key bake of this size adds to the .blend (3 float32 per vertex and frame)."""
    return int(frames) * int(vertex_count) * 12


# --- where bakes go -------------------------------------------------------------------------------

def bakes_folder(blend_path=None):
    """The bakes folder of the .blend at `blend_path` (default: the open one). InputError for an
    unsaved file (the bake must travel with it)."""
    blend_path = blend_path or bpy.data.filepath
    if not blend_path:
        raise InputError("Save the .blend first: a Mesh Cache bake is written next to it")
    folder, name = os.path.split(blend_path)
    return os.path.join(folder, f"blendcache_{os.path.splitext(name)[0]}", "bakes")


_PINNED = {}        # {object name: identity} its new bakes take (farm tasks, `pinned_identities`)


def bake_name(obj, identity):
    """The file name of the object's bake of `identity`: its name for people to read (every
    character but letters, digits, '_' and '-' made '_'), the identity for ownership."""
    return f"{re.sub(r'[^A-Za-z0-9_-]', '_', obj.name)}.{identity}.pc2"


def new_bake_name(obj):
    """The file name of a new bake of `obj`, with a new identity."""
    return bake_name(obj, uuid.uuid4().hex[:16])


def identity_of(obj, file_name):
    """The identity in `file_name` if it names a bake of `obj` (``bake_name``), else None."""
    parts = file_name.rsplit(".", 2)
    if len(parts) == 3 and IDENTITY.fullmatch(parts[1]) and file_name == bake_name(obj, parts[1]):
        return parts[1]
    return None


def new_bake_path(obj):
    """A path for a new bake of `obj`: a new identity, or the one pinned for it."""
    identity = _PINNED.get(obj.name)
    name = new_bake_name(obj) if identity is None else bake_name(obj, identity)
    return os.path.join(bakes_folder(), name)


@contextlib.contextmanager
def pinned_identities(identities):
    """While inside, a new bake of an object named in `identities` ({object name: identity})
    takes that identity (a farm task writes the file its job named)."""
    saved = dict(_PINNED)
    _PINNED.update(identities)
    try:
        yield
    finally:
        _PINNED.clear()
        _PINNED.update(saved)


def folder_problem(folder):
    """Why `folder` cannot be made or written to, or None."""
    path = folder
    while not os.path.lexists(path) and os.path.dirname(path) != path:
        path = os.path.dirname(path)
    if not os.path.isdir(path):
        return f"{path} is a file, not a folder"
    if not os.access(path, os.W_OK | os.X_OK):
        return f"the folder {path} is not writable"
    return None


def require_bake_folder(obj):
    """Refuse (InputError), before any work, a Mesh Cache bake that could not be written."""
    problem = folder_problem(bakes_folder())
    if problem is not None:
        raise InputError(f"'{obj.name}' cannot be baked to a Mesh Cache: {problem}")


def _make_folders(folder, transaction):
    """os.makedirs(folder); undone, the folders it made go again."""
    made = []
    path = folder
    while not os.path.lexists(path) and os.path.dirname(path) != path:
        made.append(path)
        path = os.path.dirname(path)

    def undo():
        for path in made:             # innermost first
            with contextlib.suppress(OSError):
                os.rmdir(path)
    transaction.undo(undo)
    os.makedirs(folder, exist_ok=True)


# --- ownership ------------------------------------------------------------------------------------

def _file_name(path):
    return re.split(r"[\\/]", path)[-1]


def owned_modifier(obj):
    """The object's bake modifier (the Mesh Cache modifier playing its recorded file), or None."""
    record = obj.rs_elastic.cache_bake_file
    if not record:
        return None
    name = _file_name(record)
    for modifier in obj.modifiers:
        if modifier.type == 'MESH_CACHE' and _file_name(modifier.filepath) == name:
            return modifier
    return None


def is_bake_modifier(obj, modifier):
    return modifier == owned_modifier(obj)


def _absolute(obj, path):
    return os.path.normpath(bpy.path.abspath(path, library=obj.library))


def bake_file(obj, modifier=None):
    """Absolute path of the .pc2 the object's bake modifier plays, or None without one."""
    modifier = modifier or owned_modifier(obj)
    return None if modifier is None else _absolute(obj, modifier.filepath)


def _delete_unplayed(paths, folder=None):
    """Delete the bake files of `paths` that no Mesh Cache modifier plays (with `folder`: only
    those in it)."""
    played = {os.path.realpath(_absolute(o, m.filepath)) for o in bpy.data.objects
              for m in o.modifiers if m.type == 'MESH_CACHE'}
    for path in paths:
        if os.path.realpath(path) in played:
            continue
        if folder is None or _same_path(os.path.dirname(path), folder):
            writes.remove_file_quietly(path)


def discard(paths):
    """Delete the bake files among `paths` that nothing plays any more and that are in this
    (saved) .blend's own bakes folder."""
    _delete_unplayed(paths, bakes_folder())


@contextlib.contextmanager
def muted(obj, depsgraph=None):
    """While inside, the object's cache bake does not play (its modifier is switched off), so
    the evaluated mesh is the object's own shape; the setting is put back on the way out."""
    modifier = owned_modifier(obj)
    if modifier is None:
        yield
        return
    saved = modifier.show_viewport, modifier.show_render
    modifier.show_viewport = modifier.show_render = False
    try:
        if depsgraph is not None:
            depsgraph.update()
        yield
    finally:
        modifier.show_viewport, modifier.show_render = saved
        if depsgraph is not None:
            depsgraph.update()


# --- writing and clearing -------------------------------------------------------------------------

def _player(obj, transaction):
    """The bake modifier to play a new file: the object's own (its settings noted, so a failure
    puts them back), or a new one at the top of the stack (removed on failure)."""
    modifier = owned_modifier(obj)
    if modifier is None:
        modifier = obj.modifiers.new(MODIFIER, 'MESH_CACHE')
        name = modifier.name
        transaction.undo(lambda: _remove_modifier(obj, name))
    else:
        writes.keep_values(transaction, modifier, PLAYER_SETTINGS)
        name, index = modifier.name, list(obj.modifiers).index(modifier)
        transaction.undo(lambda: obj.modifiers.move(
            list(obj.modifiers).index(obj.modifiers[name]), index))
    obj.modifiers.move(list(obj.modifiers).index(modifier), 0)   # where shape keys act
    return modifier


def write(obj, frames, positions):
    """Write poses (F, n, 3) of consecutive ``frames`` to a new .pc2 and make the object's bake
    modifier play it; the previous cache bake's file goes at the next save if nothing plays it
    then. Returns the new file's path."""
    with writes.transaction(f"Writing the Mesh Cache bake of '{obj.name}'") as transaction:
        path = new_bake_path(obj)
        _make_folders(os.path.dirname(path), transaction)
        transaction.undo(lambda: writes.remove_file_quietly(path))
        write_pc2(path, positions)
        _play(obj, path, frames[0], transaction)
    _UNSAVED.add(path)
    return path


def play(obj, path, first_frame):
    """Make the object's bake modifier play the existing .pc2 at `path` (a farm task's) from
    scene frame `first_frame`, and record it as the object's bake; the previous cache bake's
    file goes once nothing plays it."""
    with writes.transaction(f"Playing a Mesh Cache bake on '{obj.name}'") as transaction:
        _play(obj, path, first_frame, transaction)


def _play(obj, path, first_frame, transaction):
    old = bake_file(obj)
    modifier = _player(obj, transaction)
    modifier.cache_format = 'PC2'
    modifier.filepath = bpy.path.relpath(path)
    modifier.deform_mode = 'OVERWRITE'
    modifier.interpolation = 'LINEAR'
    modifier.time_mode = 'FRAME'
    modifier.play_mode = 'SCENE'
    modifier.frame_start = float(first_frame)
    modifier.frame_scale = 1.0
    writes.keep_values(transaction, obj.rs_elastic, ["cache_bake_file"])
    obj.rs_elastic.cache_bake_file = modifier.filepath
    if old is not None and not _same_path(old, path):
        transaction.after(lambda: _RELEASED.add(old))


def clear(obj):
    """Remove the cache bake's modifier (its file goes at the next save if nothing plays it
    then). Returns how many frames it held, or None if the object has no cache bake."""
    modifier = owned_modifier(obj)
    if modifier is None:
        return None
    frames = len(frames_of(obj))
    with writes.transaction(f"Clearing the Mesh Cache bake of '{obj.name}'") as transaction:
        path, name = bake_file(obj, modifier), modifier.name
        transaction.after(lambda: _RELEASED.add(path))
        writes.keep_values(transaction, obj.rs_elastic, ["cache_bake_file"])
        obj.rs_elastic.cache_bake_file = ""
        saved = _modifier_settings(obj, modifier)
        transaction.remove(lambda: _remove_modifier(obj, name),
                           undo=lambda: _restore_modifier(obj, saved))
    return frames


def _remove_modifier(obj, name):
    obj.modifiers.remove(obj.modifiers[name])


def _modifier_settings(obj, modifier):
    """(name, index in the stack, {setting: value}) of a Mesh Cache modifier."""
    values = {p.identifier: getattr(modifier, p.identifier) for p in modifier.bl_rna.properties
              if not p.is_readonly and p.type not in ('POINTER', 'COLLECTION')
              and p.identifier not in ("name", "is_active", "persistent_uid")}
    return modifier.name, list(obj.modifiers).index(modifier), values


def _restore_modifier(obj, saved):
    """Make a removed Mesh Cache modifier again, where it was, from `_modifier_settings`."""
    name, index, values = saved
    modifier = obj.modifiers.new(name, 'MESH_CACHE')
    for key, value in values.items():
        setattr(modifier, key, value)
    obj.modifiers.move(list(obj.modifiers).index(modifier), index)


def frames_of(obj):
    """Scene frames of the object's cache bake (empty without one, or if its file is gone)."""
    modifier = owned_modifier(obj)
    if modifier is None:
        return []
    try:
        samples, _ = read_pc2_header(bake_file(obj, modifier))
    except (OSError, ValueError):
        return []
    start = int(round(modifier.frame_start))
    return list(range(start, start + samples))


def poses(obj):
    """(frames, positions (F, n, 3) float64) of the cache bake, or ([], None)."""
    frames = frames_of(obj)
    if not frames:
        return [], None
    samples, _ = read_pc2(bake_file(obj))
    return frames, samples.astype(np.float64)


# --- saving under another name --------------------------------------------------------------------

_UNSAVED = set()    # bake files written since the open .blend was last saved where it is
_RELEASED = set()   # bake files a Clear Bake or a re-bake stopped playing since then
_MOVED = []     # during a save: (object, modifier, filepath before, record before, file made)


def _same_path(a, b):
    return os.path.realpath(a) == os.path.realpath(b)


def _link_or_copy(source, target):
    """Put `source`'s content at `target`: a hard link, else a copy. False if `target` was there
    already (a bake's file name is never reused for other content)."""
    if os.path.exists(target):
        return False
    os.makedirs(os.path.dirname(target), exist_ok=True)
    try:
        os.link(source, target)
    except OSError:
        part = target + ".part"
        try:
            shutil.copyfile(source, part)
            os.replace(part, target)
        except BaseException:
            writes.remove_file_quietly(part)
            raise
    return True


def before_save(filepath):
    """save_pre: saved to another folder or name, the .blend gets its own copy of each cache bake
    in its own bakes folder, and the modifier plays that copy (written relative to the open file,
    Blender remaps it to the new one). A bake that cannot be copied keeps playing the old file."""
    _MOVED.clear()
    if not bpy.data.filepath or not os.path.isdir(os.path.dirname(filepath)):
        return          # nothing baked yet, or a save that is bound to fail
    target_folder = bakes_folder(filepath)
    for obj in bpy.data.objects:
        if obj.library is not None or obj.type != 'MESH':
            continue
        modifier = owned_modifier(obj)
        source = bake_file(obj, modifier)
        if source is None or not os.path.isfile(source) \
                or _same_path(os.path.dirname(source), target_folder):
            continue
        target = os.path.join(target_folder, os.path.basename(source))
        try:
            made = _link_or_copy(source, target)
        except OSError as exc:
            print(f"RS Elastic: the Mesh Cache bake of '{obj.name}' could not be copied next to "
                  f"{filepath} ({writes.reason(exc)}); it still plays {source}")
            continue
        _MOVED.append((obj.name, modifier.name, modifier.filepath, obj.rs_elastic.cache_bake_file,
                       target if made else None))
        modifier.filepath = bpy.path.relpath(target)
        # A string setting is not remapped by Blender: written relative to the new file.
        obj.rs_elastic.cache_bake_file = bpy.path.relpath(target, start=os.path.dirname(filepath))


def _moved_players():
    for name, modifier_name, before, record, made in _MOVED:
        obj = bpy.data.objects.get(name)
        modifier = None if obj is None else obj.modifiers.get(modifier_name)
        if modifier is not None:
            yield obj, modifier, before, record, made


def after_save(filepath):
    """save_post: a saved copy (the open file stays the old one) leaves the open file's bakes
    playing their own files. Saved as the open file, what nothing plays now is deleted: the
    files released since the last save that are in its own bakes folder, and those written
    since then wherever they are (the save moved their bakes to its own copies)."""
    if not _same_path(filepath, bpy.data.filepath):
        for obj, modifier, before, record, _ in _moved_players():
            modifier.filepath, obj.rs_elastic.cache_bake_file = before, record
        _MOVED.clear()
        return
    _MOVED.clear()
    _delete_unplayed(sorted(_RELEASED), bakes_folder(filepath))
    _delete_unplayed(sorted(_UNSAVED))
    forget_session()


def forget_session():
    """load_post, and after a save: no file written or released is pending any more."""
    _UNSAVED.clear()
    _RELEASED.clear()


def after_failed_save(filepath):
    """save_post_fail: everything as before the save, and the copies made for it gone."""
    for obj, modifier, before, record, made in _moved_players():
        modifier.filepath, obj.rs_elastic.cache_bake_file = before, record
        if made is not None:
            writes.remove_file_quietly(made)
    _MOVED.clear()
