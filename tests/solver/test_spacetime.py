"""Tests for solver.spacetime: space-time editing with material optimisation (SPEC.md 5 and 8).

Oracles: finite-difference Hessians and gradients of the objective, a dense normal-equation solve
assembled row by row from E_f's definition, the analytic damped oscillator, closed-form
one-parameter least squares, full RS volumes, and a full-space Newmark reference simulation.
"""

from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from solver import fem, meshgen, modes, reduced, rs
from solver import spacetime as st


class QuadraticDeformer:
    """Analytic nonlinear test deformer q(z) = A z + 1/2 C(z, z), C symmetric in its last two."""

    def __init__(self, m, rb, rng, curvature=0.3):
        self.num_coords, self.basis_size = m, rb
        self.A = rng.normal(size=(rb, m))
        C = curvature * rng.normal(size=(rb, m, m))
        self.C = 0.5 * (C + C.transpose(0, 2, 1))

    def q(self, z):
        return self.A @ z + 0.5 * np.einsum("bij,i,j->b", self.C, z, z)

    def q_jacobian(self, z):
        return self.A + np.einsum("bij,j->bi", self.C, z)

    def q_batch(self, Z):
        return Z @ self.A.T + 0.5 * np.einsum("bij,fi,fj->fb", self.C, Z, Z)

    def q_jacobian_batch(self, Z):
        return self.A[None] + np.einsum("bij,fj->fbi", self.C, Z)


def small_problem(deformer, r, frames=9, fix_start=True, seed=0, sampling=None, mu=0.0,
                  scheme="auto"):
    """Few frames, 3 handle constraints and 2 keyframes with random data."""
    rng = np.random.default_rng(seed)
    m, rb = deformer.num_coords, deformer.basis_size
    eigenvalues = np.linspace(2.0, 20.0, r)
    handles = st.HandleConstraints(frames=[3, 5, 5], rows=rng.normal(size=(3, 3, rb)),
                                   rest=rng.normal(size=(3, 3)), targets=rng.normal(size=(3, 3)),
                                   weights=[1.0, 0.5, 2.0])
    keys = st.Keyframes(frames=[frames - 1, 4], poses=rng.normal(size=(2, m)), weights=[3.0, 0.7])
    damping = st.rayleigh_damping(eigenvalues, 0.2, 0.01)
    return st.SpaceTimeProblem(frames, 0.1, eigenvalues, damping,
                               deformer, handles=handles, keyframes=keys, gamma=5.0, mu=mu,
                               sampling=sampling, fix_start=fix_start, scheme=scheme)


def free_unknowns(problem, Z):
    return Z[problem.first_free:].reshape(-1)


def with_unknowns(problem, Z, x):
    Z = Z.copy()
    Z[problem.first_free:] = x.reshape(-1, problem.num_modes)
    return Z


def fd_hessian(f, x, step):
    """Dense central-difference Hessian of scalar f at x (exact for quadratics up to round-off)."""
    n = len(x)
    E = np.eye(n) * step
    H = np.empty((n, n))
    for i in range(n):
        for j in range(i, n):
            H[i, j] = H[j, i] = (f(x + E[i] + E[j]) - f(x + E[i] - E[j]) - f(x - E[i] + E[j])
                                 + f(x - E[i] - E[j])) / (4.0 * step * step)
    return H


def fd_gradient(f, x, step):
    E = np.eye(len(x)) * step
    return np.array([(f(x + e) - f(x - e)) / (2.0 * step) for e in E])


def dense_from_band(ab):
    """Symmetric (n, n) matrix of lower banded storage ab[d, j] = A[j + d, j]."""
    n = ab.shape[1]
    A = np.zeros((n, n))
    for d in range(ab.shape[0]):
        for j in range(n - d):
            A[j + d, j] = A[j, j + d] = ab[d, j]
    return A


# 1. E_f: separable, pentadiagonal, exact banded Gauss-Newton matrix ---------------------------

@pytest.mark.parametrize("fix_start, scheme", [(True, "central"), (False, "central"),
                                               (True, "average")])
def test_banded_gauss_newton_matrix_is_the_exact_hessian_of_a_quadratic_problem(fix_start,
                                                                               scheme):
    """With a linear deformer J is quadratic in Z, so its FD Hessian is the GN matrix exactly."""
    rng = np.random.default_rng(1)
    r, m = 2, 3
    deformer = reduced.LinearDeformer(m)
    S = np.eye(m, r) + 0.3 * rng.normal(size=(m, r))
    problem = small_problem(deformer, r, fix_start=fix_start, sampling=S, scheme=scheme)
    Z = rng.normal(size=(problem.frames, r))

    def J(x):
        return st.objective(problem, with_unknowns(problem, Z, x), problem.eigenvalues,
                            problem.damping, S)

    ab, g = st.normal_equations(problem, Z, problem.eigenvalues, problem.damping, S)
    assert ab.shape == (2 * r + 1, len(free_unknowns(problem, Z)))
    H = fd_hessian(J, free_unknowns(problem, Z), 1e-2)
    dense = dense_from_band(ab)
    print(f"banded GN matrix vs FD Hessian: max error {np.abs(dense - H).max():.2e} "
          f"(max entry {np.abs(H).max():.2e})")
    np.testing.assert_allclose(dense, H, atol=1e-6 * np.abs(H).max())
    np.testing.assert_allclose(g, fd_gradient(J, free_unknowns(problem, Z), 1e-4),
                               rtol=1e-6, atol=1e-6 * np.abs(g).max())


def test_control_energy_separates_per_mode_and_is_pentadiagonal():
    rng = np.random.default_rng(2)
    F, r = 8, 3
    lam, dmp = np.array([1.0, 5.0, 30.0]), np.array([0.1, 0.5, 2.0])

    def e_f(x):
        return st.control_energy(x.reshape(F, r), lam, dmp, 0.1)

    H = fd_hessian(e_f, rng.normal(size=F * r), 1e-2).reshape(F, r, F, r)
    frame, mode = np.meshgrid(np.arange(F), np.arange(r), indexing="ij")
    coupled = ((mode[:, :, None, None] == mode[None, None])
               & (np.abs(frame[:, :, None, None] - frame[None, None]) <= 2))
    assert np.abs(H[~coupled]).max() < 1e-6 * np.abs(H).max()
    assert np.abs(H[coupled]).min() > 1e-3              # every band entry is really used
    d0, d1, d2 = st.control_energy_bands(F, lam, dmp, 0.1)
    i = np.arange(F)
    for k in range(r):
        np.testing.assert_allclose(H[i, k, i, k], d0[:, k], rtol=1e-6)
        np.testing.assert_allclose(H[i[:-1] + 1, k, i[:-1], k], d1[:, k], rtol=1e-6)
        np.testing.assert_allclose(H[i[:-2] + 2, k, i[:-2], k], d2[:, k], rtol=1e-6)


