"""Bakes to a Mesh Cache: a .pc2 file on disk played by Blender's own Mesh Cache modifier.

A shape-key bake costs frames x vertices x 12 bytes inside the .blend (1,000 frames of a
100k-vertex mesh: 1.2 GB) and makes the shape-key list unusable. For long shots the bake is
written instead to ``blendcache_<blend>/bakes/<object>.pc2`` next to the saved .blend (a file
the cache pruning never touches) and played by a Mesh Cache modifier named ``MODIFIER`` at the
top of the stack in Overwrite mode: it replaces the base positions before every other modifier,
exactly where shape keys act, so an Armature modifier still carries the bake.

PC2 layout (little-endian): char[12] "POINTCACHE2\\0", int32 version 1, int32 point count,
float32 start frame, float32 sample rate, int32 sample count, then float32 (samples, points, 3).
The file's start is 0 and its rate 1; the modifier's Frame Start puts sample 0 on the bake's
first scene frame.

Ownership: the object's ``rs_elastic.cache_bake_file`` records the file the extension wrote;
the modifier is recognised by that record and its name. Clear Bake removes both; a user's own
Mesh Cache modifiers are never touched.
"""
import contextlib
import os
import re

import bpy
import numpy as np

from .scene import InputError

MODIFIER = "RS Elastic Bake"
HEADER = np.dtype([("magic", "S12"), ("version", "<i4"), ("points", "<i4"), ("start", "<f4"),
                   ("rate", "<f4"), ("samples", "<i4")])
SUGGEST_BYTES = 64 * 2 ** 20    # shape keys above this size: the panel suggests a Mesh Cache


def write_pc2(path, positions):
    """Write poses (F, n, 3) [object space] as a .pc2 file (start 0, rate 1)."""
    positions = np.ascontiguousarray(positions, dtype="<f4")
    header = np.array([(b"POINTCACHE2\0", 1, positions.shape[1], 0.0, 1.0, positions.shape[0])],
                      dtype=HEADER)
    temporary = path + ".part"              # a failed write never leaves half a bake behind
    with open(temporary, "wb") as f:
        f.write(header.tobytes())
        f.write(positions.tobytes())
    os.replace(temporary, path)


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


def bake_path(obj):
    """Absolute path of the object's .pc2 bake next to the saved .blend. Raises InputError for
    an unsaved file (the bake must travel with it)."""
    if not bpy.data.filepath:
        raise InputError("Save the .blend first: a Mesh Cache bake is written next to it")
    folder, name = os.path.split(bpy.data.filepath)
    folder = os.path.join(folder, f"blendcache_{os.path.splitext(name)[0]}", "bakes")
    return os.path.join(folder, re.sub(r"[^A-Za-z0-9_-]", "_", obj.name) + ".pc2")


def owned_modifier(obj):
    """The object's bake modifier, or None."""
    modifier = obj.modifiers.get(MODIFIER)
    if modifier is None or modifier.type != 'MESH_CACHE' or not obj.rs_elastic.cache_bake_file:
        return None
    return modifier


def is_bake_modifier(obj, modifier):
    return modifier == owned_modifier(obj)


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


def write(obj, frames, positions):
    """Write poses (F, n, 3) of consecutive ``frames`` to the object's .pc2 and set up the
    modifier that plays it (replacing a previous cache bake). Returns the file's path."""
    path = bake_path(obj)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    write_pc2(path, positions)
    modifier = owned_modifier(obj) or obj.modifiers.new(MODIFIER, 'MESH_CACHE')
    obj.modifiers.move(list(obj.modifiers).index(modifier), 0)   # where shape keys act
    modifier.cache_format = 'PC2'
    modifier.filepath = bpy.path.relpath(path)
    modifier.deform_mode = 'OVERWRITE'
    modifier.interpolation = 'LINEAR'
    modifier.time_mode = 'FRAME'
    modifier.play_mode = 'SCENE'
    modifier.frame_start = float(frames[0])
    modifier.frame_scale = 1.0
    obj.rs_elastic.cache_bake_file = modifier.filepath
    return path


def clear(obj):
    """Remove the cache bake (modifier and file). Returns how many frames it held (0: none)."""
    modifier = owned_modifier(obj)
    if modifier is None:
        return 0
    path = bpy.path.abspath(obj.rs_elastic.cache_bake_file)
    frames = len(frames_of(obj))
    obj.modifiers.remove(modifier)
    obj.rs_elastic.cache_bake_file = ""
    if os.path.isfile(path):
        os.remove(path)
    return frames


def frames_of(obj):
    """Scene frames of the object's cache bake (empty without one, or if its file is gone)."""
    modifier = owned_modifier(obj)
    if modifier is None:
        return []
    try:
        samples, _ = read_pc2(bpy.path.abspath(obj.rs_elastic.cache_bake_file))
    except (OSError, ValueError):
        return []
    start = int(round(modifier.frame_start))
    return list(range(start, start + len(samples)))


def poses(obj):
    """(frames, positions (F, n, 3) float64) of the cache bake, or ([], None)."""
    frames = frames_of(obj)
    if not frames:
        return [], None
    samples, _ = read_pc2(bpy.path.abspath(obj.rs_elastic.cache_bake_file))
    return frames, samples.astype(np.float64)
