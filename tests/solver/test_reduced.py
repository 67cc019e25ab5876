"""Tests for solver.reduced: reduced RS with cubature (SPEC.md 4 and 8).

Oracles: full RS (rs.PoissonReconstruction, Psi), libigl's cotangent Laplacian, rs.rs_target and
its finite-difference-tested Jacobian, central finite differences, embed.embed_points, exact
linear algebra. The trained deformer is built once per module (about 5 s).
"""

import math

import igl
import numpy as np
import pytest
import scipy.sparse as sp

from solver import cache, cubature, embed, fem, meshgen, modes, reduced, rs

DEG = np.pi / 180.0
NUM_MODES = 10


def diagonal(X):
    return float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))


def max_error(u, u_ref, X):
    """Largest vertex displacement error relative to the bounding-box diagonal."""
    return float(np.linalg.norm(np.reshape(u, (-1, 3)) - np.reshape(u_ref, (-1, 3)),
                                axis=1).max() / diagonal(X))


@pytest.fixture(scope="module")
def bar():
    """Pinned 4:1:1 bar (16 x 4 x 4 cells, 1536 tets), 10 modes, trained reduced RS.

    Defaults: basis of 120 (modes, series terms, snapshot POD), cubature of <= 150 tets.
    """
    X, T = meshgen.box_tet_mesh((4.0, 1.0, 1.0), (16, 4, 4))
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    K = fem.stiffness_matrix(X, T, 1.0e6, 0.45)
    masses = fem.lumped_masses(X, T, 1000.0)
    result = modes.linear_modes(K, masses, NUM_MODES, pinned_nodes=pinned)
    W = result.vectors
    modal_rs = rs.linear_rs(rs.rs_operator(X, T), W)
    recon = rs.PoissonReconstruction(X, T, pinned_nodes=pinned)
    deformer, info = reduced.prepare_reduced_rs(X, T, masses, W, result.eigenvalues, recon,
                                                modal_rs=modal_rs, seed=0)
    print(f"prepared: rB = {deformer.basis_size}, |C| = {len(deformer.cubature_tets)}, "
          f"fit residual {info['relative_residual']:.2e}, seconds {info['seconds']}")
    return dict(X=X, T=T, pinned=pinned, masses=masses, W=W, eigenvalues=result.eigenvalues,
                modal_rs=modal_rs, recon=recon, deformer=deformer, info=info)


@pytest.fixture(scope="module")
def held_out(bar):
    """40 poses never used in training (another seed), rotations up to 90 deg, and full RS."""
    Z = cubature.training_poses(NUM_MODES, bar["eigenvalues"], 40, np.random.default_rng(1234),
                                max_rotation=90.0 * DEG, modal_rs=bar["modal_rs"])
    full = np.stack([bar["recon"].reconstruct(bar["modal_rs"] @ z) for z in Z])
    return Z, full


def held_out_error(deformer, bar, held_out):
    Z, full = held_out
    return max(max_error(deformer.displacement(z), u, bar["X"]) for z, u in zip(Z, full))


# Basis ---------------------------------------------------------------------------------------

def test_basis_holds_pins_exactly_and_is_mass_orthonormal(bar):
    B = bar["deformer"].basis
    rows = B.reshape(len(bar["X"]), 3, -1)[bar["pinned"]]
    assert np.all(rows == 0.0)
    gram = B.T @ (np.repeat(bar["masses"], 3)[:, None] * B)
    np.testing.assert_allclose(gram, np.eye(B.shape[1]), atol=1e-10)
    # The modes come first, unchanged (they are already M-orthonormal).
    np.testing.assert_allclose(B[:, :NUM_MODES], bar["W"], atol=1e-9 * np.abs(bar["W"]).max())
    assert B.shape[1] == reduced.default_basis_size(NUM_MODES) == 120


def test_basis_spans_the_second_order_terms(bar):
    """Without a cap every Psi(d^2 b / dz_i dz_j) lies in span B (projection residual ~ 0)."""
    X, T, recon, modal_rs = bar["X"], bar["T"], bar["recon"], bar["modal_rs"]
    B = reduced.second_order_basis(X, T, bar["masses"], modal_rs, recon, bar["W"],
                                   max_size=1000, order=2)
    assert B.shape[1] == NUM_MODES + NUM_MODES * (NUM_MODES + 1) // 2
    m_diag = np.repeat(bar["masses"], 3)
    for i, j in [(0, 0), (0, 1), (2, 7), (9, 9)]:
        c = recon.solve(reduced.second_order_targets(modal_rs, i, j)).reshape(-1)
        residual = c - B @ (B.T @ (m_diag * c))
        assert np.linalg.norm(residual) < 1e-8 * np.linalg.norm(c)