def test_gradient_through_a_nonlinear_deformer_matches_finite_differences():
    rng = np.random.default_rng(3)
    deformer = QuadraticDeformer(4, 6, rng)
    S = np.eye(4, 3) + 0.2 * rng.normal(size=(4, 3))
    problem = small_problem(deformer, 3, sampling=S)
    Z = 0.5 * rng.normal(size=(problem.frames, 3))
    _, g = st.normal_equations(problem, Z, problem.eigenvalues, problem.damping, S)
    fd = fd_gradient(lambda x: st.objective(problem, with_unknowns(problem, Z, x),
                                            problem.eigenvalues, problem.damping, S),
                     free_unknowns(problem, Z), 1e-6)
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-7 * np.abs(fd).max())


def test_simulate_modal_has_zero_control_energy_and_follows_the_oscillator():
    h, frames = 1.0 / 240.0, 2401                        # 10 s
    lam, dmp = np.array([4.0, 100.0, 400.0]), np.array([0.0, 0.4, 2.0])
    t = np.arange(frames) * h
    omega_d = np.sqrt(lam - dmp ** 2 / 4.0)
    exact = np.exp(-0.5 * dmp * t[:, None]) * (np.cos(omega_d * t[:, None])
                                               + 0.5 * dmp / omega_d * np.sin(omega_d * t[:, None]))
    Z = st.simulate_modal(lam, dmp, exact[0], exact[1], frames, h)
    residual = np.abs(st.dynamics_residual(Z, lam, dmp, h)).max()
    error = np.abs(Z - exact).max()
    print(f"simulate_modal: max |E_f residual| {residual:.2e}, max error vs oscillator {error:.2e}")
    assert residual < 1e-9 * np.abs(st.stencil(lam, dmp, h)).max()
    assert error < 0.02                                  # second order: about (omega h)^2 t omega


def test_average_scheme_stays_bounded_where_central_differences_explode():
    """h sqrt(lambda) = 2.5 (a 9.5 Hz mode at 24 fps): beyond the central scheme's limit of 2."""
    h, lam, dmp = 1.0 / 24.0, np.array([(2.5 * 24.0) ** 2, 4.0]), np.array([0.5, 0.1])
    central = st.simulate_modal(lam, dmp, [1.0, 1.0], [1.0, 1.0], 100, h, "central")
    average = st.simulate_modal(lam, dmp, [1.0, 1.0], [1.0, 1.0], 100, h, "average")
    assert np.abs(central[:, 0]).max() > 1e20
    assert np.abs(average).max() < 2.0                   # damped and stable: no growth
    assert np.abs(average[-20:]).max() < np.abs(average[:20]).max()
    assert np.abs(st.dynamics_residual(average, lam, dmp, h, "average")).max() < 1e-6
    assert st.resolve_scheme("auto", h, lam) == "average"
    assert st.resolve_scheme("auto", h, lam[1:]) == "central"
    # Both schemes agree to O(h^2) on a well-resolved mode (30 frames per period).
    fine = [st.simulate_modal([4.0], [0.1], [1.0], [np.cos(2.0 / 90.0)], 91, 1.0 / 90.0, s)
            for s in ("central", "average")]
    assert np.abs(fine[0] - fine[1]).max() < 0.01


# 2. Gauss-Newton on a quadratic problem: one step, dense oracle -------------------------------

def dense_control_rows(problem):
    """(rows of E_f over the free frames, straight from its definition)."""
    F, r, h, s = problem.frames, problem.num_modes, problem.h, problem.first_free
    rows = []
    for i in range(1, F - 1):
        for k in range(r):
            row = np.zeros((F, r))
            row[i - 1, k] = 1.0 / h ** 2 - problem.damping[k] / (2.0 * h)
            row[i, k] = -2.0 / h ** 2 + problem.eigenvalues[k]
            row[i + 1, k] = 1.0 / h ** 2 + problem.damping[k] / (2.0 * h)
            rows.append(row.reshape(-1))
    return np.array(rows)[:, s * r:]


def dense_handle_rows(problem):
    """(rows (3c, free unknowns), values (3c,)): handle j's position minus rest, = target - rest
    when met (q = z)."""
    F, r, s = problem.frames, problem.num_modes, problem.first_free
    c = problem.handles
    rows, values = [], []
    for j in range(len(c)):
        block = np.zeros((3, F, r))
        block[:, c.frames[j]] = c.rows[j] @ problem.sampling
        rows.extend(block.reshape(3, -1))
        values.extend(c.targets[j] - c.rest[j])
    return np.array(rows)[:, s * r:], np.array(values)


def dense_quadratic_solution(problem):
    """Minimiser of E_f + gamma E_c + E_k for q = z, from rows assembled one by one."""
    A = dense_control_rows(problem)
    C, values = dense_handle_rows(problem)
    scale = np.repeat(np.sqrt(problem.gamma * problem.handles.weights), 3)
    rows = np.vstack([A, scale[:, None] * C])
    rhs = np.r_[np.zeros(len(A)), scale * values]
    return np.linalg.solve(rows.T @ rows, rows.T @ rhs).reshape(-1, problem.num_modes)


def test_gauss_newton_solves_a_quadratic_problem_in_one_step():
    rng = np.random.default_rng(4)
    r = 3
    eigenvalues = np.array([6.0, 40.0, 150.0])
    rows = rng.normal(scale=0.05, size=(1, 3, r))        # one handle, linear deformer
    handles = st.HandleConstraints([25], rows, np.zeros((1, 3)), [[0.3, -0.2, 0.1]], 1.0)
    h = 1.0 / 24.0
    damping = st.rayleigh_damping(eigenvalues, 0.1, 0.002)
    gamma, _ = st.suggest_weights(h, eigenvalues, damping, reduced.LinearDeformer(r), rows)
    problem = st.SpaceTimeProblem(40, h, eigenvalues, damping, reduced.LinearDeformer(r),
                                  handles=handles, gamma=gamma)
    expected = dense_quadratic_solution(problem)
    one = st.solve(problem, iterations=1, continuation=False)
    error = np.abs(one.Z[2:] - expected).max() / np.abs(expected).max()
    print(f"one GN step vs dense solve: relative error {error:.2e}; "
          f"handle residual {one.handle_residuals[0]:.2e} m")
    assert error < 1e-8
    np.testing.assert_array_equal(one.Z[:2], 0.0)        # hard start at rest
    full = st.solve(problem, continuation=False)
    assert full.converged and full.iterations == 2       # the second step only confirms
    assert abs(full.objective - one.objective) <= 1e-10 * one.objective
    warm = st.solve(problem)                             # with the continuation: same minimum
    assert abs(warm.objective - one.objective) <= 1e-9 * one.objective


