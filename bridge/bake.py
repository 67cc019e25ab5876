"""Shape-key output: sets of named keys, and baked animations (one key per frame).

A bake goes to shape keys (below) or, with the object's Bake To set to Mesh Cache, to a .pc2
file played by a Mesh Cache modifier (``mesh_cache``); either replaces the other.

A baked animation is the form every RS Elastic bake takes: key `RS Bake 0042` holds frame 42's
pose and is keyed 0 on frame 41, 1 on frame 42 and 0 on frame 43, with constant interpolation, so
scrubbing plays the bake. Baking again replaces the previous bake (its keys and their F-curves).

Ownership. The extension only ever removes or changes keys it made. Shape keys (ShapeKey) cannot
hold custom properties, so the tags live on the Key datablock: `key["rs_elastic"]` maps the name
of each key the extension wrote to its role ("bake", "take", "preview", "basis", "inbetween").
A key the user renames loses its tag and becomes the user's; a user's key is never tagged, so a
key named `RS Bake notes` or a first key named `Rest` is left alone. The Basis is removed only if
the extension created it and nothing else is left on it.

Bakes made before the tags (untagged, recognised by name) are migrated by `_legacy_role`: a key
named exactly `RS Bake <digits>` whose F-curve is the bake's own 0-1-0 step, or `RS Take
<digits>` with no F-curve, or the preview key's name. That pattern is specific enough that a user
key does not match it by accident. Their untagged Basis cannot be told from a user's, so it is
kept (it repeats the mesh, so nothing shows). Untagged in-between keys stay the user's: a new
interpolation adds its keys beside them.

Tags follow names, so a key the user deletes by hand leaves its name tagged until the extension
next writes keys (`_tag` forgets names that no longer exist); a key the user creates under that
very name in between would count as the extension's.

Writing (bridge/writes.py): every write here runs in a transaction. New keys are added first (the
extension's old keys of the same names renamed out of their way, their F-curves following the
names), and the old keys are removed only once everything new is written, so a failure on the way
leaves the keys, their data, tags and F-curves as they were. Nothing is written outside Object
Mode: Edit Mode keeps its own copy of the keys and writes it back when it is left.
"""
import re

import bpy
import numpy as np

from . import animation, mesh_cache, writes
from .scene import InputError, require_single_user

BAKE_PREFIX = "RS Bake "
TAKE_PREFIX = "RS Take "     # a kept bake: the input motion of a space-time edit
PREVIEW_KEY = "RS Elastic Preview"
ASIDE_PREFIX = "RS Replaced "  # an old key renamed out of the way of its replacement
TAGS = "rs_elastic"          # ID property on the Key datablock: {key name: role}

BLOW_UP_FACTOR = 100.0       # a pose larger than this × the body's rest size has blown up


def bake_key_name(frame):
    return f"{BAKE_PREFIX}{frame:04d}"


# --- ownership ----------------------------------------------------------------------------------

def _value_path(name):
    return f'key_blocks["{name}"].value'


def _legacy_role(keys, block):
    """The role of an untagged key written before tagging existed, or None (the user's)."""
    if block.name == PREVIEW_KEY:
        return "preview"
    match = re.fullmatch(r"RS (Bake|Take) (\d+)", block.name)
    if match is None:
        return None
    curves = animation.fcurves(keys, create=False)
    curve = None if curves is None else curves.find(_value_path(block.name))
    if match.group(1) == "Take":
        return "take" if curve is None else None
    if curve is None or len(curve.keyframe_points) != 3:
        return None
    frame = int(match.group(2))
    co = np.empty(6)
    curve.keyframe_points.foreach_get("co", co)
    return "bake" if np.allclose(co, [frame - 1, 0, frame, 1, frame + 1, 0]) else None


def role(keys, block):
    """What the extension made `block` for ("bake", "take", …), or None if it is the user's."""
    tags = keys.get(TAGS)
    if tags is not None and block.name in tags.keys():
        return tags[block.name]
    return _legacy_role(keys, block)


def _tag(keys, roles):
    """Record {key name: role} for keys the extension just wrote (one write for many keys)."""
    tags = keys.get(TAGS)
    tags = {} if tags is None else tags.to_dict()
    names = set(keys.key_blocks.keys())
    tags = {name: r for name, r in tags.items() if name in names}   # forget removed keys
    tags.update(roles)
    keys[TAGS] = tags


def _untag(keys, name):
    tags = keys.get(TAGS)
    if tags is not None and name in tags.keys():
        del tags[name]


def owned_keys(obj, what):
    """The object's shape keys the extension made for `what` (a role)."""
    keys = obj.data.shape_keys
    if keys is None:
        return []
    return [b for b in keys.key_blocks if role(keys, b) == what]