def test_series_targets_are_the_taylor_coefficients_of_the_rs_map(bar):
    """mode_series_targets (powers as repeated cross products) against matrix powers of
    [w]x, and against the RS map itself: b(z e_i) minus its series to order 4 is O(z^5)."""
    modal_rs = bar["modal_rs"]
    omega, eps = modal_rs[:, :3, 4], modal_rs[:, 3:, 4] @ rs.STRAIN_BASIS.reshape(6, 9)
    K, eps = rs.skew(omega), eps.reshape(-1, 3, 3)
    for k in (1, 2, 3, 4):
        power = np.linalg.matrix_power(K, k - 1)
        expected = (power @ K) / math.factorial(k) + (power @ eps) / math.factorial(k - 1)
        np.testing.assert_allclose(reduced.mode_series_targets(modal_rs, 4, k), expected,
                                   rtol=0, atol=1e-12 * np.abs(expected).max())
    scale = 1.0 / rs.max_mode_rotations(modal_rs)[4]         # z = scale: 1 rad at most

    def remainder(z):
        exact = rs.rs_target(z * modal_rs[:, :, 4])
        series = sum(z ** k * reduced.mode_series_targets(modal_rs, 4, k) for k in (1, 2, 3, 4))
        return np.abs(exact - series).max()

    ratio = remainder(0.02 * scale) / remainder(0.01 * scale)
    assert 28.0 < ratio < 36.0                                   # 2^5 = 32


def test_candidate_batches_do_not_change_the_candidates(bar, monkeypatch):
    """Basis candidates solved 8 per thread, or one at a time (the memory bound met), are the
    same columns; the screen keeps the same terms either way."""
    args = bar["modal_rs"], bar["recon"], 3, 30, None
    batched = reduced._series_candidates(*args)
    monkeypatch.setattr(reduced, "BATCH_MEMORY", 1)
    single = reduced._series_candidates(*args)
    assert batched.shape == single.shape == (3 * len(bar["X"]), 30)
    np.testing.assert_allclose(batched, single, rtol=0, atol=1e-12 * np.abs(single).max())


def test_basis_cap_keeps_modes_and_drops_dependent_vectors(bar):
    X, T, recon, modal_rs = bar["X"], bar["T"], bar["recon"], bar["modal_rs"]
    B = reduced.second_order_basis(X, T, bar["masses"], modal_rs, recon, bar["W"], max_size=25,
                                   order=2)
    assert B.shape[1] == 25
    np.testing.assert_allclose(B[:, :NUM_MODES], bar["W"], atol=1e-9 * np.abs(bar["W"]).max())
    # Feeding the same snapshots twice adds nothing the second time (near-dependent, dropped).
    snaps = reduced.rs_snapshots(modal_rs, recon, np.eye(NUM_MODES)[:3] * 5.0)
    doubled = reduced.second_order_basis(X, T, bar["masses"], modal_rs, recon, bar["W"],
                                         max_size=200, order=2,
                                         snapshots=np.hstack([snaps, snaps]), snapshot_size=100)
    assert doubled.shape[1] == NUM_MODES + 55 + 3


def test_basis_progress_can_abort(bar):
    calls = []

    def progress(fraction, message):
        calls.append((fraction, message))
        if len(calls) == 5:
            raise KeyboardInterrupt("cancelled")

    with pytest.raises(KeyboardInterrupt):
        reduced.second_order_basis(bar["X"], bar["T"], bar["masses"], bar["modal_rs"],
                                   bar["recon"], bar["W"], progress=progress)
    assert len(calls) == 5 and all(0.0 <= f <= 1.0 for f, _ in calls)


# Exact reduced fit ---------------------------------------------------------------------------

