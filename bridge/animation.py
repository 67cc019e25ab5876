"""F-curves of an ID (an object, a shape-key datablock) on every Blender from 4.2 to 5.x.

The one place that knows how actions differ between versions, chosen by feature detection:
- Blender 4.2 and 4.3: an action holds its F-curves directly (`action.fcurves`).
- Blender 4.4 and later: actions are layered and slotted. An ID animates through its slot; the
  slot's F-curves live in a channel bag of the action's keyframe strip. 5.0 added
  `anim_utils.action_ensure_channelbag_for_slot`; 4.4 and 4.5 only have the strip's own
  `channelbag(slot, ensure=True)`, and `action.fcurves` is gone in 5.0.

One function per need: `fcurves` (get or create the collection), `insert_keys`, `remove_fcurves`,
and the readers `keyed_frames` and `keyframes`.
"""
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
    """Sorted integer frames that carry a keyframe on any channel of `data_path`."""
    curves = fcurves(id_block)
    if curves is None:
        return []
    frames = set()
    for curve in curves:
        if curve.data_path == data_path:
            co = np.empty(len(curve.keyframe_points) * 2)
            curve.keyframe_points.foreach_get("co", co)
            frames.update(int(round(f)) for f in co[0::2])
    return sorted(frames)


def keyframes(id_block, data_path, index=0):
    """(k, 2) array of (frame, value) keyframes of one channel, or an empty array."""
    curves = fcurves(id_block)
    curve = None if curves is None else curves.find(data_path, index=index)
    if curve is None:
        return np.empty((0, 2))
    co = np.empty(len(curve.keyframe_points) * 2)
    curve.keyframe_points.foreach_get("co", co)
    return co.reshape(-1, 2)
