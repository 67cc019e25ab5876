"""Reduced RS with cubature: SPEC.md section 4 [L14].

Full RS warping maps modal coordinates z (m,) to a pose by solving a global Poisson problem
(``rs.PoissonReconstruction``). The reduced version restricts the displacement to a basis B
(3N, rB) and the least-squares fit to a few cubature tets C with weights w_e >= 0:

    y_e = (QW)_e z                          (9,)  RS coordinates of tet e, linear in z
    q(z) = sum_{e in C} w_e P_e vec(b_e(y_e))   (rB,) with P_e = (B^T L B)^-1 (G_e B)^T V_e
    u = B q                                 (N, 3) displacement [m]

Everything per evaluation lives in C and the reduced space, so a pose costs O(|C| rB) whatever
the mesh size. Rows of B (e.g. Phi B for render vertices, or a handful of vertices) give any part
of the pose without the rest ("partial reconstruction").

Shapes and units: X (N, 3) [m], T (E, 4), ``modal_rs`` (E, 9, m) = ``rs.linear_rs(Q, W)`` the
linear RS coordinates of the modes (radians and strain per unit z), B (3N, rB) node-major [m per
unit q]. With B mass-orthonormal (B^T M B = I), |q| is the mass-weighted RMS norm of u times
sqrt(total mass), which makes errors in q meaningful.

``LinearDeformer`` has the same interface for plain linear modal motion (q = z, B = W).
"""

import numpy as np
import scipy.linalg

from . import fem, rs


# ---------------------------------------------------------------------------------------------
# Basis: linear modes plus second-order terms of the RS map

def max_mode_rotations(modal_rs):
    """(m,) largest rotation |omega_e| over tets per unit of each modal coordinate [rad]."""
    return np.linalg.norm(np.asarray(modal_rs)[:, :3, :], axis=1).max(axis=0)


def second_order_targets(modal_rs, i, j):
    """d^2 b / dz_i dz_j at rest, (E, 3, 3) (SPEC section 4).

    b = [w]x + eps + [w]x eps + 1/2 [w]x^2 + O(3) with w = sum z_k w^k, eps = sum z_k eps^k, so
    d^2 b / dz_i dz_j = [w^i]x eps^j + [w^j]x eps^i + 1/2 ([w^i]x [w^j]x + [w^j]x [w^i]x).
    """
    modal_rs = np.asarray(modal_rs)
    Ki, Kj = rs.skew(modal_rs[:, :3, i]), rs.skew(modal_rs[:, :3, j])
    Si = np.einsum("ek,kab->eab", modal_rs[:, 3:, i], rs.STRAIN_BASIS)
    Sj = np.einsum("ek,kab->eab", modal_rs[:, 3:, j], rs.STRAIN_BASIS)
    return Ki @ Sj + Kj @ Si + 0.5 * (Ki @ Kj + Kj @ Ki)


def second_order_basis(X, T, masses, modal_rs, recon, modes_W, max_size=120, drop_tol=1e-6,
                       progress=None):
    """Displacement basis B (3N, rB) [m]: the modes W, then second-order RS vectors (SPEC 4).

    X (N, 3), T (E, 4): the tet mesh (kept for the signature; the geometry enters through
    ``recon`` and ``modal_rs``). masses (N,) lumped node masses [kg]; modal_rs (E, 9, m) linear
    RS of the modes; recon a ``rs.PoissonReconstruction`` with the body's pins; modes_W (3N, m).

    Candidates: for each pair i <= j, c_ij = Psi(d^2 b / dz_i dz_j) (one Poisson solve, which
    honours the pins), scaled to its actual second-order contribution when modes i and j each
    turn by 1 rad at their most rotating tet: a_i a_j c_ij for i < j, 1/2 a_i^2 c_ii, with
    a_i = 1 / max_e |omega^i_e|. This makes candidates of different modes comparable.

    Selection (pivoted Gram-Schmidt in the mass inner product): the modes come first, in
    order; then repeatedly the candidate with the largest M-norm *outside* the current span is
    appended (importance = how much new displacement it adds at 1 rad). A candidate whose
    remaining norm falls to ``drop_tol`` times its own norm is dropped as near-dependent. Stops
    at ``max_size`` columns or when no candidate is left. Vectors are re-orthogonalised once
    (classical Gram-Schmidt twice), so B^T M B = I to round-off; rows of pinned DOFs stay
    exactly 0 since every candidate is 0 there.

    progress: optional callable(fraction, message), called between Poisson solves and picks;
    an exception raised inside it aborts the build and propagates.
    Returns B (3N, rB), rB <= max(max_size, m).
    """
    modal_rs = np.asarray(modal_rs, dtype=np.float64)
    W = np.asarray(modes_W, dtype=np.float64)
    m_diag = np.repeat(np.asarray(masses, dtype=np.float64), 3)          # (3N,) diag of M
    num_modes = W.shape[1]
    candidates = _second_order_candidates(modal_rs, recon, progress)     # (3N, m(m+1)/2)
    basis = _mass_orthonormal(W, m_diag)
    extra = max(int(max_size) - basis.shape[1], 0)
    picked = _pivoted_gram_schmidt(basis, candidates, m_diag, extra, drop_tol, progress)
    assert picked.shape[1] >= num_modes
    return picked


