"""Cubature training for reduced RS: SPEC.md section 4 (An, Kim & James 2008).

A cubature replaces a sum over all E tets by a weighted sum over a few, chosen so that it
reproduces the full sum on training poses. ``greedy_nnls`` is the generic greedy non-negative
least-squares selection (usable for any per-element quantity, e.g. energy cubature);
``reduced.train_reduced_rs_cubature`` applies it to the reduced RS fit
q(z) = sum_e P_e vec(b_e(y_e)); ``training_poses`` gives the poses every cubature is trained
on. This module depends on ``rs`` only, and ``reduced`` builds on it.

Choices written down here:

- Every weight re-fit is on all poses, kept cheap by a QR reduction: with the
  picked columns A_S = Q R (maintained incrementally, one Gram-Schmidt step per pick),
  |A_S w - b|^2 = |R w - Q^T b|^2 + const, so ``scipy.optimize.nnls(R, Q^T b)`` (k x k) has the
  same minimiser as the tall problem (n x k, n = poses x rB). Hence no pose subsets are needed,
  and the residual never increases from one pick to the next (the old weights stay feasible).
- Candidates: each pick scores a fresh random subset of the unpicked elements by the cosine
  between their column and the residual (only positive correlations can help with w >= 0).
- Picks whose NNLS weight ends at 0 are dropped from the returned cubature.
"""

import numpy as np
import scipy.linalg
from scipy.optimize import nnls

from . import rs, threads

DEG = np.pi / 180.0


# ---------------------------------------------------------------------------------------------
# Training poses

def training_poses(num_modes, eigenvalues, count, rng, max_rotation=120.0 * DEG, modal_rs=None,
                   max_strain=1.0, single_fraction=1.0 / 3.0, min_rotation_fraction=0.05):
    """Random modal coordinates Z (count, m) for training, with large rotations.

    Each pose gets a target angle theta ~ U(min_rotation_fraction, 1) * max_rotation [rad]
    (default up to 120 deg, beyond the 90 deg users typically reach) and is scaled so that
    its largest per-tet rotation max_e |omega_e(z)| equals theta, unless its largest strain
    max_e |eps_e(z)|_F would then pass ``max_strain`` (default 100 %): the pose stops there.
    Without the cap, strain-dominated modes (axial stretch, whose rotations are tiny) would be
    driven to 200 % strain and more, far outside what the body will do. This needs
    ``modal_rs`` (E, 9, m); without it z is taken to be in radians (max |omega| per unit
    z_i = 1), scaling uses the bound sum_i |z_i| and strain is not capped.

    - The first ``single_fraction`` of the poses are single-mode, cycling through the modes
      with random signs, so every mode is trained up to large rotations on its own.
    - The others mix a random subset of 2..m modes with Gaussian coefficients in rotation
      units, weighted by (lambda_1 / lambda_i)^(1/4): low modes dominate natural motion, yet
      high ones still appear. eigenvalues (m,) [rad^2/s^2]; None weights all modes equally.
    rng: ``np.random.Generator``.
    """
    m = int(num_modes)
    count = int(count)
    modal_rs = None if modal_rs is None else np.asarray(modal_rs)[:, :, :m]
    per_unit = np.ones(m) if modal_rs is None else rs.max_mode_rotations(modal_rs)
    per_unit = np.maximum(per_unit, 1e-300)
    if eigenvalues is None:
        falloff = np.ones(m)
    else:
        ev = np.maximum(np.asarray(eigenvalues, dtype=np.float64)[:m], 1e-300)
        falloff = (ev[0] / ev) ** 0.25
    n_single = min(count, int(round(single_fraction * count)))
    Z = np.zeros((count, m))
    modes = np.arange(n_single) % m
    Z[np.arange(n_single), modes] = rng.choice([-1.0, 1.0], n_single) / per_unit[modes]
    for t in range(n_single, count):                                  # one draw per pose
        active = rng.choice(m, size=rng.integers(2, m + 1) if m > 1 else 1, replace=False)
        Z[t, active] = rng.normal(size=len(active)) * falloff[active] / per_unit[active]
    theta = rng.uniform(min_rotation_fraction, 1.0, count) * max_rotation
    if modal_rs is None:
        return Z * (theta / np.maximum(np.abs(Z).sum(axis=1), 1e-300))[:, None]
    rotation, strain = pose_extremes(modal_rs, Z)
    factor = np.minimum(theta / rotation, max_strain / strain)
    return Z * factor[:, None]


