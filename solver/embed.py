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