def _second_order_candidates(modal_rs, recon, progress):
    """(3N, P) scaled Psi-solves of d^2 b / dz_i dz_j for all pairs i <= j (see the caller)."""
    num_modes = modal_rs.shape[2]
    scale = 1.0 / np.maximum(max_mode_rotations(modal_rs), 1e-300)
    pairs = [(i, j) for j in range(num_modes) for i in range(j + 1)]
    columns = np.empty((3 * recon.num_nodes, len(pairs)))
    for k, (i, j) in enumerate(pairs):                           # one Poisson solve per pair
        if progress is not None:
            progress(0.8 * k / len(pairs), f"second-order basis vector {k + 1}/{len(pairs)}")
        factor = scale[i] * scale[j] * (0.5 if i == j else 1.0)
        columns[:, k] = factor * recon.solve(second_order_targets(modal_rs, i, j)).reshape(-1)
    return columns


def _mass_orthonormal(W, m_diag):
    """W (3N, m) made M-orthonormal by a Cholesky factor of W^T M W (span and order kept)."""
    gram = W.T @ (m_diag[:, None] * W)
    return scipy.linalg.solve_triangular(scipy.linalg.cholesky(gram), W.T, trans="T").T


def _pivoted_gram_schmidt(basis, candidates, m_diag, extra, drop_tol, progress):
    """Append up to ``extra`` M-orthonormal vectors from candidates, largest residual first."""
    norms = np.sqrt(np.einsum("ik,i,ik->k", candidates, m_diag, candidates))
    residual = candidates - basis @ (basis.T @ (m_diag[:, None] * candidates))
    alive = norms > 0.0
    picked = [basis]
    for step in range(extra):
        if progress is not None:
            progress(0.8 + 0.2 * step / max(extra, 1), f"orthonormalising basis ({step}/{extra})")
        remaining = np.sqrt(np.einsum("ik,i,ik->k", residual, m_diag, residual))
        alive &= remaining > drop_tol * norms                  # near-dependent: drop for good
        if not alive.any():
            break
        best = int(np.argmax(np.where(alive, remaining, -1.0)))
        vector = residual[:, best] / remaining[best]
        current = np.hstack(picked)
        vector -= current @ (current.T @ (m_diag * vector))    # second pass: orthogonality
        vector /= np.sqrt(vector @ (m_diag * vector))
        picked.append(vector[:, None])
        alive[best] = False
        residual -= np.outer(vector, vector @ (m_diag[:, None] * residual))
    return np.hstack(picked)


# ---------------------------------------------------------------------------------------------
# Projections P_e and the exact reduced fit

