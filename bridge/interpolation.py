"""RS interpolation of two shape keys (``solver.poses.interpolate_poses``): read the keys and
the prepared body, blend; the operator writes the result."""
from ..solver import poses
from . import prepared, scene
from .scene import InputError


def in_betweens(obj, key_from, key_to, ts):
    """(poses (len(ts), n, 3), how many tets the two keys invert) of the blend of the object's
    shape keys ``key_from`` and ``key_to`` at weights ``ts``. Raises InputError."""
    body = prepared.require(obj)
    if key_from == key_to:
        raise InputError("Pick two different shape keys")
    points_a = scene.shape_key_positions(obj, key_from)
    points_b = scene.shape_key_positions(obj, key_to)
    return poses.interpolate_poses(body, scene.base_vertices(obj), points_a, points_b, ts)
