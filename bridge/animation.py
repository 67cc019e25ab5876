"""F-curves of an ID (an object, a shape-key datablock) on every Blender from 4.2 to 5.x.

The one place that knows how actions differ between versions, chosen by feature detection:
- Blender 4.2 and 4.3: an action holds its F-curves directly (`action.fcurves`).
- Blender 4.4 and later: actions are layered and slotted. An ID animates through its slot; the
  slot's F-curves live in a channel bag of the action's keyframe strip. 5.0 added
  `anim_utils.action_ensure_channelbag_for_slot`; 4.4 and 4.5 only have the strip's own
  `channelbag(slot, ensure=True)`, and `action.fcurves` is gone in 5.0.

One function per need: `fcurves` (get or create the collection), `insert_keys`, `remove_fcurves`,
and the readers `keyed_frames` and `keyframes`. The readers see the keys as the scene plays them:
those of the active action, and those of the actions in the NLA strips that play, at the scene
frames each strip puts them on (`strip_frames`).
"""
import math

import numpy as np


def fcurves(id_block, create=False):
    """The F-curve collection animating `id_block`, or None (create=False and nothing animated)."""
    anim = id_block.animation_data
    if anim is None or anim.action is None:
        if not create:
            return None
        import bpy
        anim = id_block.animation_data_create()
        anim.action = bpy.data.actions.new(f"{id_block.name} RS Elastic")
    action = anim.action
    if not hasattr(action, "layers"):
        return action.fcurves                          # legacy actions (4.2, 4.3)
    slot = anim.action_slot
    if slot is None:
        if not create:
            return None
        slot = action.slots.new(id_type=id_block.id_type, name=id_block.name)
        anim.action_slot = slot
    return _slot_curves(action, slot, create)


def _slot_curves(action, slot, create=False):
    """The F-curves of `slot` in `action` (4.4+), or the action's own (4.2, 4.3), or None."""
    if not hasattr(action, "layers"):
        return action.fcurves
    if slot is None:
        return None
    bag = _channelbag(action, slot, create)
    return None if bag is None else bag.fcurves


def _channelbag(action, slot, create):
    """The channel bag of `slot` in a layered action (4.4+), made if `create`; else None."""
    from bpy_extras import anim_utils
    ensure = getattr(anim_utils, "action_ensure_channelbag_for_slot", None)     # 5.0+
    if create and ensure is not None:
        return ensure(action, slot)
    for layer in action.layers:
        for strip in layer.strips:
            bag = strip.channelbag(slot, ensure=False)
            if bag is not None:
                return bag
    if not create:
        return None
    layer = action.layers[0] if len(action.layers) else action.layers.new("Layer")
    strip = layer.strips[0] if len(layer.strips) else layer.strips.new(type='KEYFRAME')
    return strip.channelbag(slot, ensure=True)


def insert_keys(id_block, data_path, points, interpolation='BEZIER', index=0):
    """Add an F-curve for `data_path` with keyframes at points (k, 2) of (frame, value).

    Replaces an existing curve of the same path and index, so inserting is idempotent.
    """
    curves = fcurves(id_block, create=True)
    old = curves.find(data_path, index=index)
    if old is not None:
        curves.remove(old)
    curve = curves.new(data_path, index=index)
    points = np.asarray(points, dtype=np.float32).reshape(-1, 2)
    curve.keyframe_points.add(len(points))
    curve.keyframe_points.foreach_set("co", points.ravel())
    for point in curve.keyframe_points:
        point.interpolation = interpolation
    curve.update()
    return curve


def remove_fcurves(id_block, data_paths):
    """Remove every F-curve of `id_block` whose path is in `data_paths`. Returns how many."""
    curves = fcurves(id_block, create=False)
    if curves is None:
        return 0
    paths = set(data_paths)
    doomed = [c for c in curves if c.data_path in paths]
    for curve in doomed:
        curves.remove(curve)
    return len(doomed)


def keyed_frames(id_block, data_path):
    """Sorted integer scene frames that carry a keyframe on any channel of `data_path` (the
    active action's and the playing NLA strips', ``keyed_points``)."""
    return sorted({int(round(frame)) for frame, _ in keyed_points(id_block, data_path)})


def keyframes(id_block, data_path, index=0):
    """(k, 2) array of (scene frame, value) keyframes of one channel, sorted by frame (the
    active action's and the playing NLA strips', ``keyed_points``), or an empty array."""
    points = sorted(keyed_points(id_block, data_path, index))
    return np.array(points, dtype=np.float64).reshape(-1, 2)


def keyed_points(id_block, data_path, index=None):
    """[(scene frame, value)] of the keyframes on `data_path` (channel `index`, or every one):
    the active action's where they are (outside the NLA's tweak mode, whose action is a
    strip's), then each playing strip's action's at the frames ``strip_frames`` maps them to."""
    anim = id_block.animation_data
    if anim is None:
        return []
    points = []
    if not anim.use_tweak_mode:
        points += _curve_points(fcurves(id_block), data_path, index)
    for strip in playing_strips(anim):
        keys = _curve_points(_slot_curves(strip.action, getattr(strip, "action_slot", None)),
                             data_path, index)
        points += [(frame, value) for at, value in keys for frame in strip_frames(strip, at)]
    return points


def _curve_points(curves, data_path, index):
    """[(frame, value)] of the keyframes of the curves on `data_path` (channel `index` or all)."""
    points = []
    for curve in () if curves is None else curves:
        if curve.data_path == data_path and (index is None or curve.array_index == index):
            co = np.empty(len(curve.keyframe_points) * 2)
            curve.keyframe_points.foreach_get("co", co)
            points += [(float(f), float(v)) for f, v in co.reshape(-1, 2)]
    return points


def playing_strips(anim):
    """The action strips the NLA plays: unmuted strips (inside meta strips too) with an action,
    on unmuted tracks, only the solo track's when one is soloed."""
    tracks = [track for track in anim.nla_tracks if not track.mute]
    if any(track.is_solo for track in tracks):
        tracks = [track for track in tracks if track.is_solo]
    pending = [strip for track in tracks for strip in track.strips]
    strips = []
    while pending:
        strip = pending.pop(0)
        if strip.mute:
            continue
        if strip.type == 'META':
            pending += list(strip.strips)
        elif strip.type == 'CLIP' and strip.action is not None:
            strips.append(strip)
    return strips


def strip_frames(strip, action_frame):
    """The scene frames on which an action strip plays its action's frame `action_frame`: once
    per repeat, offset by the strip's start and stretched by its scale, counted from the
    action's end when reversed (Blender's NLA time mapping), within the strip. A strip whose
    time is animated maps its own way: every frame of its span is given instead."""
    start, end = strip.frame_start, strip.frame_end
    if strip.use_animated_time:
        return [float(f) for f in range(math.ceil(start), math.floor(end) + 1)]
    first, last, scale = strip.action_frame_start, strip.action_frame_end, abs(strip.scale)
    if not first <= action_frame <= last or scale == 0.0:
        return []
    offset = (last - action_frame) if strip.use_reverse else (action_frame - first)
    period = (last - first) * scale
    count = max(1, math.ceil(strip.repeat - 1e-9)) if period > 0.0 else 1
    frames = [start + offset * scale + r * period for r in range(count)]
    return [f for f in frames if f <= end + 1e-6]
