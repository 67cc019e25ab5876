"""Shape-key output: sets of named keys, and baked animations (one key per frame).

A baked animation is the form every RS Elastic bake takes: key `RS Bake 0042` holds frame 42's
pose and is keyed 0 on frame 41, 1 on frame 42 and 0 on frame 43, with constant interpolation, so
scrubbing plays the bake. Baking again replaces the previous bake (its keys and their F-curves);
the user's own shape keys and keyframes are never touched.
"""
import numpy as np

from .animation import fcurves as _fcurves

BAKE_PREFIX = "RS Bake "
TAKE_PREFIX = "RS Take "     # a kept bake: the input motion of a space-time edit


def bake_key_name(frame):
    return f"{BAKE_PREFIX}{frame:04d}"


def _ensure_basis(obj):
    if obj.data.shape_keys is None:
        obj.shape_key_add(name="Basis", from_mix=False)


def _set_positions(key_block, positions):
    key_block.data.foreach_set("co", np.asarray(positions, dtype=np.float32).ravel())


def replace_key_set(obj, prefix, names, positions):
    """Remove the keys whose name starts with `prefix`, then add one key per (name, positions)."""
    remove_keys(obj, prefix)
    _ensure_basis(obj)
    for name, pose in zip(names, positions):
        key = obj.shape_key_add(name=name, from_mix=False)
        _set_positions(key, pose)
        key.value = 0.0
    obj.data.update()


def write_bake(obj, frames, positions):
    """Replace the object's bake with one key per frame. positions: (F, n, 3) base-vertex poses.

    Returns the names of the user's keys whose value is not 0: they add on top of the bake.
    """
    clear_bake(obj)
    _ensure_basis(obj)
    keys = obj.data.shape_keys
    for frame, pose in zip(frames, positions):
        key = obj.shape_key_add(name=bake_key_name(frame), from_mix=False)
        _set_positions(key, pose)
        key.value = 0.0
    fcurves = _fcurves(keys, create=True)
    for frame in frames:
        curve = fcurves.new(f'key_blocks["{bake_key_name(frame)}"].value', index=0)
        curve.keyframe_points.add(3)
        curve.keyframe_points.foreach_set(
            "co", np.array([frame - 1, 0.0, frame, 1.0, frame + 1, 0.0], dtype=np.float32))
        for point in curve.keyframe_points:
            point.interpolation = 'CONSTANT'
        curve.update()
    obj.data.update()
    return [k.name for k in keys.key_blocks
            if k != keys.reference_key and not k.name.startswith(BAKE_PREFIX) and k.value != 0.0]


def clear_bake(obj):
    """Remove the bake's keys and F-curves. Returns how many keys were removed."""
    return remove_keys(obj, BAKE_PREFIX)


def bake_frames(obj):
    """Sorted frames of the object's current bake (empty if none)."""
    keys = obj.data.shape_keys
    if keys is None:
        return []
    return sorted(int(k.name[len(BAKE_PREFIX):]) for k in keys.key_blocks
                  if k.name.startswith(BAKE_PREFIX) and k.name[len(BAKE_PREFIX):].isdigit())


def remove_keys(obj, prefix):
    keys = obj.data.shape_keys
    if keys is None:
        return 0
    doomed = [k for k in keys.key_blocks if k.name.startswith(prefix)]
    fcurves = _fcurves(keys, create=False)
    if fcurves is not None:
        names = {f'key_blocks["{k.name}"].value' for k in doomed}
        for curve in [c for c in fcurves if c.data_path in names]:
            fcurves.remove(curve)
    for key in doomed:
        obj.shape_key_remove(key)
    _drop_bare_basis(obj)
    return len(doomed)


def _drop_bare_basis(obj):
    """Remove a Basis left alone with nothing animating it: it only repeats the mesh, and the
    bake or key set that needed it is gone, so the object is as it was before."""
    keys = obj.data.shape_keys
    if keys is None or len(keys.key_blocks) != 1:
        return
    curves = _fcurves(keys, create=False)
    if curves is not None and len(curves) > 0:
        return
    basis = np.empty(len(obj.data.vertices) * 3, dtype=np.float32)
    keys.key_blocks[0].data.foreach_get("co", basis)
    mesh = np.empty_like(basis)
    obj.data.vertices.foreach_get("co", mesh)
    if np.array_equal(basis, mesh):
        obj.shape_key_clear()


def keep_bake_as_take(obj):
    """Turn the current bake into the take (the input motion of later edits). Returns its frames.

    The take's keys stay at 0 and are not animated, so they show nothing by themselves; a
    previous take is replaced.
    """
    frames = bake_frames(obj)
    if not frames:
        return []
    remove_keys(obj, TAKE_PREFIX)
    keys = obj.data.shape_keys
    curves = _fcurves(keys, create=False)
    for frame in frames:
        block = keys.key_blocks[bake_key_name(frame)]
        if curves is not None:
            curve = curves.find(f'key_blocks["{block.name}"].value')
            if curve is not None:
                curves.remove(curve)
        block.value = 0.0
        block.name = f"{TAKE_PREFIX}{frame:04d}"
    obj.data.update()
    return frames


def take_poses(obj):
    """(frames, positions (F, n, 3)) of the stored take, or ([], None)."""
    keys = obj.data.shape_keys
    if keys is None:
        return [], None
    blocks = sorted((int(k.name[len(TAKE_PREFIX):]), k) for k in keys.key_blocks
                    if k.name.startswith(TAKE_PREFIX) and k.name[len(TAKE_PREFIX):].isdigit())
    if not blocks:
        return [], None
    n = len(obj.data.vertices)
    positions = np.empty((len(blocks), n * 3), dtype=np.float32)
    for row, (_, block) in zip(positions, blocks):
        block.data.foreach_get("co", row)
    return [f for f, _ in blocks], positions.reshape(len(blocks), n, 3).astype(np.float64)