def test_three_frames_with_a_fixed_start_solve_their_one_free_frame():
    """Frames 0 and 1 are the start at rest and frame 2 is the only unknown: E_f has the one
    residual row c z_2 (c = 1/h^2 + d/2h per mode, central scheme), so the minimum of
    E_f + gamma E_c is the least squares of that row and the handle on frame 2."""
    rng = np.random.default_rng(5)
    r, h = 3, 1.0 / 24.0
    eigenvalues = np.array([6.0, 40.0, 150.0])
    damping = st.rayleigh_damping(eigenvalues, 0.1, 0.002)
    rows = rng.normal(scale=0.05, size=(1, 3, r))
    target = np.array([0.3, -0.2, 0.1])
    handles = st.HandleConstraints([2], rows, np.zeros((1, 3)), [target], 1.0)
    gamma, _ = st.suggest_weights(h, eigenvalues, damping, reduced.LinearDeformer(r), rows)
    problem = st.SpaceTimeProblem(3, h, eigenvalues, damping, reduced.LinearDeformer(r),
                                  handles=handles, gamma=gamma)
    assert problem.scheme == "central" and problem.first_free == 2
    c = 1.0 / h ** 2 + damping / (2.0 * h)
    A = rows[0]
    expected = np.linalg.solve(np.diag(c ** 2) + gamma * A.T @ A, gamma * A.T @ target)
    for options in ({}, {"continuation": False}):
        result = st.solve(problem, **options)
        assert result.converged, result.reason
        np.testing.assert_array_equal(result.Z[:2], 0.0)
        error = np.abs(result.Z[2] - expected).max() / np.abs(expected).max()
        print(f"3 frames {options}: relative error {error:.1e}, handle residual "
              f"{result.handle_residuals[0]:.1e} m")
        assert error < 1e-10
    met = st.solve(problem, exact_handles=True)
    assert met.converged and met.handle_residuals[0] < 1e-9 * np.linalg.norm(target)
    with pytest.raises(ValueError, match="at least 3 frames"):
        st.SpaceTimeProblem(2, h, eigenvalues, damping, reduced.LinearDeformer(r))


def dense_constrained_solution(problem):
    """Minimiser of E_f subject to every handle met exactly (q = z), by its KKT system."""
    A = dense_control_rows(problem)
    C, values = dense_handle_rows(problem)
    n, k = A.shape[1], len(C)
    kkt = np.block([[A.T @ A, C.T], [C, np.zeros((k, k))]])
    return np.linalg.solve(kkt, np.r_[np.zeros(n), values])[:n].reshape(-1, problem.num_modes)


def test_exact_handles_meet_the_constrained_minimum_that_a_soft_penalty_misses():
    """Two handles on a linear deformer with a deliberately soft gamma (1e-4 of the suggested
    one): the penalty solve misses them; ``exact_handles`` (method of multipliers) meets them
    and lands on the KKT solution of min E_f subject to the handles (a dense reference)."""
    rng = np.random.default_rng(8)
    r = 3
    eigenvalues = np.array([6.0, 40.0, 150.0])
    rows = rng.normal(scale=0.05, size=(2, 3, r))
    handles = st.HandleConstraints([15, 25], rows, np.zeros((2, 3)),
                                   [[0.3, -0.2, 0.1], [-0.1, 0.2, 0.2]], 1.0)
    h = 1.0 / 24.0
    damping = st.rayleigh_damping(eigenvalues, 0.1, 0.002)
    gamma, _ = st.suggest_weights(h, eigenvalues, damping, reduced.LinearDeformer(r), rows)
    problem = st.SpaceTimeProblem(40, h, eigenvalues, damping, reduced.LinearDeformer(r),
                                  handles=handles, gamma=1e-4 * gamma)
    expected = dense_constrained_solution(problem)
    soft = st.solve(problem)
    exact = st.solve(problem, exact_handles=True)
    scale = np.abs(expected).max()
    soft_error = np.abs(soft.Z[2:] - expected).max() / scale
    exact_error = np.abs(exact.Z[2:] - expected).max() / scale
    print(f"soft penalty: miss {soft.handle_residuals.max():.2e} m, off the constrained "
          f"minimum by {soft_error:.2e}; exact handles: miss {exact.handle_residuals.max():.2e}"
          f" m, off by {exact_error:.2e}")
    assert soft.handle_residuals.max() > 1e-2 and soft_error > 1e-2      # the control
    assert exact.handle_residuals.max() <= 1e-8 and exact_error <= 1e-6
    assert exact.objective >= soft.objective       # the soft minimum of J is not the constrained one
    assert exact.converged and exact.reason.startswith("handles met to")


def test_exact_handles_that_contradict_each_other_are_reported_unmet():
    """Two handles on the same vertices and frame with targets 0.4 m apart: no motion meets
    both, the multipliers cannot lower the larger miss (0.2 m each at best), and the result
    says so instead of claiming convergence."""
    r = 3
    eigenvalues = np.array([6.0, 40.0, 150.0])
    rows = np.random.default_rng(9).normal(scale=0.05, size=(1, 3, r))
    handles = st.HandleConstraints([15, 15], np.concatenate([rows, rows]), np.zeros((2, 3)),
                                   [[0.2, 0.0, 0.0], [-0.2, 0.0, 0.0]], 1.0)
    h = 1.0 / 24.0
    damping = st.rayleigh_damping(eigenvalues, 0.1, 0.002)
    gamma, _ = st.suggest_weights(h, eigenvalues, damping, reduced.LinearDeformer(r),
                                  np.concatenate([rows, rows]))
    problem = st.SpaceTimeProblem(40, h, eigenvalues, damping, reduced.LinearDeformer(r),
                                  handles=handles, gamma=gamma)
    result = st.solve(problem, exact_handles=True)
    print(result.reason)
    assert result.handle_residuals.max() >= 0.2 - 1e-9
    assert not result.converged and "stay up to" in result.reason