def _remove_named(obj, names):
    """Remove the extension's keys `names` and their F-curves now; drop the Basis if the
    extension made it and nothing else is left on it."""
    keys = obj.data.shape_keys
    if keys is None or not names:
        return 0
    animation.remove_fcurves(keys, {_value_path(name) for name in names})
    for name in names:
        block = keys.key_blocks.get(name)
        if block is not None:
            obj.shape_key_remove(block)
            _untag(keys, name)
    _drop_own_basis(obj)
    return len(names)


def _drop_own_basis(obj):
    keys = obj.data.shape_keys
    if keys is None or len(keys.key_blocks) != 1:
        return
    if role(keys, keys.key_blocks[0]) == "basis":
        obj.shape_key_clear()


# --- writing keys in a transaction ---------------------------------------------------------------

def require_writable(obj, verb="bake"):
    """Refuse (InputError) writing the object's keys or modifiers: a mesh shared by linked
    duplicates, or an object outside Object Mode."""
    require_single_user(obj)
    writes.require_object_mode(obj, verb)


def _keep_tags(obj, transaction):
    """Undone, the tags are as they are now."""
    keys = obj.data.shape_keys
    saved = None if keys is None or keys.get(TAGS) is None else keys[TAGS].to_dict()

    def undo():
        keys = obj.data.shape_keys
        if keys is None:
            return
        if saved is None:
            if keys.get(TAGS) is not None:
                del keys[TAGS]
        else:
            keys[TAGS] = saved
    transaction.undo(undo)


def _take_back_keys(obj, names, had_keys):
    keys = obj.data.shape_keys
    if keys is None:
        return
    animation.remove_fcurves(keys, {_value_path(name) for name in names})
    if not had_keys:
        obj.shape_key_clear()
        return
    for name in reversed(names):
        block = keys.key_blocks.get(name)
        if block is not None:
            obj.shape_key_remove(block)


def add_keys(obj, names, what, transaction):
    """New keys tagged as the extension's `what`, on a Basis (the user's first key if there is
    one, else one the extension adds and tags). Blender may suffix a name that is taken.
    Undone, they go again, with their F-curves."""
    made = []
    had_keys = obj.data.shape_keys is not None
    _keep_tags(obj, transaction)
    transaction.undo(lambda: _take_back_keys(obj, made, had_keys))
    roles = {}
    if not had_keys:
        made.append(obj.shape_key_add(name="Basis", from_mix=False).name)
        roles[made[-1]] = "basis"
    for name in names:
        made.append(obj.shape_key_add(name=name, from_mix=False).name)
        roles[made[-1]] = what
    keys = obj.data.shape_keys
    _tag(keys, roles)
    return [keys.key_blocks[name] for name in made[len(made) - len(names):]]


def _set_aside(obj, blocks, transaction):
    """Rename the extension's old keys out of the way of new ones with the same names (their
    F-curves follow the names; their roles stay tagged). Undone, they get their names back.
    Returns their new names, for `remove_keys_later`."""
    keys = obj.data.shape_keys
    if not blocks:
        return []
    _keep_tags(obj, transaction)
    renamed = []                                   # (name now, name before)

    def undo():
        for now, before in reversed(renamed):
            keys.key_blocks[now].name = before
    transaction.undo(undo)
    roles = {}
    for block in blocks:
        before, what = block.name, role(keys, block)
        block.name = ASIDE_PREFIX + before
        renamed.append((block.name, before))
        roles[block.name] = what
    _tag(keys, roles)
    return [now for now, _ in renamed]


def remove_keys_later(obj, names, transaction):
    """Remove the extension's keys `names` (and their F-curves) once everything new is written."""
    if names:
        transaction.remove(lambda: _remove_named(obj, list(names)))


def _keep_animation(obj, transaction):
    """Undone, the Key's animation data is as now: an action made for new F-curves goes again
    (the F-curves themselves go with their keys)."""
    keys = obj.data.shape_keys
    had_data = keys.animation_data is not None
    action = keys.animation_data.action if had_data else None
    actions = set(bpy.data.actions)

    def undo():
        keys = obj.data.shape_keys
        if keys is not None and action is None and keys.animation_data is not None:
            if had_data:
                keys.animation_data.action = None
            else:
                keys.animation_data_clear()
        for made in set(bpy.data.actions) - actions:
            if made.users == 0:
                bpy.data.actions.remove(made)
    transaction.undo(undo)


