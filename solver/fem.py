"""Linear (P1) tetrahedral finite elements: SPEC.md section 1.

Conventions used throughout the package:

- ``X`` (N, 3) float rest positions in metres; ``T`` (E, 4) int tetrahedra.
- Node-major flattening of positions: ``x.reshape(-1) = [x0, y0, z0, x1, ...]`` (length 3N).
- Row-major flattening of a 3x3 gradient: ``vec(F)[3 i + j] = F[i, j] = dx_i / dX_j``.
- ``G`` (9E, 3N) maps flattened positions to every tet's ``vec(F_e)``, so ``G @ X.reshape(-1)``
  is ``vec(I)`` per tet and ``G @ u.reshape(-1) = vec(grad u)``.
"""

import igl
import numpy as np
import scipy.sparse as sp

# vec(I) for row-major 3x3 flattening.
VEC_I = np.eye(3).reshape(-1)


def _edge_matrices(X, T):
    """Dm per tet, (E, 3, 3): columns are X_b - X_a, X_c - X_a, X_d - X_a."""
    X = np.asarray(X, dtype=np.float64)
    T = np.asarray(T)
    return np.transpose(X[T[:, 1:]] - X[T[:, :1]], (0, 2, 1))


def orient_tets(X, T):
    """Return a copy of ``T`` (E, 4) with every tet positively oriented (det Dm > 0).

    Negative tets get their last two indices swapped, which flips the sign of det Dm.
    """
    T = np.array(T, copy=True)
    negative = np.linalg.det(_edge_matrices(X, T)) < 0.0
    T[np.ix_(negative, [2, 3])] = T[np.ix_(negative, [3, 2])]
    return T


def tet_volumes(X, T):
    """Signed tet volumes (E,) in m^3: det(Dm) / 6 (positive after ``orient_tets``)."""
    return np.linalg.det(_edge_matrices(X, T)) / 6.0


def shape_gradients(X, T):
    """Gradients of the four P1 shape functions per tet, (E, 4, 3) in 1/m.

    Rows of Dm^-1 are the gradients of nodes b, c, d; node a's is minus their sum
    (the shape functions sum to one).
    """
    inv = np.linalg.inv(_edge_matrices(X, T))
    return np.concatenate([-inv.sum(axis=1, keepdims=True), inv], axis=1)


def gradient_operator(X, T):
    """Sparse G (9E, 3N), csr: ``(G @ x.reshape(-1))[9e + 3i + j] = dx_i/dX_j`` on tet e.

    Entry (9e + 3i + j, 3 T[e, k] + i) = grad phi_k[j]: 36 entries per tet.
    """
    T = np.asarray(T)
    n_tets, n_nodes = len(T), len(X)
    grads = shape_gradients(X, T)                                   # (E, 4, 3): e, k, j
    e, k, i, j = np.meshgrid(np.arange(n_tets), np.arange(4), np.arange(3), np.arange(3),
                             indexing="ij")
    rows = 9 * e + 3 * i + j
    cols = 3 * T[e, k] + i
    vals = grads[e, k, j]
    G = sp.coo_matrix((vals.ravel(), (rows.ravel(), cols.ravel())),
                      shape=(9 * n_tets, 3 * n_nodes))
    return G.tocsr()


def scalar_gradient_operator(X, T):
    """Sparse D (3E, N), csr: (D @ f)[3e + j] = d f / d X_j on tet e for nodal scalars f."""
    T = np.asarray(T, dtype=np.int64)
    grads = shape_gradients(X, T)                             # (E, 4, 3)
    rows = np.broadcast_to(3 * np.arange(len(T))[:, None, None] + np.arange(3), grads.shape)
    cols = np.broadcast_to(T[:, :, None], grads.shape)
    return sp.csr_matrix((grads.ravel(), (rows.ravel(), cols.ravel())),
                         shape=(3 * len(T), len(X)))


def lame_parameters(youngs, poisson):
    """Lame parameters (mu, lam) in Pa from Young's modulus [Pa] and Poisson's ratio [-].

    youngs: a number, or (E,) one per tet (a painted body, ``painted_youngs``): the result is
    then two (E,) arrays. Raises ValueError for any E <= 0 or not finite, or nu outside
    (-1, 0.5), where the material is not stable.
    """
    poisson = float(poisson)
    values = np.asarray(youngs, dtype=np.float64)
    if not np.all(np.isfinite(values)) or not np.all(values > 0.0):
        bad = values if values.ndim == 0 else values[~(np.isfinite(values) & (values > 0.0))][0]
        raise ValueError(f"Young's modulus must be positive (got {float(bad):g} Pa)")
    if not np.isfinite(poisson) or not -1.0 < poisson < 0.5:
        raise ValueError(f"Poisson's ratio must lie strictly between -1 and 0.5 (got {poisson:g})")
    youngs = float(values) if values.ndim == 0 else values
    mu = youngs / (2.0 * (1.0 + poisson))
    lam = youngs * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson))
    return mu, lam