class ArcDeformer:
    """A handle that mode 0 carries along a circle (radius 1 m, centre (0, -1)) and mode 1
    moves off it only weakly: q(z) = (sin z0, cos z0 - 1 + c (z1 + z1^3)) [m]. A target off
    the circle is reachable, but only by driving mode 1 far."""

    num_coords = basis_size = 2

    def __init__(self, c=1e-3):
        self.c = c

    def q_batch(self, Z):
        Z = np.atleast_2d(Z)
        return np.stack([np.sin(Z[:, 0]),
                         np.cos(Z[:, 0]) - 1.0 + self.c * (Z[:, 1] + Z[:, 1] ** 3)], axis=1)

    def q_jacobian_batch(self, Z):
        Z = np.atleast_2d(Z)
        J = np.zeros((len(Z), 2, 2))
        J[:, 0, 0], J[:, 1, 0] = np.cos(Z[:, 0]), -np.sin(Z[:, 0])
        J[:, 1, 1] = self.c * (1.0 + 3.0 * Z[:, 1] ** 2)
        return J

    def q(self, z):
        return self.q_batch(z)[0]

    def q_jacobian(self, z):
        return self.q_jacobian_batch(z)[0]


def arc_problem(stiff_eigenvalue, tightness):
    """The ArcDeformer's handle keyed on frame 20 of 30 to (0.5, -0.12), 1.2 cm outside the
    circle; mode 1 at ``stiff_eigenvalue`` [rad^2/s^2]."""
    deformer = ArcDeformer()
    rows = np.array([[[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]]])
    handles = st.HandleConstraints([20], rows, np.zeros((1, 3)), [[0.5, -0.12, 0.0]], 1.0)
    h, eigenvalues = 1.0 / 24.0, np.array([40.0, stiff_eigenvalue])
    damping = st.rayleigh_damping(eigenvalues, 0.0, 0.002)
    gamma, _ = st.suggest_weights(h, eigenvalues, damping, deformer, rows, tightness=tightness)
    return st.SpaceTimeProblem(30, h, eigenvalues, damping, deformer, handles=handles,
                               gamma=gamma)


@pytest.mark.parametrize("tightness, exact", [(1e4, False), (1e6, True)])
def test_a_target_reachable_only_by_forcing_the_body_is_left_where_the_handle_closed_in(
        tightness, exact, monkeypatch):
    """Mode 1 stiff (lambda 4000): the continuation's first stage holds the handle on the
    circle, 1.21 cm from the target (the analytic distance |T - centre| - 1); raising gamma
    would meet it only with thousands of times the control energy. The solve ends at that
    first stage (the same Z as a plain penalty solve at its gamma) and says why. Control:
    with the check switched off the handle is met (or nearly) at > REACH_FORCING x the energy."""
    problem = arc_problem(4000.0, tightness)
    result = st.solve(problem, iterations=60, exact_handles=exact)
    outside = np.hypot(0.5, -0.12 + 1.0) - 1.0
    miss = result.handle_residuals.max()
    stage_gamma = problem.gamma * st.WARM_TIGHTNESS / st.handle_tightness(problem)
    stage = st.solve(replace(problem, gamma=stage_gamma), continuation=False,
                     tolerance=st.WARM_TOLERANCE)
    monkeypatch.setattr(st._Reach, "judge", lambda self, staged: st._Reach(staged))
    forced = st.solve(problem, iterations=60, exact_handles=exact)
    print(f"held: miss {miss:.4e} m (off the circle by {outside:.4e}), E_f "
          f"{result.control_energy:.3g}; forced: miss {forced.handle_residuals.max():.2e} m, "
          f"E_f {forced.control_energy:.3g}\n{result.reason}")
    assert not result.converged and "only by forcing the body" in result.reason
    assert abs(miss - outside) <= 0.02 * outside
    np.testing.assert_allclose(result.Z, stage.Z, atol=1e-4 * np.abs(stage.Z).max())
    assert forced.control_energy > st.REACH_FORCING * result.control_energy
    assert forced.handle_residuals.max() < 0.2 * miss


def test_a_target_the_modes_reach_cheaply_is_met_as_before():
    """Mode 1 soft (lambda 400): the same target costs E_f ~ 7e4 at every stage (no jump), so
    the check lets the solve go on and the multipliers meet it."""
    result = st.solve(arc_problem(400.0, 1e6), iterations=60, exact_handles=True)
    print(result.reason, f"E_f {result.control_energy:.3g}")
    assert result.converged and result.handle_residuals.max() < 1e-9


# 3. Large edit with reduced RS --------------------------------------------------------------

@pytest.fixture(scope="module")
def reduced_bar():
    """Pinned 4:1:1 bar (16 x 4 x 4 cells, 1536 tets), 20 modes, the product's ReducedRS
    (``prepare_reduced_rs``) with a small training set so it builds in about a second."""
    X, T = meshgen.box_tet_mesh((4.0, 1.0, 1.0), (16, 4, 4))
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    masses = fem.lumped_masses(X, T, 1000.0)
    result = modes.linear_modes(fem.stiffness_matrix(X, T, 1.0e6, 0.45), masses, 20, pinned)
    recon = rs.PoissonReconstruction(X, T, pinned_nodes=pinned)
    deformer, _ = reduced.prepare_reduced_rs(X, T, masses, result.vectors, result.eigenvalues,
                                             recon, num_snapshots=40, num_poses=40,
                                             max_tets=80, tol=3e-3, candidates=100)
    return X, T, result.eigenvalues, result.vectors, deformer.basis, deformer


def arc_tip(theta, length=4.0):
    """Tip centroid of the bar's centre line bent into an arc of angle theta in the x-z plane."""
    radius = length / theta
    return np.array([radius * np.sin(theta), 0.5, 0.5 - radius * (1.0 - np.cos(theta))])


def bend_tip(X, T, eigenvalues, deformer, basis):
    """Tip handle keyed to a 45 deg arc on frame 30 and a 90 deg arc on frame 60 of 100."""
    tip = np.flatnonzero(X[:, 0] > 4.0 - 1e-9)
    rows, rest = st.handle_geometry(X, basis, tip)
    handles = st.HandleConstraints([30, 60], [rows, rows], [rest, rest],
                                   [arc_tip(np.pi / 4), arc_tip(np.pi / 2)], 1.0)
    h = 1.0 / 24.0
    damping = st.rayleigh_damping(eigenvalues, 0.1, 0.002)
    gamma, _ = st.suggest_weights(h, eigenvalues, damping, deformer, handles.rows)
    problem = st.SpaceTimeProblem(100, h, eigenvalues, damping, deformer, handles=handles,
                                  gamma=gamma)
    result = st.solve(problem, iterations=100)
    q = deformer.q_batch(result.inputs)                                   # (F, rB)
    rest_volume = rs.volume(X, T, X)
    volumes = np.array([rs.volume(X, T, X + (basis @ qi).reshape(-1, 3)) for qi in q])
    return result, volumes / rest_volume


