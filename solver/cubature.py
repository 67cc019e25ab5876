"""Cubature training for reduced RS: SPEC.md section 4 (An, Kim & James 2008).

A cubature replaces a sum over all E tets by a weighted sum over a few, chosen so that it
reproduces the full sum on training poses. ``greedy_nnls`` is the generic greedy non-negative
least-squares selection (usable for any per-element quantity, e.g. energy cubature);
``reduced.train_reduced_rs_cubature`` applies it to the reduced RS fit
q(z) = sum_e P_e vec(b_e(y_e)); ``training_poses`` gives the poses every cubature is trained
on. This module depends on ``rs`` only, and ``reduced`` builds on it.

Choices written down here:

- Every weight re-fit is on all poses, kept cheap by a k x k reduction: with the picked
  columns A_S and R^T R = A_S^T A_S (grown by one Cholesky column per pick), Qb = R^-T A_S^T b,
  |A_S w - b|^2 = |R w - Qb|^2 + |b|^2 - |Qb|^2, so the NNLS of (R, Qb) (k x k) has the same
  minimiser as the tall problem (n x k, n = poses x rB). Hence no pose subsets are needed, and
  the residual never increases from one pick to the next (the old weights stay feasible).
- Re-fits are Lawson and Hanson's active-set NNLS, warm-started from the previous weights.
  Every EXACT_EVERY picks and at the end of every block it runs to its optimality test: R is
  square and non-singular (dependent picks are refused), so the NNLS minimiser is unique and
  this is the fit ``scipy.optimize.nnls`` finds; in between only the new pick joins the free
  weights. The QR of the free columns is kept from one re-fit to the next by Givens insertions
  and deletions (``_PassiveQR``), so a re-fit after one more pick costs O(k^2), not O(k^3):
  at 40 modes (k ~ 1,000 picks) fits from scratch took 50 of a 61 s training.
- The inner products a new column needs come from one BLAS-3 product per block of
  candidates, so the n x k picked columns are read twice per block, not several times per pick.
- Candidates: each block is a fresh random subset of the unpicked elements, scored by the
  cosine between their column and the residual (only positive correlations can help with
  w >= 0); the best few of them are kept for the block's picks. With a ``screen`` (the
  reduced RS cubature: ``reduced.RemainderScreen``; the energy cubature: ``StoredScreen``, a
  float32 copy of every column) the subset, or every unpicked element, is scored without
  forming its columns, and only those best few are formed.
- Picks whose NNLS weight ends at 0 are dropped from the returned cubature.
"""

import numpy as np
import scipy.linalg

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

SCREEN = 4      # candidates kept per pick after a block's first scoring
EXACT_EVERY = 8   # picks between re-fits to the NNLS optimum (and at the end of every block)
DEPENDENT = 1e-6   # a column whose part outside the picked ones is below this is dependent