def pose_extremes(modal_rs, Z, chunk=16):
    """Largest rotation max_e |omega_e(z)| [rad] and strain max_e |eps_e(z)|_F per pose (F,).

    modal_rs (E, 9, m), Z (F, m); ``chunk`` poses at a time bounds memory (E x 9 x chunk per
    thread; the chunks run on several threads, ``threads.ordered_map``).
    """
    Z = np.atleast_2d(Z)
    # |eps|_F^2 counts the off-diagonal entries (layout xx, xy, xz, yy, yz, zz) twice.
    weights = np.array([1.0, 2.0, 2.0, 1.0, 2.0, 1.0])

    def extremes(start):                 # squared norms, maximised, then one sqrt per pose
        y = rs.warp_pose_block(modal_rs, Z[start:start + chunk])          # (E, 9, chunk)
        y *= y
        return (np.sqrt(y[:, :3].sum(axis=1).max(axis=0)),
                np.sqrt(np.einsum("k,ekf->ef", weights, y[:, 3:]).max(axis=0)))

    parts = threads.ordered_map(extremes, range(0, len(Z), chunk))
    rotation = np.concatenate([part[0] for part in parts]) if parts else np.empty(0)
    strain = np.concatenate([part[1] for part in parts]) if parts else np.empty(0)
    return np.maximum(rotation, 1e-300), np.maximum(strain, 1e-300)


# ---------------------------------------------------------------------------------------------
# Greedy NNLS

QR_DELETE_LIMIT = 16    # Givens deletion while the columns left out are under 1/16 of those kept
REORTHOGONALISE = 0.5 ** 0.5    # second Gram-Schmidt pass when a column keeps less of its norm


def greedy_nnls(columns, target, tol=1e-3, max_picks=200, candidates=None, rng=None,
                num_columns=None, refit_every=4, picks_per_block=1, progress=None):
    """Greedy sparse non-negative fit target ~ A[:, S] w, w >= 0 (An et al. 2008).

    columns: the matrix A (n, K), or a callable ``columns(indices) -> (n, len(indices))`` that
      computes only the requested columns (then ``num_columns`` = K is required). A block it
      returns is read only until the next call, so the callable may refill one buffer.
    target: (n,). tol: stop when |residual| / |target| <= tol. max_picks: at most this many.
    candidates: size of the random subset of unpicked columns scored per pick (None: all).
    rng: ``np.random.Generator`` (default seeded 0). progress: optional callable(fraction,
      message) called before each pick; an exception raised in it aborts and propagates.
    picks_per_block: picks taken from one computed block of candidate columns before a new
      random block is drawn (re-scored against the updated residual after each pick). Columns
      are the expensive part when they are computed on demand, so a large fit (hundreds of
      picks) takes several per block; 1 draws a fresh block for every pick.

    Each pick takes the candidate with the largest cosine to the residual, then re-fits the
    weights (module docstring): every ``refit_every`` picks by ``scipy.optimize.nnls`` on all
    columns; in between by unconstrained least squares on the columns with positive weight
    plus the new one, falling back to NNLS when that turns a weight negative. Either way the
    weights stay >= 0 and the residual cannot grow (the previous weights remain feasible).

    Returns (picked (k,) int64 indices with w > 0, weights (k,) > 0, history: list of relative
    residuals, the first for w = 0, then one per accepted pick; non-increasing).
    """
    target = np.asarray(target, dtype=np.float64).reshape(-1)
    if callable(columns):
        if num_columns is None:
            raise ValueError("num_columns is required when columns is a callable")
        get = columns
    else:
        matrix = np.asarray(columns, dtype=np.float64)
        num_columns = matrix.shape[1]

        def get(indices):
            return matrix[:, indices]
    rng = np.random.default_rng(0) if rng is None else rng
    fit = _IncrementalNNLS(target, min(int(max_picks), int(num_columns)))
    available = np.ones(int(num_columns), dtype=bool)
    history = [1.0]
    misses = 0
    while history[-1] > tol and fit.size < fit.capacity and available.any():
        if progress is not None:
            progress(fit.size / fit.capacity, f"cubature pick {fit.size + 1}/{fit.capacity}, "
                                              f"residual {history[-1]:.2e}")
        pool = np.flatnonzero(available)
        if candidates is not None and len(pool) > candidates:
            pool = rng.choice(pool, size=int(candidates), replace=False)
        whole = len(pool) == available.sum()
        block = np.asarray(get(pool), dtype=np.float64)               # (n, |pool|)
        if _picks_from_block(fit, block, pool, available, picks_per_block, tol, refit_every,
                             history):
            misses = 0
            continue
        misses += 1                              # no candidate here can lower the residual
        if whole or misses >= 5:
            break
    keep = fit.weights > 0.0
    return fit.indices[keep], fit.weights[keep], history