def painted_youngs(youngs, ratio, weights):
    """(E,) Young's modulus [Pa] of tets painted with weights (E,) in [0, 1] (a stiffness group):
    E(w) = youngs * ratio ** (1 - w), so weight 1 is ``youngs`` and weight 0 is ratio * youngs
    (ratio > 0, finite; above 1 the painted part is the soft one).

    Geometric, not linear, interpolation: equal steps of paint give equal factors of stiffness
    (and of frequency, which goes as sqrt(E)), so a uniform gradient of paint along a tail softens
    it by the same factor per unit length, and a weight of 0.5 is the geometric mean. Linear
    interpolation of a 1:1000 range would put everything below youngs / 2 into the last tenth of
    the weights.
    """
    ratio = float(ratio)
    if not (np.isfinite(ratio) and ratio > 0.0):
        raise ValueError(f"the stiffness ratio must be a positive number (got {ratio:g})")
    weights = np.clip(np.asarray(weights, dtype=np.float64), 0.0, 1.0)
    return float(youngs) * ratio ** (1.0 - weights)


def _sym9():
    """(9, 9) projector vec(A) -> vec((A + A^T) / 2)."""
    swap = np.eye(9).reshape(3, 3, 9).transpose(1, 0, 2).reshape(9, 9)  # vec(A) -> vec(A^T)
    return 0.5 * (np.eye(9) + swap)


def elasticity_tensor(mu, lam):
    """C = 2 mu Sym9 + lam vec(I) vec(I)^T, so psi(grad u) = 1/2 m^T C m, m = vec(grad u): (9, 9)
    for numbers mu, lam [Pa], (E, 9, 9) for per-tet (E,) ones."""
    mu, lam = np.asarray(mu, dtype=np.float64), np.asarray(lam, dtype=np.float64)
    return (2.0 * mu[..., None, None] * _sym9()
            + lam[..., None, None] * np.outer(VEC_I, VEC_I))


def _tet_weights(volumes, C):
    """csr (9E, 9E) block diagonal of V_e C_e: volumes (E,) [m^3], C (9, 9) or (E, 9, 9) [Pa].

    The entries are those of ``sp.kron(sp.diags(volumes), sp.csr_matrix(C))`` in its own order
    (each block's nonzero pattern, row-major, each entry the single product V_e C_ij), so a
    uniform material gives the same K bit for bit as a kron of one tensor does."""
    C = np.broadcast_to(C, (len(volumes), 9, 9))
    rows, cols = np.nonzero(np.any(C != 0.0, axis=0))        # row-major, as csr_matrix(C) keeps
    offsets = 9 * np.arange(len(volumes))[:, None]
    data = volumes[:, None] * C[:, rows, cols]
    return sp.coo_matrix((data.ravel(), ((offsets + rows).ravel(), (offsets + cols).ravel())),
                         shape=(9 * len(volumes),) * 2).tocsr()


def stiffness_matrix(X, T, youngs, poisson):
    """Linear-elastic stiffness K = sum_e V_e G_e^T C_e G_e, csr (3N, 3N) in N/m; symmetric PSD.

    youngs: Young's modulus [Pa], one number or (E,) per tet (a painted body); poisson one
    number. C_e = ``elasticity_tensor`` of the tet's Lame parameters (``lame_parameters``).
    Either tet orientation gives the same K (unsigned volumes are the quadrature weights).
    """
    mu, lam = lame_parameters(youngs, poisson)
    G = gradient_operator(X, T)
    volumes = np.abs(tet_volumes(X, T))  # G does not depend on orientation, so neither does K
    weights = _tet_weights(volumes, elasticity_tensor(mu, lam))
    K = (G.T @ weights @ G).tocsr()
    # Round-off makes K very slightly asymmetric; symmetrise so eigsh / Cholesky see exact symmetry.
    return ((K + K.T) * 0.5).tocsr()


def lumped_masses(X, T, density):
    """Lumped node masses (N,) in kg: m_k = density * sum over tets containing k of V_e / 4.

    libigl's BARYCENTRIC mass matrix is exactly this diagonal up to the density.
    """
    density = float(density)
    if not np.isfinite(density) or density <= 0.0:
        raise ValueError(f"density must be positive (got {density:g} kg/m^3)")
    M = igl.massmatrix(np.asarray(X, dtype=np.float64), np.asarray(T, dtype=np.int64),
                       igl.MASSMATRIX_TYPE_BARYCENTRIC)
    return density * np.asarray(M.diagonal(), dtype=np.float64)


def mesh_volume(X, T):
    """Total volume of the tet mesh in m^3 (sum of unsigned tet volumes)."""
    return float(np.abs(tet_volumes(X, T)).sum())