def test_exact_q_is_the_full_rs_pose_projected_on_the_basis(bar):
    """q = (B^T L B)^-1 B^T L Psi(y): the L-orthogonal projection of the full RS pose.

    L = -cotmatrix kron I3 (libigl); Psi(y) from rs.PoissonReconstruction, which solves the
    same least-squares problem over all displacements.
    """
    deformer, X, T = bar["deformer"], bar["X"], bar["T"]
    B = deformer.basis
    L = sp.kron(-igl.cotmatrix(X, T), sp.identity(3)).tocsr()
    z = 2.0 * bar["info"]["cubature_poses"][-1]                 # beyond the training range
    u_full = bar["recon"].reconstruct(bar["modal_rs"] @ z).reshape(-1)
    expected = np.linalg.solve(B.T @ (L @ B), B.T @ (L @ u_full))
    np.testing.assert_allclose(deformer.exact_q(z), expected, rtol=0,
                               atol=1e-9 * np.abs(expected).max())


def test_exact_q_with_a_complete_basis_is_full_rs():
    """B = identity on the free DOFs: the reduced fit is the full reconstruction Psi."""
    X, T = meshgen.box_tet_mesh((1.5, 0.5, 0.5), (3, 1, 1))
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    free = np.repeat(~np.isin(np.arange(len(X)), pinned), 3)
    B = np.eye(3 * len(X))[:, free]
    W = np.random.default_rng(0).normal(size=(3 * len(X), 2)) * free[:, None]
    modal_rs = rs.linear_rs(rs.rs_operator(X, T), W)
    recon = rs.PoissonReconstruction(X, T, pinned_nodes=pinned)
    deformer = reduced.ReducedRS.build(X, T, modal_rs, B, recon, np.arange(len(T)),
                                       np.ones(len(T)))
    z = np.array([0.7, -1.3])
    u_full = recon.reconstruct(modal_rs @ z)
    np.testing.assert_allclose(B @ deformer.exact_q(z), u_full.reshape(-1), atol=1e-12)
    # A "cubature" of every tet with unit weights is the exact sum.
    np.testing.assert_allclose(deformer.q(z), deformer.exact_q(z), atol=1e-12)


def test_cubature_of_all_tets_with_unit_weights_equals_exact_q(bar):
    X, T = bar["X"], bar["T"]
    full = reduced.ReducedRS.build(X, T, bar["modal_rs"], bar["deformer"].basis, bar["recon"],
                                   np.arange(len(T)), np.ones(len(T)))
    for z in bar["info"]["cubature_poses"][:5]:
        exact = full.exact_q(z)
        np.testing.assert_allclose(full.q(z), exact, atol=1e-10 * np.abs(exact).max())


# Accuracy against full RS --------------------------------------------------------------------

def test_held_out_large_rotation_poses_within_one_percent_of_the_diagonal(bar, held_out):
    Z, full = held_out
    rotation, strain = cubature.pose_extremes(bar["modal_rs"], Z)
    assert rotation.max() > 80.0 * DEG                            # really large rotations
    deformer, X = bar["deformer"], bar["X"]
    errors = np.array([max_error(deformer.displacement(z), u, X) for z, u in zip(Z, full)])
    exact = np.array([max_error(deformer.basis @ deformer.exact_q(z), u, X)
                      for z, u in zip(Z, full)])
    linear = np.array([max_error(bar["W"] @ z, u, X) for z, u in zip(Z, full)])
    print(f"held-out (max rotation {rotation.max() / DEG:.1f} deg, strain {strain.max():.2f}): "
          f"reduced RS max {errors.max():.4f}, mean {errors.mean():.4f}; all-tet fit max "
          f"{exact.max():.4f}; linear modes max {linear.max():.3f} (of the diagonal)")
    assert errors.max() <= 0.01
    assert linear.max() > 0.2                                     # the poses are nonlinear


def test_error_falls_as_the_cubature_grows(bar, held_out):
    X, T, deformer = bar["X"], bar["T"], bar["deformer"]
    poses = bar["info"]["cubature_poses"]
    errors = []
    for size in (10, 40):
        tets, weights, fit = reduced.train_reduced_rs_cubature(
            X, T, bar["modal_rs"], deformer.basis, bar["recon"], poses, max_tets=size,
            rng=np.random.default_rng(3))
        smaller = reduced.ReducedRS.build(X, T, bar["modal_rs"], deformer.basis, bar["recon"],
                                          tets, weights, projection=fit["projection"])
        errors.append(held_out_error(smaller, bar, held_out))
    errors.append(held_out_error(deformer, bar, held_out))
    print("held-out max error for |C| <= 10, 40, "
          f"{len(deformer.cubature_tets)}: " + ", ".join(f"{e:.4f}" for e in errors))
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 0.25 * errors[0]


