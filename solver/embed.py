"""Embedding render-mesh vertices in the tet mesh: SPEC.md section 7.

Each render vertex p gets the four P1 shape-function values of one tet at p, giving a sparse
Phi (P, N) with ``Phi @ x`` the render positions for tet-node positions x (N, 3).

Choice for points outside the tet mesh: fTetWild only approximates the surface within its
envelope, so some render vertices lie slightly outside every tet. Such a point uses the tet that
owns the boundary face nearest to it, with that tet's *affine* coordinates extended beyond the
tet (some weights slightly negative, all summing to one). Clamping them to the tet would move the
vertex at rest; the affine extension reproduces it exactly (Phi @ X == P up to round-off) and
follows the tet's deformation, which is what the surface did when it was inside the envelope.
"""

import dataclasses

import igl
import numpy as np
import scipy.sparse as sp

from . import fem


def embed_points(X, T, P):
    """Sparse Phi (len(P), N) csr of tet shape-function weights; rows sum to 1, Phi @ X == P.

    X: (N, 3) tet nodes, T: (E, 4) tets, P: (M, 3) points (e.g. render vertices), same units.
    Points inside the mesh get barycentric coordinates of a containing tet (found with libigl's
    AABB tree); points outside use the affine coordinates of the tet owning the nearest boundary
    face (see the module docstring). Zero weights are not stored.
    """
    X = np.ascontiguousarray(X, dtype=np.float64)
    T = np.ascontiguousarray(T, dtype=np.int64)
    P = np.ascontiguousarray(np.reshape(P, (-1, 3)), dtype=np.float64)
    tet = _containing_tets(X, T, P)
    outside = tet < 0
    if outside.any():
        tet[outside] = _nearest_boundary_tets(X, T, P[outside])
    weights = _affine_coordinates(X, T[tet], P)
    rows = np.repeat(np.arange(len(P)), 4)
    Phi = sp.csr_matrix((weights.ravel(), (rows, T[tet].ravel())), shape=(len(P), len(X)))
    Phi.eliminate_zeros()
    return Phi


def pinned_nodes_from_vertices(Phi, vertex_mask):
    """Tet nodes (p,) int64 carrying non-zero weight for any render vertex selected by vertex_mask.

    vertex_mask: (M,) bool (or an int index array) over Phi's rows. Pinning all these nodes
    holds the selected render vertices exactly, since each is a combination of pinned nodes only.
    """
    rows = sp.csr_matrix(Phi)[np.asarray(vertex_mask)]
    return np.unique(rows.indices[rows.data != 0.0]).astype(np.int64)


PIN_THRESHOLD = 0.5   # a render vertex weighted this much or more in a pin group is pinned

# How much nearer the whole render surface a tet-surface node may be than the pinned faces and
# still be pinned, as a fraction of the render mesh's bounding-box diagonal. fTetWild puts the
# tet surface anywhere within its envelope (default 1e-3 of the diagonal) of the render surface,
# so a node meant to lie on a pinned face's rim can sit up to one envelope along the unpinned
# neighbour face: it is then an envelope nearer to that face than to the pinned one. Twice the
# default envelope pins those rim nodes, and spreads the pin at most that far onto neighbours.
PIN_TOLERANCE = 2e-3


@dataclasses.dataclass(frozen=True)
class SurfacePins:
    """What a pin group holds (``pin_surface``).

    nodes: (p,) int64 sorted unique tet nodes held fixed.
    embedding: (n, N) csr, Phi with the row of every clamped render vertex (a pinned vertex of a
        pinned face) moved onto the pinned tet-surface facet nearest to it. Use it for
        displacements (``embedding @ u``, u (N, 3)): a pinned vertex then moves exactly as its
        pinned nodes do, i.e. not at all. Its clamped rows are not exact at rest (the vertex
        sits up to about one tet edge from that facet), so map positions with the exact Phi.
    clamped: (k,) int64 render vertices whose rows were moved.
    """
    nodes: np.ndarray
    embedding: sp.csr_matrix
    clamped: np.ndarray