class ReducedProjection:
    """The reduced least-squares fit q = (B^T L B)^-1 B^T G^T V vec(b) for a basis B.

    Holds the Cholesky factor of the reduced Laplacian B^T L B (rB, rB) [m^3 per unit q^2,
    from L = G^T (V kron I9) G], and gives per-tet projections ``tet_projections(tets)``
    (k, rB, 9) = P_e only for the tets asked for (never all of them: E rB 9 floats is large),
    and the exact all-tet fit ``exact_q(b)`` through the sparse scalar gradient of ``recon``.
    """

    def __init__(self, X, T, B, recon):
        self.X = np.asarray(X, dtype=np.float64)
        self.T = np.asarray(T, dtype=np.int64)
        self.basis = np.asarray(B, dtype=np.float64)
        self.recon = recon
        self.num_nodes = len(self.X)
        B3 = self.basis.reshape(self.num_nodes, 3, -1)
        # B^T L B = sum over coordinates of B_c^T L_s B_c (L = L_s kron I3).
        gram = sum(B3[:, c, :].T @ (recon.laplacian @ B3[:, c, :]) for c in range(3))
        self.gram_factor = scipy.linalg.cho_factor(0.5 * (gram + gram.T))

    @property
    def basis_size(self):
        return self.basis.shape[1]

    def tet_projections(self, tets):
        """P_e (k, rB, 9) = (B^T L B)^-1 (G_e B)^T V_e for tet indices ``tets`` (k,)."""
        tets = np.asarray(tets, dtype=np.int64)
        grads = fem.shape_gradients(self.X, self.T[tets])                    # (k, 4, 3)
        B_nodes = self.basis.reshape(self.num_nodes, 3, -1)[self.T[tets]]     # (k, 4, 3, rB)
        GB = np.einsum("kaj,kair->rkij", grads, B_nodes)                       # (rB, k, 3, 3)
        GB *= self.recon.volumes[tets][None, :, None, None]
        P = scipy.linalg.cho_solve(self.gram_factor, GB.reshape(self.basis_size, -1))
        return np.ascontiguousarray(P.reshape(self.basis_size, len(tets), 9).transpose(1, 0, 2))

    def exact_q(self, b):
        """Reduced coordinates (rB,) or (F, rB) fitting targets b (E, 3, 3) or (F, E, 3, 3).

        q = (B^T L B)^-1 B^T G^T V vec(b), the all-tet (no cubature) reduced reconstruction; for
        several poses the sparse product handles all of them at once.
        """
        b = np.asarray(b, dtype=np.float64)
        single = b.ndim == 3
        b = b.reshape(-1, len(self.T), 3, 3)
        frames = len(b)
        weighted = self.recon.volumes[None, :, None, None] * b                # (F, E, 3, 3)
        # column (f, i) holds b[f, :, i, :] flattened tet-major: the rhs of coordinate i.
        stacked = weighted.transpose(1, 3, 0, 2).reshape(3 * len(self.T), 3 * frames)
        rhs = np.asarray(self.recon.gradient.T @ stacked)                      # (N, 3F)
        rhs = rhs.reshape(self.num_nodes, frames, 3).transpose(1, 0, 2).reshape(frames, -1)
        q = scipy.linalg.cho_solve(self.gram_factor, (rhs @ self.basis).T).T   # (F, rB)
        return q[0] if single else q


# ---------------------------------------------------------------------------------------------
# The deformers

