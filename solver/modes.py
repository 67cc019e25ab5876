"""Linear modal analysis, K w = lambda M w: SPEC.md section 2.

Pinned nodes are Dirichlet conditions: their three DOFs are eliminated and the returned mode
vectors are zero there. A body without pins is free: it has six zero-frequency rigid motions,
which are computed and then dropped, so the returned modes are deformation modes only.

Solver: shift-invert Lanczos (``scipy.sparse.linalg.eigsh``) about a small negative shift
sigma = -SHIFT_FRACTION * mean(diag K / diag M). A negative shift keeps K - sigma M positive
definite even for a free (singular) K, and since every eigenvalue is >= 0 > sigma the eigenvalues
nearest sigma are exactly the lowest ones. mean(diag K / diag M) is of the order of the largest
eigenvalue, so the shift scales with the problem's units and mesh size. The computed subspace is
cleaned with a Rayleigh-Ritz step, which makes W^T M W = I and W^T K W = diag(lambda) hold to
round-off even for the repeated eigenvalues of symmetric bodies. Small problems (few DOFs) use a
dense generalized eigensolver instead, where ARPACK is inefficient or not applicable.

Determinism: an eigenvector is only defined up to its sign, and inside a cluster of repeated
eigenvalues (symmetric bodies) up to any rotation of the cluster's basis; ARPACK's default start
vector is random. Both solvers therefore end in ``canonical_basis``: ARPACK starts from a fixed
smooth field, a few extra eigenpairs are computed so no cluster is cut at the end of the list,
and each cluster's basis is replaced by the Gram-Schmidt (in M) of the M-projections of fixed,
asymmetric test fields of the rest positions (``orientation_fields``), which also fixes every sign.
The test fields are functions of the rest positions normalised by their bounding box, so the
result does not depend on the node numbering, the position or the scale of the body. Without
rest positions the fields are functions of the node index: still deterministic, but then a
renumbering of the nodes may flip signs.
"""

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import connected_components

from .cholesky import SupernodalCholesky
from .ordering import dof_order, nested_dissection_blocks, node_graph

NUM_RIGID = 6
SHIFT_FRACTION = 1e-6
DENSE_LIMIT = 600  # free DOFs up to which the dense solver is used
CLUSTER_RTOL = 1e-8  # eigenvalues this close (relative) form one cluster of repeated values
EXTRA_PAIRS = 4      # eigenpairs computed beyond the request, so a cluster is not cut in two
NUM_FIELDS = 16     # fixed test fields that orient the modes (a cluster may not be larger)
FACTORISATIONS = ("supernodal", "superlu_nd", "superlu_mmd")


@dataclass
class LinearModes:
    """Result of ``linear_modes``.

    eigenvalues: (r,) ascending, in rad^2/s^2.
    vectors: (3N, r) node-major mode shapes, mass-normalised (W^T M W = I), zero on pinned nodes.
    pinned_nodes: (p,) int node indices that were held fixed (empty for a free body).
    """

    eigenvalues: np.ndarray
    vectors: np.ndarray
    pinned_nodes: np.ndarray

    @property
    def frequencies_hz(self):
        """(r,) natural frequencies sqrt(lambda) / 2 pi in Hz (round-off negatives clipped to 0)."""
        return np.sqrt(np.maximum(self.eigenvalues, 0.0)) / (2.0 * np.pi)

    @property
    def mnf(self):
        """Minimal natural frequency sqrt(lambda_1) in rad/s ([P15]'s nonlinearity indicator)."""
        return float(np.sqrt(max(self.eigenvalues[0], 0.0)))

    def for_material(self, youngs, density):
        """These modes, computed at Young's modulus 1 Pa and density 1 kg/m^3, for a body of
        Young's modulus ``youngs`` [Pa] and uniform density ``density`` [kg/m^3] (both > 0).
        K is linear in E and M in rho: K w = lambda M w gives (E K) w' = lambda' (rho M) w'
        with lambda' = lambda E / rho and w' = w / sqrt(rho), mass-normalised in rho M."""
        return LinearModes(self.eigenvalues * (float(youngs) / float(density)),
                           self.vectors * (1.0 / np.sqrt(float(density))), self.pinned_nodes)

    def to_arrays(self):
        """dict of numpy arrays for ``cache.save``."""
        return dict(eigenvalues=self.eigenvalues, vectors=self.vectors,
                    pinned_nodes=self.pinned_nodes)

    @classmethod
    def from_arrays(cls, arrays):
        """Inverse of ``to_arrays``."""
        return cls(eigenvalues=arrays["eigenvalues"], vectors=arrays["vectors"],
                   pinned_nodes=arrays["pinned_nodes"].astype(np.int64))


