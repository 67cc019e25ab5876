"""Carry a pose of the render mesh over to the tet nodes.

A shape key moves the render vertices p (n, 3); RS coordinates need the tet nodes' positions
x (N, 3). The nodes are found by least squares

    x = argmin  β ‖Φ x − p‖²  +  Σ_{tets e,f sharing a face} w_ef ‖∇x|_e − ∇x|_f‖²

The second term penalises jumps of the deformation gradient across faces. It vanishes for every
affine map, so rest poses, rigid motions and uniform stretches carry over exactly; a general pose
carries over as the smoothest piecewise-linear field that fits the vertices. β is large, so the
vertices are matched as closely as the tet mesh can. Each coordinate is an independent scalar
problem with the same matrix: it is factored once.
"""
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from . import fem, rs

FIT_WEIGHT = 1e6   # β relative to the smoothness term's scale


def face_adjacent_pairs(T):
    """(P, 2) int pairs (e, f), e < f, of tets that share a face, from (E, 4) tets."""
    neighbours = rs.tet_neighbours(T)                                   # (E, 4), -1 on the boundary
    e = np.repeat(np.arange(len(T)), 4)
    f = neighbours.ravel()
    keep = f > e
    return np.stack([e[keep], f[keep]], axis=1)


class PoseTransfer:
    """Positions of the tet nodes from positions of embedded points.

    X (N, 3), T (E, 4): the tet mesh; Phi (n, N) sparse: the embedding (points = Phi @ nodes).
    """

    def __init__(self, X, T, Phi):
        pairs = face_adjacent_pairs(T)
        volumes = np.abs(fem.tet_volumes(X, T))
        weights = np.repeat(0.5 * (volumes[pairs[:, 0]] + volumes[pairs[:, 1]]), 3)
        rows = np.arange(len(pairs))
        jump = sp.csr_matrix((np.r_[np.ones(len(pairs)), -np.ones(len(pairs))],
                              (np.r_[rows, rows], np.r_[pairs[:, 0], pairs[:, 1]])),
                             shape=(len(pairs), len(T)))
        J = sp.kron(jump, sp.identity(3)) @ fem.scalar_gradient_operator(X, T)   # (3P, N)
        smooth = (J.T @ sp.diags(weights) @ J).tocsc()
        fit = (Phi.T @ Phi).tocsc()
        self.beta = FIT_WEIGHT * smooth.diagonal().mean() / max(fit.diagonal().mean(), 1e-300)
        # A whisper of identity keeps the matrix definite if the points leave an affine map free.
        tiny = 1e-12 * smooth.diagonal().mean()
        A = self.beta * fit + smooth + tiny * sp.identity(len(X), format="csc")
        self._solve = spla.factorized(A.tocsc())
        self._Phi = Phi

    def nodes_from_points(self, points):
        """(N, 3) node positions whose embedding best matches `points` (n, 3)."""
        rhs = self.beta * (self._Phi.T @ np.asarray(points, dtype=np.float64))
        return np.column_stack([self._solve(np.ascontiguousarray(rhs[:, i])) for i in range(3)])