def greedy_nnls(columns, target, tol=1e-3, max_picks=200, candidates=None, rng=None,
                num_columns=None, picks_per_block=1, progress=None, screen=None):
    """Greedy sparse non-negative fit target ~ A[:, S] w, w >= 0 (An et al. 2008).

    columns: the matrix A (n, K), or a callable ``columns(indices) -> (n, len(indices))`` that
      computes only the requested columns (then ``num_columns`` = K is required). A block it
      returns is read only until the next call, so the callable may refill one buffer.
    target: (n,). tol: stop when |residual| / |target| <= tol. max_picks: at most this many.
    candidates: size of the random subset of unpicked columns drawn per block (None: all).
    rng: ``np.random.Generator`` (default seeded 0). progress: optional callable(fraction,
      message) called before each block; an exception raised in it aborts and propagates.
    picks_per_block: picks taken from one computed block of candidate columns before a new
      random block is drawn. Columns are the expensive part when they are computed on demand,
      so a large fit (hundreds of picks) takes several per block; 1 draws a fresh block for
      every pick.
    screen: optional callable(residual (n,), indices (s,)) -> (s,) the cosines of those
      columns with the residual, computed without forming them (``reduced.RemainderScreen``):
      then only the SCREEN x picks_per_block best-scored candidates of a block are formed
      (their exact scores, computed from the formed columns, decide the picks).

    Each pick takes the candidate with the largest cosine to the residual (after the block's
    first pick, among the ``SCREEN`` x picks_per_block best of its first scoring, re-scored
    exactly in k-space: ``_picks_from_block``), then re-fits the weights, warm-started (module
    docstring); each block ends at the NNLS optimum of all picked columns. The weights stay
    >= 0 and the residual cannot grow (the previous weights remain feasible).
    The residual is recomputed on all n rows after each block.

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
        shortlist = SCREEN * max(int(picks_per_block), 1)
        if screen is not None and len(pool) > shortlist:     # form only the best-scored
            scores = np.nan_to_num(np.asarray(screen(fit.residual, pool)), nan=-np.inf)
            pool = pool[np.sort(np.argpartition(-scores, shortlist - 1)[:shortlist])]
        block = np.asarray(get(pool), dtype=np.float64)               # (n, |pool|)
        if _picks_from_block(fit, block, pool, available, picks_per_block, tol, history):
            misses = 0
            continue
        misses += 1                              # no candidate here can lower the residual
        if whole or misses >= 5:
            break
    keep = fit.weights > 0.0
    return fit.indices[keep], fit.weights[keep], history


def _picks_from_block(fit, block, pool, available, count, tol, history):
    """Up to ``count`` greedy picks from one block (n, |pool|) of candidate columns, each the
    unpicked column with the largest cosine to the current residual, followed by a re-fit;
    appends the relative residual after each accepted pick to ``history``. Returns whether
    anything was picked.

    The first pick scores the whole block against the residual; the later ones only the
    ``SCREEN`` x count best of that scoring, and in k-space: with their inner products with
    the picked columns, the target and each other (one BLAS-3 product per block),
    r^T c = b^T c - w^T (A^T c) is exact without touching the n rows again."""
    count = max(int(count), 1)
    norms = np.maximum(np.sqrt(np.einsum("ij,ij->j", block, block)), 1e-300)
    score = (fit.residual @ block) / norms
    score[~available[pool]] = -np.inf
    shortlist = np.arange(block.shape[1])
    if len(shortlist) > SCREEN * count:
        shortlist = np.sort(np.argpartition(-score, SCREEN * count)[:SCREEN * count])
    columns = block[:, shortlist]
    if not np.isfinite(score[shortlist]).any():
        return False
    cross, target_inner, gram = fit.inner_products(columns)
    norms = norms[shortlist]
    open_ = available[pool[shortlist]]
    picked = False
    for _ in range(count):
        score = np.where(open_, (target_inner - fit.weights @ cross) / norms, -np.inf)
        best = int(np.argmax(score))
        if not score[best] > 0.0:
            break
        picked, open_[best] = True, False
        available[pool[shortlist[best]]] = False
        if fit.add(pool[shortlist[best]], columns[:, best], cross[:, best],
                   target_inner[best], gram[best, best]):
            cross = np.vstack([cross, gram[best]])
            history.append(fit.refit(exact=fit.size % EXACT_EVERY == 0))
        if history[-1] <= tol or fit.size >= fit.capacity:
            break
    if picked and len(history) > 1:                  # the optimum, its residual on all n rows
        fit.refit(exact=True)
        history[-1] = fit.exact_residual()
    return picked


class StoredScreen:
    """``greedy_nnls``'s screen from a stored copy of every column (n, K), typically float32:
    the cosine of each with the residual, one (n,) by (n, K) product per block. The copy only
    ranks the candidates; ``greedy_nnls`` forms the best few exactly and they decide."""

    def __init__(self, columns):
        self.columns = columns
        self.norms = np.maximum(np.sqrt(np.einsum("ij,ij->j", columns, columns,
                                                  dtype=np.float64)), 1e-300)

    def __call__(self, residual, indices):
        """(k,) cosines (up to |residual|) of the columns ``indices`` (k,) with residual (n,)."""
        scores = np.asarray(residual).astype(self.columns.dtype) @ self.columns
        return scores[indices] / self.norms[indices]


class _IncrementalNNLS:
    """NNLS over a growing column set A (n, k), reduced to k x k through R^T R = A^T A.

    R grows by one Cholesky column per pick from the new column's inner products with the
    picked ones (``inner_products``, computed for a whole shortlist at once), and
    Qb = R^-T A^T b, so |A w - b|^2 = |R w - Qb|^2 + |b|^2 - |Qb|^2: the NNLS of (R, Qb)
    (k x k) has the same minimiser as the tall problem (``refit``). The n x k columns are read
    once per block of picks (the inner products) and once for the exact residual."""

    def __init__(self, target, capacity):
        n = len(target)
        self.target, self.capacity = target, capacity
        self.target_sq = float(target @ target)
        self.norm = max(np.sqrt(self.target_sq), 1e-300)
        # Column-major: the first k columns are one contiguous block for the BLAS products.
        self.A = np.empty((n, capacity), order="F")
        self.R = np.zeros((capacity, capacity))
        self.Qb = np.empty(capacity)
        self.size = 0
        self.indices = np.empty(0, dtype=np.int64)
        self.weights = np.empty(0)
        self.residual = target.copy()
        self.free = _PassiveQR()             # the columns whose weight is > 0
        self.largest = 0.0                   # max |R| (the NNLS's round-off scale)

    def inner_products(self, columns):
        """(A^T C (k, s), b^T C (s,), C^T C (s, s)) of candidate columns C (n, s)."""
        return (self.A[:, :self.size].T @ columns, self.target @ columns, columns.T @ columns)

    def add(self, index, column, cross, target_inner, length_sq):
        """Append a column (n,) given A^T a (k,), b^T a and |a|^2 (weight 0 until ``refit``);
        False (nothing appended) if it is numerically dependent on the picked ones."""
        k = self.size
        coupling = scipy.linalg.solve_triangular(self.R[:k, :k], cross, trans="T") if k \
            else np.empty(0)
        rest = length_sq - float(coupling @ coupling)
        if not rest > DEPENDENT ** 2 * length_sq:
            return False
        self.A[:, k] = column
        self.R[:k, k], self.R[k, k] = coupling, np.sqrt(rest)
        self.largest = max(self.largest, float(np.abs(self.R[:k + 1, k]).max()))
        self.Qb[k] = (target_inner - coupling @ self.Qb[:k]) / self.R[k, k]
        self.indices = np.append(self.indices, index)
        self.weights = np.append(self.weights, 0.0)
        self.size = k + 1
        self.free.grow()
        return True

    def refit(self, exact=True):
        """Re-fit the weights after a pick (``active_set_nnls`` from the current ones): to the
        NNLS optimum, or (not ``exact``) letting only the new column join the free weights,
        which is cheaper and cannot raise the residual either (picks whose weights went to 0
        come back at the next exact re-fit if they help). Returns the relative residual from
        the k x k reduction (``exact_residual`` recomputes it on the n rows)."""
        k = self.size
        R, Qb = self.R[:k, :k], self.Qb[:k]
        entering = None if exact else k - 1          # add() left the new pick out of free
        self.weights = active_set_nnls(R, Qb, self.weights, self.free, self.largest,
                                       entering=entering)
        misfit = R @ self.weights - Qb
        outside = max(self.target_sq - float(Qb @ Qb), 0.0)
        return float(np.sqrt(outside + misfit @ misfit)) / self.norm

    def exact_residual(self):
        """Recompute the residual b - A w on all n rows; returns its relative norm."""
        self.residual = self.target - self.A[:, :self.size] @ self.weights
        return float(np.sqrt(self.residual @ self.residual)) / self.norm


class _PassiveQR:
    """The QR factorisation R[:, P] = Q Rp (Q (k, k) orthogonal, Rp (k, p) upper trapezoidal)
    of the columns P (p,) of a k x k matrix R whose weights are free in ``active_set_nnls``.

    Kept up to date by Givens rotations (``scipy.linalg.qr_insert`` / ``qr_delete``,
    O(k^2) each) as columns enter and leave P, and as R grows by a row (``grow``: R's new row
    is zero in every old column)."""

    def __init__(self):
        self.Q, self.Rp = np.ones((0, 0)), np.zeros((0, 0))
        self.columns = np.empty(0, dtype=np.int64)

    def grow(self):
        """R gained a last row and column (the column not in P)."""
        k, p = len(self.Q) + 1, len(self.columns)
        Q = np.zeros((k, k))
        Q[:-1, :-1], Q[-1, -1] = self.Q, 1.0
        Rp = np.zeros((k, p))
        Rp[:-1] = self.Rp
        self.Q, self.Rp = Q, Rp

    def insert(self, R, column):
        """Append R[:, column] to P."""
        p = len(self.columns)
        if p == 0:
            self.Q, self.Rp = scipy.linalg.qr(R[:, [column]])
        else:
            self.Q, self.Rp = scipy.linalg.qr_insert(self.Q, self.Rp, R[:, column], p,
                                                     which="col", check_finite=False)
        self.columns = np.append(self.columns, column)

    def remove(self, position):
        """Take the ``position``-th column of P out of it."""
        if len(self.columns) == 1:
            self.Q, self.Rp = np.eye(len(self.Q)), np.zeros((len(self.Q), 0))
        else:
            self.Q, self.Rp = scipy.linalg.qr_delete(self.Q, self.Rp, position, 1, which="col",
                                                     overwrite_qr=True, check_finite=False)
        self.columns = np.delete(self.columns, position)

    def solve(self, b):
        """argmin |R[:, P] x - b| (p,)."""
        p = len(self.columns)
        return scipy.linalg.solve_triangular(self.Rp[:p], (self.Q.T @ b)[:p], check_finite=False)


def active_set_nnls(R, b, weights, free, largest=None, max_rounds=None, entering=None):
    """min |R w - b| over w >= 0 for R (k, k) non-singular, by Lawson and Hanson's active set
    started from feasible ``weights`` (k,) whose positive entries are the columns of ``free``
    (a ``_PassiveQR`` of R, updated in place; empty for a cold start); largest: max |R| if
    known (the round-off scale of the optimality test).

    Outer loop: the column with the largest positive dual R^T (b - R w) joins the free set,
    until none is above round-off. Inner loop: solve on the free set; while a weight is not
    positive, step from the feasible point towards that solution until the first such weight
    reaches 0 and take it out. The objective never grows (a convex quadratic moved towards its
    minimiser on a subspace that holds the current point). With ``entering`` (a column
    index), only that column joins, for one inner loop: no optimality test. Returns w (k,)."""
    k = R.shape[1]
    w = np.zeros(k)
    w[free.columns] = weights[free.columns]
    if entering is not None:
        free.insert(R, int(entering))
        _free_step(R, b, w, free, int(entering))
        return w
    largest = np.abs(R).max() if largest is None else largest
    tolerance = 10.0 * np.finfo(float).eps * k * largest * max(np.abs(b).max(), 1e-300)
    refused = np.zeros(k, dtype=bool)
    for _ in range(max_rounds or 3 * k + 10):
        dual = R.T @ (b - R @ w)
        dual[free.columns] = -np.inf
        dual[refused] = -np.inf
        best = int(np.argmax(dual))
        if not dual[best] > tolerance:
            break
        free.insert(R, best)
        if not _free_step(R, b, w, free, best):
            refused[best] = True          # round-off: its own solution weight is not positive
    return w


def _free_step(R, b, w, free, entered):
    """The inner loop of ``active_set_nnls`` after column ``entered`` joined the free set: w
    (k,) updated in place. False if ``entered`` itself had to leave at once (no progress)."""
    while len(free.columns):
        trial = free.solve(b)
        bad = np.flatnonzero(trial <= 0.0)
        if not len(bad):
            w[free.columns] = trial
            return True
        current = w[free.columns]
        gap = current[bad] - trial[bad]
        ratio = np.where(gap > 0.0, current[bad] / np.where(gap > 0.0, gap, 1.0), 0.0)
        step = float(ratio.min())
        moved = np.maximum(current + step * (trial - current), 0.0)
        moved[bad[int(np.argmin(ratio))]] = 0.0
        w[free.columns] = moved
        leaving = np.flatnonzero(moved <= 0.0)
        gone = free.columns[leaving]
        for position in leaving[::-1]:              # from the right: positions stay valid
            free.remove(int(position))
        w[gone] = 0.0
        if entered in gone and step == 0.0:
            return False
    return True