def rigid_motions(X):
    """(3N, 6) infinitesimal rigid motions of the nodes X (N, 3), node-major.

    Columns 0-2: unit translations along x, y, z. Columns 3-5: rotations omega x (X - centroid)
    for omega = e_x, e_y, e_z (centring keeps the columns well conditioned).
    """
    X = np.asarray(X, dtype=np.float64)
    n = len(X)
    R = np.zeros((n, 3, 6))
    R[:, :, :3] = np.eye(3)
    rel = X - X.mean(axis=0)
    for axis in range(3):  # three columns, not a loop over nodes
        R[:, :, 3 + axis] = np.cross(np.eye(3)[axis], rel)
    return R.reshape(3 * n, 6)


def count_near_zero(eigenvalues, rel_tol=1e-6):
    """Number of eigenvalues with |lambda| <= rel_tol * max |lambda| (rigid-motion count)."""
    ev = np.asarray(eigenvalues, dtype=np.float64)
    return int(np.sum(np.abs(ev) <= rel_tol * np.abs(ev).max()))


def linear_modes(K, masses, num_modes, pinned_nodes=None, rest_positions=None,
                 factorisation="auto", progress=lambda fraction, message: None):
    """Lowest ``num_modes`` deformation modes of (K, diag(masses) kron I3).

    K: (3N, 3N) sparse symmetric stiffness [N/m]; masses: (N,) lumped node masses [kg];
    pinned_nodes: optional int array of node indices held fixed; rest_positions: optional
    (N, 3) rest positions X [m] that orient the modes (signs, bases of repeated eigenvalues)
    independently of the node numbering (see the module docstring). Without pins the body is free
    and its six rigid motions are skipped. With pins nothing is skipped: pins that do not stop
    every rigid motion (one node, or nodes on one line) leave near-zero modes in the result.
    factorisation: how the shift-invert matrix is factored (``_shifted_solver``): "supernodal"
    (``solver.cholesky`` over a nested dissection of the rest positions; needs them),
    "superlu_nd" (SuperLU in that order), "superlu_mmd" (SuperLU's minimum degree) or "auto"
    (supernodal when rest positions are given). All give the same modes to round-off; on large
    meshes the supernodal Cholesky is several times faster and nested dissection fills far less
    than minimum degree (``make bench``, modes rows).
    progress(fraction, message) is called before each shift-invert solve (tens of them, a
    fraction of a second apart on large bodies), so a caller can report and cancel there by
    raising; fraction grows towards 1 with the solves (ARPACK's count is not known ahead).
    Returns ``LinearModes`` in ascending order.
    Raises ValueError when nothing can move, the request cannot be met or the mesh is unusable.
    """
    K = sp.csr_matrix(K, dtype=np.float64)
    masses = np.asarray(masses, dtype=np.float64)
    n_nodes = len(masses)
    if K.shape != (3 * n_nodes, 3 * n_nodes):
        raise ValueError(f"stiffness is {K.shape} but {n_nodes} node masses need "
                         f"({3 * n_nodes}, {3 * n_nodes})")
    if not np.all(masses > 0.0):
        raise ValueError(f"{np.sum(~(masses > 0.0))} node(s) have no mass "
                         "(not used by any tetrahedron); remove unreferenced nodes first")
    pinned = _check_pins(pinned_nodes, n_nodes)
    free_nodes = np.ones(n_nodes, dtype=bool)
    free_nodes[pinned] = False
    _check_connectivity(K, pinned)

    n_rigid = NUM_RIGID if len(pinned) == 0 else 0
    free_dofs = np.repeat(free_nodes, 3)
    max_modes = int(free_dofs.sum()) - n_rigid - 1  # eigsh needs k < number of DOFs
    num_modes = int(num_modes)
    if num_modes < 1:
        raise ValueError(f"ask for at least one mode (got {num_modes})")
    if num_modes > max_modes:
        raise ValueError(f"asked for {num_modes} modes but this body has at most {max(max_modes, 0)} "
                         f"({free_nodes.sum()} free nodes); use fewer modes or a finer mesh")

    K_free = K[free_dofs][:, free_dofs]
    m_free = np.repeat(masses, 3)[free_dofs]
    fields = orientation_fields(rest_positions, n_nodes)[free_dofs]
    wanted = num_modes + n_rigid
    k = min(wanted + EXTRA_PAIRS, int(free_dofs.sum()) - 1)
    if factorisation not in ("auto", *FACTORISATIONS):
        raise ValueError(f"unknown factorisation {factorisation!r}")
    if factorisation == "auto":
        factorisation = "superlu_mmd" if rest_positions is None else "supernodal"
    elif factorisation != "superlu_mmd" and rest_positions is None:
        raise ValueError(f"{factorisation} orders by the rest positions: pass them")
    points = (None if rest_positions is None
              else np.asarray(rest_positions, dtype=np.float64)[free_nodes])
    vals, vecs = _lowest_eigenpairs(K_free, m_free, k, start=fields[:, 0], points=points,
                                    factorisation=factorisation, progress=progress)
    vals, vecs = canonical_basis(vals, vecs, m_free, fields)
    W = np.zeros((3 * n_nodes, num_modes))
    W[free_dofs] = vecs[:, n_rigid:wanted]
    return LinearModes(eigenvalues=vals[n_rigid:wanted], vectors=W, pinned_nodes=pinned)


