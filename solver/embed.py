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


# How much nearer the whole render surface a tet-surface node may be than the pinned faces and
# still be pinned, as a fraction of the render mesh's bounding-box diagonal. fTetWild puts the
# tet surface anywhere within its envelope (default 1e-3 of the diagonal) of the render surface,
# so a node meant to lie on a pinned face's rim can sit up to one envelope along the unpinned
# neighbour face: it is then an envelope nearer to that face than to the pinned one. Twice the
# default envelope pins those rim nodes, and spreads the pin at most that far onto neighbours.
PIN_TOLERANCE = 2e-3


def pinned_nodes_from_surface(X, T, Phi, vertices, triangles, weights, threshold=0.5,
                              tolerance=PIN_TOLERANCE):
    """-> (p,) int64 sorted unique tet-node indices to hold fixed.
    X (N,3) tet nodes, T (E,4) tets, Phi (n,N) csr embedding of the render vertices,
    vertices (n,3) render-mesh vertices in the same space as X, triangles (m,3) int render triangles,
    weights (n,) pin weights in [0,1].

    Rule: a render vertex is pinned when its weight >= threshold; a render face is pinned when
    all its vertices are pinned. The pinned tet nodes are
    (a) every node that carries weight for a pinned render vertex (``pinned_nodes_from_vertices``),
        so the pinned render vertices hold exactly, and
    (b) every node on the tet mesh's boundary whose distance to the pinned faces is at most its
        distance to the whole render surface plus ``tolerance`` x the render mesh's bounding-box
        diagonal (see PIN_TOLERANCE): the nodes whose nearest part of the surface is painted.
    Interior nodes are never added by (b), so nodes behind a pinned face stay free. Distances are
    Euclidean in the given space, so the rule does not depend on the body's orientation or scale.
    """
    X = np.ascontiguousarray(X, dtype=np.float64)
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    triangles = np.ascontiguousarray(triangles, dtype=np.int64)
    pinned_vertex = np.asarray(weights, dtype=np.float64) >= threshold
    by_vertex = pinned_nodes_from_vertices(Phi, pinned_vertex)
    pinned_faces = triangles[pinned_vertex[triangles].all(axis=1)]
    if len(pinned_faces) == 0:
        return by_vertex
    boundary = np.unique(igl.boundary_facets(np.ascontiguousarray(T, dtype=np.int64))[0])
    points = X[boundary]
    to_pinned = np.sqrt(igl.point_mesh_squared_distance(points, vertices, pinned_faces)[0])
    to_surface = np.sqrt(igl.point_mesh_squared_distance(points, vertices, triangles)[0])
    used = vertices[np.unique(triangles)]
    slack = tolerance * np.linalg.norm(used.max(axis=0) - used.min(axis=0))
    by_face = boundary[to_pinned <= to_surface + slack]
    return np.union1d(by_vertex, by_face).astype(np.int64)


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
