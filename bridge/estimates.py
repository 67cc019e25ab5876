"""What the panels show before any work starts: how much fTetWild will mesh and roughly how
long, against its time limit, and what the Rayleigh damping means for the slowest mode. Cheap
enough for every redraw. Also the lines that say what to do when fTetWild would run, or ran,
past its time limit (one recipe for the panel and the operators)."""
import math

import bpy
import numpy as np

from ..solver import dynamics, proxy

_MESHED = {}    # (object pointer, counts, edge length, budget) -> (triangles, meshed, closed,
                #                                                  thinness)


def _evaluated_mesh(obj):
    """The object's mesh after its modifiers (what Prepare meshes), not copied; None if they
    leave no mesh."""
    evaluated = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
    mesh = evaluated.data
    return mesh if isinstance(mesh, bpy.types.Mesh) else None


def _is_closed(mesh):
    """Every edge a face uses has exactly two faces (a closed manifold, which the proxy can
    simplify)."""
    corner_edges = np.empty(len(mesh.loops), dtype=np.int32)
    attribute = mesh.attributes.get(".corner_edge")     # far faster than mesh.loops
    if attribute is not None:
        attribute.data.foreach_get("value", corner_edges)
    else:
        mesh.loops.foreach_get("edge_index", corner_edges)
    faces_per_edge = np.bincount(corner_edges, minlength=len(mesh.edges))
    return bool(np.all(faces_per_edge[faces_per_edge > 0] == 2))


def _volume(mesh, areas):
    """|Enclosed volume| [m^3] of the mesh from its polygons' areas (n,), centres and normals:
    the divergence theorem, exact for planar polygons."""
    centres = np.empty(3 * len(mesh.polygons), dtype=np.float32)
    normals = np.empty(3 * len(mesh.polygons), dtype=np.float32)
    mesh.polygons.foreach_get("center", centres)
    mesh.polygons.foreach_get("normal", normals)
    centres = centres.reshape(-1, 3).astype(np.float64)
    centres -= centres.mean(axis=0)
    products = np.einsum("ij,ij->i", centres, normals.reshape(-1, 3))
    return abs(float(np.dot(areas, products)) / 3.0)


def surface_estimate(obj, settings):
    """(triangles, triangles fTetWild will mesh, closed, thinness) of the object's evaluated mesh
    (its modifiers applied), from its polygons' areas, centres and the bounding box, without
    triangulating (cached per mesh and settings). A surface that is not a closed manifold is
    meshed whole. thinness: ``proxy.thinness`` at the tet edge."""
    mesh = _evaluated_mesh(obj)
    if mesh is None or len(mesh.polygons) == 0:
        return 0, 0, True, 1.0
    key = (obj.as_pointer(), len(mesh.vertices), len(mesh.polygons), len(mesh.loops),
           settings.edge_length, settings.proxy_triangles)
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
        closed = _is_closed(mesh)
        thinness = proxy.thinness(float(areas.sum()), _volume(mesh, areas.astype(np.float64)),
                                  settings.edge_length * diagonal)
        if len(_MESHED) > 64:
            _MESHED.clear()
        _MESHED[key] = (triangles, min(triangles, budget) if closed else triangles, closed,
                        thinness)
    return _MESHED[key]


def mesh_estimate(obj, settings):
    """(triangles, triangles fTetWild will mesh) of the object's evaluated mesh
    (``surface_estimate``)."""
    return surface_estimate(obj, settings)[:2]


def mesher_seconds(triangles, thinness=1.0):
    """Rough seconds fTetWild takes for a surface of this many triangles and thinness."""
    return proxy.tetwild_seconds(triangles, thinness)


def mesher_line(obj, settings):
    """(text, over the limit) for the Tet Mesh panel: what fTetWild meshes, roughly how long,
    and the time limit."""
    triangles, meshed, closed, thinness = surface_estimate(obj, settings)
    if not closed:
        what = f"all {triangles:,} triangles (not a closed manifold, so no proxy)"
    elif meshed < triangles:
        what = f"a {meshed:,}-triangle proxy of {triangles:,}"
    else:
        what = f"{triangles:,} triangles"
    seconds, limit = mesher_seconds(meshed, thinness), settings.mesher_time_limit
    return f"fTetWild meshes {what}: roughly {seconds:.0f} s (limit {limit:g} s)", seconds > limit


def over_limit(object_name, triangles, closed, limit, thinness=1.0):
    """The refusal when fTetWild's estimate for `triangles` is over the time limit [s]."""
    seconds = mesher_seconds(triangles, thinness)
    if not closed:
        return (f"'{object_name}' is not a closed manifold, so fTetWild would mesh all "
                f"{triangles:,} of its triangles, roughly {seconds:.0f} s, over its Time Limit "
                f"of {limit:g} s: close the surface so that a simplified proxy can stand in for "
                "it, or raise the Time Limit")
    return (f"'{object_name}': fTetWild would mesh {triangles:,} triangles, roughly "
            f"{seconds:.0f} s, over its Time Limit of {limit:g} s: try fewer Proxy Triangles, "
            "a coarser Edge Length, or a higher Time Limit")


def out_of_time(object_name, triangles, closed, limit, thinness=1.0):
    """The refusal when fTetWild ran to its time limit [s] on `triangles` and was stopped."""
    seconds = mesher_seconds(triangles, thinness)
    why = "" if seconds > 0.5 * limit else "; self-intersecting or very thin parts take far longer"
    if not closed:
        return (f"'{object_name}': fTetWild did not finish within its Time Limit of {limit:g} s "
                f"(estimated {seconds:.0f} s for all {triangles:,} triangles of a surface that is "
                f"not a closed manifold{why}): close the surface, or try a coarser Edge Length, a "
                "larger Envelope, or a higher Time Limit")
    return (f"'{object_name}': fTetWild did not finish within its Time Limit of {limit:g} s "
            f"(estimated {seconds:.0f} s for {triangles:,} triangles{why}): try a coarser Edge "
            "Length, fewer Proxy Triangles, a larger Envelope, or a higher Time Limit")


def first_mode_damping_ratio(settings, frequency_hz):
    """The damping ratio ζ of the Rayleigh damping at a mode of this frequency (Hz)."""
    return dynamics.damping_ratio(settings.damping_mass, settings.damping_stiffness,
                                  2.0 * math.pi * frequency_hz)