def pin_surface(X, T, Phi, vertices, triangles, weights, threshold=PIN_THRESHOLD,
                tolerance=PIN_TOLERANCE, node_weights=None):
    """-> SurfacePins: the tet nodes a pin group holds and the embedding that holds its vertices.

    X (N,3) tet nodes, T (E,4) tets, Phi (n,N) csr exact embedding of the render vertices
    (``embed_points``), vertices (n,3) render vertices in the same space as X, triangles (m,3)
    int render triangles, weights (n,) pin weights in [0,1]; node_weights (N,) optional: the
    weights carried into the volume, for a group that paints volume rather than skin (a
    rig's Follow Rig, ``rig.node_values``).

    Rule: a render vertex is pinned when its weight >= threshold; a render face is pinned when
    all its vertices are pinned.
    (a) A tet node on the tet mesh's boundary is pinned when its distance to the pinned faces is
        at most its distance to the whole render surface plus ``tolerance`` x the render mesh's
        bounding-box diagonal (see PIN_TOLERANCE): the nodes whose nearest part of the surface
        is painted. So a painted face clamps as a whole and a painted strip holds the strip.
    (b) A pinned vertex of a pinned face is held by the tet-surface facet (all three nodes
        pinned by (a)) nearest to it, if one lies within a mean boundary edge: its embedding row
        moves onto that facet, so it holds exactly and no node behind the face is pinned.
    (c) Any other pinned vertex (painted alone or along a line, or with no pinned facet near
        it) is held by pinning every node of its tet (``pinned_nodes_from_vertices``).
    (d) With node_weights, every node whose carried weight is >= threshold is pinned too: the
        flesh inside a painted part follows it.
    Interior nodes are pinned only by (c) and (d), so without node_weights nodes behind a
    pinned face stay free. Distances are Euclidean in the given space: the rule does not
    depend on the body's pose or scale.
    """
    X = np.ascontiguousarray(X, dtype=np.float64)
    T = np.ascontiguousarray(T, dtype=np.int64)
    Phi = sp.csr_matrix(Phi)
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    triangles = np.ascontiguousarray(triangles, dtype=np.int64)
    pinned_vertex = np.asarray(weights, dtype=np.float64) >= threshold
    pinned_faces = triangles[pinned_vertex[triangles].all(axis=1)]
    clamped = np.zeros(0, dtype=np.int64)
    by_face = np.zeros(0, dtype=np.int64)
    rows = None
    if len(pinned_faces):
        facets = np.asarray(igl.boundary_facets(T)[0], dtype=np.int64)
        by_face = _nodes_nearest_pinned_faces(X, facets, vertices, triangles, pinned_faces,
                                              tolerance)
        held = np.zeros(len(X), dtype=bool)
        held[by_face] = True
        pinned_facets = facets[held[facets].all(axis=1)]
        if len(pinned_facets):
            reach = np.linalg.norm(X[facets] - X[np.roll(facets, 1, axis=1)], axis=2).mean()
            clamped, rows = _rows_on_facets(X, pinned_facets, vertices,
                                            np.unique(pinned_faces), reach)
    by_tet = pinned_vertex.copy()
    by_tet[clamped] = False
    nodes = np.union1d(by_face, pinned_nodes_from_vertices(Phi, by_tet)).astype(np.int64)
    if node_weights is not None:
        nodes = np.union1d(nodes, np.flatnonzero(np.asarray(node_weights) >= threshold))
    embedding = Phi if rows is None else _replace_rows(Phi, clamped, rows)
    return SurfacePins(nodes, embedding, clamped)


def _nodes_nearest_pinned_faces(X, facets, vertices, triangles, pinned_faces, tolerance):
    """(q,) tet-surface nodes whose nearest part of the render surface is pinned (rule (a))."""
    boundary = np.unique(facets)
    points = X[boundary]
    to_pinned = np.sqrt(igl.point_mesh_squared_distance(points, vertices, pinned_faces)[0])
    to_surface = np.sqrt(igl.point_mesh_squared_distance(points, vertices, triangles)[0])
    used = vertices[np.unique(triangles)]
    slack = tolerance * np.linalg.norm(used.max(axis=0) - used.min(axis=0))
    return boundary[to_pinned <= to_surface + slack]


def _rows_on_facets(X, facets, vertices, candidates, reach):
    """Rule (b): (k,) candidates within ``reach`` of a facet, and their (k, N) csr rows: the
    barycentric coordinates of the nearest point on the nearest facet (f, 3) of X."""
    squared, nearest, closest = igl.point_mesh_squared_distance(vertices[candidates], X, facets)
    near = np.sqrt(squared) <= reach
    facet = facets[np.asarray(nearest)[near]]                                  # (k, 3)
    weights = _triangle_coordinates(X[facet], np.asarray(closest)[near])
    k = len(facet)
    rows = sp.csr_matrix((weights.ravel(), (np.repeat(np.arange(k), 3), facet.ravel())),
                         shape=(k, len(X)))
    rows.eliminate_zeros()
    return candidates[near].astype(np.int64), rows


def _triangle_coordinates(corners, points):
    """(k, 3) barycentric coordinates of points (k, 3) in triangles corners (k, 3, 3), clipped
    to the triangle (the points are its nearest points, so only round-off is clipped)."""
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    e1, e2, d = b - a, c - a, points - a
    g11, g12, g22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    r1, r2 = (d * e1).sum(1), (d * e2).sum(1)
    det = g11 * g22 - g12 * g12
    det = np.where(det > 0.0, det, np.inf)     # a degenerate facet: its first corner
    s = (g22 * r1 - g12 * r2) / det
    t = (g11 * r2 - g12 * r1) / det
    weights = np.clip(np.column_stack([1.0 - s - t, s, t]), 0.0, None)
    return weights / weights.sum(axis=1, keepdims=True)


def _replace_rows(Phi, row_indices, rows):
    """Phi (n, N) csr with rows ``row_indices`` (k,) replaced by ``rows`` (k, N)."""
    keep = np.ones(Phi.shape[0])
    keep[row_indices] = 0.0
    scatter = sp.csr_matrix((np.ones(len(row_indices)), (row_indices, np.arange(len(row_indices)))),
                            shape=(Phi.shape[0], len(row_indices)))
    out = (sp.diags(keep) @ Phi + scatter @ rows).tocsr()
    out.eliminate_zeros()
    out.sort_indices()
    return out


def _containing_tets(X, T, P):
    """(M,) index of a tet containing each point, -1 where none does."""
    tree = igl.AABB()
    tree.init(X, T)
    return np.asarray(igl.in_element(X, T, P, tree), dtype=np.int64)


def _nearest_boundary_tets(X, T, P):
    """(M,) for each point, the tet owning the boundary face nearest to it."""
    faces, face_tet, _ = igl.boundary_facets(T)
    _, nearest_face, _ = igl.point_mesh_squared_distance(P, X, faces)
    return np.asarray(face_tet, dtype=np.int64)[nearest_face]


def _affine_coordinates(X, tets, P):
    """(M, 4) shape-function values phi_k(p) = phi_k(X_a) + grad phi_k . (p - X_a) per point/tet."""
    grads = fem.shape_gradients(X, tets)                       # (M, 4, 3)
    offset = P - X[tets[:, 0]]
    weights = np.einsum("mkj,mj->mk", grads, offset)
    weights[:, 0] += 1.0                                       # phi_a(X_a) = 1, others 0
    return weights