def test_large_edit_meets_the_handle_and_keeps_volume_unlike_linear_modes(reduced_bar):
    X, T, eigenvalues, W, B, deformer = reduced_bar
    diagonal = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))
    rs_result, rs_volume = bend_tip(X, T, eigenvalues, deformer, B)
    linear_result, linear_volume = bend_tip(X, T, eigenvalues,
                                            reduced.LinearDeformer(len(eigenvalues), W), W)
    rs_miss = rs_result.handle_residuals / diagonal
    rs_dev, linear_dev = np.abs(rs_volume - 1.0).max(), np.abs(linear_volume - 1.0).max()
    print(f"90 deg bend, reduced RS: residual / diagonal {rs_miss.max():.2e} "
          f"({rs_result.iterations} GN steps), volume ratio in [{rs_volume.min():.4f}, "
          f"{rs_volume.max():.4f}]; linear modes: residual / diagonal "
          f"{(linear_result.handle_residuals / diagonal).max():.2e}, volume ratio in "
          f"[{linear_volume.min():.4f}, {linear_volume.max():.4f}]")
    assert rs_result.converged
    assert rs_miss.max() <= 1e-3
    assert rs_dev < 0.05
    assert linear_dev > 0.1 and linear_dev > 3.0 * rs_dev
    # It really is a 90 deg edit: the tip sits 1.45 m closer to the root than at rest.
    tip = np.flatnonzero(X[:, 0] > 4.0 - 1e-9)
    rows, rest = st.handle_geometry(X, B, tip)
    assert (rows @ deformer.q(rs_result.inputs[60]) + rest)[0] < 2.6


def test_continuation_avoids_the_poor_basin_of_stiff_handles(reduced_bar):
    """Five cross-sections keyed onto a 45 deg, then a 90 deg arc (the bench's edit).

    Oracle: path following in the size of the edit. The same problem with the targets moved
    from rest in ten steps of 10 %, each solved from the previous one, follows the natural
    basin from the undeformed bar; the one-shot solve with the penalty continuation must meet
    the handles and reach that objective within 10 % (measured: 3.81e6 against 3.77e6,
    residuals 8e-7 and 4e-7 of the diagonal; the cold solve lands in a basin that depends on
    the modes' signs, 2.7e8 to 1.9e9, so it is only printed).
    """
    X, T, eigenvalues, W, B, deformer = reduced_bar
    planes = np.unique(X[:, 0])
    stations = planes[np.searchsorted(planes, np.arange(1, 6) * 0.8 - 1e-9)]
    geometry = [st.handle_geometry(X, B, np.flatnonzero(np.abs(X[:, 0] - s) < 1e-9))
                for s in stations]
    targets = [np.array([np.sin(a * s / 4.0), 0.0, np.cos(a * s / 4.0) - 1.0]) * 4.0 / a
               + [0.0, 0.5, 0.5] for a in (np.pi / 4, np.pi / 2) for s in stations]
    handles = st.HandleConstraints(np.repeat([30, 60], 5), [g[0] for g in geometry] * 2,
                                   [g[1] for g in geometry] * 2, targets, 1.0)
    h = 1.0 / 24.0
    damping = st.rayleigh_damping(eigenvalues, 0.1, 0.002)
    gamma, _ = st.suggest_weights(h, eigenvalues, damping, deformer, handles.rows)
    problem = st.SpaceTimeProblem(100, h, eigenvalues, damping, deformer, handles=handles,
                                  gamma=gamma)
    warm = st.solve(problem, iterations=100)
    followed = None
    for fraction in np.linspace(0.1, 1.0, 10):
        partial = replace(handles, targets=handles.rest + fraction * (handles.targets
                                                                     - handles.rest))
        followed = st.solve(replace(problem, handles=partial), iterations=100,
                            initial=None if followed is None else followed.Z,
                            continuation=False)
    cold = st.solve(problem, iterations=100, continuation=False)
    diagonal = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))
    print(f"five handles, 90 deg arc: J with continuation {warm.objective:.4e} (residual / "
          f"diagonal {warm.handle_residuals.max() / diagonal:.1e}), path-followed "
          f"{followed.objective:.4e} ({followed.handle_residuals.max() / diagonal:.1e}), "
          f"cold {cold.objective:.3e}")
    assert [entry[1] for entry in warm.history[:2]] == ["start", "warm"]
    assert np.all(np.diff(warm.objective_history) <= 0.0)
    assert followed.handle_residuals.max() <= 1e-3 * diagonal   # the reference is an answer
    assert warm.handle_residuals.max() <= 1e-3 * diagonal
    # Nearby local minima of the natural family differ by ~1 %; the poor basin is 70x higher.
    assert warm.objective <= 1.10 * followed.objective


