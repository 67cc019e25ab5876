"""A simplified, closed proxy of a dense render surface, for fTetWild to tetrahedralise.

The render mesh is embedded in the tets afterwards (``embed.embed_points``: every render vertex
gets barycentric weights in the tet that holds it, or the nearest one), so the tet mesh only
has to follow the body's shape at the scale of its own edges. fTetWild's time grows with the
input's triangle count (a 200k-triangle mesh was still at 5 % after 150 s), while the tets it
makes at a given edge length need far fewer: a closed surface meshed at edge L has about
area / (sqrt(3)/4 L^2) triangles. So a surface with more than ``triangle_budget`` triangles is
simplified first by libigl's edge-collapse ``igl.decimate``, which keeps a closed manifold
closed and manifold. The proxy's edges are about the tet edge: fTetWild refines the tets near
every input triangle, so a finer proxy made more tets and slower meshing at no better quality
(octopus: 898 triangles 7,647 tets 9.9 CPU s, its 500-triangle proxy 3,108 tets 6.2 s, the
smallest dihedral angle 10 degrees either way). The edge-collapse shrinks a convex body,
though (a sphere's proxy of 500 triangles holds 96 % of its volume, of 1,500 98.7 %), so no
proxy has fewer than ``MIN_BUDGET`` triangles. A surface that is not a closed
edge-manifold (it is then fTetWild's job to repair) is passed on as it is.

Shapes: V (n, 3) float vertices [m], F (m, 3) int triangles.
"""
import igl
import numpy as np

PROXY_EDGE_FRACTION = 1.0   # proxy edge / tet edge (0.5 before: 4x the triangles, more tets)
MIN_BUDGET = 1500           # never simplify below this many triangles


def surface_area(V, F):
    """Total area [m^2] of the triangles F over V."""
    V, F = np.asarray(V, dtype=np.float64), np.asarray(F, dtype=np.int64)
    return 0.5 * float(np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]),
                                      axis=1).sum())


def triangle_budget(V, F, edge_length_fac):
    """Triangles a proxy needs for tets of edge ``edge_length_fac`` x the bounding-box diagonal
    (``budget_for`` of the surface's area and diagonal)."""
    V = np.asarray(V, dtype=np.float64)
    used = V[np.unique(np.asarray(F))]
    return budget_for(surface_area(V, F), float(np.linalg.norm(np.ptp(used, axis=0))),
                      edge_length_fac)


def budget_for(area, diagonal, edge_length_fac):
    """area / (sqrt(3)/4 l^2) at l = PROXY_EDGE_FRACTION x edge_length_fac x diagonal [m],
    at least MIN_BUDGET: the equilateral triangles of edge l that tile the area [m^2]."""
    edge = PROXY_EDGE_FRACTION * edge_length_fac * diagonal
    if not edge > 0.0:
        return MIN_BUDGET
    return max(MIN_BUDGET, int(np.ceil(area / (np.sqrt(3.0) / 4.0 * edge ** 2))))


# fTetWild seconds per input triangle and fixed cost, fitted on this project's bench machine
# (2 cores: cow 5,520 triangles 9.9 s, knight 1,000 triangles 2.9 s, edge 0.05): a rough guide.
TETWILD_SECONDS = (1.35, 1.55e-3)


def tetwild_seconds(triangles):
    """Rough fTetWild time [s] for a surface of this many triangles (``TETWILD_SECONDS``)."""
    return TETWILD_SECONDS[0] + TETWILD_SECONDS[1] * int(triangles)


def is_closed_manifold(F):
    """Every edge of F (m, 3) has exactly two faces (no boundary, no fins)."""
    F = np.asarray(F, dtype=np.int64)
    edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return bool(np.all(counts == 2))


def proxy_surface(V, F, budget):
    """(V', F', simplified) with at most ``budget`` triangles when F has more and is a closed
    edge-manifold; else (V, F, False) unchanged. Deterministic (libigl's collapse order is)."""
    V = np.ascontiguousarray(V, dtype=np.float64)
    F = np.ascontiguousarray(F, dtype=np.int64)
    if len(F) <= budget or not is_closed_manifold(F):
        return V, F, False
    U, G = igl.decimate(V, F, int(budget))[:2]
    U, G = np.asarray(U, dtype=np.float64), np.asarray(G, dtype=np.int64)
    if len(G) < 4 or not is_closed_manifold(G):
        return V, F, False                       # fTetWild copes with the original
    return U, G, True