class ReducedRS:
    """Reduced RS deformer z (m,) -> q (rB,) -> u = B q (SPEC section 4).

    Attributes:
      num_coords           m, number of modal coordinates z.
      basis                B (3N, rB) [m per unit q] (may be None when loaded without it).
      basis_size           rB.
      cubature_tets        (C,) int64 tet indices.
      cubature_weights     (C,) float64, >= 0.
      projections          P_C (C, rB, 9) for the cubature tets only.
      modal_rs_cubature    (C, 9, m) linear RS of the modes on the cubature tets.

    ``exact_q`` (the all-tet fit) needs the full mesh: it works on objects made by ``build``
    (which keeps a ``ReducedProjection`` and the full modal_rs by reference), or after
    ``attach_full``; a deformer loaded by ``from_arrays`` alone is evaluation-only.
    """

    def __init__(self, basis, cubature_tets, cubature_weights, projections, modal_rs_cubature,
                 projection=None, modal_rs=None):
        self.basis = None if basis is None else np.asarray(basis, dtype=np.float64)
        self.cubature_tets = np.asarray(cubature_tets, dtype=np.int64).reshape(-1)
        self.cubature_weights = np.asarray(cubature_weights, dtype=np.float64).reshape(-1)
        self.projections = np.asarray(projections, dtype=np.float64)
        self.modal_rs_cubature = np.ascontiguousarray(modal_rs_cubature, dtype=np.float64)
        self.num_coords = self.modal_rs_cubature.shape[2]
        self.basis_size = self.projections.shape[1]
        # Weighted projections flattened to (rB, 9C): q = wP @ vec(b) over all cubature tets
        # is one matrix-vector product, and the Jacobian one matrix-matrix product.
        self._weighted = np.ascontiguousarray(
            (self.cubature_weights[:, None, None] * self.projections)
            .transpose(1, 0, 2).reshape(self.basis_size, -1))
        self._projection, self._modal_rs = projection, modal_rs

    @classmethod
    def build(cls, X, T, modal_rs, B, recon, cubature_tets, cubature_weights, projection=None):
        """Deformer for basis B (3N, rB) and a trained cubature (tets (C,), weights (C,)).

        recon: the body's ``rs.PoissonReconstruction`` (its Laplacian and gradient define
        L and G); projection: an existing ``ReducedProjection`` for the same B to reuse.
        """
        projection = ReducedProjection(X, T, B, recon) if projection is None else projection
        tets = np.asarray(cubature_tets, dtype=np.int64)
        modal_rs = np.asarray(modal_rs, dtype=np.float64)
        return cls(projection.basis, tets, cubature_weights, projection.tet_projections(tets),
                   modal_rs[tets], projection=projection, modal_rs=modal_rs)

    def attach_full(self, X, T, modal_rs, recon):
        """Give a loaded deformer the full-mesh data ``exact_q`` needs (requires ``basis``)."""
        self._projection = ReducedProjection(X, T, self.basis, recon)
        self._modal_rs = np.asarray(modal_rs, dtype=np.float64)

    # -- evaluation ---------------------------------------------------------------------------

    def q(self, z):
        """Reduced coordinates q (rB,) of modal coordinates z (m,): sum_C w_e P_e vec(b_e)."""
        y = self.modal_rs_cubature @ np.asarray(z, dtype=np.float64)             # (C, 9)
        return self._weighted @ rs.rs_target(y).reshape(-1)

    def q_jacobian(self, z):
        """dq/dz (rB, m) = sum_C w_e P_e (db/dy)_e (QW)_e (analytic, SPEC section 4)."""
        y = self.modal_rs_cubature @ np.asarray(z, dtype=np.float64)
        chain = rs.rs_target_jacobian(y) @ self.modal_rs_cubature                # (C, 9, m)
        return self._weighted @ chain.reshape(-1, self.num_coords)

    def q_batch(self, Z, chunk=256):
        """q for many frames: Z (F, m) -> (F, rB); frames are processed ``chunk`` at a time."""
        Z = np.atleast_2d(np.asarray(Z, dtype=np.float64))
        out = np.empty((len(Z), self.basis_size))
        for start in range(0, len(Z), chunk):                       # bounds temporary memory
            Zc = Z[start:start + chunk]
            y = np.einsum("ckm,fm->fck", self.modal_rs_cubature, Zc).reshape(-1, 9)
            out[start:start + chunk] = rs.rs_target(y).reshape(len(Zc), -1) @ self._weighted.T
        return out

    def q_jacobian_batch(self, Z, chunk=64):
        """dq/dz for many frames: Z (F, m) -> (F, rB, m)."""
        Z = np.atleast_2d(np.asarray(Z, dtype=np.float64))
        m = self.num_coords
        out = np.empty((len(Z), self.basis_size, m))
        for start in range(0, len(Z), chunk):
            Zc = Z[start:start + chunk]
            y = np.einsum("ckm,fm->fck", self.modal_rs_cubature, Zc).reshape(-1, 9)
            J = rs.rs_target_jacobian(y).reshape(len(Zc), -1, 9, 9)              # (F, C, 9, 9)
            chain = (J @ self.modal_rs_cubature[None]).reshape(len(Zc), -1, m)    # (F, 9C, m)
            out[start:start + chunk] = self._weighted @ chain
        return out

    def exact_q(self, z):
        """All-tet reduced fit (rB,) of z (m,), no cubature (training and tests).

        (B^T L B)^-1 B^T G^T V vec(b(QW z)) over every tet via the sparse gradient operator.
        Also accepts Z (F, m) and returns (F, rB).
        """
        if self._projection is None:
            raise RuntimeError("exact_q needs the full mesh: use ReducedRS.build or attach_full")
        Z = np.asarray(z, dtype=np.float64)
        targets = rs.rs_target(np.einsum("ekm,...m->...ek", self._modal_rs, Z).reshape(-1, 9))
        return self._projection.exact_q(targets.reshape(Z.shape[:-1] + (-1, 3, 3)))

    def displacement(self, z, rows=None):
        """Displacement of z (m,): (N, 3) = B q [m], or ``rows @ q`` reshaped (k, 3).

        rows: optional (3k, rB) rows of a linear map of B, e.g. (Phi B) for render vertices or
        B restricted to some vertices (``basis_rows``). The caller precomputes it once: this
        is what makes partial reconstruction cost O(k rB) instead of O(N rB).
        """
        return _apply_rows(self.basis if rows is None else rows, self.q(z))

    def displacement_jacobian(self, z, rows):
        """d u_rows / dz (3k, m) = rows @ dq/dz for precomputed rows (3k, rB)."""
        return np.asarray(rows) @ self.q_jacobian(z)

    # -- cache --------------------------------------------------------------------------------

    def save_arrays(self, include_basis=True):
        """dict of numpy arrays for ``cache.save``; B is optional (it is 3N x rB)."""
        arrays = dict(cubature_tets=self.cubature_tets, cubature_weights=self.cubature_weights,
                      projections=self.projections, modal_rs_cubature=self.modal_rs_cubature)
        if include_basis and self.basis is not None:
            arrays["basis"] = self.basis
        return arrays

    @classmethod
    def from_arrays(cls, arrays):
        """Inverse of ``save_arrays`` (an evaluation-only deformer, see the class docstring)."""
        return cls(arrays.get("basis"), arrays["cubature_tets"], arrays["cubature_weights"],
                   arrays["projections"], arrays["modal_rs_cubature"])


