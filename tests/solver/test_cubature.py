"""Tests for solver.cubature: greedy NNLS, training poses, reduced RS cubature training.

Oracles: synthetic problems with a known sparse non-negative solution, scipy.optimize.nnls,
the formed columns against the screen that scores them without forming them,
the rotation and strain of poses computed directly from modal_rs.
"""

import numpy as np
import pytest
from scipy.optimize import nnls

from solver import cubature, fem, meshgen, modes, reduced, rs

DEG = np.pi / 180.0


def sparse_problem(seed=0, rows=300, columns=400, support=8):
    """A (rows, columns) Gaussian, w* >= 0 with ``support`` non-zeros, target = A w*."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(rows, columns))
    truth = np.zeros(columns)
    chosen = rng.choice(columns, support, replace=False)
    truth[chosen] = rng.uniform(0.5, 2.0, support)
    return A, truth, A @ truth


def full_weights(picked, weights, size):
    w = np.zeros(size)
    w[picked] = weights
    return w


# Greedy NNLS ---------------------------------------------------------------------------------

def test_greedy_nnls_recovers_an_exactly_sparse_nonnegative_combination():
    A, truth, target = sparse_problem()
    picked, weights, history = cubature.greedy_nnls(A, target, tol=1e-10, max_picks=30)
    np.testing.assert_array_equal(np.sort(picked), np.flatnonzero(truth))
    np.testing.assert_allclose(full_weights(picked, weights, A.shape[1]), truth, atol=1e-10)
    assert history[-1] <= 1e-10 and len(history) == len(truth.nonzero()[0]) + 1


def test_greedy_nnls_with_callable_columns_and_random_candidates():
    A, truth, target = sparse_problem(seed=1)
    requested = []

    def columns(indices):
        requested.append(len(indices))
        return A[:, indices]

    picked, weights, history = cubature.greedy_nnls(
        columns, target, tol=1e-10, max_picks=60, candidates=150, num_columns=A.shape[1],
        rng=np.random.default_rng(2))
    assert max(requested) == 150                                  # only subsets are computed
    np.testing.assert_allclose(full_weights(picked, weights, A.shape[1]), truth, atol=1e-8)
    assert history[-1] <= 1e-10
    with pytest.raises(ValueError):
        cubature.greedy_nnls(columns, target)                     # num_columns is required


def test_greedy_nnls_with_a_screen_forms_only_the_best_scored_columns_and_fits_the_same():
    """A screen that gives the exact cosines leaves the fit bit for bit as it was (same random
    blocks, same shortlists), while only the shortlist of each block is formed."""
    A, truth, target = sparse_problem(seed=3)
    norms = np.linalg.norm(A, axis=0)
    formed = {False: [], True: []}

    def fit(screened):
        def columns(indices):
            formed[screened].append(len(indices))
            return A[:, indices]

        def screen(residual, indices):
            return residual @ A[:, indices] / norms[indices]

        return cubature.greedy_nnls(columns, target, tol=1e-10, max_picks=60, candidates=200,
                                    num_columns=A.shape[1], rng=np.random.default_rng(6),
                                    picks_per_block=2, screen=screen if screened else None)

    plain, screened = fit(False), fit(True)
    np.testing.assert_array_equal(screened[0], plain[0])
    np.testing.assert_array_equal(screened[1], plain[1])
    assert screened[2] == plain[2]
    assert set(formed[False]) == {200} and set(formed[True]) == {cubature.SCREEN * 2}
    assert len(formed[True]) == len(formed[False]) > 1
    np.testing.assert_allclose(full_weights(*screened[:2], A.shape[1]), truth, atol=1e-8)


def test_greedy_nnls_weights_nonnegative_and_residual_never_grows():
    """A target outside the cone of the columns: weights stay > 0, the fit is the NNLS optimum."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(120, 60))
    target = rng.normal(size=120)
    # Positive columns and target (seed 0): an in-between least-squares update goes negative
    # there, so the NNLS fallback is exercised.
    positive = np.random.default_rng(0)
    A_pos = positive.random(size=(120, 60))
    target_pos = positive.random(120)
    for matrix, b in ((A, target), (A_pos, target_pos)):
        picked, weights, history = cubature.greedy_nnls(matrix, b, tol=1e-12, max_picks=60)
        assert np.all(weights > 0.0)
        assert np.all(np.diff(history) <= 1e-12)
        # The returned cubature is the fit the history reports (no hidden negative weight).
        achieved = np.linalg.norm(matrix[:, picked] @ weights - b) / np.linalg.norm(b)
        assert achieved == pytest.approx(history[-1], rel=1e-10)
        # ... and the NNLS optimum of the columns it picked (scipy's, an independent solver).
        best, _ = nnls(matrix[:, picked], b)
        np.testing.assert_allclose(weights, best, atol=1e-9 * np.abs(best).max())
    picked, weights, history = cubature.greedy_nnls(A, target, tol=1e-12, max_picks=60)
    assert history[-1] > 0.1                                       # not reachable with w >= 0
    # Once no column correlates positively with the residual, the fit is the global NNLS one.
    best, _ = nnls(A, target)
    optimum = np.linalg.norm(A @ best - target) / np.linalg.norm(target)
    assert history[-1] <= optimum + 1e-9