# Partial reconstruction ----------------------------------------------------------------------

def test_partial_reconstruction_equals_rows_of_the_full_reconstruction(bar):
    deformer, X, T = bar["deformer"], bar["X"], bar["T"]
    z = bar["info"]["cubature_poses"][7]
    u = deformer.displacement(z)                                   # (N, 3) = B q
    np.testing.assert_allclose(u.reshape(-1), deformer.basis @ deformer.q(z), atol=1e-12)
    vertices = np.array([5, 77, 200, len(X) - 1])
    rows = reduced.basis_rows(deformer.basis, vertices)
    scale = np.abs(u).max()
    np.testing.assert_allclose(deformer.displacement(z, rows=rows), u[vertices],
                               atol=1e-12 * scale)
    evaluator = deformer.row_evaluator(rows)
    assert evaluator.fused                                         # 12 rows < rB: folded path
    np.testing.assert_allclose(evaluator.displacement(z), u[vertices], atol=1e-11 * scale)
    # Render-like points inside the body through Phi B (the caller's precomputed rows).
    points = np.random.default_rng(4).uniform([0.1, 0.1, 0.1], [3.9, 0.9, 0.9], (50, 3))
    Phi = embed.embed_points(X, T, points)
    PhiB = (Phi @ deformer.basis.reshape(len(X), -1)).reshape(-1, deformer.basis_size)
    np.testing.assert_allclose(deformer.displacement(z, rows=PhiB), Phi @ u, atol=1e-12 * scale)
    assert not deformer.row_evaluator(PhiB).fused                  # 150 rows >= rB: through q
    np.testing.assert_allclose(deformer.row_evaluator(PhiB).displacement(z), Phi @ u,
                               atol=1e-12 * scale)


# Jacobians -----------------------------------------------------------------------------------

def central_differences(f, z, steps):
    """(out, m) central differences of f: (m,) -> (out,), per-coordinate steps (m,)."""
    columns = []
    for k, h in enumerate(steps):
        dz = np.zeros_like(z)
        dz[k] = h
        columns.append((f(z + dz) - f(z - dz)) / (2.0 * h))
    return np.stack(columns, axis=1)


def column_errors(J, fd):
    return np.linalg.norm(J - fd, axis=0) / np.linalg.norm(fd, axis=0)


@pytest.mark.parametrize("which", ["rest", "small", "large"])
def test_q_jacobian_matches_central_differences(bar, which):
    deformer = bar["deformer"]
    per_unit = rs.max_mode_rotations(bar["modal_rs"])
    z = {"rest": np.zeros(NUM_MODES),
         "small": 1e-3 * bar["info"]["cubature_poses"][30],
         "large": bar["info"]["cubature_poses"][40]}[which]
    steps = 1e-5 / per_unit                                        # 1e-5 rad per step
    fd = central_differences(deformer.q, z, steps)
    errors = column_errors(deformer.q_jacobian(z), fd)
    print(f"dq/dz vs central differences ({which}): max relative column error {errors.max():.1e}")
    assert errors.max() <= 1e-5
    # Partial reconstruction of a few vertices (folded path) and its joint evaluation.
    rows = reduced.basis_rows(deformer.basis, [10, 300, 420])
    evaluator = deformer.row_evaluator(rows)
    fd_rows = central_differences(lambda v: evaluator.displacement(v).reshape(-1), z, steps)
    u, J = evaluator.evaluate(z)
    assert column_errors(J, fd_rows).max() <= 1e-5
    np.testing.assert_allclose(evaluator.jacobian(z), J, atol=1e-12 * np.abs(J).max())
    np.testing.assert_allclose(u, evaluator.displacement(z), atol=1e-14)
    np.testing.assert_allclose(deformer.displacement_jacobian(z, rows), J,
                               atol=1e-10 * np.abs(J).max())


