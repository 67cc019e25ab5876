"""A take from an animation, the material fitted to it, the motion continued (issue 28).

Oracles: the seed's experiment (SPEC.md section 5, "Recovering material"): a full-space linear
FEM reference (Newmark, assembled here from fem's per-tet stiffness) of a pinned bar whose
Young's modulus falls threefold from root to tip (the painted material's per-tet E); a uniform
body takes its first frames, fits, continues; its error on the rest of the reference against
the uniform material's; a take of poses the body's own modes make is read back exactly.
"""
import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from solver import fem, meshgen, preparation, problems, spacetime, take

LENGTH, WIDTH, POISSON, DENSITY = 4.0, 1.0, 0.3, 1000.0
ROOT_YOUNGS, RATIO, UNIFORM_YOUNGS = 3.0e6, 1.0 / 3.0, 2.0e6
FPS, RAYLEIGH, MODES = 30.0, (0.05, 0.002), 12
KEYED, FRAMES = 150, 300


def reference_animation(X, T, pinned, tet_youngs, tip, frames, substeps=4):
    """Displacements (frames, N, 3) [m] of full-space linear FEM with per-tet Young's modulus
    tet_youngs (E,), Rayleigh damping RAYLEIGH, Newmark average acceleration with ``substeps``
    per frame; it starts at rest in the static deflection under an oblique tip load, scaled so
    the largest displacement is ``tip`` [m]."""
    K = fem.stiffness_matrix(X, T, tet_youngs, POISSON)
    free = np.repeat(~np.isin(np.arange(len(X)), pinned), 3)
    K = sp.csr_matrix(0.5 * (K + K.T))[free][:, free]
    M = np.repeat(fem.lumped_masses(X, T, DENSITY), 3)[free]
    C = RAYLEIGH[0] * sp.diags(M) + RAYLEIGH[1] * K
    load = np.zeros((len(X), 3))
    load[X[:, 0] > X[:, 0].max() - 1e-9] = [0.0, 0.6, 1.0]
    u = spla.spsolve(K.tocsc(), load.reshape(-1)[free])
    u *= tip / np.abs(u).max()
    v, dt = np.zeros_like(u), 1.0 / FPS / substeps
    a = -(K @ u) / M
    step = spla.splu((K + (2.0 / dt) * C + sp.diags(4.0 / dt ** 2 * M)).tocsc())
    out = np.zeros((frames, 3 * len(X)))
    out[0, free] = u
    for n in range(1, frames * substeps):                # the recurrence over time is inherent
        rhs = M * (4.0 / dt ** 2 * u + 4.0 / dt * v + a) + C @ (2.0 / dt * u + v)
        u_new = step.solve(rhs)
        a_new = 4.0 / dt ** 2 * (u_new - u) - 4.0 / dt * v - a
        v, u, a = v + 0.5 * dt * (a + a_new), u_new, a_new
        if n % substeps == 0:
            out[n // substeps, free] = u
    return out.reshape(frames, len(X), 3)


@pytest.fixture(scope="module")
def bar():
    """A 4 x 1 x 1 m bar (12 x 3 x 3 cells) pinned at x = 0, its render vertices the tet nodes:
    the uniform body (12 modes, reduced RS) and the painted reference's per-tet E (the painted
    material's recipe: weight 1 - x / L, ratio 1/3, so 3e6 Pa at the root, 1e6 Pa at the tip)."""
    X, T = meshgen.box_tet_mesh((LENGTH, WIDTH, WIDTH), (12, 3, 3))
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    body = preparation.prepare_body(X, T, X, UNIFORM_YOUNGS, POISSON, DENSITY, MODES, pinned)
    scale = preparation.stiffness_scale(body.tet_body, 1.0 - X[:, 0] / LENGTH, RATIO)
    return body, X, T, pinned, ROOT_YOUNGS * scale


def test_a_take_the_modes_can_make_is_read_back_exactly(bar):
    """Poses made by the body's own reduced RS from known modal coordinates (the tip moving up
    to ~1.9 m on a 4 m bar) come back as those coordinates, with a fit residual within the
    reduced model's own accuracy (its cubature: 1e-3 of the pose's size)."""
    body, X, *_ = bar
    z = np.zeros((5, MODES))
    z[:, 0] = np.linspace(10.0, 80.0, 5)              # mode 1, growing
    z[:, 2] = np.linspace(0.0, 6.0, 5)
    source = body.surface_positions(X, z)
    inputs, residuals = take.take_to_modal(body, X, source)
    tip = np.abs(source - X).max()
    print(f"take of the body's own poses: tip {tip:.3f} m, worst residual {residuals.max():.2e} m")
    assert tip > 0.5                                    # large enough to need RS, not linear
    assert residuals.max() < 1e-3 * tip
    np.testing.assert_allclose(inputs, z, atol=1e-3 * np.abs(z).max())


def simulated_continuation(body, X, fitted, use_fitted, truth):
    """RMS error [m] against truth (k, N, 3) displacements of the body's simulation (Linear
    material, reduced RS) from the fit's last frame with the fitted material (its stiffness and
    its Rayleigh damping) or the prepared one, started from the fit's state."""
    potential = problems.linear_potential(body, UNIFORM_YOUNGS, POISSON)
    damping = RAYLEIGH
    if use_fitted:
        potential, damping = take.FittedPotential(potential, fitted), take.fitted_rayleigh(fitted)
        S, G = fitted.sampling, fitted.sampling.T @ fitted.sampling
        restricted = scipy.linalg.eigh(S.T @ potential.rest_hessian @ S, G, eigvals_only=True)
        np.testing.assert_allclose(restricted, np.sort(fitted.eigenvalues), rtol=1e-8)
    simulation = problems.simulation(body, potential, problems.SimulationSettings(
        h=fitted.h, density=DENSITY, damping_mass=damping[0], damping_stiffness=damping[1]))
    simulation.set_state(*take.continuation_state(fitted))
    positions = simulation.run(len(truth)).world_positions(X, body.surface_basis)[1:]
    return float(np.sqrt(np.mean(take.position_rms(positions, X + truth) ** 2)))


def test_fitted_material_continues_the_take_closer_than_the_uniform_material(bar):
    """The seed's experiment, linear regime (tip ~6 % of the length): the uniform body takes
    frames 1-150 of the painted reference, fits and continues to 300; its RMS error on
    151-300 is at most a third of the uniform material's and under 2 % of the diagonal."""
    body, X, T, pinned, tet_youngs = bar
    U = reference_animation(X, T, pinned, tet_youngs, 0.06 * LENGTH, FRAMES)
    frames = np.arange(1, KEYED + 1)
    source = X + U[:KEYED]
    inputs, residuals = take.take_to_modal(body, X, source)
    h = 1.0 / FPS
    errors, simulated = {}, {}
    for optimise in (False, True):
        fitted = take.fit_material(body, X, frames, source, inputs, h, *RAYLEIGH,
                                   optimise=optimise)
        assert fitted.last_frame == KEYED
        continued = body.surface_positions(X, take.continue_motion(fitted, FRAMES - KEYED))
        errors[optimise] = float(np.sqrt(np.mean(take.position_rms(continued, X + U[KEYED:]) ** 2)))
        simulated[optimise] = simulated_continuation(body, X, fitted, optimise, U[KEYED:])
    diagonal = np.linalg.norm([LENGTH, WIDTH, WIDTH])
    print(f"take: worst frame residual {residuals.max():.4f} m (frame "
          f"{frames[np.argmax(residuals)]}); fit residual {fitted.residual:.4f} m; "
          f"continuation 151-300 RMS uniform {errors[False]:.4f} m, fitted {errors[True]:.4f} m "
          f"(ratio {errors[True] / errors[False]:.3f}, {100 * errors[True] / diagonal:.2f} % of "
          f"the diagonal); frequencies prepared {np.round(fitted.prepared_frequencies[:3], 3)} "
          f"-> fitted {np.round(fitted.frequencies[:3], 3)} Hz")
    print(f"simulated on (reduced RS, Linear): uniform {simulated[False]:.4f} m, fitted "
          f"{simulated[True]:.4f} m (ratio {simulated[True] / simulated[False]:.3f})")
    assert fitted.converged, fitted.reason
    assert errors[True] <= errors[False] / 3.0
    assert errors[True] < 0.02 * diagonal
    assert errors[False] > 0.01 * diagonal               # the uniform material really is off
    assert simulated[True] <= simulated[False] / 3.0
    assert simulated[True] < 0.02 * diagonal
    assert residuals.max() < 0.01 * diagonal              # the modes express the take


def test_fitted_material_continues_a_take_past_45_degrees(bar):
    """The seed's experiment with large rotations: the reference is the painted bar's own
    reduced RS simulation (Linear material, the same tets, stiffness 3e6 Pa at the root falling
    to 1e6 at the tip) released from a bend whose tip turns past 45 deg; the uniform body takes
    frames 1-150, fits, continues to 300. At most a third of the uniform material's error and
    under 2 % of the diagonal on 151-300."""
    body, X, T, pinned, _ = bar
    painted = preparation.prepare_body(
        X, T, X, ROOT_YOUNGS, POISSON, DENSITY, MODES, pinned,
        settings=preparation.ReducedSettings(basis_size=30, cubature_tets=60, training_poses=24),
        stiffness=(1.0 - X[:, 0] / LENGTH, RATIO))
    h = 1.0 / FPS
    simulation = problems.simulation(
        painted, problems.linear_potential(painted, ROOT_YOUNGS, POISSON),
        problems.SimulationSettings(h=h, density=DENSITY, damping_mass=RAYLEIGH[0],
                                    damping_stiffness=RAYLEIGH[1]))
    start = np.zeros(MODES)
    start[:2] = 75.0, 37.5                                # modes 1 and 2, mass-normalised
    simulation.set_state(start)
    reference = simulation.run(FRAMES - 1).world_positions(X, painted.surface_basis)
    tip, before = X[:, 0] > LENGTH - 1e-9, np.abs(X[:, 0] - LENGTH * 11 / 12) < 1e-9
    axis = reference[:, tip].mean(axis=1) - reference[:, before].mean(axis=1)
    turn = np.degrees(np.arccos(axis[:, 0] / np.linalg.norm(axis, axis=1))).max()

    frames = np.arange(1, KEYED + 1)
    inputs, residuals = take.take_to_modal(body, X, reference[:KEYED])
    errors = {}
    for optimise in (False, True):
        fitted = take.fit_material(body, X, frames, reference[:KEYED], inputs, h, *RAYLEIGH,
                                   optimise=optimise)
        continued = body.surface_positions(X, take.continue_motion(fitted, FRAMES - KEYED))
        errors[optimise] = float(np.sqrt(np.mean(
            take.position_rms(continued, reference[KEYED:]) ** 2)))
    diagonal = np.linalg.norm([LENGTH, WIDTH, WIDTH])
    print(f"take past 45 deg: tip turns up to {turn:.1f} deg; worst frame residual "
          f"{residuals.max():.4f} m; continuation 151-300 RMS uniform {errors[False]:.4f} m, "
          f"fitted {errors[True]:.4f} m (ratio {errors[True] / errors[False]:.3f}, "
          f"{100 * errors[True] / diagonal:.2f} % of the diagonal)")
    assert turn > 45.0
    assert fitted.converged, fitted.reason
    assert errors[True] <= errors[False] / 3.0
    assert errors[True] < 0.02 * diagonal


def test_a_fitted_material_survives_its_plain_form(bar):
    """to_dict / from_dict (what the .blend keeps) give back every number."""
    body, X, *_ = bar
    rng = np.random.default_rng(4)
    fitted = take.FittedMaterial(rng.random(8), rng.random(8), rng.random((12, 8)),
                                 rng.random(8), rng.random(8), rng.random((2, 8)), 1, 150,
                                 1 / 30, "central", 0.01, 42, False, "why")
    back = take.FittedMaterial.from_dict(fitted.to_dict())
    for name in take.FittedMaterial.ARRAYS:
        np.testing.assert_array_equal(getattr(back, name), getattr(fitted, name))
    assert (back.first_frame, back.last_frame, back.worst_frame, back.reason) == (1, 150, 42, "why")


def test_an_edit_with_the_fitted_material_starts_from_it_and_keeps_its_free_motion(bar):
    """Use Fitted Material: the space-time problem takes the fitted eigenvalues, damping and
    sampling; and the fitted material's own continuation, given as the take of an edit with
    that material, costs no control force (E_f = 0 up to round-off) while the prepared
    material's does not fit it."""
    body, X, *_ = bar
    m = body.deformer.num_coords
    rng = np.random.default_rng(2)
    r = take.fitted_modes(m)
    fitted = take.FittedMaterial(body.linear_modes.eigenvalues[:r] * rng.uniform(1.2, 1.6, r),
                                 np.full(r, 0.1), np.eye(m, r), body.linear_modes.eigenvalues[:r],
                                 np.full(r, 0.05), np.array([np.full(r, 4.0), np.full(r, 3.9)]),
                                 1, 40, 1.0 / FPS, "central", 0.0, 1)
    inputs = take.continue_motion(fitted, 30)
    settings = problems.SpaceTimeSettings(h=1.0 / FPS, fitted=fitted)
    frames = list(range(41, 71))
    problem = problems.spacetime_problem(body, X, frames, take=(frames, list(
        body.surface_positions(X, inputs))), settings=settings).problem
    np.testing.assert_array_equal(problem.eigenvalues, fitted.eigenvalues)
    np.testing.assert_array_equal(problem.sampling, fitted.sampling)
    Z = inputs[:, :r]
    own = spacetime.control_energy(Z, fitted.eigenvalues, fitted.damping, fitted.h, "central")
    prepared = spacetime.control_energy(Z, fitted.prepared_eigenvalues, fitted.prepared_damping,
                                        fitted.h, "central")
    print(f"E_f of the fitted material's free motion: own {own:.2e}, prepared {prepared:.2e}")
    assert own < 1e-12 * prepared
    assert prepared > 0.0
