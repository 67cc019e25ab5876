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


# fTetWild's CPU seconds ~ thinness x (a + b x triangles meshed), fitted to measurements on the
# shared meshes at the default settings (bench/run_bench.py: MESHER_MEASURED, mesher_fit; spot
# 1.8 s, cow 4.5, knight 4.7, octopus 9.0, all within 1.5x). The triangle count alone could not
# tell spot's 1,500 triangles (1.8 s) from the octopus's 898 (9.0 s): thin parts (tentacles,
# legs) keep fTetWild's optimisation busy. On an idle machine its threads make the wall time at
# most the CPU time.
TETWILD_SECONDS = (1.21, 9.8e-4)
THINNESS_RANGE = (0.5, 8.0)     # outside what was measured (0.8-4.0) the fit is not trusted


def thinness(area, volume, edge):
    """area [m^2] x edge [m] / |volume| [m^3], clipped to THINNESS_RANGE: about the share of the
    tets that touch the surface (1 for a blob, 4 for the octopus, large for a sheet)."""
    if not abs(volume) > 0.0:
        return THINNESS_RANGE[1]
    return float(np.clip(area * edge / abs(volume), *THINNESS_RANGE))


def surface_thinness(V, F, edge_length_fac):
    """``thinness`` of the closed surface (V, F) at tets of edge ``edge_length_fac`` x its
    bounding-box diagonal."""
    V, F = np.asarray(V, dtype=np.float64), np.asarray(F, dtype=np.int64)
    used = V[np.unique(F)]
    centre = used.mean(axis=0)
    a, b, c = (V[F[:, i]] - centre for i in range(3))
    volume = np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0
    diagonal = float(np.linalg.norm(np.ptp(used, axis=0)))
    return thinness(surface_area(V, F), volume, edge_length_fac * diagonal)


def tetwild_seconds(triangles, thinness=1.0):
    """Rough fTetWild time [s] for a surface of this many triangles and ``thinness``
    (``TETWILD_SECONDS``)."""
    return thinness * (TETWILD_SECONDS[0] + TETWILD_SECONDS[1] * int(triangles))


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
