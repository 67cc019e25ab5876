"""Read the space-time constraints of a body from the scene: handles (Empties bound to vertex
groups) and pose keys (shape keys keyed to 1 on a frame). Main thread only."""
import dataclasses

import numpy as np

from . import animation, bake, scene


@dataclasses.dataclass
class HandleTrack:
    """One handle's targets, in the body's object space (its rest frame)."""
    name: str
    vertices: np.ndarray   # (k,) base-vertex indices
    weight: float
    frames: np.ndarray     # (c,) int scene frames
    targets: np.ndarray    # (c, 3) metres, object space


def _is_motion_key(keys, block):
    """The extension's bake, take and preview keys are motion, never pose constraints."""
    return bake.role(keys, block) in ("bake", "take", "preview")


def read_handles(obj, blender_scene, frames):
    """HandleTracks of the body over `frames` (sorted ints), and warnings for handles skipped."""
    warnings, plans = [], []
    frame_set = set(int(f) for f in frames)
    for number, handle in enumerate(obj.rs_elastic.handles, start=1):
        empty = handle.empty
        label = f"Handle {number}"
        if empty is None or blender_scene.objects.get(empty.name) is None:
            warnings.append(f"{label}: its Empty was deleted; the handle is ignored")
            continue
        label = f"Handle '{empty.name}'"
        try:
            indices = np.flatnonzero(scene.vertex_group_mask(obj, handle.vertex_group))
        except scene.InputError:
            warnings.append(f"{label}: vertex group '{handle.vertex_group}' is gone; ignored")
            continue
        if len(indices) == 0:
            warnings.append(f"{label}: vertex group '{handle.vertex_group}' is empty; ignored")
            continue
        if handle.follow:
            wanted = sorted(frame_set)
        else:
            wanted = [f for f in animation.keyed_frames(empty, "location") if f in frame_set]
        if not wanted:
            warnings.append(f"{label}: no location keys in the frame range; ignored")
            continue
        plans.append((empty, indices, handle.weight, np.array(wanted)))
    targets = _world_to_body(obj, blender_scene, plans)
    tracks = [HandleTrack(empty.name, indices, weight, wanted, targets[i])
              for i, (empty, indices, weight, wanted) in enumerate(plans)]
    return tracks, warnings


def _world_to_body(obj, blender_scene, plans):
    """Each plan's Empty positions on its frames, in the body's object space at that frame."""
    needed = sorted({int(f) for *_, wanted in plans for f in wanted})
    current = blender_scene.frame_current
    at_frame = {}
    try:
        for frame in needed:       # one scene evaluation per frame, shared by all handles
            blender_scene.frame_set(frame)
            to_body = np.array(obj.matrix_world.inverted())
            at_frame[frame] = {empty.name: (to_body @ np.r_[np.array(empty.matrix_world.translation), 1.0])[:3]
                               for empty, *_ in plans}
    finally:
        blender_scene.frame_set(current)
    return [np.array([at_frame[int(f)][empty.name] for f in wanted]) for empty, _, _, wanted in plans]


def read_pose_keys(obj, frames):
    """[(frame, key name)]: the user's shape keys keyed to 1.0 on a frame of the range."""
    keys = obj.data.shape_keys
    if keys is None:
        return []
    frame_set = set(int(f) for f in frames)
    poses = []
    for block in keys.key_blocks:
        if block == keys.reference_key or _is_motion_key(keys, block):
            continue
        for frame, value in animation.keyframes(keys, f'key_blocks["{block.name}"].value'):
            if abs(value - 1.0) < 1e-6 and int(round(frame)) in frame_set:
                poses.append((int(round(frame)), block.name))
    return sorted(poses)
