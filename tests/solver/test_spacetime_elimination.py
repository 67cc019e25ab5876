"""The space-time GN step with the frames no handle touches eliminated (issue 30, item 3).

Oracles: a dense solve of the banded normal equations (``normal_equations``) for the step, the
gradient of J by central differences and the Newton decrement g^T H^-1 g / 2 (the decrease a
GN step still predicts, H the GN matrix) for the stationarity of the result, and an independent
minimiser (scipy's L-BFGS-B on the full objective with the analytic gradient) for its value.
"""

import numpy as np
import pytest
import scipy.linalg
import scipy.optimize

from solver import spacetime as st
from test_spacetime import QuadraticDeformer


def edit(frames, r=3, seed=0, keyframes=True, gamma=50.0):
    """A free-tailed edit: 2 handles on frames 0.3 F and 0.6 F, a keyframe, external forces."""
    rng = np.random.default_rng(seed)
    deformer = QuadraticDeformer(r + 1, 6, rng)
    keyed = [round(0.3 * frames), round(0.6 * frames)]
    handles = st.HandleConstraints(frames=np.repeat(keyed, 2), rows=rng.normal(size=(4, 3, 6)),
                                   rest=rng.normal(size=(4, 3)), weights=[1.0, 0.5, 2.0, 1.0],
                                   targets=rng.normal(size=(4, 3)))
    keys = (st.Keyframes(frames=[round(0.45 * frames)], poses=0.3 * rng.normal(size=(1, r + 1)),
                         weights=[2.0]) if keyframes else None)
    eigenvalues = np.linspace(2.0, 30.0, r)
    return st.SpaceTimeProblem(frames, 1.0 / 24.0, eigenvalues,
                               st.rayleigh_damping(eigenvalues, 0.1, 0.01), deformer,
                               handles=handles, keyframes=keys, gamma=gamma, mu=0.0,
                               external_forces=0.1 * rng.normal(size=(frames, r)))


def dense_from_band(ab):
    n = ab.shape[1]
    A = np.zeros((n, n))
    for d in range(ab.shape[0]):
        A[np.arange(d, n), np.arange(n - d)] = ab[d, :n - d]
    return A + np.tril(A, -1).T


@pytest.mark.parametrize("keyframes", [False, True])
def test_eliminated_step_is_the_dense_gauss_newton_step(monkeypatch, keyframes):
    """Without chord corrections and damping, one eliminated step is -H^-1 g of the full system."""
    monkeypatch.setattr(st, "CORRECTIONS", 0)
    problem = edit(60, keyframes=keyframes)
    Z0 = 0.2 * np.random.default_rng(3).normal(size=(60, problem.num_modes))
    Z0[:2] = 0.0
    ab, g = st.normal_equations(problem, Z0, problem.eigenvalues, problem.damping,
                                problem.sampling)
    expected = Z0.copy()
    expected[2:] += np.linalg.solve(dense_from_band(ab), -g).reshape(-1, problem.num_modes)
    state = st._State(problem, Z0.copy(), 0.0)
    elimination = st._elimination(state)
    assert elimination is not None
    st._eliminated_step(state, 0.0, elimination)
    assert state.value < st._State(problem, Z0.copy(), 0.0).value     # the step was accepted
    np.testing.assert_allclose(state.Z, expected, rtol=0, atol=1e-9 * np.abs(expected).max())


def predicted_decrease(problem, Z):
    """Newton decrement g^T H^-1 g / 2 of J at Z, H the banded GN matrix."""
    ab, g = st.normal_equations(problem, Z, problem.eigenvalues, problem.damping,
                                problem.sampling)
    return 0.5 * float(g @ scipy.linalg.solveh_banded(ab, g, lower=True))


def fd_gradient(problem, Z, step=1e-6):
    """Central-difference dJ/dZ on the free frames."""
    base = Z[2:].reshape(-1)
    grad = np.empty_like(base)
    for i in range(len(base)):
        values = []
        for sign in (1.0, -1.0):
            x = base.copy()
            x[i] += sign * step
            trial = Z.copy()
            trial[2:] = x.reshape(-1, problem.num_modes)
            values.append(st.objective(problem, trial, problem.eigenvalues, problem.damping,
                                       problem.sampling))
        grad[i] = (values[0] - values[1]) / (2.0 * step)
    return grad


