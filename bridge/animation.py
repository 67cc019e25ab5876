"""Read and write F-curves of an ID (object, shape-key datablock) in Blender 4.2 to 5.x.

Blender 4.4 moved F-curves from `action.fcurves` into slotted, layered actions; these helpers hide
the difference.
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
        return action.fcurves                          # Blender < 4.4: legacy actions
    from bpy_extras import anim_utils
    if anim.action_slot is None:
        if not create:
            return None
        anim.action_slot = action.slots.new(id_type=id_block.id_type, name=id_block.name)
    if create:
        return anim_utils.action_ensure_channelbag_for_slot(action, anim.action_slot).fcurves
    bag = anim_utils.action_get_channelbag_for_slot(action, anim.action_slot)
    return None if bag is None else bag.fcurves


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