class LinearDeformer:
    """Linear modal motion with the ReducedRS interface: q(z) = z, dq/dz = I, B = W.

    num_coords: m; basis: optional W (3N, m) for ``displacement`` without rows.
    """

    def __init__(self, num_coords, basis=None):
        self.num_coords = int(num_coords)
        self.basis = None if basis is None else np.asarray(basis, dtype=np.float64)
        self.basis_size = self.num_coords

    def q(self, z):
        return np.array(z, dtype=np.float64).reshape(self.num_coords)

    def q_jacobian(self, z):
        return np.eye(self.num_coords)

    def q_batch(self, Z):
        return np.array(np.atleast_2d(Z), dtype=np.float64)

    def q_jacobian_batch(self, Z):
        return np.broadcast_to(np.eye(self.num_coords),
                               (len(np.atleast_2d(Z)), self.num_coords, self.num_coords)).copy()

    def exact_q(self, z):
        return self.q(z) if np.ndim(z) == 1 else self.q_batch(z)

    def displacement(self, z, rows=None):
        return _apply_rows(self.basis if rows is None else rows, self.q(z))

    def displacement_jacobian(self, z, rows):
        return np.array(rows, dtype=np.float64)

    def save_arrays(self, include_basis=True):
        arrays = dict(num_coords=np.array(self.num_coords))
        if include_basis and self.basis is not None:
            arrays["basis"] = self.basis
        return arrays

    @classmethod
    def from_arrays(cls, arrays):
        return cls(int(arrays["num_coords"]), arrays.get("basis"))


def basis_rows(B, vertices):
    """Rows (3k, rB) of B (3N, rB) for vertex indices (k,), node-major, for ``displacement``."""
    vertices = np.asarray(vertices, dtype=np.int64)
    B = np.asarray(B)
    return np.ascontiguousarray(B.reshape(-1, 3, B.shape[1])[vertices].reshape(-1, B.shape[1]))


def _apply_rows(rows, q):
    """(k, 3) displacement rows @ q; rows (3k, rB)."""
    if rows is None:
        raise ValueError("no basis: pass rows (3k, rB) or build the deformer with its basis")
    return (np.asarray(rows) @ q).reshape(-1, 3)