def test_greedy_nnls_several_picks_per_block_recover_the_sparse_combination():
    """Later picks of a block are scored in k-space (r^T c = b^T c - w^T A^T c) among the
    block's best first scores: they must still find the exact sparse solution."""
    A, truth, target = sparse_problem(seed=4, support=12)
    for per_block in (4, 12):
        picked, weights, history = cubature.greedy_nnls(A, target, tol=1e-10, max_picks=40,
                                                        picks_per_block=per_block)
        np.testing.assert_array_equal(np.sort(picked), np.flatnonzero(truth))
        np.testing.assert_allclose(full_weights(picked, weights, A.shape[1]), truth, atol=1e-9)
        assert history[-1] <= 1e-10 and np.all(np.diff(history) <= 1e-12)


def test_gram_cholesky_fit_is_the_qr_of_the_picked_columns():
    """The k x k reduction grown from inner products only: R is Householder QR's R (signs
    made positive), and |R w - Qb|^2 + |b|^2 - |Qb|^2 is the tall residual for any w."""
    rng = np.random.default_rng(5)
    A = rng.normal(size=(200, 30)) @ np.diag(np.logspace(0, 3, 30))      # cond ~ 1e3
    b = rng.normal(size=200)
    fit = cubature._IncrementalNNLS(b, 30)
    for start in range(0, 30, 7):                      # blocks of inner products, as in picks
        block = A[:, start:start + 7]
        cross, target_inner, gram = fit.inner_products(block)
        for j in range(block.shape[1]):
            assert fit.add(start + j, block[:, j], cross[:, j], target_inner[j], gram[j, j])
            cross = np.vstack([cross, gram[j]])
    _, R = np.linalg.qr(A)
    R *= np.sign(np.diag(R))[:, None]
    np.testing.assert_allclose(fit.R, R, rtol=1e-9, atol=1e-9 * np.abs(R).max())
    w = rng.uniform(0.0, 1.0, 30)
    reduced_sq = np.sum((fit.R @ w - fit.Qb) ** 2) + b @ b - fit.Qb @ fit.Qb
    assert reduced_sq == pytest.approx(np.sum((A @ w - b) ** 2), rel=1e-9)
    dependent = A[:, :2].sum(axis=1)                       # in the span: not appended
    cross, target_inner, gram = fit.inner_products(dependent[:, None])
    assert not fit.add(99, dependent, cross[:, 0], target_inner[0], gram[0, 0])
    assert fit.size == 30


