"""Reduced RS with cubature: SPEC.md section 4 [L14].

Full RS warping maps modal coordinates z (m,) to a pose by solving a global Poisson problem
(``rs.PoissonReconstruction``). The reduced version restricts the displacement to a basis B
(3N, rB) and the least-squares fit to a few cubature tets C with weights w_e >= 0:

    y_e = (QW)_e z                          (9,)  RS coordinates of tet e, linear in z
    q(z) = sum_{e in C} w_e P_e vec(b_e(y_e))   (rB,) with P_e = (B^T L B)^-1 (G_e B)^T V_e
    u = B q                                 (N, 3) displacement [m]

(``ReducedRS`` integrates the linear part of b exactly and only the rest by cubature; see its
docstring.) Everything per evaluation lives in C and the reduced space, so a pose costs
O(|C| rB) whatever the mesh size. Rows of B (e.g. Phi B for render vertices, or a handful of
vertices) give any part of the pose without the rest ("partial reconstruction").

Shapes and units: X (N, 3) [m], T (E, 4), ``modal_rs`` (E, 9, m) = ``rs.linear_rs(Q, W)`` the
linear RS coordinates of the modes (radians and strain per unit z), B (3N, rB) node-major [m per
unit q]. With B mass-orthonormal (B^T M B = I), |q| is the mass-weighted RMS norm of u times
sqrt(total mass), which makes errors in q meaningful.

Pipeline: ``prepare_reduced_rs`` does everything (training poses, basis, cubature);
``second_order_basis`` and ``train_reduced_rs_cubature`` (on ``cubature.greedy_nnls``) are
its steps.
``LinearDeformer`` has the same interface for plain linear modal motion (q = z, B = W).
"""

import math
import time

import numpy as np
import scipy.linalg

from . import cubature, fem, rs, threads


# ---------------------------------------------------------------------------------------------
# Basis: linear modes plus second-order terms of the RS map

def second_order_targets(modal_rs, i, j):
    """d^2 b / dz_i dz_j at rest, (E, 3, 3) (SPEC section 4).

    b = [w]x + eps + [w]x eps + 1/2 [w]x^2 + O(3) with w = sum z_k w^k, eps = sum z_k eps^k, so
    d^2 b / dz_i dz_j = [w^i]x eps^j + [w^j]x eps^i + 1/2 ([w^i]x [w^j]x + [w^j]x [w^i]x).
    """
    fields = _mode_fields(np.asarray(modal_rs)[:, :, [i, j]])
    return np.ascontiguousarray(_pair_entries(*fields, 0, 1).transpose(2, 0, 1))


def mode_series_targets(modal_rs, i, k):
    """k-th Taylor coefficient of b along mode i alone, (E, 3, 3) (k >= 1).

    b(z e_i) = exp(z [w^i]x)(I + z eps^i) - I = sum_k z^k ([w^i]x^k / k! + [w^i]x^(k-1) eps^i
    / (k-1)!); k = 2 gives 1/2 d^2 b / dz_i^2 of ``second_order_targets``.
    """
    fields = _mode_fields(np.asarray(modal_rs)[:, :, [i]])
    return np.ascontiguousarray(_series_entries(*fields, 0, k).transpose(2, 0, 1))


def _mode_fields(modal_rs):
    """Per mode, tets last (contiguous, for ``_pair_entries``): omega (m, 3, E) and the strain
    matrices eps (m, 3, 3, E) of modal_rs (E, 9, m)."""
    fields = np.ascontiguousarray(np.asarray(modal_rs).transpose(2, 1, 0))       # (m, 9, E)
    strain = np.einsum("mke,kij->mije", fields[:, 3:], rs.STRAIN_BASIS)
    return fields[:, :3], np.ascontiguousarray(strain)


def _pair_entries(omega, strain, i, j):
    """d^2 b / dz_i dz_j entry-major (3, 3, E) from ``_mode_fields``, entry by entry on (E,)
    arrays: [a]x S is the cross product of a with the columns of S, and
    1/2 ([a]x [b]x + [b]x [a]x) = 1/2 (a b^T + b a^T) - (a . b) I."""
    wi, wj, Si, Sj = omega[i], omega[j], strain[i], strain[j]
    dot = wi[0] * wj[0] + wi[1] * wj[1] + wi[2] * wj[2]
    out = np.empty((3, 3, wi.shape[1]))
    for r in range(3):
        p, n = (r + 1) % 3, (r + 2) % 3          # (a x s)_r = a_p s_n - a_n s_p
        for c in range(3):
            entry = out[r, c]
            np.multiply(wi[p], Sj[n, c], out=entry)
            entry -= wi[n] * Sj[p, c]
            entry += wj[p] * Si[n, c]
            entry -= wj[n] * Si[p, c]
            entry += 0.5 * (wi[r] * wj[c] + wj[r] * wi[c])
            if r == c:
                entry -= dot
    return out


_NEXT, _AFTER = [1, 2, 0], [2, 0, 1]     # (a x s)_r = a_next s_after - a_after s_next


def _series_entries(omega, strain, i, k):
    """``mode_series_targets`` entry-major (3, 3, E) from ``_mode_fields``:
    [w]x^(k-1) ([w]x / k + eps) / (k-1)!, the powers as repeated cross products with the
    columns (no stacks of 3 x 3 products)."""
    w = omega[i]
    M = strain[i].copy()
    M += rs.skew(w.T).transpose(1, 2, 0) / k                        # [w]x / k + eps
    for _ in range(k - 1):
        M = w[_NEXT][:, None, :] * M[_AFTER] - w[_AFTER][:, None, :] * M[_NEXT]
    return M / math.factorial(k - 1)


SNAPSHOT_CHUNK = 16    # poses whose RS coordinates one product makes (rs_snapshots)
SNAPSHOT_BATCH = 8     # poses per batched Poisson solve: fixed, so results are too


def rs_snapshots(modal_rs, recon, Z, progress=None):
    """Full RS displacements (3N, S) [m] of poses Z (S, m): recon.reconstruct(modal_rs z).

    The poses of a chunk are solved in batches of SNAPSHOT_BATCH on several threads
    (``threads.ordered_map``), one batched Poisson solve each (``recon.solve_batch``, the
    factor of ``recon`` reused; the batches do not depend on the thread count, nor then does
    the result); pins hold exactly.
    """
    Z = np.atleast_2d(np.asarray(Z, dtype=np.float64))
    out = np.empty((3 * recon.num_nodes, len(Z)))
    n_tets = np.shape(modal_rs)[0]
    poses = np.empty((min(SNAPSHOT_CHUNK, len(Z)), 9 * n_tets))     # reused by every chunk
    for start in range(0, len(Z), SNAPSHOT_CHUNK):
        count = min(SNAPSHOT_CHUNK, len(Z) - start)
        if progress is not None:
            progress(start / len(Z), f"full RS snapshots {start + 1}-{start + count} "
                                     f"of {len(Z)}")
        Y = modal_rs_poses(modal_rs, Z[start:start + count],
                           out=poses[:count]).reshape(count, n_tets, 9)
        parts = threads.fixed_parts(count, SNAPSHOT_BATCH)
        # Targets pose by pose, as they are solved (a generator: one target per thread in
        # memory; 8 poses' targets at once ran 40 % slower), then one batched solve per thread.
        solved = threads.ordered_map(lambda part: recon.solve_batch(
            (rs.rs_target_entries(y) for y in Y[part]), entry_major=True), parts)
        out[:, start:start + count] = np.concatenate(solved).reshape(count, -1).T
    return out


