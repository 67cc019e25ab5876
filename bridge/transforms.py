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
from .scene import InputError

SINGULAR = 1e-12   # a smallest singular value below this times the largest: scaled to zero


def world_matrices(objects, blender_scene, frames, names):
    """(len(objects), F, 4, 4) world matrices of each object on each of ``frames`` (one
    frame_set per frame, the current frame restored). names: how messages call each object
    ("'Bar'", "handle 'Bar Handle'"). InputError on the first object and frame whose transform
    is not finite."""
    current = blender_scene.frame_current
    matrices = np.empty((len(objects), len(frames), 4, 4))
    try:
        for f, frame in enumerate(frames):
            blender_scene.frame_set(int(frame))
            for i, obj in enumerate(objects):
                matrices[i, f] = np.array(obj.matrix_world)
    finally:
        blender_scene.frame_set(current)
    finite = np.isfinite(matrices).all(axis=(2, 3))
    if not finite.all():
        i, f = np.argwhere(~finite)[0]
        raise InputError(f"The transform of {names[i]} on frame {int(frames[f])} is not a "
                         "finite number: check the keys, drivers and parents that move it")
    return matrices


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