def test_progress_reports_every_step_and_follows_the_solve_to_its_end(reduced_bar):
    """The bench's edit (continuation stages, then the motion): progress(fraction, text) comes
    once per GN step, stages included (as many reports as the solve's iterations), never goes
    back, stays within [0, 0.99], and a converged solve ends at 0.99 (its last run's decrease
    reached the tolerance), where steps against the 200-step limit said 0.18. The solve is the
    same with it as without it (bit for bit)."""
    problem, _ = bench_edit(reduced_bar)
    reports = []
    result = st.solve(problem, progress=lambda fraction, text: reports.append((fraction, text)))
    fractions = np.array([fraction for fraction, _ in reports])
    print(f"{len(reports)} reports over {result.iterations} steps: "
          f"{np.round(fractions[::5], 3)} ... {fractions[-1]:.3f}")
    assert result.converged and len(reports) == result.iterations
    assert np.all(np.diff(fractions) >= 0.0) and fractions[0] >= 0.0
    assert fractions[-1] == 0.99 and result.iterations / st.step_limit(problem) < 0.25
    assert fractions[len(fractions) // 2] < 0.9          # not at the end from the start
    assert reports[-1][1] == f"step {result.iterations}, objective {result.objective:.4g}"
    np.testing.assert_array_equal(result.Z, st.solve(problem).Z)


# 4. Material optimisation -------------------------------------------------------------------

def material_problem(seed=5):
    """Handles that follow a 1.3 Hz circle, on a body whose modes ring at other frequencies."""
    rng = np.random.default_rng(seed)
    r, m = 3, 5
    deformer = QuadraticDeformer(m, 6, rng, curvature=0.1)
    eigenvalues = np.array([20.0, 150.0, 500.0])
    h, frames = 1.0 / 24.0, 72
    keyed = np.arange(10, frames, 6)
    phase = 2.0 * np.pi * 1.3 * keyed * h
    targets = 0.5 * np.stack([np.cos(phase) - 1.0, np.sin(phase), 0.2 * np.sin(2 * phase)], axis=1)
    rows = 0.3 * rng.normal(size=(3, deformer.basis_size))
    handles = st.HandleConstraints(keyed, np.repeat(rows[None], len(keyed), 0),
                                   np.zeros((len(keyed), 3)), targets, 1.0)
    damping = st.rayleigh_damping(eigenvalues, 0.2, 0.001)
    gamma, _ = st.suggest_weights(h, eigenvalues, damping, deformer, handles.rows, tightness=100.0)
    return st.SpaceTimeProblem(frames, h, eigenvalues, damping, deformer, handles=handles,
                               gamma=gamma)


def test_sampling_gradient_matches_finite_differences():
    rng = np.random.default_rng(6)
    problem = material_problem()
    problem.keyframes = st.Keyframes([20, 40], rng.normal(size=(2, 5)), [2.0, 1.0])
    S = np.eye(5, 3) + 0.3 * rng.normal(size=(5, 3))
    Z = rng.normal(size=(problem.frames, 3))
    value, grad = st.sampling_objective(problem, Z, S, mu=7.0)
    fd = fd_gradient(lambda s: st.sampling_objective(problem, Z, s.reshape(5, 3), 7.0)[0],
                     S.reshape(-1), 1e-6).reshape(5, 3)
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-7 * np.abs(fd).max())
    terms = st.objective_terms(problem, Z, problem.eigenvalues, problem.damping, S, 7.0)
    assert abs(value - sum(terms[1:])) <= 1e-12 * value


def test_fit_material_is_exact_and_non_negative():
    h = 1.0 / 24.0
    lam, dmp = np.array([3.0, 50.0, 200.0]), np.array([0.2, 1.0, 0.0])
    Z = st.simulate_modal(lam, dmp, [1.0, 0.0, 0.5], [0.9, 0.1, 0.45], 60, h)
    fitted_lam, fitted_dmp = st.fit_material(Z, h, np.ones(3), np.ones(3))
    np.testing.assert_allclose(fitted_lam, lam, rtol=1e-8)
    np.testing.assert_allclose(fitted_dmp, dmp, atol=1e-8)
    # A growing motion wants d < 0: the constrained optimum is d = 0 and the 1-D fit of lambda.
    growing = st.simulate_modal([10.0], [-0.5], [1.0], [1.0], 60, h)
    g_lam, g_dmp = st.fit_material(growing, h, [1.0], [1.0])
    z, acc = growing[1:-1, 0], (growing[2:, 0] - 2 * growing[1:-1, 0] + growing[:-2, 0]) / h ** 2
    assert g_dmp[0] == 0.0
    np.testing.assert_allclose(g_lam[0], -(z @ acc) / (z @ z), rtol=1e-10)
    # A mode that never moves keeps its values.
    still = np.zeros((10, 2))
    still[:, 0] = np.linspace(0.0, 1.0, 10) ** 2
    kept_lam, kept_dmp = st.fit_material(still, h, [7.0, 8.0], [0.1, 0.2])
    assert (kept_lam[1], kept_dmp[1]) == (8.0, 0.2)
    # The averaged stiffness of the stable scheme is fitted just as exactly.
    Z = st.simulate_modal(lam, dmp, [1.0, 0.0, 0.5], [0.9, 0.1, 0.45], 60, h, "average")
    fitted_lam, fitted_dmp = st.fit_material(Z, h, np.ones(3), np.ones(3), "average")
    np.testing.assert_allclose(fitted_lam, lam, rtol=1e-8)
    np.testing.assert_allclose(fitted_dmp, dmp, atol=1e-8)


def test_material_optimisation_is_monotone_and_lowers_control_energy():
    problem = material_problem()
    seen = []
    z_only = st.solve(problem)
    material = st.solve(problem, optimise_material=True, iterations=8,
                        callback=lambda i, value: seen.append(value))
    history = material.objective_history
    blocks = [entry[1] for entry in material.history]
    print(f"material optimisation: J {history[0]:.4e} -> {history[-1]:.4e} in {len(history)} "
          f"steps; E_f with Z alone {z_only.control_energy:.4e}, with material "
          f"{material.control_energy:.4e}; lambda {np.round(material.eigenvalues, 2)}, "
          f"d {np.round(material.damping, 3)}, mu {material.mu:.3e}")
    assert {"z", "material", "sampling"} <= set(blocks)
    assert np.all(np.diff(history) <= 1e-12 * history[0])
    np.testing.assert_array_equal(seen, history[1:])
    assert material.control_energy < 0.9 * z_only.control_energy
    assert np.all(material.eigenvalues >= 0.0) and np.all(material.damping >= 0.0)
    assert material.objective <= z_only.objective * (1.0 + 1e-12)
    assert not np.allclose(material.sampling, np.eye(5, 3))


def test_cancel_raises_and_start_state_is_held():
    problem = material_problem()
    with pytest.raises(st.SolveCancelled):
        st.solve(problem, should_cancel=lambda: True)
    calls = []

    def cancel_later():
        calls.append(1)
        return len(calls) > 3

    with pytest.raises(st.SolveCancelled):
        st.solve(problem, optimise_material=True, should_cancel=cancel_later)
    problem.start_state = np.array([[0.01, 0.0, 0.0], [0.02, 0.0, 0.0]])
    result = st.solve(problem)
    np.testing.assert_array_equal(result.Z[:2], problem.start_state)


def test_pose_to_modal_inverts_linear_rs_and_small_poses():
    X, T = meshgen.box_tet_mesh((2.0, 0.5, 0.5), (8, 2, 2))
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    W = modes.linear_modes(fem.stiffness_matrix(X, T, 1e6, 0.3), fem.lumped_masses(X, T, 1e3),
                           6, pinned).vectors
    modal_rs = rs.linear_rs(rs.rs_operator(X, T), W)
    volumes = np.abs(fem.tet_volumes(X, T))
    z = np.random.default_rng(7).normal(size=(2, 6))
    np.testing.assert_allclose(st.pose_to_modal(modal_rs, volumes, rs.warp_modes(modal_rs, z[0])),
                               z[0], rtol=1e-9)
    small = 1e-4 * z / np.abs(W @ z.T).max()
    y = np.stack([rs.pose_to_rs(X, T, X + (W @ zi).reshape(-1, 3))[0] for zi in small])
    np.testing.assert_allclose(st.pose_to_modal(modal_rs, volumes, y), small,
                               atol=1e-3 * np.abs(small).max())