def second_order_basis(X, T, masses, modal_rs, recon, modes_W, max_size=120, drop_tol=1e-6,
                       order=3, snapshots=None, snapshot_size=None, screen=2.0,
                       progress=None):
    """Displacement basis B (3N, rB) [m]: the modes W, then second-order RS vectors (SPEC 4).

    X (N, 3), T (E, 4): the tet mesh (kept for the signature; the geometry enters through
    ``recon`` and ``modal_rs``). masses (N,) lumped node masses [kg]; modal_rs (E, 9, m) linear
    RS of the modes; recon a ``rs.PoissonReconstruction`` with the body's pins; modes_W (3N, m).

    Candidates (one Poisson solve each, which honours the pins):
    - SPEC 4: for each pair i <= j, Psi(d^2 b / dz_i dz_j);
    - beyond SPEC 4, for each mode alone the Taylor terms of orders 3..``order`` of the
      rotation exponential (``mode_series_targets``; order=2 switches them off). Second order
      alone leaves up to about 2 % of the bounding-box diagonal on single modes turned by
      90 deg (pinned 4:1:1 bar, 10 modes); orders 3-4 roughly halve that.
    Every candidate is scaled to the displacement it actually adds when the modes involved
    each turn by REFERENCE_ANGLE (90 deg) at their most rotating tet: z_i = 90 deg / max_e
    |omega^i_e|, times z_i z_j (i < j), z_i^2 / 2 (i = j) or z_i^k. This ranks terms of
    different modes and orders on one scale. With many modes (m(m+1)/2 pairs) only the
    ``screen`` x (columns available) terms with the largest scaled targets (volume-weighted
    norm, no solve needed) are solved; screen=None solves every term.

    Selection (pivoted Gram-Schmidt in the mass inner product): the modes come first, in
    order; then repeatedly the candidate with the largest M-norm *outside* the current span is
    appended (the most new displacement at 90 deg first). A candidate whose remaining norm
    falls to ``drop_tol`` times its own norm is dropped as near-dependent. Vectors are
    orthogonalised twice (classical Gram-Schmidt), so B^T M B = I to round-off; rows of pinned
    DOFs stay exactly 0 since every candidate is 0 there.

    Optional enrichment (beyond SPEC 4, recommended for 90 deg poses of mixed modes, where
    the terms above leave 1-2 %): ``snapshots`` (3N, S) are full RS displacements of training
    poses (``rs_snapshots``); their part outside the span so far is compressed by POD (mass
    inner product, method of snapshots) and its leading directions fill the end of the basis.
    ``snapshot_size`` (default: half the room left by the modes) is reserved for them; the
    series candidates get the rest, and snapshots fill whatever the series leave unused.

    progress: optional callable(fraction, message), called between Poisson solves and picks;
    an exception raised inside it aborts the build and propagates.
    Returns B (3N, rB), m <= rB <= max(max_size, m).
    """
    modal_rs = np.asarray(modal_rs, dtype=np.float64)
    W = np.asarray(modes_W, dtype=np.float64)
    m_diag = np.repeat(np.asarray(masses, dtype=np.float64), 3)          # (3N,) diag of M
    room = max(int(max_size) - W.shape[1], 0)
    if snapshots is not None and snapshot_size is None:
        snapshot_size = room // 2
    reserved = 0 if snapshots is None else min(int(snapshot_size), room)
    keep = None if screen is None else int(np.ceil(screen * (room - reserved)))
    candidates = _series_candidates(modal_rs, recon, order, keep, progress)
    basis = _pivoted_gram_schmidt(_mass_orthonormal(W, m_diag), candidates, m_diag,
                                  room - reserved, drop_tol, progress)
    if snapshots is not None:
        basis = _append_snapshot_modes(basis, np.asarray(snapshots, dtype=np.float64), m_diag,
                                       int(max_size) - basis.shape[1], drop_tol)
    return basis


REFERENCE_ANGLE = 0.5 * np.pi   # rotation [rad] at which basis candidates are ranked
CANDIDATE_BATCH = 8             # basis candidates solved at once (24 right-hand sides)
BATCH_MEMORY = 256 * 2 ** 20    # bytes of candidate targets (72 per tet) held at once, at most