def orientation_fields(rest_positions, n_nodes, count=NUM_FIELDS):
    """(3N, count) fixed smooth displacement fields with no symmetry, node-major.

    Field j at node x: sin(2 pi k_j . xh + phase_jc) for component c, where xh is the rest
    position centred on its bounding box and divided by the box diagonal (so the fields do not
    depend on translation or scale), and k_j, phase_jc are fixed irrational-ish numbers (golden
    ratio sequence) so that no reflection or rotation of a symmetric body maps a field onto
    itself. Without rest positions xh is built from the node index instead.
    """
    if rest_positions is None:
        t = (np.arange(n_nodes, dtype=np.float64) + 0.5) / n_nodes
        xh = np.stack([t, t * t, np.sqrt(t)], axis=1)
    else:
        X = np.asarray(rest_positions, dtype=np.float64).reshape(n_nodes, 3)
        lo, hi = X.min(axis=0), X.max(axis=0)
        xh = (X - 0.5 * (lo + hi)) / max(float(np.linalg.norm(hi - lo)), np.finfo(float).tiny)
    golden = (np.sqrt(5.0) - 1.0) / 2.0
    seq = np.mod(golden * np.arange(1, 1 + 6 * count), 1.0).reshape(count, 6)
    wave = 0.7 + 1.6 * seq[:, :3] * (1.0 + np.arange(count)[:, None] / 4.0)  # (count, 3) cycles
    phase = 2.0 * np.pi * seq[:, 3:]                                        # (count, 3)
    arg = 2.0 * np.pi * (xh @ wave.T)                                       # (N, count)
    fields = np.sin(arg[:, None, :] + phase.T[None, :, :])                  # (N, 3, count)
    return fields.reshape(3 * n_nodes, count)


def canonical_basis(vals, vecs, m, fields, rtol=CLUSTER_RTOL):
    """Eigenpairs with every sign and every repeated-eigenvalue basis fixed by ``fields``.

    vals: (k,) ascending; vecs: (n, k) M-orthonormal (M = diag(m)); fields: (n, f) test fields.
    Eigenvalues closer than rtol * max(|lambda|, 1e-6 max|lambda|) form a cluster. In each
    cluster (a single mode too) the basis becomes the Gram-Schmidt in M of the projections of
    the test fields onto the cluster's span, taking at each step the field with the largest
    remaining projection (pivoted QR): the result depends only on the span, not on the basis
    the eigensolver happened to return. The eigenvalues are kept (a cluster's spread is below
    rtol, so W^T K W stays diagonal to that accuracy). Returns (vals, vecs) in the same order.
    """
    vals, vecs = np.array(vals, dtype=np.float64), np.array(vecs, dtype=np.float64)
    scale = np.abs(vals).max() if len(vals) else 0.0
    tol = rtol * np.maximum(np.abs(vals[1:]), 1e-6 * scale)
    starts = np.flatnonzero(np.r_[True, np.diff(vals) > tol])
    ends = np.r_[starts[1:], len(vals)]
    proj = vecs.T @ (m[:, None] * fields)                   # (k, f) M-projections
    for a, b in zip(starts, ends):
        C = proj[a:b]
        if C.shape[1] < b - a:
            raise ValueError(f"a cluster of {b - a} repeated eigenvalues exceeds the "
                             f"{C.shape[1]} test fields")
        Q, R, _ = scipy.linalg.qr(C, pivoting=True, mode="economic")
        Q = Q * np.where(np.diag(R) < 0.0, -1.0, 1.0)[None, :]  # positive projections
        vecs[:, a:b] = vecs[:, a:b] @ Q
    return vals, vecs


def _check_pins(pinned_nodes, n_nodes):
    """Sorted unique pinned node indices (p,) int64; ValueError if out of range or all pinned."""
    pinned = np.unique(np.asarray([] if pinned_nodes is None else pinned_nodes,
                                  dtype=np.int64).reshape(-1))
    if len(pinned) and (pinned[0] < 0 or pinned[-1] >= n_nodes):
        raise ValueError(f"pinned node indices must lie in [0, {n_nodes}); "
                         f"got range [{pinned[0]}, {pinned[-1]}]")
    if len(pinned) == n_nodes:
        raise ValueError("all nodes are pinned, so nothing can vibrate; pin fewer vertices")
    return pinned


