"""Read the space-time constraints of a body from the scene: handles (Empties bound to vertex
groups) and pose keys (shape keys keyed to 1 on a frame). Main thread only."""
import numpy as np

from ..solver import spacetime
from ..solver.problems import HandleTrack
from . import animation, bake, scene, transforms


ROTATION_PATHS = ("rotation_euler", "rotation_quaternion", "rotation_axis_angle")


def _orientation_frames(empty, handle, wanted, frame_set):
    """Every frame of the span of the Empty's rotation keys (and the position frames).

    Every frame, not only the keys: a target only knows the rotation modulo 360 deg and the
    solve keeps the winding only when successive targets are close (solver.spacetime,
    "Winding"); evaluated per frame, the keyed F-curve's rotation moves little between
    neighbouring frames, so a 360 deg key is no longer the same target as 0.
    """
    if handle.follow:
        return sorted(frame_set)
    keyed = {f for path in ROTATION_PATHS for f in animation.keyed_frames(empty, path)}
    keyed = [f for f in keyed | set(wanted) if f in frame_set]
    return [int(f) for f in spacetime.winding_span(keyed) if int(f) in frame_set]


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
        if handle.weight == 0.0:        # a documented meaning: weight 0 switches a handle off
            warnings.append(f"{label}: its weight is 0, so it is ignored")
            continue
        if handle.follow:
            wanted = sorted(frame_set)
        else:
            wanted = [f for f in animation.keyed_frames(empty, "location") if f in frame_set]
        turning = (_orientation_frames(empty, handle, wanted, frame_set)
                   if getattr(handle, "orientation", False) else [])
        if not wanted and not turning:
            warnings.append(f"{label}: no location keys in the frame range, so it is ignored "
                            "(with Follow Every Frame on, it is followed wherever it goes)")
            continue
        plans.append((empty, indices, handle.weight, np.array(wanted, dtype=np.int64),
                      np.array(turning, dtype=np.int64)))
    targets, rotations = _world_to_body(obj, blender_scene, plans, min(frame_set))
    tracks = [HandleTrack(empty.name, indices, weight, wanted, targets[i],
                          turning if len(turning) else None,
                          rotations[i] if len(turning) else None)
              for i, (empty, indices, weight, wanted, turning) in enumerate(plans)]
    warnings += [f"Handle '{track.name}': its Empty turns more than {FAST_TURN_DEG}° between "
                 "two frames; the twist's winding may be lost (key more slowly)"
                 for track in tracks if track.rotations is not None and _fastest_turn(track)
                 > np.radians(FAST_TURN_DEG)]
    return tracks, warnings


FAST_TURN_DEG = 90   # per-frame turn above which per-frame targets no longer carry the winding


def _fastest_turn(track):
    """Largest rotation angle [rad] between the track's successive orientation targets."""
    R = track.rotations
    if len(R) < 2:
        return 0.0
    trace = np.einsum("fji,fji->f", R[:-1], R[1:])
    return float(np.arccos(np.clip(0.5 * (trace - 1.0), -1.0, 1.0)).max())


def _world_to_body(obj, blender_scene, plans, first):
    """Each plan's Empty positions on its frames, in the body's object space at that frame, and
    its rotations on its orientation frames: O(f) O(first)^T, O = Qb^T Qe, Qb and Qe the
    orthogonal polar factors of the body's and the Empty's transforms (scale dropped), i.e. the
    turn since the range's first frame, where the body is at rest. A mirrored body's Qb is a
    reflection; O(f) O(first)^T is then the Empty's turn conjugated by it, a proper rotation: the
    mirror image of the turn, as the body's own space sees it. InputError for a transform that
    is not finite, or a body scaled to zero, on a frame read."""
    needed = sorted({int(f) for plan in plans for f in np.r_[plan[3], plan[4]]}
                    | ({int(first)} if any(len(plan[4]) for plan in plans) else set()))
    if not needed:
        return [np.zeros((0, 3)) for _ in plans], [np.zeros((0, 3, 3)) for _ in plans]
    empties = [plan[0] for plan in plans]
    names = [f"'{obj.name}'"] + [f"handle '{empty.name}'" for empty in empties]
    # From the keys where that is exact: setting the scene's frame would put an Empty the
    # artist is dragging back on its key (Live reads while the drag runs).
    matrices = transforms.curve_world_matrices([obj] + empties, blender_scene, needed, names)
    if matrices is None:                                 # one scene evaluation per frame
        matrices = transforms.world_matrices([obj] + empties, blender_scene, needed, names)
    transforms.require_invertible(f"'{obj.name}'", matrices[0], needed)
    row = {frame: i for i, frame in enumerate(needed)}
    to_body = np.linalg.inv(matrices[0])                                     # (F, 4, 4)
    targets, rotations = [], []
    for i, (empty, _, _, wanted, turning) in enumerate(plans, start=1):
        at = [row[int(f)] for f in wanted]
        targets.append(np.einsum("fij,fj->fi", to_body[at, :3, :3], matrices[i, at, :3, 3])
                       + to_body[at, :3, 3])
        rotations.append(_turns(obj, empty, matrices[0], matrices[i], needed,
                                [row[int(f)] for f in turning], row.get(int(first))))
    return targets, rotations


def _turns(obj, empty, body, handle, frames, turning, first):
    """(o, 3, 3) the Empty's turns O(f) O(first)^T on the rows `turning` of the transforms
    (F, 4, 4) sampled on `frames` (see ``_world_to_body``)."""
    if not turning:
        return np.zeros((0, 3, 3))
    turned = (np.swapaxes(transforms.orthogonal_parts(f"'{obj.name}'", body, frames)[0], 1, 2)
              @ transforms.orthogonal_parts(f"handle '{empty.name}'", handle, frames)[0])
    return turned[turning] @ turned[first].T


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