def _picks_from_block(fit, block, pool, available, count, tol, refit_every, history):
    """Up to ``count`` greedy picks from one block (n, |pool|) of candidate columns, each the
    unpicked column with the largest cosine to the current residual; appends the relative
    residual after each accepted pick to ``history``. Returns whether anything was picked."""
    norms = np.maximum(np.sqrt(np.einsum("ij,ij->j", block, block)), 1e-300)
    picked = False
    for _ in range(max(int(count), 1)):
        score = (fit.residual @ block) / norms
        score[~available[pool]] = -np.inf
        best = int(np.argmax(score))
        if not score[best] > 0.0:
            break
        picked = True
        available[pool[best]] = False
        if fit.add(pool[best], block[:, best]):
            history.append(fit.refit(full=fit.size % max(int(refit_every), 1) == 0))
        if history[-1] <= tol or fit.size >= fit.capacity:
            break
    return picked


class _IncrementalNNLS:
    """NNLS over a growing column set, reduced to k x k through an incremental QR."""

    def __init__(self, target, capacity):
        n = len(target)
        self.target, self.capacity = target, capacity
        self.norm = max(float(np.linalg.norm(target)), 1e-300)
        # Column-major: the first k columns are one contiguous block for the BLAS products.
        self.A = np.empty((n, capacity), order="F")
        self.Q = np.empty((n, capacity), order="F")
        self.R = np.zeros((capacity, capacity))
        self.Qb = np.empty(capacity)
        self.size = 0
        self.indices = np.empty(0, dtype=np.int64)
        self.weights = np.empty(0)
        self.residual = target.copy()

    def add(self, index, column):
        """Append a column; False (and nothing appended) if it is numerically dependent."""
        k = self.size
        Q = self.Q[:, :k]
        r = Q.T @ column
        v = column - Q @ r
        length, rho = np.linalg.norm(column), np.linalg.norm(v)
        if rho < REORTHOGONALISE * length:      # cancellation: a second pass ("twice is enough")
            correction = Q.T @ v
            v -= Q @ correction
            r += correction
            rho = np.linalg.norm(v)
        if rho <= 1e-10 * length:
            return False
        self.A[:, k], self.Q[:, k] = column, v / rho
        self.R[:k, k], self.R[k, k] = r, rho
        self.Qb[k] = self.Q[:, k] @ self.target
        self.indices = np.append(self.indices, index)
        self.size += 1
        return True

    def refit(self, full=True):
        """Re-fit the weights (see ``greedy_nnls``); returns the relative residual."""
        k = self.size
        R, Qb = self.R[:k, :k], self.Qb[:k]
        weights = None
        if not full:
            weights = np.zeros(k)
            passive = np.append(np.flatnonzero(self.weights > 0.0), k - 1)
            if len(passive) == k:                # all columns: R is square upper triangular
                weights = scipy.linalg.solve_triangular(R, Qb)
            else:
                weights[passive] = _passive_least_squares(R, Qb, passive)
            if np.any(weights[passive] <= 0.0):
                weights = None
        if weights is None:
            weights, _ = nnls(R, Qb, maxiter=max(50, 30 * k))
        self.weights = weights
        self.residual = self.target - self.A[:, :k] @ self.weights
        return float(np.linalg.norm(self.residual)) / self.norm


def _passive_least_squares(R, b, passive):
    """argmin |R[:, passive] x - b| for R (k, k) upper triangular of full rank, passive (p,)
    sorted column indices. With few columns left out, the QR of R[:, passive] is R with those
    columns deleted by Givens rotations (``scipy.linalg.qr_delete``, O(k^2) per column);
    otherwise a Householder QR of R[:, passive] (O(k p^2))."""
    k, p = R.shape[1], len(passive)
    dropped = np.setdiff1d(np.arange(k), passive)
    if QR_DELETE_LIMIT * len(dropped) > p:
        Q, Rp = scipy.linalg.qr(R[:, passive], mode="economic")
        return scipy.linalg.solve_triangular(Rp, Q.T @ b)
    Q, Rp = np.eye(k), np.array(R, dtype=np.float64)
    for column in dropped[::-1]:                 # from the right: indices stay valid
        Q, Rp = scipy.linalg.qr_delete(Q, Rp, int(column), 1, which="col", overwrite_qr=True,
                                       check_finite=False)
    return scipy.linalg.solve_triangular(Rp[:p], (Q.T @ b)[:p])
