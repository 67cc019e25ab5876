"""What the panels show before any work starts: how much fTetWild will mesh and roughly how
long, and what the Rayleigh damping means for the slowest mode. Cheap enough for every redraw."""
import math

import numpy as np

from ..solver import dynamics, proxy

_MESHED = {}    # (mesh pointer, polygons, edge length, budget) -> (triangles, proxy triangles)


def mesh_estimate(obj, settings):
    """(triangles, triangles fTetWild will mesh) of the object's own mesh, from its polygons'
    areas and the bounding box, without triangulating (cached per mesh and settings)."""
    mesh = obj.data
    key = (mesh.as_pointer(), len(mesh.polygons), settings.edge_length, settings.proxy_triangles)
    if key not in _MESHED:
        sizes = np.empty(len(mesh.polygons), dtype=np.int32)
        areas = np.empty(len(mesh.polygons), dtype=np.float32)
        mesh.polygons.foreach_get("loop_total", sizes)
        mesh.polygons.foreach_get("area", areas)
        triangles = int(np.maximum(sizes - 2, 0).sum())
        corners = np.array(obj.bound_box)
        diagonal = float(np.linalg.norm(corners.max(axis=0) - corners.min(axis=0)))
        budget = settings.proxy_triangles or proxy.budget_for(float(areas.sum()), diagonal,
                                                              settings.edge_length)
        if len(_MESHED) > 64:
            _MESHED.clear()
        _MESHED[key] = (triangles, min(triangles, budget))
    return _MESHED[key]


def mesher_seconds(triangles):
    """Rough seconds fTetWild takes for a surface of this many triangles."""
    return proxy.tetwild_seconds(triangles)


def first_mode_damping_ratio(settings, frequency_hz):
    """The damping ratio ζ of the Rayleigh damping at a mode of this frequency (Hz)."""
    return dynamics.damping_ratio(settings.damping_mass, settings.damping_stiffness,
                                  2.0 * math.pi * frequency_hz)
