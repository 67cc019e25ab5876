"""Rotation-strain (RS) coordinates and their Poisson reconstruction: SPEC.md section 3 [H11].

Per tet e the RS coordinates are ``y_e`` (9,) laid out as

    [wx, wy, wz, exx, exy, exz, eyy, eyz, ezz]

with ``w`` (omega) a rotation vector in radians (axis * angle) and ``e`` (epsilon) the symmetric
strain, dimensionless. Arrays of them are (E, 9).

- Linear map (small displacements): ``y = Q u``, omega = axial(skew grad u), epsilon = sym grad u.
- Nonlinear inverse (a pose -> y): ``F = I + grad u = R S`` (polar), omega = log R, epsilon = S - I.
- Forward target: ``b_e(y) = exp(omega)(I + epsilon) - I`` (3x3), the displacement gradient
  every tet asks for; ``PoissonReconstruction`` finds the displacement u whose P1 gradient fits
  all targets best in the volume-weighted least-squares sense (Psi of SPEC section 3).

Choices written down here:

- Polar decomposition by SVD ``F = U diag(s) V^T``; reflections go into S, not R:
  ``R = U D V^T``, ``S = V D diag(s) V^T`` with ``D = diag(1, 1, det(U V^T))``. So det R = +1
  always and ``R S = F`` holds exactly, also for inverted tets (S then has one negative
  eigenvalue), which makes ``rs_target(pose_to_rs(x)) = F - I`` for every tet.
- ``log`` is multivalued: all rotation vectors of a rotation lie on its axis line,
  ``(theta + 2 pi k) n`` for integers k (k < 0 gives the vectors pointing along -n, which is the
  +-axis equivalence near pi). Given a reference vector, the k closest to it is chosen. The
  exponential map is singular on the spheres |omega| = 2 pi k, where no continuous choice exists.
- Without a per-tet reference, ``pose_to_rs`` seeds the tet with the smallest rotation angle
  (its principal value is the least ambiguous) and propagates over face-neighbour BFS fronts,
  each new tet taking the branch closest to the mean omega of its already-assigned neighbours.
  Each connected piece of the mesh gets its own seed.
"""

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import connected_components
from scipy.spatial.transform import Rotation

from . import fem

SMALL_ANGLE = 1e-4  # below this the Rodrigues derivatives (exp_rotation_derivative) use series
TWO_PI = 2.0 * np.pi

# (i, j) of the six strain entries in y[:, 3:], in layout order.
STRAIN_INDEX = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def _strain_basis():
    """(6, 3, 3) d(I + eps)/d eps_k: off-diagonal entries appear twice in the symmetric matrix."""
    basis = np.zeros((6, 3, 3))
    for k, (i, j) in enumerate(STRAIN_INDEX):
        basis[k, i, j] = basis[k, j, i] = 1.0
    return basis


STRAIN_BASIS = _strain_basis()


def _rs_projector():
    """(9, 9) P9: vec(grad u) (row-major) -> [omega, epsilon] of one tet (SPEC section 3)."""
    P = np.zeros((9, 9))
    # omega = ((m7 - m5)/2, (m2 - m6)/2, (m3 - m1)/2), i.e. [omega]x = skew(grad u).
    for row, (plus, minus) in enumerate(((7, 5), (2, 6), (3, 1))):
        P[row, plus], P[row, minus] = 0.5, -0.5
    for k, (i, j) in enumerate(STRAIN_INDEX):
        P[3 + k, 3 * i + j] += 0.5
        P[3 + k, 3 * j + i] += 0.5
    return P


RS_PROJECTOR = _rs_projector()


# ---------------------------------------------------------------------------------------------
# Linear RS operator

def rs_operator(X, T):
    """Sparse Q (9E, 3N), csr: ``(Q @ u.reshape(-1)).reshape(E, 9)`` = linear RS coords of u.

    Q = (I_E kron P9) G with G = fem.gradient_operator: omega = axial(skew grad u),
    epsilon = sym grad u per tet. u in metres gives omega in radians and dimensionless strain.
    """
    G = fem.gradient_operator(X, T)
    blocks = sp.kron(sp.identity(len(T), format="csr"), sp.csr_matrix(RS_PROJECTOR), format="csr")
    return (blocks @ G).tocsr()