def test_batches_equal_stacked_single_evaluations(bar):
    deformer = bar["deformer"]
    Z = bar["info"]["cubature_poses"][:7]
    np.testing.assert_allclose(deformer.q_batch(Z), np.stack([deformer.q(z) for z in Z]),
                               rtol=0, atol=1e-12)
    J = deformer.q_jacobian_batch(Z)
    assert J.shape == (7, deformer.basis_size, NUM_MODES)
    np.testing.assert_allclose(J, np.stack([deformer.q_jacobian(z) for z in Z]), atol=1e-12)
    # Chunking must not change anything.
    np.testing.assert_allclose(deformer.q_batch(Z, chunk=3), deformer.q_batch(Z), atol=1e-12)
    np.testing.assert_allclose(deformer.q_jacobian_batch(Z, chunk=2), J, atol=1e-12)
    evaluator = deformer.row_evaluator(reduced.basis_rows(deformer.basis, [3, 99]))
    u, Jr = evaluator.evaluate_batch(Z)
    np.testing.assert_allclose(u, np.stack([evaluator.displacement(z) for z in Z]), atol=1e-12)
    np.testing.assert_allclose(Jr, np.stack([evaluator.jacobian(z) for z in Z]), atol=1e-12)
    # q_jacobian_batch also matches central differences frame by frame (one frame checked).
    steps = 1e-5 / rs.max_mode_rotations(bar["modal_rs"])
    fd = central_differences(deformer.q, Z[5], steps)
    assert column_errors(J[5], fd).max() <= 1e-5


def test_single_precision_rounds_only_the_nonlinear_part(bar):
    """``astype(float32)`` (the dynamics' deformer): its products act on the RS remainder alone,
    so q and dq/dz stay exact at rest and their rounding is a float32-sized fraction of the
    nonlinear part (q - A z, dq/dz - A) at small and large poses; ``q_gradient`` stays the
    transpose product of its own Jacobian."""
    deformer = bar["deformer"]
    single = deformer.astype(np.float32)
    assert single.dtype == np.float32 and single.weighted_projections.dtype == np.float32
    assert deformer.astype(np.float64) is deformer and single.astype(np.float32) is single
    A = deformer.linear_map
    rest = np.zeros(NUM_MODES)
    assert np.array_equal(single.q_jacobian(rest), A) and not single.q(rest).any()
    rng = np.random.default_rng(21)
    poses = bar["info"]["cubature_poses"]
    for z in (1e-3 * poses[30], poses[40], poses[5]):
        nonlinear_q = np.abs(deformer.q(z) - A @ z).max()
        J = deformer.q_jacobian(z)
        nonlinear_J = np.abs(J - A).max()
        q_error = np.abs(single.q(z) - deformer.q(z)).max() / nonlinear_q
        J_error = np.abs(single.q_jacobian(z) - J).max() / nonlinear_J
        g = rng.normal(size=deformer.basis_size)
        g_error = (np.abs(single.q_gradient(z, g) - single.q_jacobian(z).T @ g).max()
                   / np.abs((J - A).T @ g).max())
        print(f"float32 against float64, relative to the nonlinear part: q {q_error:.1e}, "
              f"dq/dz {J_error:.1e}, (dq/dz)^T g {g_error:.1e}")
        assert nonlinear_q > 0 and q_error < 1e-6 and J_error < 1e-5 and g_error < 1e-5
        assert q_error > 0                     # it did compute in float32