def _keep_fcurves(keys, paths, transaction):
    """Undone, the F-curves of `paths` are back with their keyframes, under these paths: note
    them before their keys are renamed, so they are restored once the names are back."""
    curves = animation.fcurves(keys, create=False)
    saved = []
    for curve in curves or []:
        if curve.data_path in paths:
            co = np.empty(len(curve.keyframe_points) * 2)
            curve.keyframe_points.foreach_get("co", co)
            saved.append((curve.data_path, curve.array_index, co,
                           [p.interpolation for p in curve.keyframe_points]))

    def undo():
        for path, index, co, interpolations in saved:
            curve = animation.insert_keys(keys, path, co.reshape(-1, 2), index=index)
            for point, interpolation in zip(curve.keyframe_points, interpolations):
                point.interpolation = interpolation
    transaction.undo(undo)


def _set_positions(key_block, positions):
    key_block.data.foreach_set("co", np.asarray(positions, dtype=np.float32).ravel())


def replace_key_set(obj, prefix, names, positions):
    """Replace the extension's in-between keys whose name starts with `prefix` by one key per
    (name, positions)."""
    require_writable(obj, "write shape keys")
    with writes.transaction(f"Writing the in-between keys of '{obj.name}'") as transaction:
        old = [b for b in owned_keys(obj, "inbetween") if b.name.startswith(prefix)]
        aside = _set_aside(obj, old, transaction)
        for key, pose in zip(add_keys(obj, names, "inbetween", transaction), positions):
            _set_positions(key, pose)
            key.value = 0.0
        remove_keys_later(obj, aside, transaction)
        obj.data.update()


# --- bakes ----------------------------------------------------------------------------------------

def check_poses(object_name, rest, poses):
    """Raise InputError if poses (F, n, 3) are not finite or a pose is far larger than the body
    at rest (a simulation or solve that blew up): nothing such is ever baked. The size, not the
    displacement, is measured, so a free body may fall any distance."""
    poses = np.asarray(poses)
    if not np.all(np.isfinite(poses)):
        raise InputError(f"The motion of '{object_name}' blew up (non-finite positions); "
                         "nothing was baked")
    size = np.linalg.norm(rest.max(axis=0) - rest.min(axis=0))
    largest = np.linalg.norm(poses.max(axis=1) - poses.min(axis=1), axis=1).max(initial=0.0)
    if largest > BLOW_UP_FACTOR * size:
        raise InputError(f"The motion of '{object_name}' blew up ({largest / size:.3g} times "
                         "its size at rest); check gravity, material and damping. Nothing "
                         "was baked")


def require_target(obj):
    """Refuse (InputError) a bake that could not be written, before any work: linked
    duplicates, another mode than Object Mode, and for a Mesh Cache bake an unsaved file or a
    bakes folder that cannot be written."""
    require_writable(obj)
    if obj.rs_elastic.bake_to == 'CACHE':
        mesh_cache.require_bake_folder(obj)


def _active_user_keys(obj):
    keys = obj.data.shape_keys
    return [] if keys is None else [
        k.name for k in keys.key_blocks
        if k != keys.reference_key and role(keys, k) is None and k.value != 0.0]


def _write_key_bake(obj, frames, positions, transaction):
    aside = _set_aside(obj, owned_keys(obj, "bake"), transaction)
    blocks = add_keys(obj, [bake_key_name(frame) for frame in frames], "bake", transaction)
    for block, pose in zip(blocks, positions):
        _set_positions(block, pose)
        block.value = 0.0
    keys = obj.data.shape_keys
    _keep_animation(obj, transaction)
    for frame, block in zip(frames, blocks):
        animation.insert_keys(keys, _value_path(block.name),
                              [(frame - 1, 0.0), (frame, 1.0), (frame + 1, 0.0)], 'CONSTANT')
    remove_keys_later(obj, aside, transaction)


def write_bake(obj, frames, positions):
    """Replace the object's bake with one key per frame, or its Mesh Cache (Bake To).
    positions: (F, n, 3) base-vertex poses. The old bake goes only once the new one is written;
    a failure leaves everything as it was (InputError).

    Returns the names of the user's keys whose value is not 0: they add on top of a key bake
    (a Mesh Cache bake overwrites them while it plays).
    """
    require_writable(obj)
    with writes.transaction(f"Baking '{obj.name}'") as transaction:
        if obj.rs_elastic.bake_to == 'CACHE':
            mesh_cache.write(obj, frames, positions)
            remove_keys_later(obj, [b.name for b in owned_keys(obj, "bake")], transaction)
        else:
            _write_key_bake(obj, frames, positions, transaction)
            mesh_cache.clear(obj)
        obj.data.update()
    return _active_user_keys(obj)


def play_cache_bake(obj, first_frame, path):
    """Make the existing .pc2 at `path` (a farm task's bake) the object's bake, played from
    scene frame `first_frame`: as `write_bake` with Bake To Mesh Cache, the file already
    written."""
    require_writable(obj)
    with writes.transaction(f"Baking '{obj.name}'") as transaction:
        mesh_cache.play(obj, path, first_frame)
        remove_keys_later(obj, [b.name for b in owned_keys(obj, "bake")], transaction)
        obj.data.update()