def test_active_set_nnls_warm_or_cold_is_scipys_optimum_and_keeps_its_factor_exact():
    """Lawson-Hanson from a cold start, and warm from the optimum of 30 columns after 10 new
    ones (and R grown row by row, as picks grow it): w >= 0, the misfit no larger than where it
    started, KKT (zero gradient on the support, none pointing into the bound off it), equal to
    scipy.optimize.nnls; the kept QR of the free columns is a QR of them."""
    rng = np.random.default_rng(6)
    R = np.triu(rng.normal(size=(40, 40))) + 6.0 * np.eye(40)
    b = rng.normal(size=40)
    reference, _ = nnls(R, b)
    free = cubature._PassiveQR()
    for _ in range(30):
        free.grow()
    start = cubature.active_set_nnls(R[:30, :30], b[:30], np.zeros(30), free)
    np.testing.assert_allclose(start, nnls(R[:30, :30], b[:30])[0], atol=1e-10)
    for _ in range(10):                                   # 10 new picks: R gains rows
        free.grow()
    start = np.append(start, np.zeros(10))
    before = np.linalg.norm(R @ start - b)
    w = cubature.active_set_nnls(R, b, start, free)
    assert np.all(w >= 0.0) and np.linalg.norm(R @ w - b) <= before + 1e-12
    support = w > 0.0
    assert 0 < support.sum() < 40                          # some weights at the bound
    assert sorted(free.columns) == list(np.flatnonzero(support))
    gradient = R.T @ (R @ w - b)
    scale = np.abs(R.T @ b).max()
    np.testing.assert_allclose(gradient[support], 0.0, atol=1e-9 * scale)
    assert np.all(gradient[~support] >= -1e-9 * scale)
    np.testing.assert_allclose(w, reference, atol=1e-10)
    p = len(free.columns)
    np.testing.assert_allclose(free.Q @ free.Rp, R[:, free.columns], atol=1e-10)
    np.testing.assert_allclose(free.Q.T @ free.Q, np.eye(40), atol=1e-12)
    np.testing.assert_allclose(np.tril(free.Rp[:p], -1), 0.0, atol=1e-12)


def test_greedy_nnls_progress_can_abort():
    A, _, target = sparse_problem()
    calls = []

    def progress(fraction, message):
        calls.append(fraction)
        if len(calls) == 3:
            raise RuntimeError("cancelled by the user")

    with pytest.raises(RuntimeError, match="cancelled"):
        cubature.greedy_nnls(A, target, tol=1e-10, progress=progress)
    assert calls == sorted(calls) and len(calls) == 3


# Training poses ------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def small_bar():
    X, T = meshgen.box_tet_mesh((4.0, 1.0, 1.0), (8, 2, 2))
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    K = fem.stiffness_matrix(X, T, 1.0e6, 0.45)
    masses = fem.lumped_masses(X, T, 1000.0)
    result = modes.linear_modes(K, masses, 6, pinned_nodes=pinned)
    modal_rs = rs.linear_rs(rs.rs_operator(X, T), result.vectors)
    recon = rs.PoissonReconstruction(X, T, pinned_nodes=pinned)
    return X, T, masses, result, modal_rs, recon


def test_training_poses_reach_the_target_rotation_or_the_strain_cap(small_bar):
    _, _, _, result, modal_rs, _ = small_bar
    Z = cubature.training_poses(6, result.eigenvalues, 60, np.random.default_rng(0),
                                max_rotation=120.0 * DEG, modal_rs=modal_rs, max_strain=1.0)
    assert Z.shape == (60, 6)
    y = np.einsum("ekm,fm->fek", modal_rs, Z)
    rotation = np.linalg.norm(y[:, :, :3], axis=2).max(axis=1)
    strain_matrix = np.einsum("fek,kab->feab", y[:, :, 3:], rs.STRAIN_BASIS)
    strain = np.linalg.norm(strain_matrix, axis=(2, 3)).max(axis=1)
    assert rotation.max() <= 120.0 * DEG + 1e-9 and strain.max() <= 1.0 + 1e-9
    capped = np.isclose(strain, 1.0)
    assert 0 < capped.sum() < 60
    assert rotation[~capped].min() >= 0.05 * 120.0 * DEG - 1e-12    # theta ~ U(0.05, 1) max
    assert rotation.max() > 90.0 * DEG                              # beyond 90 deg are trained
    free = cubature.training_poses(6, result.eigenvalues, 60, np.random.default_rng(0),
                                   max_rotation=120.0 * DEG, modal_rs=modal_rs,
                                   max_strain=np.inf)
    rotation_free, _ = cubature.pose_extremes(modal_rs, free)
    assert rotation_free.min() >= 6.0 * DEG - 1e-12 and rotation_free.max() <= 120 * DEG + 1e-9
    assert rotation_free.max() > 110.0 * DEG
    single = np.count_nonzero(Z, axis=1) == 1
    assert single.sum() == 20 and set(np.argmax(np.abs(Z[single]), axis=1)) == set(range(6))
    assert (np.count_nonzero(Z, axis=1) >= 2).sum() == 40
    np.testing.assert_array_equal(Z, cubature.training_poses(
        6, result.eigenvalues, 60, np.random.default_rng(0), max_rotation=120.0 * DEG,
        modal_rs=modal_rs, max_strain=1.0))
    np.testing.assert_allclose(cubature.pose_extremes(modal_rs, Z), (rotation, strain),
                               rtol=1e-12)