def test_the_last_pose_is_kept_and_only_that_pose(bar, monkeypatch):
    """q and dq/dz of the last pose asked (or of the fused evaluation's pose) come back without
    a product; another pose is evaluated afresh; what a caller does to a returned array does
    not reach what is kept."""
    deformer = bar["deformer"].astype(np.float32)        # a fresh object: nothing kept yet
    Z = bar["info"]["cubature_poses"][:4]
    q0, J0 = deformer.q_batch(Z[1:2])[0], deformer.q_jacobian_batch(Z[1:2])[0]
    Q, J = deformer.q_batch_and_jacobian(Z, 1)
    monkeypatch.setattr(deformer, "q_batch", lambda *a, **k: pytest.fail("q recomputed"))
    monkeypatch.setattr(deformer, "q_jacobian_batch", lambda *a, **k: pytest.fail("J recomputed"))
    q, Jk = deformer.q(Z[1].copy()), deformer.q_jacobian(Z[1].copy())
    assert np.array_equal(q, Q[1]) and np.array_equal(Jk, J)
    q[:] = 0.0
    Jk[:] = 0.0
    assert np.array_equal(deformer.q(Z[1]), Q[1]) and np.array_equal(deformer.q_jacobian(Z[1]), J)
    monkeypatch.undo()
    np.testing.assert_allclose(Q[1], q0, rtol=0, atol=1e-5 * np.abs(q0).max())
    np.testing.assert_allclose(J, J0, rtol=0, atol=1e-5 * np.abs(J0).max())
    assert np.array_equal(deformer.q(Z[2]), deformer.q_batch(Z[2:3])[0])   # another pose
    assert np.array_equal(deformer.q_jacobian(Z[3]), deformer.q_jacobian_batch(Z[3:4])[0])


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_q_batch_and_jacobian_equal_the_separate_evaluations(bar, dtype):
    """The integrator's fused evaluation (q at several poses and dq/dz at one of them from one
    product): the same values as ``q_batch`` and ``q_jacobian`` (to round-off in float64,
    within float32's rounding of the nonlinear part in float32)."""
    deformer = bar["deformer"].astype(dtype)
    exact = bar["deformer"]
    Z = bar["info"]["cubature_poses"][:5]
    for at in (0, 2, 4):
        Q, J = deformer.q_batch_and_jacobian(Z, at)
        assert Q.shape == (5, deformer.basis_size) and J.shape == (deformer.basis_size, NUM_MODES)
        nonlinear_q = np.abs(exact.q_batch(Z) - Z @ exact.linear_map.T).max()
        nonlinear_J = np.abs(exact.q_jacobian(Z[at]) - exact.linear_map).max()
        tolerance = 1e-12 if dtype == np.float64 else 1e-5
        # against evaluations afresh (q_jacobian would hand back the kept J)
        assert np.abs(Q - deformer.q_batch(Z)).max() <= tolerance * nonlinear_q
        assert (np.abs(J - deformer.q_jacobian_batch(Z[at:at + 1])[0]).max()
                <= tolerance * nonlinear_J)