def _series_candidates(modal_rs, recon, order, keep, progress):
    """(3N, P) scaled Psi-solves of the pair and single-mode terms (see the caller).

    Only the ``keep`` terms with the largest volume-weighted target norm |factor b|_V are
    kept (a cheap screen: Psi is a least-squares fit, so a small target cannot give a large
    displacement); keep None keeps them all. Each target is built once: a term is solved when
    it enters the running top ``keep`` (and still holds its column at the end of its batch of
    MAX_WORKERS x CANDIDATE_BATCH terms, fewer where they would pass BATCH_MEMORY) and its column
    dropped when a larger one displaces it (screening first would build every kept target
    twice, which costs more than the few solves of terms displaced later); memory stays
    ``keep`` columns of 3N plus a batch of targets.
    """
    num_modes = modal_rs.shape[2]
    amplitude = REFERENCE_ANGLE / np.maximum(rs.max_mode_rotations(modal_rs), 1e-300)
    terms = [(i, j, None) for j in range(num_modes) for i in range(j + 1)]
    terms += [(i, i, k) for k in range(3, int(order) + 1) for i in range(num_modes)]
    fields = _mode_fields(modal_rs)

    def scaled_target(i, j, k):
        if k is None:
            factor = amplitude[i] * amplitude[j] * (0.5 if i == j else 1.0)
            return factor * _pair_entries(*fields, i, j)
        return amplitude[i] ** k * _series_entries(*fields, i, k)

    slots = len(terms) if keep is None else min(int(keep), len(terms))
    columns = np.empty((3 * recon.num_nodes, slots))
    if slots == 0:
        return columns
    held_terms = np.full(slots, -1)                 # the term each column holds
    held_sizes = np.full(slots, -np.inf)

    def sized_target(n):                            # entry-major (3, 3, E) targets throughout
        target = scaled_target(*terms[n])
        flat = target.reshape(9, -1)
        return target, float(np.einsum("ke,ke->e", flat, flat) @ recon.volumes)

    # Terms go in batches of MAX_WORKERS x CANDIDATE_BATCH: their targets are built side by
    # side, the running top ``keep`` is updated in term order (as one term at a time would),
    # and the batch's terms that still hold a column are solved CANDIDATE_BATCH at a time, one
    # batched solve per part on the threads. Batches and parts are fixed, not per thread, so
    # the result does not depend on the thread count.
    per_part = max(1, min(CANDIDATE_BATCH,
                          BATCH_MEMORY // (72 * len(recon.volumes) * threads.MAX_WORKERS)))
    batch = per_part * threads.MAX_WORKERS
    for first in range(0, len(terms), batch):
        if progress is not None:
            progress(0.8 * first / len(terms), f"basis candidate {first + 1}/{len(terms)}")
        numbers = range(first, min(first + batch, len(terms)))
        built = dict(zip(numbers, threads.ordered_map(sized_target, numbers)))
        for n, (_, size) in built.items():
            slot = int(np.argmin(held_sizes))       # the smallest kept so far
            if size > held_sizes[slot]:
                held_terms[slot], held_sizes[slot] = n, size
        fresh = np.flatnonzero(np.isin(held_terms, numbers))      # slots taken in this batch
        solved = threads.ordered_map(lambda part: recon.solve_batch(
            [built[n][0] for n in held_terms[fresh[part]]], entry_major=True),
            threads.fixed_parts(len(fresh), per_part))
        for slot, u in zip(fresh, (u for part in solved for u in part)):
            columns[:, slot] = u.reshape(-1)
    used = held_terms >= 0
    return columns[:, used][:, np.argsort(held_terms[used])]


def _mass_orthonormal(W, m_diag):
    """W (3N, m) made M-orthonormal by a Cholesky factor of W^T M W = U^T U: W U^-1 (span and
    order kept; the small inverse, then one tall product on several threads)."""
    upper = scipy.linalg.cholesky(threads.inner(W, W, m_diag))
    return threads.matmul(W, scipy.linalg.solve_triangular(upper, np.eye(len(upper))))


RECOMPUTE_FRACTION = 1e-4   # recompute a downdated norm below this share of its last exact one


def _pivoted_gram_schmidt(basis, candidates, m_diag, extra, drop_tol, progress):
    """Append up to ``extra`` M-orthonormal vectors from candidates, largest residual first.

    The candidates' remaining squared M-norms are downdated after each pick (minus the squared
    coefficient on the new vector) and recomputed for a column once its value has fallen below
    RECOMPUTE_FRACTION of its last exact one, as LAPACK's pivoted QR does: the downdate then
    never loses more than a few digits, far from the ``drop_tol`` decision. The candidates
    themselves are never updated: the new vector v is M-orthogonal to everything before it,
    so its coefficient on a candidate's residual is v^T M c, read from the candidate as given
    (one pass over them per pick, where updating them in place took three); only the picked
    column and stale ones are projected out, twice (classical Gram-Schmidt, twice is enough)."""
    start = basis.shape[1]
    out = np.empty((basis.shape[0], start + max(extra, 0)), order="F")
    out[:, :start] = basis
    norms = np.sqrt(np.einsum("ik,i,ik->k", candidates, m_diag, candidates))
    residual = candidates - threads.matmul(basis, threads.inner(basis, candidates, m_diag))
    remaining2 = np.einsum("ik,i,ik->k", residual, m_diag, residual)
    del residual
    exact2 = remaining2.copy()                 # each column's last exactly computed value
    alive = norms > 0.0
    size = start
    for step in range(max(extra, 0)):
        if progress is not None:
            progress(0.8 + 0.2 * step / extra, f"orthonormalising basis ({step}/{extra})")
        remaining = np.sqrt(np.maximum(remaining2, 0.0))
        alive &= remaining > drop_tol * norms                  # near-dependent: drop for good
        if not alive.any():
            break
        best = int(np.argmax(np.where(alive, remaining, -1.0)))
        vector = _project_out(out[:, :size], m_diag, candidates[:, best])
        vector /= np.sqrt(vector @ (m_diag * vector))
        out[:, size] = vector
        size += 1
        alive[best] = False
        coefficients = (m_diag * vector) @ candidates
        remaining2 -= coefficients * coefficients
        stale = np.flatnonzero(alive & (remaining2 < RECOMPUTE_FRACTION * exact2))
        if len(stale):
            part = _project_out(out[:, :size], m_diag, candidates[:, stale])
            remaining2[stale] = exact2[stale] = np.einsum("ik,i,ik->k", part, m_diag, part)
    return out[:, :size]


def _project_out(Q, m_diag, x):
    """x (n,) or (n, k) minus its M-projection on the M-orthonormal columns of Q (n, q), in
    two classical Gram-Schmidt passes (for a block x, the tall products on several threads)."""
    for _ in range(2):
        if x.ndim == 1:
            x = x - Q @ (Q.T @ (m_diag * x))
        else:
            x = x - threads.matmul(Q, threads.inner(Q, x, m_diag))
    return x


def _append_snapshot_modes(basis, snapshots, m_diag, count, drop_tol):
    """basis plus up to ``count`` POD directions of the snapshots' part outside its span."""
    if count <= 0 or snapshots.shape[1] == 0:
        return basis
    residual = _project_out(basis, m_diag, snapshots)
    # Method of snapshots: eigenvectors of the S x S mass Gram matrix give the POD modes.
    gram = threads.inner(residual, residual, m_diag)
    values, vectors = np.linalg.eigh(0.5 * (gram + gram.T))
    order = np.argsort(values)[::-1]
    values, vectors = values[order], vectors[:, order]
    # Directions are kept relative to the snapshots' own energy, not to the leading leftover:
    # when the basis already spans every free DOF (tiny meshes) the leftover is round-off,
    # whose directions would make B^T L B singular.
    energy = float(np.einsum("ik,i,ik->", snapshots, m_diag, snapshots))
    if values[0] <= drop_tol ** 2 * energy:
        return basis
    count = min(count, int(np.sum(values > drop_tol ** 2 * energy)))      # energies: tol^2
    modes = threads.matmul(residual, vectors[:, :count] / np.sqrt(values[:count]))
    # Re-orthonormalise (round-off of the Gram route) against the basis and each other.
    modes -= threads.matmul(basis, threads.inner(basis, modes, m_diag))
    modes = _mass_orthonormal(modes, m_diag)
    return np.hstack([basis, modes])


# ---------------------------------------------------------------------------------------------
# Fast per-tet targets b(y) and their derivatives for the few cubature tets
#
# Entry-major: a quantity of n tets (or tets x poses) is laid out (9, n), one contiguous row per
# entry of its 3 x 3 matrix (row-major vec), so every numpy operation runs on long rows; stacks
# of n 3 x 3 products, or slices of (n, 9) rows, cost several times more for a few hundred
# tets, where each call costs more than its arithmetic.

# d vec(b) / dy at y = 0 (9, 9): b ~ [omega]x + eps, the linear part of the RS map.
LINEAR_TARGET = np.concatenate([rs.skew(np.eye(3)).transpose(1, 2, 0).reshape(9, 3),
                                rs.STRAIN_BASIS.transpose(1, 2, 0).reshape(9, 6)], axis=1)
# vec([omega]x) = omega[_SKEW_INDEX] * _SKEW_SIGN (row-major: 0, -w2, w1, w2, 0, -w0, -w1, w0, 0)
_SKEW_INDEX = np.array([0, 2, 1, 2, 0, 0, 1, 0, 0])
_SKEW_SIGN = np.array([0.0, -1.0, 1.0, 1.0, 0.0, -1.0, -1.0, 1.0, 0.0])[:, None]
# omega[_OUTER_ROWS] * omega[_OUTER_COLS] = vec(omega omega^T).
_OUTER_ROWS, _OUTER_COLS = np.repeat(np.arange(3), 3), np.tile(np.arange(3), 3)
# vec(eps) = eps6[_SYMMETRIC] for the six strain entries (xx, xy, xz, yy, yz, zz).
_SYMMETRIC = np.array([0, 1, 2, 1, 3, 4, 2, 4, 5])
_DIAGONAL = slice(0, 9, 4)                               # rows of vec(M) on M's diagonal
# <M, E_k> = M[_STRAIN_UPPER] + M[_STRAIN_LOWER], halved on the diagonal (vec M rows).
_STRAIN_UPPER = np.array([3 * i + j for i, j in rs.STRAIN_INDEX])
_STRAIN_LOWER = np.array([3 * j + i for i, j in rs.STRAIN_INDEX])
_STRAIN_DIAGONAL = np.array([0, 3, 5])
# (s x F e_b)[a] = s[_NEXT[a]] F[_AFTER[a], b] - s[_AFTER[a]] F[_NEXT[a], b].
_NEXT, _AFTER = np.array([1, 2, 0]), np.array([2, 0, 1])
# Column b of R E_k is R's column _STRAIN_SOURCE[b, k] where E_k[i, b] = 1 (_STRAIN_MASK), else 0.
_STRAIN_SOURCE, _STRAIN_MASK = np.zeros((3, 6), dtype=np.int64), np.zeros((3, 6, 1))
for _k, (_i, _j) in enumerate(rs.STRAIN_INDEX):
    _STRAIN_SOURCE[[_j, _i], _k], _STRAIN_MASK[[_j, _i], _k] = (_i, _j), 1.0


def _rs_map(y, jacobian, remainder=False):
    """vec(b(y)) (9, n) of RS coordinates y (9, n), entry-major, or with ``remainder`` the
    nonlinear remainder vec(r(y)) = vec(b(y) - [omega]x - eps); with ``jacobian`` also vec(R),
    vec(J_l) and vec(F) (9, n) each: the rotation exp([omega]x), the left Jacobian of SO(3)
    and F = I + b = R (I + eps).

    With K = [omega]x and K^2 = omega omega^T - t^2 I (t = |omega|):
    R = (1 - b t^2) I + a K + b omega omega^T, J_l = (1 - e t^2) I + b K + e omega omega^T
    (a, b, e: ``rs.rodrigues_coefficients``). Derivatives: d vec(b) / d omega_i =
    vec([J_l e_i]x F) and d vec(b) / d eps_k = vec(R E_k), formed per tet by
    ``_target_derivatives`` (the chains) and contracted with a vector without forming them by
    ``ReducedRS.q_gradient`` (cheaper there). Elementwise operations only: each tet's result is the
    same to the last bit whatever else is in the call (the cubature's training splits its
    tets over threads).
    """
    omega = y[:3]
    t2 = omega[0] * omega[0] + omega[1] * omega[1] + omega[2] * omega[2]
    a, b, e = rs.rodrigues_coefficients(t2)
    K = omega[_SKEW_INDEX] * _SKEW_SIGN
    outer = omega[_OUTER_ROWS] * omega[_OUTER_COLS]
    R = a * K
    R += b * outer
    R[_DIAGONAL] += 1.0 - b * t2
    S = y[3:][_SYMMETRIC]
    S[_DIAGONAL] += 1.0
    n = y.shape[1]
    R3, S3 = R.reshape(3, 3, n), S.reshape(3, 3, n)
    F = R3[:, 0, None] * S3[0] + R3[:, 1, None] * S3[1] + R3[:, 2, None] * S3[2]
    F = F.reshape(9, n)
    if remainder:                                       # F - I - K - eps = F - K - S
        target = F - K
        target -= S
    else:
        target = F.copy() if jacobian else F
        target[_DIAGONAL] -= 1.0
    if not jacobian:
        return target
    J_l = b * K
    J_l += e * outer
    J_l[_DIAGONAL] += 1.0 - e * t2
    return target, R, J_l, F


def fast_remainders(y):
    """vec(r(y)) (9, n) = vec(b(y)) - [omega]x - eps of RS coordinates y (9, n), entry-major
    (as ``remainder_entries``, for the few cubature tets)."""
    return _rs_map(y, False, remainder=True)


def fast_targets(y, jacobian=False):
    """vec(b(y)) (n, 9) as ``rs.rs_target``, and optionally d vec(b)/dy (n, 9, 9) as
    ``rs.rs_target_jacobian``, for y (n, 9): the same quantities, computed by ``_rs_map`` (the
    deformer's map, faster for the few hundred cubature tets)."""
    y = np.ascontiguousarray(np.asarray(y, dtype=np.float64).reshape(-1, 9).T)
    if not jacobian:
        return _rs_map(y, False).T
    target, R, J_l, F = _rs_map(y, True)
    return target.T, _target_derivatives(R, J_l, F).transpose(2, 0, 1)


def _target_derivatives(R, J_l, F):
    """d vec(b)/dy (9, 9, n) [row of vec(b), coordinate of y, tet] from ``_rs_map``'s vec R,
    J_l and F (9, n): d vec(b)/d omega_i = vec([J_l e_i]x F) (the cross products of J_l's
    column i with F's columns) and d vec(b)/d eps_k = vec(R E_k). Elementwise, as the map."""
    n = R.shape[1]
    J_l, F, R = J_l.reshape(3, 3, n), F.reshape(3, 3, n), R.reshape(3, 3, n)
    spin = (J_l[_NEXT][:, None] * F[_AFTER][:, :, None]
            - J_l[_AFTER][:, None] * F[_NEXT][:, :, None])               # [a, b, i, tet]
    strain = R[:, _STRAIN_SOURCE] * _STRAIN_MASK                         # [a, b, k, tet]
    return np.concatenate([spin.reshape(9, 3, n), strain.reshape(9, 6, n)], axis=1)


# ---------------------------------------------------------------------------------------------
# Projections P_e and the exact reduced fit

DEPENDENT_BASIS = 1e-12   # smallest / largest eigenvalue of B^T L B below which B is dependent


class ReducedProjection:
    """The reduced least-squares fit q = (B^T L B)^-1 B^T G^T V vec(b) for a basis B.

    Holds the Cholesky factor of the reduced Laplacian B^T L B (rB, rB) [from
    L = G^T (V kron I9) G], and gives per-tet projections ``tet_projections(tets)``
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
        gram = 0
        for c in range(3):
            B_c = np.ascontiguousarray(B3[:, c, :])
            gram = gram + threads.inner(B_c, recon.laplacian @ B_c)
        gram = 0.5 * (gram + gram.T)
        extremes = scipy.linalg.eigvalsh(gram)[[0, -1]] if len(gram) else np.ones(2)
        if not extremes[0] > DEPENDENT_BASIS * extremes[1]:   # also catches NaN
            raise ValueError(f"the reduced basis ({self.basis.shape[1]} vectors) is not "
                             "independent on this mesh's free nodes; use fewer modes or a "
                             "finer mesh")
        self.gram_factor = scipy.linalg.cho_factor(gram)
        # B (B^T L B)^-1 (3N, rB): P_e and the exact fit then need no per-call solve. The small
        # inverse, then one tall product on several threads (2.5x faster than cho_solve on B^T).
        inverse = scipy.linalg.cho_solve(self.gram_factor, np.eye(len(gram)))
        self.solved_basis = threads.matmul(self.basis, 0.5 * (inverse + inverse.T))
        self.shape_gradients = fem.shape_gradients(self.X, self.T)         # (E, 4, 3)
        self._linear_map = None                 # (modal_rs it was made for, A)

    @property
    def basis_size(self):
        return self.basis.shape[1]

    def tet_projections(self, tets):
        """P_e (k, rB, 9) = (B^T L B)^-1 (G_e B)^T V_e for tet indices ``tets`` (k,)."""
        tets = np.asarray(tets, dtype=np.int64)
        r = self.basis_size
        nodes = self.solved_basis.reshape(self.num_nodes, 3 * r)[self.T[tets]]  # (k, 4, 3 rB)
        # (G_e B~)[i, j, :] = sum_a grad_a[j] B~[node a, i, :], as a batched (3 x 4)(4 x 3 rB).
        GB = np.swapaxes(self.shape_gradients[tets], 1, 2) @ nodes               # (k, j, (i, r))
        GB = GB.reshape(len(tets), 3, 3, r).transpose(0, 3, 2, 1)                 # (k, r, i, j)
        P = GB.reshape(len(tets), r, 9) * self.recon.volumes[tets][:, None, None]
        return np.ascontiguousarray(P)

    def exact_q(self, b, entry_major=False):
        """Reduced coordinates (rB,) or (F, rB) fitting targets b (E, 3, 3) or (F, E, 3, 3).

        q = (B^T L B)^-1 B^T G^T V vec(b), the all-tet (no cubature) reduced reconstruction.
        b may also be (.., E, 9), or an iterable of F (E, 3, 3) targets (then (F, rB)); with
        ``entry_major``, an iterable of F (3, 3, E) targets (``rs.rs_target_entries``).
        """
        if entry_major or not isinstance(b, np.ndarray):
            return self._exact_q_batch(b, entry_major)
        b = np.asarray(b, dtype=np.float64)
        single = b.size == 9 * len(self.T)
        q = self._exact_q_batch(b.reshape(-1, len(self.T), 3, 3))
        return q[0] if single else q

    def _exact_q_batch(self, b, entry_major=False):
        """(F, rB) fits of F >= 1 poses' targets b (F, E, 3, 3), or an iterable of (E, 3, 3)
        ((3, 3, E) with ``entry_major``): the right-hand side of each pose (kept small: one
        pose at a time), then one product."""
        rhs = np.stack([self.recon.right_hand_side(target, entry_major).reshape(-1)
                        for target in b])
        return rhs @ self.solved_basis                                          # (F, rB)

    def linear_map(self, modal_rs):
        """(rB, m) exact reduced coordinates of the linear targets [omega^i]x + eps^i per mode.

        For modal_rs = Q W these targets are grad(w_i), so this is the L-projection of W on B
        (the identity on W's own columns when B starts with them).
        """
        if self._linear_map is not None and self._linear_map[0] is modal_rs:
            return self._linear_map[1]          # training and ``ReducedRS.build`` both ask
        source = modal_rs
        modal_rs = np.asarray(modal_rs, dtype=np.float64)
        # Mode by mode (one target in memory), entry-major: LINEAR_TARGET (9, 9) @ RS (9, E).
        targets = (LINEAR_TARGET @ modal_rs[:, :, i].T for i in range(modal_rs.shape[2]))
        A = self.exact_q(targets, entry_major=True).T
        self._linear_map = (source, A)
        return A


# ---------------------------------------------------------------------------------------------
# The deformers

class ReducedRS:
    """Reduced RS deformer z (m,) -> q (rB,) -> u = B q (SPEC section 4).

    Choice (beyond SPEC 4): the linear part of the RS map is integrated exactly and only the
    nonlinear remainder by cubature,

        q(z) = A z + sum_C w_e P_e vec(b_e(y_e) - [omega_e]x - eps_e),

    with A (rB, m) = ``ReducedProjection.linear_map`` the exact all-tet fit of the linear
    targets. Small poses and the Jacobian at rest are therefore exact (q = z on the modes'
    coordinates), and the cubature spends its tets on the rotation nonlinearity. Evaluated
    as q = A z + (w P) vec(r) with r = b - [omega]x - eps the remainder (``remainder_entries``).

    Attributes:
      num_coords           m, number of modal coordinates z.
      basis                B (3N, rB) [m per unit q] (may be None when loaded without it).
      basis_size           rB.
      cubature_tets        (C,) int64 tet indices.
      cubature_weights     (C,) float64, >= 0.
      projections          P_C (C, rB, 9) for the cubature tets only.
      modal_rs_cubature    (C, 9, m) linear RS of the modes on the cubature tets.
      linear_map           A (rB, m).
      weighted_projections (w P) (rB, 9C): w_e P_e, entry-major (column k C + e is entry k
                           of tet e's 9), in dtype.
      dtype                of the (w P) products: float64, or what ``astype`` gave.

    ``exact_q`` (the all-tet fit) needs the full mesh: it works on objects made by ``build``
    (which keeps a ``ReducedProjection`` and the full modal_rs by reference), or after
    ``attach_full``; a deformer loaded by ``from_arrays`` alone is evaluation-only.
    """

    def __init__(self, basis, cubature_tets, cubature_weights, projections, modal_rs_cubature,
                 linear_map, projection=None, modal_rs=None, dtype=np.float64):
        self.basis = None if basis is None else np.asarray(basis, dtype=np.float64)
        self.cubature_tets = np.asarray(cubature_tets, dtype=np.int64).reshape(-1)
        self.cubature_weights = np.asarray(cubature_weights, dtype=np.float64).reshape(-1)
        self.projections = np.asarray(projections, dtype=np.float64)
        self.modal_rs_cubature = np.ascontiguousarray(modal_rs_cubature, dtype=np.float64)
        self.linear_map = np.asarray(linear_map, dtype=np.float64)
        self.num_coords = self.modal_rs_cubature.shape[2]
        self.basis_size = self.projections.shape[1]
        m = self.num_coords
        # Weighted projections flattened to (rB, 9C), entry-major (column k C + e: entry k of
        # tet e, the layout of ``_rs_map``): q = A z + wP @ vec(r) over all cubature tets is one
        # matrix-vector product, and the Jacobian one matrix-matrix product. They act on the
        # remainder r alone, so in float32 (``astype``) their rounding is relative to the
        # nonlinear part: small poses and the Jacobian at rest stay exact.
        self.dtype = np.dtype(dtype)
        C = len(self.cubature_tets)
        self.weighted_projections = np.ascontiguousarray(
            (self.cubature_weights[:, None, None] * self.projections)
            .transpose(1, 2, 0).reshape(self.basis_size, -1), dtype=self.dtype)
        # dy/dz at the cubature tets, entry-major (9C, m): y = rows @ z for all of them at once.
        self._modal_rs_rows = np.ascontiguousarray(
            self.modal_rs_cubature.transpose(1, 0, 2)).reshape(9 * C, m)
        self._projection, self._modal_rs = projection, modal_rs
        self._kept_q = self._kept_jacobian = self._kept_map = None

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
                   modal_rs[tets], projection.linear_map(modal_rs), projection=projection,
                   modal_rs=modal_rs)

    def astype(self, dtype):
        """This deformer with its cubature products (the (rB, 9C) weighted projections) in
        dtype: float32 halves the memory they read per evaluation and runs the products about
        twice as fast (the dynamics' steps); q's rounding is then about 1e-7 of its nonlinear
        part, too coarse for finite differences. Shares every other array."""
        if np.dtype(dtype) == self.dtype:
            return self
        return ReducedRS(self.basis, self.cubature_tets, self.cubature_weights, self.projections,
                         self.modal_rs_cubature, self.linear_map, self._projection,
                         self._modal_rs, dtype)

    def for_mode_scale(self, factor):
        """This deformer for the modes W times ``factor`` > 0 (the modes of a uniform density
        rho are those at 1 kg/m^3 times 1 / sqrt(rho), ``modes.LinearModes.for_material``).
        The same displacement W z' factor = W z is the pose z = factor z', so q'(z') =
        q(factor z'): the cubature tets' RS coordinates per unit z and A are scaled; B, the
        cubature and the projections are the same arrays. Evaluation-only (as ``from_arrays``:
        a scaled copy of the full mesh's modal RS would cost as much as the body's own)."""
        factor = float(factor)
        if factor == 1.0:
            return self
        return ReducedRS(self.basis, self.cubature_tets, self.cubature_weights, self.projections,
                         self.modal_rs_cubature * factor, self.linear_map * factor,
                         dtype=self.dtype)

    def attach_full(self, X, T, modal_rs, recon):
        """Give a loaded deformer the full-mesh data ``exact_q`` needs (requires ``basis``)."""
        self._projection = ReducedProjection(X, T, self.basis, recon)
        self._modal_rs = np.asarray(modal_rs, dtype=np.float64)

    # -- evaluation ---------------------------------------------------------------------------

    def q(self, z):
        """Reduced coordinates q (rB,) of modal coordinates z (m,) (class docstring).

        The last pose's q and dq/dz are kept (``_kept``): a simulation's potentials (the
        reconstruction barrier, a rig's springs) ask for them at the pose its Newton iteration
        has just evaluated, with the same deformer (``dynamics.step_deformer``); so is its RS
        map, for ``q_gradient`` there."""
        z = np.asarray(z, dtype=np.float64)
        return self._kept("_kept_q", z, lambda: self._q_keeping_map(z))

    def _q_keeping_map(self, z):
        """q (rB,) of one pose z (m,) as ``q_batch`` computes it, keeping the RS map's R, J_l
        and F (9, C) there (``_kept_map``) for ``q_gradient``: the dynamics' Newton asks for
        the gradient at the pose whose q its line search has just accepted."""
        Z = z[None]
        remainders, R, J_l, F = _rs_map(self._rs_coordinates(Z), True, remainder=True)
        self._kept_map = (z.copy(), R, J_l, F)
        return ((self.weighted_projections @ self._lowered(remainders.reshape(-1, 1))).T
                + Z @ self.linear_map.T)[0]

    def q_jacobian(self, z):
        """dq/dz (rB, m) = A + sum_C w_e P_e (dr/dy)_e (QW)_e (analytic, SPEC section 4)."""
        z = np.asarray(z, dtype=np.float64)
        return self._kept("_kept_jacobian", z, lambda: self.q_jacobian_batch(z[None])[0])

    def _kept(self, name, z, evaluate):
        """evaluate() at pose z, or a copy of what was kept for z under ``name``. One
        (pose, value) tuple, replaced whole: a reader never pairs one pose with another's."""
        kept = getattr(self, name)
        if kept is not None and np.array_equal(kept[0], z):
            return kept[1].copy()
        value = evaluate()
        setattr(self, name, (z.copy(), value.copy()))
        return value

    def q_gradient(self, z, g):
        """(dq/dz)^T g (m,) for g (rB,) without forming dq/dz: g goes back through the
        cubature (9C,) and each tet's RS-map derivative. O(rB C + C m), a fraction of
        ``q_jacobian``'s O(rB C m) (the dynamics' Newton iterations after the first)."""
        C, z = len(self.cubature_tets), np.asarray(z, dtype=np.float64)
        kept = self._kept_map
        if kept is not None and np.array_equal(kept[0], z):
            _, R, J_l, F = kept
        else:
            _, R, J_l, F = _rs_map(self._rs_coordinates(z[None]), True)           # (9, C)
        g = np.asarray(g, dtype=np.float64)
        lam = (self._lowered(g) @ self.weighted_projections).astype(np.float64, copy=False)
        lam = lam.reshape(9, C)                                 # dE/d vec(r), entry-major
        # <lam, [u]x F> = u . vee(lam F^T - F lam^T): the rotation part through J_l
        M = np.einsum("ikc,jkc->ijc", lam.reshape(3, 3, C), F.reshape(3, 3, C)).reshape(9, C)
        vee = M[[7, 2, 3]] - M[[5, 6, 1]]
        g_omega = np.einsum("kic,kc->ic", J_l.reshape(3, 3, C), vee)
        # <lam, R E_k> = <R^T lam, E_k>: the strain part
        RtL = np.einsum("jic,jkc->ikc", R.reshape(3, 3, C), lam.reshape(3, 3, C)).reshape(9, C)
        g_eps = RtL[_STRAIN_UPPER] + RtL[_STRAIN_LOWER]
        g_eps[_STRAIN_DIAGONAL] *= 0.5
        g_y = np.concatenate([g_omega, g_eps]) - LINEAR_TARGET.T @ lam     # d r/dy, not db/dy
        return g @ self.linear_map + g_y.reshape(-1) @ self._modal_rs_rows

    def q_batch(self, Z, chunk=256):
        """q for many frames: Z (F, m) -> (F, rB); frames are processed ``chunk`` at a time."""
        Z = np.atleast_2d(np.asarray(Z, dtype=np.float64))
        out = np.empty((len(Z), self.basis_size))
        for start in range(0, len(Z), chunk):                       # bounds temporary memory
            Zc = Z[start:start + chunk]
            remainders = self._lowered(self._remainder_columns(Zc))
            out[start:start + chunk] = ((self.weighted_projections @ remainders).T
                                        + Zc @ self.linear_map.T)
        return out

    def q_jacobian_batch(self, Z, chunk=64):
        """dq/dz for many frames: Z (F, m) -> (F, rB, m)."""
        Z = np.atleast_2d(np.asarray(Z, dtype=np.float64))
        out = np.empty((len(Z), self.basis_size, self.num_coords))
        for start in range(0, len(Z), chunk):
            out[start:start + chunk] = self.weighted_projections @ self._lowered(
                self._chains(Z[start:start + chunk]))
        return out + self.linear_map

    def exact_q(self, z):
        """All-tet reduced fit (rB,) of z (m,), no cubature (training and tests).

        (B^T L B)^-1 B^T G^T V vec(b(QW z)) over every tet via the sparse gradient operator.
        Also accepts Z (F, m) and returns (F, rB).
        """
        if self._projection is None:
            raise RuntimeError("exact_q needs the full mesh: use ReducedRS.build or attach_full")
        Z = np.asarray(z, dtype=np.float64)
        targets = rs.rs_target(modal_rs_poses(self._modal_rs, Z.reshape(-1, Z.shape[-1])))
        return self._projection.exact_q(targets.reshape(Z.shape[:-1] + (-1, 3, 3)))

    def displacement(self, z, rows=None):
        """Displacement of z (m,): (N, 3) = B q [m], or ``rows @ q`` reshaped (k, 3).

        rows: optional (3k, rB) rows of a linear map of B, e.g. (Phi B) for render vertices or
        B restricted to some vertices (``basis_rows``). The caller precomputes it once: this
        is what makes partial reconstruction cost O(k rB) instead of O(N rB). For a few
        vertices evaluated many times, ``row_evaluator`` is faster still.
        """
        return _apply_rows(self.basis if rows is None else rows, self.q(z))

    def displacement_jacobian(self, z, rows):
        """d u_rows / dz (3k, m) = rows @ dq/dz for precomputed rows (3k, rB)."""
        return np.asarray(rows) @ self.q_jacobian(z)

    def row_evaluator(self, rows):
        """``RowEvaluator`` for fixed rows (3k, rB): the fastest path for a few vertices."""
        return RowEvaluator(self, rows)

    def _rs_coordinates(self, Z):
        """y (9, C F) at the cubature tets of poses Z (F, m), entry-major, column e F + t."""
        return (self._modal_rs_rows @ Z.T).reshape(9, -1)

    def _remainder_columns(self, Z):
        """vec r (9C, F), entry-major, the remainders of poses Z (F, m) at the cubature tets."""
        return fast_remainders(self._rs_coordinates(Z)).reshape(-1, len(Z))

    def _chains(self, Z):
        """(dr/dy)(dy/dz) (F, 9C, m) at the cubature tets for poses Z (F, m)."""
        return self._remainders_and_chains(Z)[1]

    def _remainders_and_chains(self, Z):
        """vec r (9C, F) and (dr/dy)(dy/dz) (F, 9C, m), from one evaluation of the RS map."""
        y = self._rs_coordinates(Z)
        remainders, R, J_l, F = _rs_map(y, True, remainder=True)
        return (remainders.reshape(-1, len(Z)),
                self._remainder_chains(R, J_l, F, len(Z)))

    def _remainder_chains(self, R, J_l, F, num_poses, out=None):
        """(dr/dy)(dy/dz) (P, 9C, m) from ``_rs_map``'s vec R, J_l and F (9, C P) of P =
        num_poses poses (column e P + t): per tet and pose the 9 x 9 derivative of the
        remainder (``_target_derivatives`` - LINEAR_TARGET) times the tet's dy/dz (9, m), one
        stacked matrix product. out: a (9, C, m) array or view to write a single pose's
        chains into (the fused product's columns), else they come in a new array."""
        C, m = len(self.cubature_tets), self.num_coords
        derivatives = _target_derivatives(R, J_l, F)
        derivatives -= LINEAR_TARGET[:, :, None]
        by_tet = np.ascontiguousarray(derivatives.transpose(2, 0, 1))           # (C P, 9, 9)
        if out is not None:
            return np.matmul(by_tet, self.modal_rs_cubature, out=out.transpose(1, 0, 2))
        chain = np.matmul(by_tet.reshape(C, num_poses, 9, 9), self.modal_rs_cubature[:, None])
        return chain.transpose(1, 2, 0, 3).reshape(num_poses, 9 * C, m)

    def q_batch_and_jacobian(self, Z, at):
        """q (F, rB) of poses Z (F, m) and dq/dz (rB, m) at pose Z[at], from one evaluation of
        the RS map and one product with the weighted projections (they are read once for
        both; the dynamics' first Newton iterate is one of the poses its integrator
        evaluates)."""
        Z = np.atleast_2d(np.asarray(Z, dtype=np.float64))
        F, C = len(Z), len(self.cubature_tets)
        y = self._rs_coordinates(Z)
        remainders, R, J_l, gradients = _rs_map(y, True, remainder=True)
        columns = np.empty((9 * C, F + self.num_coords), dtype=self.dtype)
        columns[:, :F] = remainders.reshape(-1, F)
        at_pose = (part.reshape(9, C, F)[:, :, at] for part in (R, J_l, gradients))  # (9, C)
        self._remainder_chains(*at_pose, 1, out=columns[:, F:].reshape(9, C, self.num_coords))
        product = self.weighted_projections @ columns
        Q, J = product[:, :F].T + Z @ self.linear_map.T, product[:, F:] + self.linear_map
        self._kept_q, self._kept_jacobian = (Z[at].copy(), Q[at].copy()), (Z[at].copy(), J.copy())
        return Q, J

    def _lowered(self, values):
        """values in this deformer's dtype (no copy in float64)."""
        return values.astype(self.dtype, copy=False)

    # -- cache --------------------------------------------------------------------------------

    def to_arrays(self, include_basis=True):
        """dict of numpy arrays for ``cache.save``; B is optional (it is 3N x rB)."""
        arrays = dict(cubature_tets=self.cubature_tets, cubature_weights=self.cubature_weights,
                      projections=self.projections, modal_rs_cubature=self.modal_rs_cubature,
                      linear_map=self.linear_map)
        if include_basis and self.basis is not None:
            arrays["basis"] = self.basis
        return arrays

    @classmethod
    def from_arrays(cls, arrays):
        """Inverse of ``to_arrays`` (an evaluation-only deformer, see the class docstring)."""
        return cls(arrays.get("basis"), arrays["cubature_tets"], arrays["cubature_weights"],
                   arrays["projections"], arrays["modal_rs_cubature"], arrays["linear_map"])


class LinearDeformer:
    """Linear modal motion with the ReducedRS interface: q(z) = z, dq/dz = I, B = W.

    num_coords: m; basis: optional W (3N, m) for ``displacement`` without rows. The baseline
    that reduced RS is compared with (it inflates large bends instead of curling them).
    """

    def __init__(self, num_coords, basis=None):
        self.num_coords = int(num_coords)
        self.basis = None if basis is None else np.asarray(basis, dtype=np.float64)
        self.basis_size = self.num_coords

    def q(self, z):
        """q = z (m,)."""
        return np.array(z, dtype=np.float64).reshape(self.num_coords)

    def q_jacobian(self, z):
        """dq/dz = I (m, m)."""
        return np.eye(self.num_coords)

    def q_batch(self, Z):
        """Q = Z (F, m)."""
        return np.array(np.atleast_2d(Z), dtype=np.float64)

    def q_jacobian_batch(self, Z):
        """(F, m, m) identities."""
        return np.broadcast_to(np.eye(self.num_coords),
                               (len(np.atleast_2d(Z)), self.num_coords, self.num_coords)).copy()

    def exact_q(self, z):
        """Same as ``q`` (or ``q_batch`` for Z (F, m)): nothing is approximated."""
        return self.q(z) if np.ndim(z) == 1 else self.q_batch(z)

    def displacement(self, z, rows=None):
        """W z as (N, 3), or rows @ z as (k, 3) for rows (3k, m) [m]."""
        return _apply_rows(self.basis if rows is None else rows, self.q(z))

    def displacement_jacobian(self, z, rows):
        """d u_rows / dz = rows (3k, m), whatever z."""
        return np.array(rows, dtype=np.float64)

    def row_evaluator(self, rows):
        """``RowEvaluator`` for fixed rows (3k, m)."""
        return RowEvaluator(self, rows)

    def to_arrays(self, include_basis=True):
        """dict of numpy arrays for ``cache.save``."""
        arrays = dict(num_coords=np.array(self.num_coords))
        if include_basis and self.basis is not None:
            arrays["basis"] = self.basis
        return arrays

    @classmethod
    def from_arrays(cls, arrays):
        """Inverse of ``to_arrays``."""
        return cls(int(arrays["num_coords"]), arrays.get("basis"))


class RowEvaluator:
    """Partial reconstruction u_J (k, 3) and d u_J / dz (3k, m) for fixed rows (3k, rB).

    rows: e.g. ``basis_rows(B, J)`` or (Phi B) restricted to some render vertices. When
    3k < rB the rows are folded into the weighted projections once, R = rows (w P) (3k, 9C),
    so an evaluation is u_J = R vec(r) + (rows A) z and d u_J/dz = R (dr/dy)(QW) + rows A,
    never forming q; otherwise it goes through q (rB,) and dq/dz. Batch methods take
    Z (F, m).
    """

    def __init__(self, deformer, rows):
        self.deformer = deformer
        self.rows = np.ascontiguousarray(rows, dtype=np.float64)
        self.fused = isinstance(deformer, ReducedRS) and len(self.rows) < deformer.basis_size
        if self.fused:
            self._folded = self.rows @ deformer.weighted_projections             # (3k, 9C)
            self._linear = self.rows @ deformer.linear_map                       # (3k, m)

    def displacement(self, z):
        """u_J (k, 3) [m] of z (m,)."""
        return self.displacement_batch(np.asarray(z, dtype=np.float64)[None])[0]

    def evaluate(self, z):
        """(u_J (k, 3), d vec(u_J)/dz (3k, m)) of z (m,), sharing the work of both."""
        u, J = self.evaluate_batch(np.asarray(z, dtype=np.float64)[None])
        return u[0], J[0]

    def evaluate_batch(self, Z):
        """(u_J (F, k, 3), d vec(u_J)/dz (F, 3k, m)) of Z (F, m)."""
        Z = np.atleast_2d(np.asarray(Z, dtype=np.float64))
        if not self.fused:
            return self.displacement_batch(Z), self.jacobian_batch(Z)
        remainders, chain = self.deformer._remainders_and_chains(Z)
        u = (self._folded @ remainders).T + Z @ self._linear.T
        return u.reshape(len(Z), -1, 3), self._folded @ chain + self._linear

    def jacobian(self, z):
        """d vec(u_J) / dz (3k, m) [m per unit z]."""
        return self.jacobian_batch(np.asarray(z, dtype=np.float64)[None])[0]

    def displacement_batch(self, Z):
        """u_J (F, k, 3) of Z (F, m)."""
        Z = np.atleast_2d(np.asarray(Z, dtype=np.float64))
        if self.fused:
            u = (self._folded @ self.deformer._remainder_columns(Z)).T + Z @ self._linear.T
        else:
            u = self.deformer.q_batch(Z) @ self.rows.T
        return u.reshape(len(Z), -1, 3)

    def jacobian_batch(self, Z):
        """d vec(u_J) / dz (F, 3k, m) of Z (F, m)."""
        Z = np.atleast_2d(np.asarray(Z, dtype=np.float64))
        if self.fused:
            return self._folded @ self.deformer._chains(Z) + self._linear
        return self.rows @ self.deformer.q_jacobian_batch(Z)


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


# ---------------------------------------------------------------------------------------------
# Reduced RS cubature

CANDIDATES = 1000   # random candidate tets scored per block of cubature picks


def train_reduced_rs_cubature(X, T, modal_rs, B, recon, poses, max_tets=150, tol=2e-3, rng=None,
                              candidates=None, projection=None, picks_per_block=None,
                              progress=None):
    """Cubature (tets, weights) for reduced RS, SPEC section 4, as ``ReducedRS`` uses it.

    ReducedRS integrates the linear part of the RS map exactly, so the cubature fits the
    nonlinear remainder r_e(y) = b_e(y) - [omega_e]x - eps_e:
    targets h_t = g_t - A z_t (g_t = exact all-tet q(z_t), A = ``linear_map``) and candidate
    columns a_e = [P_e vec(r_e(y_e(z_t)))]_t, both divided per pose by |g_t| so that poses of
    any size count alike relative to their full q.

    X (N, 3), T (E, 4): the tet mesh; modal_rs (E, 9, m); B (3N, rB) the basis; recon: the
    body's ``rs.PoissonReconstruction``; poses: Z (F, m) training modal coordinates (see
    ``cubature.training_poses``); projection: an existing ``ReducedProjection`` for B.
    Each block of picks draws ``candidates`` random tets (None: ``CANDIDATES``), scores
    them without their columns (``RemainderScreen``) and forms the columns of the best
    few only. tol: on |residual| / |target| of the normalised fit. picks_per_block: see
    ``cubature.greedy_nnls``; None takes max(1, max_tets // 16), so a large cubature
    (hundreds of tets, for a basis that grows with the mode count) does not score a fresh
    block at every pick (measured, 10k-tet bar, 20 modes, 288 tets: 16 picks from blocks of
    1,000 candidates fit as well as 4 from 400).
    progress(fraction, message): optional, see ``greedy_nnls``.

    Returns tets (C,) int64, weights (C,) > 0 and info dict: ``history`` (relative residual per
    pick), ``relative_residual`` (final), ``poses``, ``projection`` (the ReducedProjection).
    """
    Z = np.atleast_2d(np.asarray(poses, dtype=np.float64))
    modal_rs = np.asarray(modal_rs, dtype=np.float64)
    if projection is None:
        projection = ReducedProjection(X, T, B, recon)
    if progress is not None:
        progress(0.0, "exact reduced fit of the training poses")
    candidates = CANDIDATES if candidates is None else int(candidates)
    picks_per_block = max(1, int(max_tets) // 16) if picks_per_block is None else picks_per_block
    # Every tet's screening factors up front when the blocks would draw about as many tets
    # as there are, each block's own otherwise (measured, the better one first: 10k-tet bar
    # 1.1 s against 1.5 s, 40k-tet bar 1.6 s against 2.3 s).
    draws = candidates * -(-int(max_tets) // max(int(picks_per_block), 1))
    screen, g = RemainderScreen.build(projection, modal_rs, Z, store=len(T) <= draws)
    scale = np.maximum(np.linalg.norm(g, axis=1), 1e-300)
    remainder = g - Z @ projection.linear_map(modal_rs).T
    target = (remainder / scale[:, None]).reshape(-1)                     # row = F-major (t, r)

    def columns(tets):
        return reduced_rs_columns(projection, modal_rs, Z, tets, scale)

    inner = None if progress is None else (lambda f, msg: progress(0.1 + 0.9 * f, msg))
    tets, weights, history = cubature.greedy_nnls(
        columns, target, tol=tol, max_picks=max_tets, candidates=candidates, rng=rng,
        num_columns=len(T), progress=inner, picks_per_block=picks_per_block, screen=screen)
    info = dict(history=history, relative_residual=history[-1], poses=Z, projection=projection)
    return tets, weights, info


class RemainderScreen:
    """Scores cubature candidates without forming their columns: the cosine of each tet's
    column with a residual, for ``cubature.greedy_nnls``'s ``screen``.

    A column is c_e = [P_e vec(r_e(t)) / s_t]_t (F rB,) with P_e = V_e (G_e B~)^T and
    B~ = B (B^T L B)^-1 (``ReducedProjection.solved_basis``). So for a residual x (F, rB),
    x_t . P_e r_e(t) = sum_a (B~ x_t)[node a] . Gamma_e[a, :, t] with the factors
    Gamma_e[a, i, t] = V_e sum_j grad_a[j] r_e(t)[i, j] / s_t (4, 3, F), and
    |c_e|^2 = sum_t Gamma_t^T (B~_e B~_e^T) Gamma_t with B~_e the tet's 12 rows of B~. A block
    of k candidates then costs one (3N, rB) x (rB, F) product and O(k F) once the factors are
    known, instead of O(k F rB 9) for its columns. ``build`` can compute every tet's factors
    with the exact fit of the training poses (one RS evaluation per tet and pose serves both);
    otherwise each block's are computed when it is scored. The factors and the inner products
    are float32: the scores only choose which columns are formed, and those are exact.

    projection: the ``ReducedProjection``; modal_rs (E, 9, m); Z (F, m) the training poses;
    scale (F,) the per-pose |g_t|.
    """

    def __init__(self, projection, modal_rs, Z, scale):
        self.projection, self.modal_rs, self.Z = projection, modal_rs, Z
        self.inverse_scale = 1.0 / np.asarray(scale, dtype=np.float64)
        self.solved_basis = projection.solved_basis.astype(np.float32)
        self.num_poses = len(Z)
        self._factors = self._norms = None      # every tet's (E, 12 F) float32 and (E,)

    @classmethod
    def build(cls, projection, modal_rs, Z, store=True, chunk=4):
        """(screen, g (F, rB)): the screen and the exact all-tet fits g_t of poses Z (F, m),
        ``chunk`` poses at a time on threads; with ``store``, every tet's factors with them
        (E x 12 F float32, twice that while they are laid out)."""
        n_tets, F = modal_rs.shape[0], len(Z)
        factors = np.empty((F, 4, 3, n_tets), dtype=np.float32) if store else None
        weighted = cls._weighted_gradients(projection, slice(None)).transpose(1, 2, 0)

        def fit(start):
            poses = modal_rs_poses(modal_rs, Z[start:start + chunk]).reshape(-1, n_tets, 9)
            remainders = [remainder_entries(y) for y in poses]                    # (3, 3, E)
            for offset, remainder in enumerate(remainders if store else ()):
                # Gamma[a, i] = sum_j grad_a[j] r[i, j] for every tet at once
                np.einsum("ajp,ijp->aip", weighted, remainder, out=factors[start + offset],
                          casting="same_kind")
            return projection.exact_q(remainders, entry_major=True)

        remainder = np.concatenate(threads.ordered_map(fit, range(0, F, chunk)), axis=0)
        g = remainder.reshape(F, -1) + Z @ projection.linear_map(modal_rs).T
        scale = np.maximum(np.linalg.norm(g, axis=1), 1e-300)
        screen = cls(projection, modal_rs, Z, scale)
        if store:
            screen._store(factors.reshape(F, 12, n_tets))
        return screen, g

    def _store(self, by_pose, step=256):
        """Keep every tet's factors, from their pose-major (F, 12, E) layout, and norms."""
        F, _, n_tets = by_pose.shape
        factors, norms = np.empty((n_tets, 12 * F), dtype=np.float32), np.empty(n_tets)
        inverse_scale = self.inverse_scale.astype(np.float32)[:, None, None]

        def part(rows):                  # tets-major, a cache-sized block of tets at a time
            for start in range(rows.start, rows.stop, step):
                block = slice(start, min(start + step, rows.stop))
                tet_major = (by_pose[:, :, block] * inverse_scale).transpose(2, 1, 0)
                factors[block] = tet_major.reshape(len(tet_major), -1)
                norms[block] = self._norms_of(np.arange(block.start, block.stop), tet_major)

        threads.ordered_map(part, threads.even_parts(n_tets))
        self._factors, self._norms = factors, norms

    def __call__(self, residual, tets):
        """Cosines (k,) of the columns of ``tets`` (k,) with a residual (F rB,), F-major."""
        tets = np.asarray(tets, dtype=np.int64)
        x = np.asarray(residual, dtype=np.float32).reshape(self.num_poses, -1)
        nodal = (self.solved_basis @ x.T).reshape(self.projection.num_nodes, -1)   # (N, 3F)
        scores = np.empty(len(tets))

        def part(rows):
            factors, norms = self.factors(tets[rows])
            gathered = nodal[self.projection.T[tets[rows]]].reshape(len(norms), -1)
            scores[rows] = np.einsum("pk,pk->p", gathered, factors) / norms

        threads.ordered_map(part, threads.even_parts(len(tets)))
        return scores

    def factors(self, tets):
        """Gamma (k, 12 F) float32, (a, i, t) per row, and |c_e| (k,) of tets (k,)."""
        if self._factors is not None:
            return self._factors[tets], self._norms[tets]
        k, F = len(tets), self.num_poses
        y = rs.warp_pose_block(self.modal_rs[tets], self.Z).transpose(0, 2, 1).reshape(-1, 9)
        remainder = remainder_entries(y).reshape(3, 3, k, F) * self.inverse_scale  # r_e(t) / s_t
        factors = np.einsum("paj,ijpt->pait", self._weighted_gradients(self.projection, tets),
                            remainder).reshape(k, 12, F)
        return factors.reshape(k, -1).astype(np.float32), self._norms_of(tets, factors)

    def _norms_of(self, tets, factors):
        """|c_e| (k,) from factors (k, 12, F) and each tet's 12 x 12 Gram of B~ rows. In
        float64: the rows of a tet nearly cancel (its gradients sum to zero)."""
        nodes = self.projection.solved_basis.reshape(self.projection.num_nodes, 3, -1)
        nodes = nodes[self.projection.T[tets]].reshape(len(factors), 12, -1)         # B~_e
        factors = np.asarray(factors, dtype=np.float64)
        gram = nodes @ nodes.transpose(0, 2, 1)                                   # (k, 12, 12)
        return np.maximum(np.sqrt(np.einsum("kat,kat->k", gram @ factors, factors)), 1e-300)

    @staticmethod
    def _weighted_gradients(projection, tets):
        """V_e grad_a (k, 4, 3) of tets (k,) or a slice."""
        return projection.shape_gradients[tets] * projection.recon.volumes[tets][:, None, None]


def remainder_entries(y):
    """The nonlinear remainder b(y) - [omega]x - eps (3, 3, n), entry-major, of RS coordinates
    y (n, 9): what the cubature integrates (``ReducedRS``)."""
    return rs.rs_target_entries(y) - (LINEAR_TARGET @ y.T).reshape(3, 3, -1)


def modal_rs_poses(modal_rs, Z, out=None):
    """RS coordinates (F E, 9), pose-major (each pose's (E, 9) block contiguous), of poses
    Z (F, m) with modal_rs (E, 9, m): one BLAS product, Z (QW)^T. out: optional C-contiguous
    (F, 9 E) array to write into (a reused buffer spares the page faults of a fresh one)."""
    Z = np.atleast_2d(np.asarray(Z, dtype=np.float64))
    modal_rs = np.asarray(modal_rs)
    product = np.matmul(Z, modal_rs.reshape(-1, modal_rs.shape[2]).T, out=out)
    return product.reshape(-1, 9)


def reduced_rs_columns(projection, modal_rs, Z, tets, scale, out=None):
    """Greedy-NNLS columns (F rB, k) of tets (k,): [P_e vec(r_e(y_e(z_t))) / scale_t]_t.

    Column-major, so each column is contiguous; the tets are split over several threads
    (``threads.ordered_map``), each writing its own columns in place. out: optional
    column-major (F rB, k) array to fill (returned)."""
    tets = np.asarray(tets, dtype=np.int64)
    shape = (len(Z) * projection.basis_size, len(tets))
    if out is None:
        out = np.empty(shape, order="F")
    elif out.shape != shape or not out.flags.f_contiguous:
        raise ValueError(f"out must be a column-major {shape} array")
    threads.ordered_map(lambda part: _tet_columns(projection, modal_rs, Z, tets[part], scale,
                                                  out[:, part]), threads.even_parts(len(tets)))
    return out


def _tet_columns(projection, modal_rs, Z, tets, scale, out):
    """``reduced_rs_columns`` of ``tets`` (k,) on one thread, into out (F rB, k) column-major."""
    P = projection.tet_projections(tets)                                  # (k, rB, 9)
    y = rs.warp_pose_block(modal_rs[tets], Z)                             # (k, 9, F)
    r = fast_remainders(y.transpose(1, 0, 2).reshape(9, -1))              # (9, k F)
    r = r.reshape(9, len(tets), len(Z)).transpose(1, 2, 0)                # (k, F, 9)
    cols = out.T.reshape(len(tets), len(Z), -1)     # a view: out's columns are contiguous
    np.matmul(r, P.transpose(0, 2, 1), out=cols)                          # (k, F, rB)
    cols /= scale[None, :, None]


# ---------------------------------------------------------------------------------------------
# Everything at once

MEMORY_BUDGET = 256 * 2 ** 20   # bytes allowed for the basis B (3N x rB float64)
SMALL_BASIS_CAP = 160           # rB for small mode counts (pairs + snapshot directions)


def default_basis_size(num_modes, num_nodes=None, num_tets=None, memory_budget=MEMORY_BUDGET):
    """Default rB for m modes: the modes and all their m(m+1)/2 products, O(m^2) as in [P15].

    Small mode counts get the pairs plus as many snapshot directions, up to
    ``SMALL_BASIS_CAP`` = 160 (m = 10: 120, m = 14: 160); from m = 17 the pairs alone exceed
    that and the size is m + m(m+1)/2 (m = 20: 230, m = 40: 860), with no fixed cap. With
    ``num_nodes`` N it is bounded by the memory budget (B takes 24 N rB bytes: the default
    256 MiB allows rB = 11 M / N, e.g. 1100 columns at N = 10,000 nodes) and by the 3N DOFs
    (a basis cannot hold more independent columns). The cubature training's columns
    (poses x rB doubles each, 80 x rB x 8 bytes) are the other cost that grows with rB;
    evaluation cost depends on the cubature size, not on rB.
    With ``num_tets`` E it is also bounded by 3 E / 8: the cubature (``default_cubature_size``)
    picks about 1.25 rB of the E tets, and a basis near the mesh's own DOF count is fitted
    exactly but not by a cubature (measured: pinned bar, 648 tets, 40 modes, rB = 501 with
    150 tets left 14 % at a 180 deg bend; rB = 216 with 270 tets 1.05 %, rB = 240 with 300
    tets 0.67 %). The modes are always kept (rB >= m).
    """
    m = int(num_modes)
    size = max(min(m + m * (m + 1), SMALL_BASIS_CAP), m + m * (m + 1) // 2)
    if num_nodes is not None:
        size = min(size, max(m, int(memory_budget) // (24 * int(num_nodes))), 3 * int(num_nodes))
    if num_tets is not None:
        size = min(size, max(m, 3 * int(num_tets) // 8))
    return size


def default_cubature_size(basis_size, num_tets=None):
    """Default cubature tet count for a basis of rB columns: max(150, 1.25 rB), <= E.

    The fit has rB equations per pose; fewer tets than columns leave part of the reduced
    space unfitted (see ``default_basis_size`` for measurements). Training time grows about
    as rB x tets (tens of seconds at rB = 240 on a 648-tet bar).
    """
    size = max(150, int(round(1.25 * int(basis_size))))
    return size if num_tets is None else min(size, int(num_tets))


def prepare_reduced_rs(X, T, masses, W, eigenvalues, recon, modal_rs=None, max_size=None,
                       order=3, snapshot_size=None, num_snapshots=200, max_tets=None, tol=2e-3,
                       num_poses=80, candidates=None, seed=0, max_rotation=np.pi, progress=None):
    """Build a ``ReducedRS`` for modes W (3N, m): returns (deformer, info).

    Steps (progress fractions in brackets): training poses (``cubature.training_poses``, up
    to ``max_rotation``, default 180 deg [rad]: edits reach half turns, and off the training
    range the error grows fast: 40 modes, 180 deg bend, 120 deg training and rB = 160 left
    2.2 % of the diagonal); full RS snapshots of ``num_snapshots`` of them [0, 0.2]; the basis
    (``second_order_basis`` with snapshot enrichment, ``max_size`` columns) [0.2, 0.5]; the
    cubature on ``num_poses`` other poses (``train_reduced_rs_cubature``) [0.5, 1].
    max_size None: ``default_basis_size`` (O(m^2), memory and mesh bounded); max_tets None:
    ``default_cubature_size(max_size)``; candidates: see ``train_reduced_rs_cubature``. The figures
    below predate the O(m^2) rule. Measured
    on a pinned 4:1:1 bar with 20 modes and held-out poses up to 90 deg (strain <= 100 %):
    rB = 120 leaves up to about 1 % of the
    bounding-box diagonal, rB = 160 about 0.75 %; 150 cubature tets add little to that (60
    tets: about 2 %). With 10 modes rB = 120 is plenty (0.3 % before cubature), and a larger
    basis only needs more cubature tets. Evaluating a few vertices costs the same whatever
    rB; it grows with the cubature size.
    masses (N,) [kg]; eigenvalues (m,) [rad^2/s^2]; recon: the body's PoissonReconstruction;
    modal_rs (E, 9, m) default ``rs.linear_rs(rs.rs_operator(X, T), W)``; seed: for the poses
    and the candidate draws (same inputs give the same result).
    progress(fraction, message): optional; raising inside it aborts the whole preparation.
    info: ``seconds`` per stage, ``history``/``relative_residual`` of the cubature fit, and the
    training poses ``snapshot_poses``, ``cubature_poses``.
    """
    if modal_rs is None:
        modal_rs = rs.linear_rs(rs.rs_operator(X, T), W)
    rng = np.random.default_rng(seed)
    num_modes = modal_rs.shape[2]
    if max_size is None:
        max_size = default_basis_size(num_modes, num_nodes=len(X), num_tets=len(T))
    if max_tets is None:
        max_tets = default_cubature_size(max_size, num_tets=len(T))

    def stage(lo, hi):
        return None if progress is None else (lambda f, msg: progress(lo + (hi - lo) * f, msg))

    seconds = {}
    start = time.perf_counter()
    snapshot_poses = cubature.training_poses(num_modes, eigenvalues, num_snapshots, rng,
                                             max_rotation=max_rotation, modal_rs=modal_rs)
    snapshots = rs_snapshots(modal_rs, recon, snapshot_poses, stage(0.0, 0.2))
    seconds["snapshots"] = time.perf_counter() - start
    start = time.perf_counter()
    B = second_order_basis(X, T, masses, modal_rs, recon, W, max_size=max_size, order=order,
                           snapshots=snapshots, snapshot_size=snapshot_size,
                           progress=stage(0.2, 0.5))
    del snapshots
    seconds["basis"] = time.perf_counter() - start
    start = time.perf_counter()
    poses = cubature.training_poses(num_modes, eigenvalues, num_poses, rng,
                                    max_rotation=max_rotation, modal_rs=modal_rs)
    tets, weights, fit = train_reduced_rs_cubature(
        X, T, modal_rs, B, recon, poses, max_tets=max_tets, tol=tol, rng=rng,
        candidates=candidates, progress=stage(0.5, 1.0))
    deformer = ReducedRS.build(X, T, modal_rs, B, recon, tets, weights,
                               projection=fit["projection"])
    seconds["cubature"] = time.perf_counter() - start
    info = dict(seconds=seconds, history=fit["history"],
                relative_residual=fit["relative_residual"], snapshot_poses=snapshot_poses,
                cubature_poses=poses)
    return deformer, info