def linear_rs(Q, W):
    """(E, 9, r) RS coordinates of each displacement basis vector: (Q @ W) reshaped.

    Q: (9E, 3N) from ``rs_operator``; W: (3N, r) e.g. linear modes. Precompute once per basis.
    """
    QW = np.asarray(Q @ np.asarray(W).reshape(Q.shape[1], -1))
    return QW.reshape(Q.shape[0] // 9, 9, -1)


def warp_modes(QW, z):
    """RS coordinates y (E, 9) of modal coordinates z (r,): y = (Q W) z, linear in z.

    The nonlinearity of RS warping lives in ``rs_target`` (exp of omega), applied by
    ``PoissonReconstruction.reconstruct``. QW: (E, 9, r) from ``linear_rs``.
    """
    return np.asarray(QW) @ np.asarray(z, dtype=np.float64)


def warp_pose_block(QW, Z):
    """RS coordinates Y (E, 9, F) of the poses Z (F, r), tets-major (a pose is Y[:, :, k]).

    ``warp_modes`` for many poses in one BLAS product (an einsum over these shapes runs several
    times slower); memory E x 9 x F, so callers chunk long pose lists.
    """
    Z = np.atleast_2d(np.asarray(Z, dtype=np.float64))
    n_tets, _, r = np.shape(QW)
    return (np.asarray(QW).reshape(-1, r) @ Z.T).reshape(n_tets, 9, len(Z))


def interpolate(y_a, y_b, t):
    """RS blend (E, 9): (1 - t) y_a + t y_b for a scalar t (0 gives y_a, 1 gives y_b).

    Rotations blend as rotation vectors, so the poses must be branch-consistent: compute
    ``y_b = pose_to_rs(X, T, x_b, reference=y_a[:, :3])[0]`` so that each tet's omega_b is the
    representative closest to omega_a; otherwise a tet whose rotation crosses pi would spin the
    long way round (up to 2 pi) while its neighbours take the short path, tearing the blend.
    """
    t = float(t)
    return (1.0 - t) * np.asarray(y_a) + t * np.asarray(y_b)


# ---------------------------------------------------------------------------------------------
# Rotations

def skew(v):
    """Cross-product matrices (..., 3, 3) of vectors v (..., 3): skew(v) @ w = v x w."""
    v = np.asarray(v, dtype=np.float64)
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -v[..., 2], v[..., 1]
    K[..., 1, 0], K[..., 1, 2] = v[..., 2], -v[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -v[..., 1], v[..., 0]
    return K


SERIES_BELOW = 1e-2  # angle [rad] below which ``rodrigues_coefficients`` use their series


def rodrigues_coefficients(t2):
    """Coefficients (a, b, e), each shaped like t2, of R and of the left Jacobian of SO(3).

    t2 = |omega|^2 [rad^2], t = |omega|, K = skew(omega): R = I + a K + b K^2 and
    J_l = I + b K + e K^2 with a = sin t / t, b = (1 - cos t) / t^2, e = (t - sin t) / t^3.
    Below SERIES_BELOW three-term series (truncation < 1e-13 relative) avoid the cancellation;
    they are evaluated only where needed. The full-RS map (``rs_target``) and the reduced
    deformer (``reduced``) share it.
    """
    shape = np.shape(t2)
    t2 = np.asarray(t2, dtype=np.float64).reshape(-1)
    small = t2 < SERIES_BELOW ** 2
    any_small = bool(small.any())
    t_sq = np.where(small, 1.0, t2) if any_small else t2
    t = np.sqrt(t_sq)
    a = np.sin(t) / t
    b = (1.0 - np.cos(t)) / t_sq
    e = (1.0 - a) / t_sq
    if any_small:
        s = t2[small]
        s2 = s * s
        a[small] = 1.0 - s / 6.0 + s2 / 120.0
        b[small] = 0.5 - s / 24.0 + s2 / 720.0
        e[small] = 1.0 / 6.0 - s / 120.0 + s2 / 5040.0
    return a.reshape(shape), b.reshape(shape), e.reshape(shape)


def exp_rotation(omega):
    """Rotation matrices (E, 3, 3) of rotation vectors omega (E, 3) [rad] (Rodrigues).

    R = I + (sin t / t) K + ((1 - cos t) / t^2) K^2, K = skew(omega), t = |omega|; the
    coefficients switch to their series below SERIES_BELOW (``rodrigues_coefficients``).
    """
    omega = np.asarray(omega, dtype=np.float64)
    a, b, _ = rodrigues_coefficients(np.einsum("...i,...i->...", omega, omega))
    K = skew(omega)
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def exp_rotation_derivative(omega):
    """dR/d omega (E, 3, 3, 3): [:, i] = dR/d omega_i for omega (E, 3) [rad].

    Above SMALL_ANGLE: Gallego & Yezzi's ((omega_i K + skew(omega x (I - R) e_i)) / t^2) R
    (SPEC section 3; its round-off grows only like eps / t). Below: the derivative of
    Rodrigues' formula with Taylor coefficients, a skew(e_i) + b (skew(e_i) K + K skew(e_i))
    + c omega_i K + d omega_i K^2, which tends to skew(e_i) at omega = 0.
    """
    omega = np.asarray(omega, dtype=np.float64).reshape(-1, 3)
    theta = np.linalg.norm(omega, axis=1)
    small = theta < SMALL_ANGLE
    dR = np.empty((len(omega), 3, 3, 3))
    if (~small).any():
        dR[~small] = _gallego_derivative(omega[~small], theta[~small])
    if small.any():
        dR[small] = _taylor_derivative(omega[small], theta[small])
    return dR


def _gallego_derivative(omega, theta):
    """Closed-form dR/d omega (M, 3, 3, 3) for theta >= SMALL_ANGLE."""
    R = exp_rotation(omega)
    K = skew(omega)
    columns = np.swapaxes(np.eye(3) - R, 1, 2)                   # [:, i] = (I - R) e_i
    inner = omega[:, :, None, None] * K[:, None] + skew(np.cross(omega[:, None], columns))
    return (inner / (theta * theta)[:, None, None, None]) @ R[:, None]


def _taylor_derivative(omega, theta):
    """Series dR/d omega (M, 3, 3, 3) for theta < SMALL_ANGLE (truncation error O(theta^4))."""
    t2 = (theta * theta)[:, None, None, None]
    a, b = 1.0 - t2 / 6.0, 0.5 - t2 / 24.0
    c, d = -1.0 / 3.0 + t2 / 30.0, -1.0 / 12.0 + t2 / 180.0        # (da/dt)/t, (db/dt)/t
    K = skew(omega)[:, None]                                      # (M, 1, 3, 3)
    E = skew(np.eye(3))[None]                                     # (1, 3, 3, 3): skew(e_i)
    w = omega[:, :, None, None]                                   # (M, 3, 1, 1)
    return a * E + b * (E @ K + K @ E) + c * w * K + d * w * (K @ K)


def polar_decomposition(F):
    """Polar decomposition F = R S of F (E, 3, 3) by batched SVD; never NaN for finite F.

    Returns R (E, 3, 3) with det R = +1, S (E, 3, 3) symmetric, and ``inverted`` (E,) bool
    where det F <= 0. Reflections are moved into S (see the module docstring), so R S = F
    exactly even for inverted or degenerate (rank-deficient, zero) F.
    """
    F = np.asarray(F, dtype=np.float64)
    U, s, Vt = np.linalg.svd(F)
    flip = np.linalg.det(U @ Vt) < 0.0
    D = np.ones(s.shape)
    D[flip, 2] = -1.0                                  # last singular value is the smallest
    R = (U * D[:, None, :]) @ Vt
    S = np.swapaxes(Vt, 1, 2) @ ((D * s)[:, :, None] * Vt)
    S = 0.5 * (S + np.swapaxes(S, 1, 2))
    return R, S, np.linalg.det(F) <= 0.0


def log_rotation(R, reference=None):
    """Rotation vectors omega (E, 3) [rad] of rotation matrices R (E, 3, 3).

    Without ``reference``: the principal value, |omega| <= pi (via scipy's quaternion
    extraction, robust at 0 and pi). With ``reference`` (E, 3): per tet the representative
    ``(theta + 2 pi k) n`` of R closest to the reference, which keeps fields continuous past pi
    (and picks -n near pi when the reference points that way).
    """
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    omega = Rotation.from_matrix(R).as_rotvec()
    if reference is None:
        return omega
    return _closest_branch(omega, np.asarray(reference, dtype=np.float64).reshape(-1, 3))


AXIS_FREE_BELOW = 1e-9   # rad: a smaller principal rotation has no axis worth keeping


def _closest_branch(omega, reference):
    """(E, 3) representative (theta + 2 pi k) n of principal omega closest to reference.

    |(theta + 2 pi k) n - ref|^2 = (theta + 2 pi k - ref.n)^2 + |ref_perp|^2, so k rounds
    (ref.n - theta) / 2 pi. At theta = 0 the axis is free: take the reference's direction. So
    also below AXIS_FREE_BELOW, where the principal axis is rounding noise (a full turn, 2 pi k,
    comes back as a rotation vector of 1e-16 in any direction).
    """
    theta = np.linalg.norm(omega, axis=1)
    ref_norm = np.linalg.norm(reference, axis=1)
    defined = theta > AXIS_FREE_BELOW
    axis = np.where(defined[:, None], omega / np.where(defined, theta, 1.0)[:, None],
                    reference / np.where(ref_norm > 0.0, ref_norm, 1.0)[:, None])
    k = np.round((np.einsum("ei,ei->e", reference, axis) - theta) / TWO_PI)
    return (theta + TWO_PI * k)[:, None] * axis


# ---------------------------------------------------------------------------------------------
# Pose -> RS (nonlinear inverse) and RS -> per-tet target

def deformation_gradients(X, T, x):
    """F (E, 3, 3) of the P1 map X -> x per tet: F_ij = dx_i / dX_j (dimensionless)."""
    grads = fem.shape_gradients(X, T)                             # (E, 4, 3)
    return np.einsum("eki,ekj->eij", np.asarray(x, dtype=np.float64)[T], grads)


def tet_neighbours(T):
    """Face neighbours (E, 4) int64: [e, f] = tet sharing the face opposite vertex f, or -1.

    Vectorised: the 4E faces are sorted, lexsorted, and equal consecutive faces paired (a
    manifold tet mesh has at most two tets per face).
    """
    T = np.asarray(T, dtype=np.int64)
    opposite = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
    faces = np.sort(T[:, opposite].reshape(-1, 3), axis=1)       # row 4e + f
    order = np.lexsort(faces.T[::-1])
    same = np.all(faces[order[1:]] == faces[order[:-1]], axis=1)
    first, second = order[:-1][same], order[1:][same]
    neighbours = np.full(4 * len(T), -1, dtype=np.int64)
    neighbours[first], neighbours[second] = second // 4, first // 4
    return neighbours.reshape(-1, 4)


def pose_to_rs(X, T, x, reference=None, neighbours=None):
    """Nonlinear RS coordinates of a pose: returns y (E, 9) and ``inverted`` (E,) bool.

    X (N, 3) rest and x (N, 3) deformed node positions [m]; F = R S per tet, omega = log R,
    epsilon = S - I. ``reference`` (E, 3) omega (or (E, 9) y) e.g. of the previous frame: each
    tet takes the rotation branch closest to it. Without it, omega is made continuous across
    faces by BFS from a seed tet (module docstring); ``neighbours`` = ``tet_neighbours(T)``
    can be passed to skip recomputing it. ``inverted`` flags tets with det F <= 0.
    """
    R, S, inverted = polar_decomposition(deformation_gradients(X, T, x))
    if reference is not None:
        omega = log_rotation(R, np.asarray(reference, dtype=np.float64)[:, :3])
    else:
        omega = _propagate_branches(log_rotation(R),
                                    tet_neighbours(T) if neighbours is None else neighbours)
    rows, cols = np.array(STRAIN_INDEX).T
    strain = (S - np.eye(3))[:, rows, cols]
    return np.concatenate([omega, strain], axis=1), inverted


def _propagate_branches(principal, neighbours):
    """(E, 3) branch-continuous omega from principal values, one BFS front at a time."""
    n_tets = len(principal)
    omega = principal.copy()
    assigned = np.zeros(n_tets, dtype=bool)
    angle = np.linalg.norm(principal, axis=1)
    front = np.empty(0, dtype=np.int64)
    while not assigned.all():
        if len(front) == 0:  # new connected piece: seed at its least ambiguous tet
            candidates = np.flatnonzero(~assigned)
            front = candidates[[np.argmin(angle[candidates])]]
            assigned[front] = True
            continue
        reached = neighbours[front].ravel()
        reached = np.unique(reached[reached >= 0])
        new = reached[~assigned[reached]]
        if len(new):
            around = neighbours[new]                                  # (F, 4)
            known = (around >= 0) & assigned[np.maximum(around, 0)]
            ref = (omega[np.maximum(around, 0)] * known[:, :, None]).sum(axis=1)
            ref /= known.sum(axis=1)[:, None]
            omega[new] = _closest_branch(principal[new], ref)
            assigned[new] = True
        front = new
    return omega


def _strain_matrix(y):
    """I + epsilon (E, 3, 3) from y (E, 9)."""
    return np.eye(3) + np.einsum("ek,kij->eij", y[:, 3:], STRAIN_BASIS)


def rs_target(y):
    """Per-tet target displacement gradients b (E, 3, 3) = exp(omega)(I + epsilon) - I.

    Written entry by entry on contiguous (E,) arrays, b = (R - I) + eps + (R - I) eps with
    R - I = a [omega]x + b_t (omega omega^T - t^2 I) (Rodrigues; a, b_t as in
    ``exp_rotation``): the full-RS reconstruction and the reduced stage's training call this
    on every tet hundreds of times, and stacks of 3 x 3 products cost twice as much. Forming
    R - I directly also keeps small rotations free of the 1 - cos cancellation."""
    return np.ascontiguousarray(rs_target_entries(y).transpose(2, 0, 1))


def rs_target_entries(y):
    """``rs_target`` entry-major: b (3, 3, E), b[i, j] the (E,) array of entry (i, j). The
    layout it is computed in, and the one ``PoissonReconstruction`` takes with
    ``entry_major=True`` (no transposed copy either way)."""
    y = np.asarray(y, dtype=np.float64).reshape(-1, 9)
    w0, w1, w2, e00, e01, e02, e11, e12, e22 = np.ascontiguousarray(y.T)
    sq0, sq1, sq2 = w0 * w0, w1 * w1, w2 * w2
    a, b, _ = rodrigues_coefficients(sq0 + sq1 + sq2)
    aw0, aw1, aw2 = a * w0, a * w1, a * w2
    b01, b02, b12 = b * w0 * w1, b * w0 * w2, b * w1 * w2
    turn = ((-b * (sq1 + sq2), b01 - aw2, b02 + aw1),           # R - I, row by row
            (b01 + aw2, -b * (sq0 + sq2), b12 - aw0),
            (b02 - aw1, b12 + aw0, -b * (sq0 + sq1)))
    eps = ((e00, e01, e02), (e01, e11, e12), (e02, e12, e22))
    out = np.empty((3, 3, len(y)))
    for i in range(3):                       # nine entries, each a sum over (E,) arrays
        for j in range(3):
            entry = out[i, j]
            np.multiply(turn[i][0], eps[0][j], out=entry)
            entry += turn[i][1] * eps[1][j]
            entry += turn[i][2] * eps[2][j]
            entry += turn[i][j]
            entry += eps[i][j]
    return out


def rs_target_jacobian(y):
    """d vec(b) / d y (E, 9, 9), vec row-major: [:, 3i + j, k] = d b_ij / d y_k.

    Columns 0-2: (dR/d omega_i)(I + epsilon); columns 3-8: R dS/d eps_k (off-diagonal strain
    entries feed both symmetric positions).
    """
    y = np.asarray(y, dtype=np.float64).reshape(-1, 9)
    n = len(y)
    J = np.empty((n, 9, 9))
    dR = exp_rotation_derivative(y[:, :3])                      # (E, 3, 3, 3)
    J[:, :, :3] = np.swapaxes((dR @ _strain_matrix(y)[:, None]).reshape(n, 3, 9), 1, 2)
    R = exp_rotation(y[:, :3])
    J[:, :, 3:] = np.swapaxes((R[:, None] @ STRAIN_BASIS[None]).reshape(n, 6, 9), 1, 2)
    return J


def volume(X, T, x):
    """Volume [m^3] of the deformed mesh: sum of tet volumes of x, signed relative to rest.

    Inverted tets count negatively; X only fixes each tet's rest orientation.
    """
    sign = np.sign(fem.tet_volumes(X, T))
    return float(np.sum(sign * fem.tet_volumes(x, T)))


# ---------------------------------------------------------------------------------------------
# Poisson reconstruction Psi

class PoissonReconstruction:
    """Psi of SPEC section 3: displacement u (N, 3) [m] from per-tet target gradients.

    u = argmin sum_e V_e |(grad u)_e - b_e|^2, i.e. L_s u[:, i] = D^T (V * b[:, i, :]) for each
    coordinate i, with L_s = D^T diag(V) D the scalar P1 Laplacian (equal to -igl.cotmatrix).
    L_s is factored once (SuperLU, symmetric mode) and shared by x, y and z.

    Boundary conditions:
    - ``pinned_nodes``: u = 0 there (Dirichlet; their rows and columns are eliminated).
    - Connected pieces without a pinned node are free: their constant null space is removed by
      pinning one anchor node per piece, then shifting the piece so its ``weights``-weighted mean
      displacement equals ``mean_displacement``. This is the KKT solution with a mean
      constraint: the right-hand side is orthogonal to constants (D 1 = 0), so the anchored
      system also satisfies the anchor's own equation, and all solutions differ by constants.
    ``weights`` (N,) default to the lumped volume per node (sum of adjacent V_e / 4) [m^3].

    Attributes: ``factor`` (scipy SuperLU of L_s on ``solved_nodes``), ``num_nodes``,
    ``pinned_nodes``, ``weights``, ``volumes`` (E,), ``laplacian`` (N, N) csr. The scalar
    gradient D (3E, N) is kept only as ``right_hand_side`` uses it (direction-major, times V).
    """

    def __init__(self, X, T, pinned_nodes=None, weights=None):
        X = np.asarray(X, dtype=np.float64)
        T = np.asarray(T, dtype=np.int64)
        self.num_nodes = len(X)
        self.volumes = np.abs(fem.tet_volumes(X, T))
        gradient = fem.scalar_gradient_operator(X, T)
        self.laplacian = (gradient.T @ sp.diags(np.repeat(self.volumes, 3)) @ gradient).tocsr()
        # D^T diag(V) with D's rows reordered direction-major, (j, e): for an entry-major
        # target b (3, 3, E), column i of the right-hand side is this times b[i] flattened.
        n_tets = len(T)
        by_direction = np.arange(3 * n_tets).reshape(n_tets, 3).T.reshape(-1)
        self._weighted_divergence = (gradient[by_direction].T
                                     @ sp.diags(np.tile(self.volumes, 3))).tocsr()
        self.weights = (fem.lumped_masses(X, T, 1.0) if weights is None
                        else np.asarray(weights, dtype=np.float64))
        self.pinned_nodes = np.unique(np.asarray([] if pinned_nodes is None else pinned_nodes,
                                                 dtype=np.int64))
        self._free_pieces, anchors = self._free_pieces_and_anchors()
        fixed = np.zeros(self.num_nodes, dtype=bool)
        fixed[self.pinned_nodes] = True
        fixed[anchors] = True
        self.solved_nodes = np.flatnonzero(~fixed)
        if len(self.solved_nodes) == 0:
            raise ValueError("every node is pinned or an anchor: nothing to reconstruct")
        L = self.laplacian[self.solved_nodes][:, self.solved_nodes].tocsc()
        self.factor = spla.splu(L, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})

    def _free_pieces_and_anchors(self):
        """Node masks of connected pieces without pins, and one anchor node for each."""
        _, labels = connected_components(self.laplacian, directed=False)
        pinned_labels = np.unique(labels[self.pinned_nodes])
        free_labels = np.setdiff1d(np.unique(labels), pinned_labels)
        pieces = [labels == label for label in free_labels]   # one per free body, usually 1
        anchors = np.array([np.flatnonzero(piece)[0] for piece in pieces], dtype=np.int64)
        return pieces, anchors

    def weighted_mean(self, u):
        """(3,) ``weights``-weighted mean of nodal vectors u (N, 3)."""
        return self.weights @ np.asarray(u) / self.weights.sum()

    def solve(self, b, mean_displacement=None):
        """Displacement u (N, 3) [m] fitting target gradients b (E, 3, 3) (b_ij = du_i/dX_j).

        Free pieces get weighted mean displacement ``mean_displacement`` (3,), default 0;
        pinned nodes get exactly 0.
        """
        return self.solve_batch([b], mean_displacement)[0]

    def solve_batch(self, b, mean_displacement=None, entry_major=False):
        """Displacements u (k, N, 3) [m] fitting k targets b (k, E, 3, 3), as ``solve`` each;
        b may be any iterable of (E, 3, 3) targets (a generator keeps one in memory at a
        time); with ``entry_major`` the targets are (3, 3, E) (``rs_target_entries``).

        The right-hand sides are formed target by target, then solved in one SuperLU call
        with 3k right-hand sides: 8 targets cost about a fifth less than 8 calls of
        ``solve`` (98k-tet bar).
        """
        rhs = np.hstack([self.right_hand_side(target, entry_major) for target in b])  # (N, 3k)
        count = rhs.shape[1] // 3
        u = np.zeros((self.num_nodes, 3 * count))
        u[self.solved_nodes] = self.factor.solve(np.ascontiguousarray(rhs[self.solved_nodes]))
        u = u.reshape(self.num_nodes, count, 3).transpose(1, 0, 2)            # (k, N, 3) view
        target = np.zeros(3) if mean_displacement is None else np.asarray(mean_displacement)
        for piece in self._free_pieces:                        # one loop turn per free body
            w = self.weights[piece]
            u[:, piece] += target - np.einsum("n,knc->kc", w, u[:, piece])[:, None] / w.sum()
        return u

    def right_hand_side(self, b, entry_major=False):
        """D^T (V b) (N, 3) for target gradients b (E, 3, 3): column i from b[:, i, :]; with
        ``entry_major``, b is (3, 3, E) (``rs_target_entries``) and needs no transposed copy.
        Column i is one sparse product with the row b[i] (3E,), flattened direction-major."""
        b = np.asarray(b, dtype=np.float64)
        entries = b.reshape(3, 3, -1) if entry_major else b.reshape(-1, 3, 3).transpose(1, 2, 0)
        return np.stack([self._weighted_divergence @ row for row in entries.reshape(3, -1)],
                        axis=1)

    def reconstruct(self, y, mean_displacement=None):
        """Displacement u (N, 3) [m] of RS coordinates y (E, 9): solve(rs_target(y))."""
        return self.solve(rs_target(y), mean_displacement)


def max_mode_rotations(modal_rs):
    """(m,) largest rotation |omega_e| over tets per unit of each modal coordinate [rad]."""
    return np.linalg.norm(np.asarray(modal_rs)[:, :3, :], axis=1).max(axis=0)