# 5. Recovering material (the seed's experiment) --------------------------------------------

def nonuniform_bar_animation(X, T, pinned, masses, youngs, poisson, damping, h, frames):
    """Full-space reference: Newmark (average acceleration, 4 substeps per frame) on linear FEM.

    youngs (E,) per-tet Young's modulus; Rayleigh damping C = a_m M + a_k K. Starts at rest in
    the static deflection under an oblique tip load (tip moved 0.25 m, ~6 % of the length).
    Returns displacements (frames, N, 3).
    """
    mu, lam = fem.lame_parameters(1.0, poisson)          # C scales linearly with E
    G = fem.gradient_operator(X, T)
    weights = np.abs(fem.tet_volumes(X, T)) * youngs
    K = G.T @ sp.kron(sp.diags(weights), sp.csr_matrix(fem.elasticity_tensor(mu, lam))) @ G
    free = np.repeat(~np.isin(np.arange(len(X)), pinned), 3)
    K = (0.5 * (K + K.T)).tocsr()[free][:, free]
    M = np.repeat(masses, 3)[free]
    C = damping[0] * sp.diags(M) + damping[1] * K
    load = np.zeros((len(X), 3))
    load[X[:, 0] > X[:, 0].max() - 1e-9] = [0.0, 0.6, 1.0]
    u = spla.spsolve(K.tocsc(), load.reshape(-1)[free])
    u *= 0.25 / np.abs(u).max()
    v, sub = np.zeros_like(u), 4
    dt = h / sub
    a = -(K @ u) / M
    solver = spla.splu((K + (2.0 / dt) * C + sp.diags(4.0 / dt ** 2 * M)).tocsc())
    out = np.zeros((frames, 3 * len(X)))
    out[0, free] = u
    for n in range(1, frames * sub):                     # reference time stepping
        rhs = M * (4.0 / dt ** 2 * u + 4.0 / dt * v + a) + C @ (2.0 / dt * u + v)
        u_new = solver.solve(rhs)
        a_new = 4.0 / dt ** 2 * (u_new - u) - 4.0 / dt * v - a
        v, u, a = v + 0.5 * dt * (a + a_new), u_new, a_new
        if n % sub == 0:
            out[n // sub, free] = u
    return out.reshape(frames, -1, 3)


def test_recovered_material_predicts_the_rest_of_the_animation_better_than_uniform():
    """300 frames of a bar whose stiffness falls 3x from root to tip; frames 0-149 are keys.

    Body: the uniform material's 12 lowest modes as candidates (Wh), 6 optimised modes. Both
    runs free-run from their own solved state at frames 148, 149 over frames 150-299, positions
    Wh S z against the reference. Measured: uniform 0.077 m RMS, recovered 0.003 m (ratio 0.04).
    """
    length, fps, frames, keyed = 4.0, 30.0, 300, 150
    h, rayleigh = 1.0 / fps, (0.05, 0.002)
    X, T = meshgen.box_tet_mesh((length, 1.0, 1.0), (12, 3, 3))
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    masses = fem.lumped_masses(X, T, 1000.0)
    stiffness = 2.0e6 * (1.5 - X[T].mean(axis=1)[:, 0] / length)         # 3e6 ... 1e6 Pa
    U = nonuniform_bar_animation(X, T, pinned, masses, stiffness, 0.3, rayleigh, h, frames)

    uniform = modes.linear_modes(fem.stiffness_matrix(X, T, 2.0e6, 0.3), masses, 12, pinned)
    W = uniform.vectors
    modal_rs = rs.linear_rs(rs.rs_operator(X, T), W)
    poses, y = [], None
    for i in range(keyed):                               # branch-continuous RS of each key
        y = rs.pose_to_rs(X, T, X + U[i], reference=y)[0]
        poses.append(y)
    zhat = st.pose_to_modal(modal_rs, np.abs(fem.tet_volumes(X, T)), np.stack(poses))
    r = 6
    eigenvalues = uniform.eigenvalues[:r]
    damping = st.rayleigh_damping(eigenvalues, *rayleigh)
    _, key_weight = st.suggest_weights(h, eigenvalues, damping, tightness=1.0)
    problem = st.SpaceTimeProblem(keyed, h, eigenvalues, damping, reduced.LinearDeformer(12, W),
                                  keyframes=st.Keyframes(np.arange(keyed), zhat, key_weight),
                                  fix_start=False)
    uniform_fit = st.solve(problem)
    recovered = st.solve(problem, optimise_material=True, iterations=10)

    def prediction_error(result):
        Z = st.simulate_modal(result.eigenvalues, result.damping, result.Z[-2], result.Z[-1],
                              frames - keyed + 2, h, result.scheme)[2:]
        predicted = (Z @ result.sampling.T @ W.T).reshape(len(Z), -1, 3)
        return float(np.sqrt(np.mean(np.sum((predicted - U[keyed:]) ** 2, axis=2))))

    uniform_error, recovered_error = prediction_error(uniform_fit), prediction_error(recovered)
    amplitude = float(np.sqrt(np.mean(np.sum(U[keyed:] ** 2, axis=2))))
    print(f"recovering material: frames 150-299 RMS error uniform {uniform_error:.4f} m, "
          f"recovered {recovered_error:.4f} m, ratio {recovered_error / uniform_error:.3f} "
          f"(RMS motion {amplitude:.4f} m); sqrt(lambda) uniform "
          f"{np.round(np.sqrt(eigenvalues[:2]), 3)} -> recovered "
          f"{np.round(np.sqrt(recovered.eigenvalues[:2]), 3)} rad/s")
    assert np.all(np.diff(recovered.objective_history) <= 1e-12 * recovered.objective_history[0])
    assert recovered.converged, recovered.reason
    assert recovered_error < 0.5 * uniform_error
    assert uniform_error > 0.3 * amplitude               # the uniform material really is off


# 6. Material optimisation that converges (issue 12) ------------------------------------------

def test_carried_sampling_gradient_matches_finite_differences():
    """d/dS' of J(Z'(S'), S') with Z' re-fitted so S' z' stays the least-squares S z."""
    rng = np.random.default_rng(8)
    problem = material_problem()
    problem.keyframes = st.Keyframes([20, 40], rng.normal(size=(2, 5)), [2.0, 1.0])
    S = np.eye(5, 3) + 0.3 * rng.normal(size=(5, 3))
    S_new = S + 0.1 * rng.normal(size=(5, 3))
    Z = 0.3 * rng.normal(size=(problem.frames, 3))
    lam, dmp = problem.eigenvalues, problem.damping

    def value(s):
        return st.carried_objective(problem, Z, S, lam, dmp, 7.0, s.reshape(5, 3))[0]

    _, grad = st.carried_objective(problem, Z, S, lam, dmp, 7.0, S_new)
    fd = fd_gradient(value, S_new.reshape(-1), 1e-6).reshape(5, 3)
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-7 * np.abs(fd).max())
    # At S' = S nothing is carried: the value is J itself.
    assert value(S) == pytest.approx(st.objective(problem, Z, lam, dmp, S, 7.0), rel=1e-12)