def test_solve_is_stationary_and_matches_an_independent_minimiser():
    problem = edit(40, seed=1)
    result = st.solve(problem, tolerance=1e-12)       # run on to stationarity
    assert result.converged, result.reason
    grad = st.z_gradient(problem, result.Z, problem.eigenvalues, problem.damping,
                         problem.sampling)[2:].reshape(-1)
    np.testing.assert_allclose(grad, fd_gradient(problem, result.Z), rtol=0,
                               atol=1e-5 * np.abs(grad).max() + 1e-6)
    assert predicted_decrease(problem, result.Z) <= 1e-8 * result.objective

    def fun(x):
        Z = result.Z.copy()
        Z[2:] = x.reshape(-1, problem.num_modes)
        value = st.objective(problem, Z, problem.eigenvalues, problem.damping, problem.sampling)
        return value, st.z_gradient(problem, Z, problem.eigenvalues, problem.damping,
                                    problem.sampling)[2:].reshape(-1)

    reference = scipy.optimize.minimize(fun, np.zeros(result.Z[2:].size), jac=True,
                                        method="L-BFGS-B",
                                        options=dict(maxiter=20000, ftol=1e-15, gtol=1e-10))
    assert result.objective <= reference.fun * (1.0 + 1e-9)
    np.testing.assert_allclose(result.objective, reference.fun, rtol=1e-6)


@pytest.mark.parametrize("frames", [400, 800])
def test_long_edits_converge_to_a_stationary_point(frames):
    """The frame count only sets the cost of one banded factor per block: a long free tail and
    long stretches between the handles converge like a short edit (KKT: |dJ/dZ| small)."""
    problem = edit(frames, seed=2)
    result = st.solve(problem, tolerance=1e-12)       # run on to stationarity
    assert result.converged, result.reason
    assert predicted_decrease(problem, result.Z) <= 1e-8 * result.objective
    # the free tail after the last handle carries no control force
    control = st.dynamics_residual(result.Z, problem.eigenvalues, problem.damping, problem.h,
                                   problem.scheme, problem.external_forces)
    assert np.abs(control[round(0.6 * frames):]).max() <= 1e-6 * np.abs(control).max()


@pytest.mark.parametrize("coupled", [False, True])
def test_band_factor_solves_and_its_frame_columns_match_the_dense_inverse(coupled):
    """``_BandFactor`` against the dense inverse: mode by mode when only E_f's bands (offsets
    0, r, 2r) are set, frame-major when a frame's block couples its modes."""
    problem = edit(40, r=3, keyframes=False)
    r, s = problem.num_modes, problem.first_free
    blocks = np.zeros((problem.frames - s, r, r))
    if coupled:                                      # a pose key's block: every mode of frame 9
        rows = np.random.default_rng(5).normal(size=(4, r))
        blocks[9] = rows.T @ rows
    ab = st._assemble_band(problem, problem.eigenvalues, problem.damping, blocks)
    factor = st._BandFactor(ab, r)
    assert factor.by_mode is not coupled
    inverse = np.linalg.inv(dense_from_band(ab))
    b = np.random.default_rng(6).normal(size=(ab.shape[1], 2))
    np.testing.assert_allclose(factor.solve(b), inverse @ b, rtol=1e-10, atol=0)
    np.testing.assert_allclose(factor.solve(b[:, 0]), inverse @ b[:, 0], rtol=1e-10, atol=0)
    frames = np.array([5, 20])
    columns = (frames[:, None] * r + np.arange(r)).reshape(-1)
    apply, block = factor.frame_columns(frames)
    w = np.random.default_rng(7).normal(size=len(columns))
    scale = np.abs(inverse).max()
    np.testing.assert_allclose(apply(w), inverse[:, columns] @ w, rtol=0,
                               atol=1e-12 * scale * np.abs(w).sum())
    np.testing.assert_allclose(block, inverse[np.ix_(columns, columns)], rtol=0,
                               atol=1e-12 * scale)