# Reduced RS cubature -------------------------------------------------------------------------

def test_reduced_rs_cubature_training(small_bar):
    X, T, masses, result, modal_rs, recon = small_bar
    B = reduced.second_order_basis(X, T, masses, modal_rs, recon, result.vectors, max_size=30)
    poses = cubature.training_poses(6, result.eigenvalues, 30, np.random.default_rng(1),
                                    modal_rs=modal_rs)
    tets, weights, info = reduced.train_reduced_rs_cubature(
        X, T, modal_rs, B, recon, poses, max_tets=60, tol=1e-3, rng=np.random.default_rng(2))
    assert len(np.unique(tets)) == len(tets) <= 60 and np.all(weights > 0.0)
    assert np.all(np.diff(info["history"]) <= 1e-12)
    # The fit the training reports is the one the deformer evaluates on the training poses.
    deformer = reduced.ReducedRS.build(X, T, modal_rs, B, recon, tets, weights,
                                       projection=info["projection"])
    g = deformer.exact_q(poses)
    h = g - poses @ deformer.linear_map.T
    misfit = (deformer.q_batch(poses) - g) / np.linalg.norm(g, axis=1)[:, None]
    assert np.linalg.norm(misfit) / np.linalg.norm(h / np.linalg.norm(g, axis=1)[:, None]) \
        == pytest.approx(info["relative_residual"], rel=1e-8)

    def cancel(fraction, message):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        reduced.train_reduced_rs_cubature(X, T, modal_rs, B, recon, poses, progress=cancel)


def test_the_screen_scores_each_tet_as_its_formed_column_would(small_bar):
    """RemainderScreen's cosines and norms, computed without the columns, against the columns
    themselves (``reduced_rs_columns``); its exact fit against the all-tet fit of the RS
    targets (``rs.rs_target`` of each pose, ``ReducedProjection.exact_q``). The same with every
    tet's factors stored and with each block's computed when it is scored."""
    X, T, masses, result, modal_rs, recon = small_bar
    B = reduced.second_order_basis(X, T, masses, modal_rs, recon, result.vectors, max_size=30)
    poses = cubature.training_poses(6, result.eigenvalues, 20, np.random.default_rng(4),
                                    max_rotation=150.0 * DEG, modal_rs=modal_rs)
    projection = reduced.ReducedProjection(X, T, B, recon)
    exact = projection.exact_q(rs.rs_target(reduced.modal_rs_poses(modal_rs, poses))
                               .reshape(len(poses), len(T), 3, 3))
    tets = np.arange(len(T) - 1, 0, -3)                              # a subset, any order
    for store in (True, False):
        screen, g = reduced.RemainderScreen.build(projection, modal_rs, poses, store=store)
        assert (screen._factors is not None) == store
        np.testing.assert_allclose(g, exact, atol=1e-12 * np.abs(exact).max())
        scale = np.linalg.norm(g, axis=1)
        target = ((g - poses @ projection.linear_map(modal_rs).T) / scale[:, None]).reshape(-1)
        columns = reduced.reduced_rs_columns(projection, modal_rs, poses, tets, scale)
        norms = np.linalg.norm(columns, axis=0)
        np.testing.assert_allclose(screen.factors(tets)[1], norms, rtol=1e-6)
        for residual in (target, np.random.default_rng(5).normal(size=target.shape)):
            cosines = residual @ columns / norms
            scores = screen(residual, tets)
            assert np.abs(scores - cosines).max() <= 1e-5 * np.abs(cosines).max()  # float32
            np.testing.assert_array_equal(np.argsort(-scores)[:5], np.argsort(-cosines)[:5])