def _check_connectivity(K, pinned):
    """Reject meshes with a part that floats freely next to another part (extra zero modes).

    A free body must be one piece; with pins, every piece must hold at least one pinned node.
    Node graph: two nodes are adjacent when their 3x3 block of K is non-zero.
    """
    n_nodes = K.shape[0] // 3
    collapse = sp.kron(sp.identity(n_nodes, format="csr"), np.ones((1, 3)), format="csr")
    graph = collapse @ abs(K) @ collapse.T
    n_parts, labels = connected_components(graph, directed=False)
    if n_parts == 1:
        return
    if len(pinned) == 0:
        raise ValueError(f"the tet mesh has {n_parts} disconnected parts; a free body must be one "
                         "connected piece (join the parts, or pin each of them)")
    unpinned = n_parts - len(np.unique(labels[pinned]))
    if unpinned:
        raise ValueError(f"{unpinned} of the mesh's {n_parts} disconnected parts have no pinned "
                         "vertex and would float freely; pin each part or join them")


def _lowest_eigenpairs(K, m, k, start, points=None, factorisation="superlu_mmd",
                       progress=lambda fraction, message: None):
    """k lowest eigenpairs of K v = lambda diag(m) v; values ascending, vectors M-orthonormal.

    start: (n,) ARPACK's start vector (fixed, so the run is reproducible). points: (n / 3, 3)
    node positions for the nested dissections; factorisation: see ``_shifted_solver``;
    progress: see ``linear_modes``.
    """
    if K.shape[0] <= DENSE_LIMIT:
        s = 1.0 / np.sqrt(m)  # symmetric scaling turns the problem into a standard one
        vals, vecs = scipy.linalg.eigh(s[:, None] * K.toarray() * s[None, :],
                                       subset_by_index=(0, k - 1))
        return vals, s[:, None] * vecs

    M = sp.diags(m, format="csc")
    sigma = -SHIFT_FRACTION * float(np.mean(K.diagonal() / m))
    progress(0.0, "factoring the shifted stiffness")
    solve = _shifted_solver(K - sigma * M, points, factorisation)
    solves = 0

    def reported_solve(b):
        nonlocal solves
        progress(solves / (solves + 4.0 * k), f"shift-invert solve {solves + 1}")
        solves += 1
        return solve(b)
    op_inv = spla.LinearOperator(K.shape, matvec=reported_solve, dtype=np.float64)
    _, vecs = spla.eigsh(K, k=k, M=M, sigma=sigma, which="LM", OPinv=op_inv, v0=start)
    return _rayleigh_ritz(K, m, vecs)


def _shifted_solver(A, points, factorisation):
    """b -> A^-1 b for the SPD shifted matrix A (n, n), factored once.

    "superlu_mmd": SuperLU's symmetric minimum degree (on a 41k-tet box it fills like its
    default COLAMD and solves ~20 % faster). "superlu_nd": SuperLU in the nested-dissection
    order of the nodes (``solver.ordering``), kept exactly (natural order, diagonal pivots: A is
    SPD, so no pivoting is needed for stability). "supernodal": ``solver.cholesky`` on the
    blocks of that nested dissection (the same order, Cholesky by dense blocks).
    points: (n / 3, 3) node positions (the nested dissections need them)."""
    if factorisation == "superlu_mmd":
        lu = spla.splu(A.tocsc(), permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
        return lu.solve
    blocks = nested_dissection_blocks(points, node_graph(A))
    if factorisation == "supernodal":
        try:
            return SupernodalCholesky(A, [dof_order(block) for block in blocks]).solve
        except np.linalg.LinAlgError:
            raise ValueError("the stiffness matrix is not positive semi-definite (inverted or "
                             "degenerate tets?); tetrahedralise the mesh again") from None
    perm = dof_order(np.concatenate(blocks))
    lu = spla.splu(sp.csc_matrix(A)[perm][:, perm].tocsc(), permc_spec="NATURAL",
                   diag_pivot_thresh=0.0, options={"SymmetricMode": True})

    def solve(b):
        out = np.empty_like(b, dtype=np.float64)
        out[perm] = lu.solve(np.ascontiguousarray(b[perm], dtype=np.float64))
        return out
    return solve


def _rayleigh_ritz(K, m, V):
    """Best eigenpairs within span(V): exact M-orthonormality and K-diagonality up to round-off."""
    K_r = V.T @ (K @ V)
    M_r = V.T @ (m[:, None] * V)
    vals, coeffs = scipy.linalg.eigh(0.5 * (K_r + K_r.T), 0.5 * (M_r + M_r.T))
    return vals, V @ coeffs
