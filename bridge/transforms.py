"""Objects' world transforms over a frame range, read once per frame and checked (main thread).

A transform that is not finite (a NaN key, a driver gone wrong, a parent's) or has no inverse
(scaled to zero) is refused in one line that names the object and the frame. A mirroring
transform (negative determinant) is valid: ``orthogonal_parts`` returns its orthogonal polar
factor, a reflection, and says whether it mirrors on every frame; the readers decide where the
mirror goes (``simulation_inputs``: a mirrored world; ``constraints``: a conjugation, which is
a proper rotation).
"""
import numpy as np

from ..solver import frames as body_frames
from . import animation
from .scene import InputError

SINGULAR = 1e-12   # a smallest singular value below this times the largest: scaled to zero


class ArtistMoving(Exception):
    """A transform (G, R, S, a gizmo drag) runs: setting the scene's frame now would put the
    objects it moves back on their keys, and the artist's move would be lost."""


def transforming():
    """Whether a transform modal operator (G, R, S, a gizmo drag) runs in some window."""
    import bpy
    return any(op.bl_idname.startswith(("TRANSFORM_OT_", "transform."))
               for window in bpy.context.window_manager.windows
               for op in window.modal_operators)


def world_matrices(objects, blender_scene, frames, names):
    """(len(objects), F, 4, 4) world matrices of each object on each of ``frames`` (one
    frame_set per frame, the current frame restored). names: how messages call each object
    ("'Bar'", "handle 'Bar Handle'"). InputError on the first object and frame whose transform
    is not finite; ArtistMoving while a transform runs (frame_set would undo its move)."""
    if transforming():
        raise ArtistMoving()
    current = blender_scene.frame_current
    matrices = np.empty((len(objects), len(frames), 4, 4))
    try:
        for f, frame in enumerate(frames):
            blender_scene.frame_set(int(frame))
            for i, obj in enumerate(objects):
                matrices[i, f] = np.array(obj.matrix_world)
    finally:
        blender_scene.frame_set(current)
    return _require_finite(matrices, frames, names)


def _require_finite(matrices, frames, names):
    finite = np.isfinite(matrices).all(axis=(2, 3))
    if not finite.all():
        i, f = np.argwhere(~finite)[0]
        raise InputError(f"The transform of {names[i]} on frame {int(frames[f])} is not a "
                         "finite number: check the keys, drivers and parents that move it")
    return matrices


def curve_world_matrices(objects, blender_scene, frames, names):
    """Like ``world_matrices`` but without setting the scene's frame, or None where that cannot
    be exact: each object's matrix on a frame from its own transform F-curves; while a transform
    runs, on the current frame as it stands (the drag: what the artist sees, not yet keyed).
    Exact for objects that only their own keys move (``follows_own_curves``); None if one is
    moved otherwise."""
    if not all(follows_own_curves(obj) for obj in objects):
        return None
    current = blender_scene.frame_current if transforming() else None
    matrices = np.empty((len(objects), len(frames), 4, 4))
    for i, obj in enumerate(objects):
        above = (np.array(obj.parent.matrix_world) @ np.array(obj.matrix_parent_inverse)
                 if obj.parent is not None else np.eye(4))
        for f, frame in enumerate(frames):
            basis = obj.matrix_basis if int(frame) == current else _keyed_basis(obj, frame)
            matrices[i, f] = above @ np.array(basis)
    return _require_finite(matrices, frames, names)


TRANSFORM_PATHS = ("location", "rotation_euler", "rotation_quaternion", "rotation_axis_angle",
                   "scale")


def follows_own_curves(obj):
    """Whether obj's world transform is its own keyed location, rotation and scale under still
    parents: no constraint, driver, NLA strip, parent other than an object's, or delta
    transform (``_keyed_basis`` composes none of them)."""
    if any(getattr(c, "enabled", not getattr(c, "mute", False)) for c in obj.constraints):
        return False
    if tuple(obj.delta_location) != (0, 0, 0) or tuple(obj.delta_scale) != (1, 1, 1) or \
            tuple(obj.delta_rotation_euler) != (0, 0, 0) or \
            tuple(obj.delta_rotation_quaternion) != (1, 0, 0, 0):
        return False
    anim = obj.animation_data
    if anim is not None and (len(anim.drivers) or len(anim.nla_tracks) or anim.use_tweak_mode
                             or anim.action_influence != 1.0
                             or anim.action_blend_type != 'REPLACE'):
        return False
    parent = obj.parent
    while parent is not None:           # a parent must stand still (its matrix is read as is)
        if obj.parent_type != 'OBJECT' or parent.animation_data is not None \
                or len(parent.constraints):
            return False
        obj, parent = parent, parent.parent
    return True


def _keyed_basis(obj, frame):
    """obj's matrix_basis on `frame`: each transform channel from its F-curve, if keyed (and the
    curve not muted), else as it stands."""
    import mathutils
    curves = animation.fcurves(obj)

    def channel(path):
        values = list(getattr(obj, path))
        if curves is not None:
            for index in range(len(values)):
                curve = curves.find(path, index=index)
                if curve is not None and not curve.mute:
                    values[index] = curve.evaluate(frame)
        return values

    mode = obj.rotation_mode
    if mode == 'QUATERNION':
        rotation = mathutils.Quaternion(channel("rotation_quaternion")).normalized()
    elif mode == 'AXIS_ANGLE':
        angle, *axis = channel("rotation_axis_angle")
        rotation = mathutils.Quaternion(axis, angle)
    else:
        rotation = mathutils.Euler(channel("rotation_euler"), mode)
    return mathutils.Matrix.LocRotScale(channel("location"), rotation, channel("scale"))


def require_invertible(name, matrices, frames):
    """InputError when the transform (F, 4, 4) of the object called `name` ('Bar') is scaled to
    zero on a frame, so that nothing can be carried into its own space."""
    s = np.linalg.svd(matrices[:, :3, :3], compute_uv=False)
    singular = s[:, -1] <= SINGULAR * s[:, 0]
    if singular.any():
        frame = int(frames[int(np.argmax(singular))])
        raise InputError(f"{name} is scaled to zero on frame {frame}, so its transform has no "
                         "inverse: give it a scale on every axis")


def orthogonal_parts(name, matrices, frames):
    """(Q (F, 3, 3), mirrored): the orthogonal polar factors of the transforms (F, 4, 4)
    (``solver.frames.polar_decomposition``; scale and shear dropped) and whether they mirror.
    InputError when the object called `name` mirrors on some frames and not on others (a scale
    that changes sign): no motion turns a body inside out."""
    Q, _ = body_frames.polar_decomposition(matrices[:, :3, :3])
    mirrors = np.linalg.det(Q) < 0.0
    if mirrors.any() and not mirrors.all():
        turned = int(np.argmax(mirrors != mirrors[0]))
        raise InputError(f"{name} turns inside out between frames {int(frames[turned - 1])} "
                         f"and {int(frames[turned])} (a scale changes sign): keep its scales' "
                         "signs over the frame range")
    return Q, bool(len(mirrors) and mirrors.all())