def test_fast_targets_match_rs_module():
    rng = np.random.default_rng(5)
    angles = np.array([0.0, 1e-9, 1e-5, 5e-3, 1e-2 - 1e-9, 1e-2 + 1e-9, 0.3, 1.0, 2.5, np.pi,
                       4.0, 7.0])
    directions = rng.normal(size=(len(angles), 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    y = np.concatenate([directions * angles[:, None], 0.2 * rng.normal(size=(len(angles), 6))],
                       axis=1)
    b, J = reduced.fast_targets(y, jacobian=True)
    np.testing.assert_allclose(b, rs.rs_target(y).reshape(-1, 9), atol=1e-15)
    np.testing.assert_allclose(J, rs.rs_target_jacobian(y), atol=1e-13)
    np.testing.assert_allclose(reduced.LINEAR_TARGET, rs.rs_target_jacobian(np.zeros((1, 9)))[0],
                               atol=0)


def test_a_tets_remainder_does_not_depend_on_the_other_tets_in_the_call():
    """``fast_remainders`` (entry-major, the cubature's columns and the deformer) is elementwise:
    a tet's remainder is the same to the last bit alone, in a slice of the tets, or among all of
    them (the training splits its tets over threads, and Prepare must not depend on how), and it
    is b(y) - [omega]x - eps of the RS module."""
    rng = np.random.default_rng(8)
    y = np.concatenate([rng.normal(size=(3, 301)), 0.3 * rng.normal(size=(6, 301))])
    whole = reduced.fast_remainders(y)
    for part in (slice(0, 1), slice(7, 8), slice(5, 42), slice(100, 301)):
        assert np.array_equal(reduced.fast_remainders(np.ascontiguousarray(y[:, part])),
                              whole[:, part])
    linear = (reduced.LINEAR_TARGET @ y).T
    np.testing.assert_allclose(whole.T, rs.rs_target(y.T).reshape(-1, 9) - linear, atol=1e-14)


# Linear baseline and cache -------------------------------------------------------------------

def test_linear_deformer_is_exactly_linear(bar):
    W = bar["W"]
    linear = reduced.LinearDeformer(NUM_MODES, W)
    z = np.random.default_rng(6).normal(size=NUM_MODES)
    np.testing.assert_array_equal(linear.q(z), z)
    np.testing.assert_array_equal(linear.q_jacobian(z), np.eye(NUM_MODES))
    np.testing.assert_allclose(linear.displacement(z), (W @ z).reshape(-1, 3), atol=1e-15)
    np.testing.assert_allclose(linear.displacement(2.0 * z), 2.0 * linear.displacement(z),
                               atol=1e-15)
    Z = np.stack([z, -z, 3 * z])
    np.testing.assert_array_equal(linear.q_batch(Z), Z)
    np.testing.assert_array_equal(linear.q_jacobian_batch(Z), np.broadcast_to(np.eye(NUM_MODES),
                                                                               (3, 10, 10)))
    rows = reduced.basis_rows(W, [1, 2])
    evaluator = linear.row_evaluator(rows)
    u, J = evaluator.evaluate(z)
    np.testing.assert_allclose(u, (rows @ z).reshape(-1, 3), atol=1e-15)
    np.testing.assert_allclose(J, rows, atol=0)


def test_save_and_load_arrays_round_trip_through_the_cache(bar, tmp_path):
    deformer = bar["deformer"]
    path = tmp_path / "reduced.npz"
    cache.save(path, "key", deformer.to_arrays())
    loaded = reduced.ReducedRS.from_arrays(cache.load(path, "key"))
    z = bar["info"]["cubature_poses"][11]
    np.testing.assert_array_equal(loaded.q(z), deformer.q(z))
    np.testing.assert_array_equal(loaded.q_jacobian(z), deformer.q_jacobian(z))
    np.testing.assert_array_equal(loaded.displacement(z), deformer.displacement(z))
    np.testing.assert_array_equal(loaded.cubature_tets, deformer.cubature_tets)
    with pytest.raises(RuntimeError):
        loaded.exact_q(z)                                          # evaluation-only until ...
    loaded.attach_full(bar["X"], bar["T"], bar["modal_rs"], bar["recon"])
    np.testing.assert_allclose(loaded.exact_q(z), deformer.exact_q(z), atol=1e-12)
    lean = reduced.ReducedRS.from_arrays(deformer.to_arrays(include_basis=False))
    assert lean.basis is None
    np.testing.assert_array_equal(lean.q(z), deformer.q(z))
    linear = reduced.LinearDeformer(NUM_MODES, bar["W"])
    again = reduced.LinearDeformer.from_arrays(linear.to_arrays())
    np.testing.assert_array_equal(again.displacement(z), linear.displacement(z))


def test_prepare_progress_can_abort_and_reports_fractions(bar):
    fractions = []

    def progress(fraction, message):
        fractions.append(fraction)
        if fraction >= 0.5:                                          # inside the cubature stage
            raise InterruptedError("cancelled")

    with pytest.raises(InterruptedError):
        reduced.prepare_reduced_rs(bar["X"], bar["T"], bar["masses"], bar["W"],
                                   bar["eigenvalues"], bar["recon"], modal_rs=bar["modal_rs"],
                                   num_snapshots=20, progress=progress)
    assert fractions == sorted(fractions) and 0.5 <= fractions[-1] < 1.0


# Range edge cases: one mode, tiny meshes --------------------------------------------------------

def tiny_body(cells, num_modes, pinned=True):
    X, T = meshgen.box_tet_mesh((2.0, 1.0, 1.0), cells)
    pins = np.flatnonzero(X[:, 0] < 1e-9) if pinned else None
    masses = fem.lumped_masses(X, T, 1000.0)
    result = modes.linear_modes(fem.stiffness_matrix(X, T, 1e6, 0.3), masses, num_modes, pins,
                                rest_positions=X)
    recon = rs.PoissonReconstruction(X, T, pinned_nodes=pins)
    deformer, _ = reduced.prepare_reduced_rs(X, T, masses, result.vectors, result.eigenvalues,
                                             recon, num_snapshots=20, num_poses=20)
    return X, T, result, recon, deformer


@pytest.mark.parametrize("cells, num_modes, pinned", [
    ((8, 2, 2), 1, True),    # num_modes = 1, the setting's minimum (was a numpy matmul error)
    ((2, 1, 1), 6, True),    # 24 free DOFs, fewer than the default basis (was a LinAlgError)
    ((1, 1, 1), 6, True),    # 12 free DOFs
    ((2, 1, 1), 1, False),   # a free body with one deformation mode
], ids=["one-mode", "24-dofs", "12-dofs", "free-one-mode"])
def test_smallest_settings_and_meshes_prepare(cells, num_modes, pinned):
    """Every declared range works. Oracle: small poses are the linear modal motion (reduced RS
    is tangent to it at rest), and the basis never outgrows the free DOFs."""
    X, T, result, recon, deformer = tiny_body(cells, num_modes, pinned)
    free_dofs = 3 * (len(X) - len(result.pinned_nodes))
    assert deformer.basis.shape[1] <= free_dofs
    z = 1e-4 / rs.max_mode_rotations(rs.linear_rs(rs.rs_operator(X, T), result.vectors))
    u = deformer.displacement(z)
    linear = (result.vectors @ z).reshape(-1, 3)
    assert np.abs(u - linear).max() <= 1e-3 * np.abs(linear).max()


def test_reduced_projection_of_a_dependent_basis_says_why():
    X, T = meshgen.box_tet_mesh((2.0, 1.0, 1.0), (1, 1, 1))
    pins = np.flatnonzero(X[:, 0] < 1e-9)
    recon = rs.PoissonReconstruction(X, T, pinned_nodes=pins)
    B = np.zeros((3 * len(X), 13))                     # 13 vectors in 12 free DOFs
    free = np.repeat(X[:, 0] > 1e-9, 3)
    B[free] = np.random.default_rng(0).normal(size=(12, 13))
    with pytest.raises(ValueError, match="not independent"):
        reduced.ReducedProjection(X, T, B, recon)


def test_threads_give_the_same_preparation_bit_for_bit(bar, monkeypatch):
    """The reduced stage maps its per-pose work over threads (solver.threads): with one worker
    and with three, the basis, cubature tets and weights are identical to the last bit (each
    pose's computation is the same; results come back in order)."""
    from solver import threads

    def prepare(workers):
        monkeypatch.setattr(threads, "worker_count", lambda: workers)
        return reduced.prepare_reduced_rs(bar["X"], bar["T"], bar["masses"], bar["W"],
                                          bar["eigenvalues"], bar["recon"],
                                          modal_rs=bar["modal_rs"], num_snapshots=40,
                                          num_poses=20)[0]

    serial, threaded = prepare(1), prepare(3)
    np.testing.assert_array_equal(threaded.basis, serial.basis)
    np.testing.assert_array_equal(threaded.cubature_tets, serial.cubature_tets)
    np.testing.assert_array_equal(threaded.cubature_weights, serial.cubature_weights)


def test_ordered_map_keeps_the_order_and_raises_what_a_call_raises():
    from solver import threads
    items = list(range(23))
    assert threads.ordered_map(lambda i: i * i, items, workers=3) == [i * i for i in items]

    def fail_on_seven(i):
        if i == 7:
            raise ValueError("seven")
        return i

    with pytest.raises(ValueError, match="seven"):
        threads.ordered_map(fail_on_seven, items, workers=3)


def test_row_block_products_match_numpy_whatever_the_thread_count(monkeypatch):
    """threads.matmul and threads.inner (fixed blocks of rows on several threads) give the
    plain products, and the same bits on one thread as on three."""
    from solver import threads
    rng = np.random.default_rng(11)
    rows = 2 * threads.ROW_BLOCK + 123                     # two full blocks and a short one
    A, C = rng.normal(size=(rows, 7)), rng.normal(size=(rows, 5))
    B, weights = rng.normal(size=(7, 4)), rng.uniform(0.5, 2.0, rows)

    def products(workers):
        monkeypatch.setattr(threads, "worker_count", lambda: workers)
        return threads.matmul(A, B), threads.inner(A, C, weights), threads.inner(A, C)

    serial, threaded = products(1), products(3)
    np.testing.assert_allclose(serial[0], A @ B, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(serial[1], A.T @ (weights[:, None] * C), rtol=1e-12, atol=1e-11)
    np.testing.assert_allclose(serial[2], A.T @ C, rtol=1e-12, atol=1e-11)
    for one, three in zip(serial, threaded):
        np.testing.assert_array_equal(one, three)
    out = np.empty((rows, 4), order="F")                  # a column-major target is filled too
    assert threads.matmul(A, B, out=out) is out
    np.testing.assert_array_equal(out, serial[0])


@pytest.mark.parametrize("count, workers", [(0, 2), (1, 4), (7, 2), (9, 4), (3, 3)])
def test_even_parts_split_a_range_into_nonempty_consecutive_slices(count, workers):
    from solver import threads
    parts = threads.even_parts(count, workers)
    assert len(parts) == min(count, workers)
    assert all(part.stop > part.start for part in parts)
    assert [i for part in parts for i in range(count)[part]] == list(range(count))
    sizes = [part.stop - part.start for part in parts]
    assert not sizes or max(sizes) - min(sizes) <= 1