def clear_bake(obj):
    """Remove the bake: its keys and F-curves, or its Mesh Cache modifier and file. Returns how
    many frames were removed, or None if the object has no bake."""
    require_writable(obj, "clear its bake")
    with writes.transaction(f"Clearing the bake of '{obj.name}'") as transaction:
        names = [b.name for b in owned_keys(obj, "bake")]
        remove_keys_later(obj, names, transaction)
        cache = mesh_cache.clear(obj)
    obj.data.update()
    if not names and cache is None:
        return None
    return len(names) + (cache or 0)


def _frame_of(block, prefix):
    digits = block.name[len(prefix):]           # "0042", or "-005" for a negative frame
    return (int(digits) if block.name.startswith(prefix) and re.fullmatch(r"-?\d+", digits)
            else None)


def _frames_and_blocks(obj, what, prefix):
    """[(frame, key)] of the extension's keys for `what`, by frame."""
    pairs = ((_frame_of(b, prefix), b) for b in owned_keys(obj, what))
    return sorted(((f, b) for f, b in pairs if f is not None), key=lambda pair: pair[0])


def bake_frames(obj):
    """Sorted frames of the object's current bake, keys or Mesh Cache (empty if none)."""
    return ([frame for frame, _ in _frames_and_blocks(obj, "bake", BAKE_PREFIX)]
            or mesh_cache.frames_of(obj))


def keep_bake_as_take(obj):
    """Turn the current bake into the take (the input motion of later edits). Returns its frames.

    The take's keys stay at 0 and are not animated, so they show nothing by themselves; a
    previous take is replaced.
    """
    require_writable(obj, "keep its bake")
    blocks = _frames_and_blocks(obj, "bake", BAKE_PREFIX)
    if not blocks:
        return _cache_bake_as_take(obj)
    with writes.transaction(f"Keeping the bake of '{obj.name}' as the take") as transaction:
        aside = _set_aside(obj, owned_keys(obj, "take"), transaction)
        keys = obj.data.shape_keys
        paths = {_value_path(block.name) for _, block in blocks}
        _keep_fcurves(keys, paths, transaction)
        animation.remove_fcurves(keys, paths)
        _keep_tags(obj, transaction)
        renamed = []                               # (key, name before)

        def undo():
            for block, before in reversed(renamed):
                block.name = before
        transaction.undo(undo)
        for frame, block in blocks:
            writes.keep_values(transaction, block, ["value"])
            block.value = 0.0
            renamed.append((block, block.name))
            block.name = f"{TAKE_PREFIX}{frame:04d}"
        _tag(keys, {block.name: "take" for _, block in blocks})     # the bake names drop out
        remove_keys_later(obj, aside, transaction)
        obj.data.update()
    return [frame for frame, _ in blocks]


def take_poses(obj):
    """(frames, positions (F, n, 3)) of the stored take, or ([], None)."""
    blocks = _frames_and_blocks(obj, "take", TAKE_PREFIX)
    if not blocks:
        return [], None
    n = len(obj.data.vertices)
    positions = np.empty((len(blocks), n * 3), dtype=np.float32)
    for row, (_, block) in zip(positions, blocks):
        block.data.foreach_get("co", row)
    return [f for f, _ in blocks], positions.reshape(len(blocks), n, 3).astype(np.float64)


def _cache_bake_as_take(obj):
    """keep_bake_as_take for a Mesh Cache bake: its poses become the take's keys (the take is
    an input the solver reads back, so it lives in the .blend), and the cache bake goes."""
    frames, positions = mesh_cache.poses(obj)
    if not frames:
        return []
    with writes.transaction(f"Keeping the bake of '{obj.name}' as the take") as transaction:
        _write_take_keys(obj, frames, positions, transaction)
        mesh_cache.clear(obj)
        obj.data.update()
    return frames


def _write_take_keys(obj, frames, positions, transaction):
    """The take's keys (at 0, not animated) for poses (F, n, 3) of ``frames``, replacing the
    previous take's."""
    aside = _set_aside(obj, owned_keys(obj, "take"), transaction)
    names = [f"{TAKE_PREFIX}{frame:04d}" for frame in frames]
    for block, pose in zip(add_keys(obj, names, "take", transaction), positions):
        _set_positions(block, pose)
        block.value = 0.0
    remove_keys_later(obj, aside, transaction)


def write_take(obj, frames, positions):
    """Make poses (F, n, 3) [object space] of ``frames`` the take (Take from Animation),
    replacing the previous take; the bake is left as it is."""
    require_writable(obj, "store a take")
    with writes.transaction(f"Storing the take of '{obj.name}'") as transaction:
        _write_take_keys(obj, frames, positions, transaction)
        obj.data.update()