def bench_edit(reduced_bar, frames=100):
    """The bench's edit (``case_spacetime``) on the small bar: five cross-sections keyed onto a
    45 deg arc at 30 % and a 90 deg arc at 60 % of the range, free afterwards."""
    X, T, eigenvalues, W, B, deformer = reduced_bar
    planes = np.unique(X[:, 0])
    stations = planes[np.searchsorted(planes, np.arange(1, 6) * 0.8 - 1e-9)]
    geometry = [st.handle_geometry(X, B, np.flatnonzero(np.abs(X[:, 0] - s) < 1e-9))
                for s in stations]
    targets = [np.array([np.sin(a * s / 4.0), 0.0, np.cos(a * s / 4.0) - 1.0]) * 4.0 / a
               + [0.0, 0.5, 0.5] for a in (np.pi / 4, np.pi / 2) for s in stations]
    keyed = [round(0.3 * frames), round(0.6 * frames)]
    handles = st.HandleConstraints(np.repeat(keyed, 5), [g[0] for g in geometry] * 2,
                                   [g[1] for g in geometry] * 2, targets, 1.0)
    h = 1.0 / 24.0
    damping = st.rayleigh_damping(eigenvalues, 0.1, 0.002)
    gamma, _ = st.suggest_weights(h, eigenvalues, damping, deformer, handles.rows)
    return st.SpaceTimeProblem(frames, h, eigenvalues, damping, deformer, handles=handles,
                               gamma=gamma), keyed[-1]


def test_material_optimisation_of_a_handle_only_edit_converges_within_its_bound(reduced_bar):
    """Oracles: block descent is monotone; the material box of ``material_freedom``; the free
    tail after the last key has an exact zero-force motion (``simulate_modal``), so its E_f
    must be round-off, as without material optimisation; handles still met."""
    X = reduced_bar[0]
    diagonal = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))
    problem, last = bench_edit(reduced_bar)
    plain = st.solve(problem)
    result = st.solve(problem, optimise_material=True)

    def tail(r):
        return st.control_energy(r.Z[last:], r.eigenvalues, r.damping, problem.h, r.scheme)

    f = problem.material_freedom
    drift = np.sqrt(result.eigenvalues / problem.eigenvalues)
    ratio = result.damping / problem.damping
    history = result.objective_history
    print(f"handle-only 90 deg edit, material optimisation: converged {result.converged} "
          f"({result.reason}); sqrt(lambda_1) {np.sqrt(problem.eigenvalues[0]):.3f} -> "
          f"{np.sqrt(result.eigenvalues[0]):.3f}, frequency ratios in [{drift.min():.3f}, "
          f"{drift.max():.3f}], damping ratios in [{ratio.min():.3f}, {ratio.max():.3f}] "
          f"(bound {f}); E_f {plain.control_energy:.4e} -> {result.control_energy:.4e}; tail "
          f"E_f {tail(result):.2e} (without material {tail(plain):.2e}); residual / diagonal "
          f"{result.handle_residuals.max() / diagonal:.1e}")
    assert result.converged, result.reason
    assert np.all(np.diff(history) <= 1e-12 * history[0])
    assert np.all(drift >= 1.0 / f * (1 - 1e-12)) and np.all(drift <= f * (1 + 1e-12))
    assert np.all(ratio >= 1.0 / f * (1 - 1e-12)) and np.all(ratio <= f * (1 + 1e-12))
    assert result.control_energy < plain.control_energy            # the material did help
    assert tail(result) <= max(tail(plain), 1e-12 * result.control_energy)
    assert result.handle_residuals.max() <= 1e-3 * diagonal


def test_sampling_moves_where_the_candidate_modes_lower_the_objective():
    """Four candidate modes, two optimised; keys ask for a pose with candidate 3 in it.

    With S = [I; 0] no input S z has a third coordinate, so every key misses by at least that
    part of its pose (a lower bound); dJ/dS is then non-zero, and S must move and beat it.
    """
    rng = np.random.default_rng(9)
    h, frames = 1.0 / 24.0, 48
    eigenvalues = np.array([30.0, 120.0])
    keyed = np.arange(8, frames, 8)
    phase = 2.0 * np.pi * 0.8 * keyed * h
    poses = np.outer(np.sin(phase), [1.0, 0.3, 0.6, 0.0])
    damping = st.rayleigh_damping(eigenvalues, 0.1, 0.002)
    _, weight = st.suggest_weights(h, eigenvalues, damping, tightness=100.0)
    problem = st.SpaceTimeProblem(frames, h, eigenvalues, damping,
                                  QuadraticDeformer(4, 6, rng),
                                  keyframes=st.Keyframes(keyed, poses, weight))
    plain = st.solve(problem)
    _, grad = st.sampling_objective(problem, plain.Z, problem.sampling, 0.0)
    result = st.solve(problem, optimise_material=True)
    moved = np.linalg.norm(result.sampling - problem.sampling)
    floor = np.linalg.norm(poses[:, 2])
    print(f"candidate modes: |dJ/dS| at [I; 0] {np.linalg.norm(grad):.3e}, |S - S0| {moved:.3f}; "
          f"J {plain.objective:.4e} -> {result.objective:.4e}; key misses {np.linalg.norm(plain.keyframe_residuals):.4f} -> "
          f"{np.linalg.norm(result.keyframe_residuals):.4f} (floor with [I; 0] {floor:.4f}); "
          f"converged {result.converged} ({result.reason})")
    assert np.linalg.norm(grad) > 1e-3 * np.abs(plain.Z).max() * weight
    assert np.linalg.norm(plain.keyframe_residuals) >= floor * (1 - 1e-9)
    assert moved > 1e-2
    assert result.objective < plain.objective
    assert np.linalg.norm(result.keyframe_residuals) < 0.5 * floor
    assert np.all(np.diff(result.objective_history) <= 1e-12 * result.objective_history[0])
