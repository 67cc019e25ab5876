"""Problem assembly from a prepared body (solver.problems) and poses read through it
(solver.poses).

Oracles: the handle rows are the mean of the handle vertices' rows of Φ B (a direct numpy
computation); a handle keyed where the model itself puts a vertex group is met; modal
coordinates of poses the modes made come back; an interpolation returns its end poses exactly.
"""
import numpy as np
import pytest
import scipy.sparse.linalg as spla

from solver import body as body_module
from solver import (embed, fem, materials, meshgen, modes, poses, preparation, problems, reduced,
                    rs, spacetime)

SIZE = (4.0, 1.0, 1.0)


@pytest.fixture(scope="module")
def bar():
    """A prepared 4:1:1 bar pinned at x = 0 (8 x 2 x 2 cells), 6 modes; its render mesh is
    a cloud of points inside it."""
    X, T = meshgen.box_tet_mesh(SIZE, (8, 2, 2))
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    masses = fem.lumped_masses(X, T, 1000.0)
    linear = modes.linear_modes(fem.stiffness_matrix(X, T, 1e6, 0.45), masses, 6, pinned)
    recon = rs.PoissonReconstruction(X, T, pinned_nodes=pinned)
    deformer, _ = reduced.prepare_reduced_rs(X, T, masses, linear.vectors, linear.eigenvalues,
                                             recon, seed=0)
    # The render mesh: the tet nodes and points inside the bar away from the pinned end, so a
    # render vertex is pinned exactly when it sits on a pinned node.
    rng = np.random.default_rng(7)
    points = np.vstack([X, rng.uniform([0.6, 0.0, 0.0], SIZE, (60, 3))])
    tet_body = body_module.TetBody(X, T, embed.embed_points(X, T, points))
    prepared = body_module.PreparedBody(tet_body, linear, deformer)
    return prepared, tet_body.embedding @ X


def test_optimised_modes_are_two_thirds_rounded_up():
    assert [problems.optimised_modes(m) for m in (1, 2, 3, 6, 20)] == [1, 2, 2, 4, 14]


def test_spread_sample_takes_the_far_ends_of_a_line_first():
    line = np.c_[np.linspace(0.0, 1.0, 11), np.zeros(11), np.zeros(11)]
    assert set(problems.spread_sample(line, 2)) == {0, 10}
    assert sorted(problems.spread_sample(line, 3)) == [0, 5, 10]


def _tip_track(rest, targets, frames, weight=1.0):
    tip = np.flatnonzero(rest[:, 0] > 3.0)
    return problems.HandleTrack("Tip", tip, weight, np.asarray(frames), np.asarray(targets))


def test_handle_rows_are_the_mean_of_the_handle_vertices_rows(bar):
    body, rest = bar
    track = _tip_track(rest, rest[rest[:, 0] > 3.0].mean(axis=0)[None].repeat(2, 0), [3, 7])
    settings = problems.SpaceTimeSettings(h=1.0 / 24.0)
    setup = problems.spacetime_problem(body, rest, list(range(1, 11)), [track], settings=settings)
    handles = setup.problem.handles
    rows = body.surface_basis.reshape(len(rest), 3, -1)[track.vertices].mean(axis=0)
    assert setup.track_slices == [slice(0, 2)]
    np.testing.assert_allclose(handles.rows, np.repeat(rows[None], 2, axis=0), rtol=1e-12)
    np.testing.assert_array_equal(handles.frames, [2, 6])           # counted from frame 1
    np.testing.assert_allclose(setup.rest_centroids[0], rest[track.vertices].mean(axis=0))
    assert setup.problem.fix_start and setup.problem.keyframes is None


def test_nothing_to_solve_for_is_refused(bar):
    body, rest = bar
    with pytest.raises(ValueError, match="nothing to solve for"):
        problems.spacetime_problem(body, rest, [1, 2, 3, 4],
                                   settings=problems.SpaceTimeSettings(h=1.0 / 24.0))


def test_a_handle_keyed_where_the_model_bends_the_tip_is_met(bar):
    body, rest = bar
    z = np.zeros(body.deformer.num_coords)
    z[0] = 0.5 / np.abs(body.surface_mode(0)).max()                 # tip about 0.5 m down
    bent = body.surface_positions(rest, z)
    tip = rest[:, 0] > 3.0
    target = bent[tip].mean(axis=0)
    settings = problems.SpaceTimeSettings(h=1.0 / 24.0, damping_mass=0.5)
    setup = problems.spacetime_problem(body, rest, list(range(1, 25)),
                                       [_tip_track(rest, target[None], [24])], settings=settings)
    result = spacetime.solve(setup.problem, iterations=30)
    reached = body.surface_positions(rest, result.inputs[-1])[tip].mean(axis=0)
    miss = np.linalg.norm(reached - target)
    print(f"tip target moved {np.linalg.norm(target - rest[tip].mean(axis=0)):.3f} m, miss {miss:.2e} m")
    assert miss < 2e-3


def test_a_take_is_followed_softly_and_frees_the_start(bar):
    body, rest = bar
    frames = list(range(1, 9))
    take = (frames, np.repeat(rest[None], len(frames), axis=0))
    setup = problems.spacetime_problem(body, rest, frames, take=take,
                                       settings=problems.SpaceTimeSettings(h=1.0 / 24.0))
    assert not setup.problem.fix_start and setup.problem.handles is None
    np.testing.assert_array_equal(setup.problem.keyframes.frames, np.arange(8))
    np.testing.assert_allclose(setup.problem.keyframes.poses, 0.0, atol=1e-9)   # rest is z = 0


def test_poses_the_modes_made_come_back_as_their_modal_coordinates(bar):
    body, rest = bar
    Z = np.zeros((3, body.linear_modes.vectors.shape[1]))
    Z[:, 0] = [0.0, 0.002, 0.004]
    Z[2, 2] = 0.003
    made = np.array([rest + body.surface(body.reconstruction.reconstruct(body.modal_rs @ z))
                     for z in Z])
    fitted = poses.poses_to_modal(body, made)
    print(f"largest error {np.abs(fitted - Z).max() / np.abs(Z).max():.2%} of the largest coordinate")
    # Not exact: the reconstruction of linear RS targets is a least-squares fit (0.5 % here).
    np.testing.assert_allclose(fitted, Z, atol=1e-2 * np.abs(Z).max())


def test_a_spin_past_a_half_turn_stays_continuous(bar):
    """Each pose's rotation branch is chained to the previous one's: a turn of the whole bar in
    steps of 40 deg up to 400 deg gives modal coordinates that move by about as much each step
    (a lost branch would jump by a full turn's worth)."""
    body, rest = bar
    centre = rest.mean(axis=0)
    angles = np.radians(np.arange(0, 401, 40))
    spin = [centre + (rest - centre) @ rs.exp_rotation(np.array([[a, 0.0, 0.0]]))[0].T
            for a in angles]
    fitted = poses.poses_to_modal(body, np.array(spin))
    steps = np.linalg.norm(np.diff(fitted, axis=0), axis=1)
    print(np.round(steps, 4))
    assert steps.max() < 1.5 * np.median(steps)


def test_an_interpolation_gives_back_its_end_poses_and_holds_the_pins(bar):
    body, rest = bar
    z = np.zeros(body.deformer.num_coords)
    z[1] = 0.3 / np.abs(body.surface_mode(1)).max()
    a, b = rest, body.surface_positions(rest, z)
    assert poses.keeps_pins(body, rest, a, b)
    out, inverted = poses.interpolate_poses(body, rest, a, b, [0.0, 0.5, 1.0])
    np.testing.assert_allclose(out[0], a, atol=1e-9)
    np.testing.assert_allclose(out[2], b, atol=1e-9)
    pinned = body.displacement_embedding[:, body.pinned_nodes].getnnz(axis=1) > 0
    np.testing.assert_allclose(out[1][pinned], rest[pinned], atol=1e-9)
    assert inverted == 0


# --- simulation ------------------------------------------------------------------------------

def test_a_free_body_falls_as_free_fall_says(bar):
    """No pins: the simulation's body is free; after 12 frames under g its centre of mass has
    dropped g t^2 / 2 (the potential is translation-invariant, nothing else acts)."""
    pinned_body, rest = bar
    free = preparation.prepare_body(pinned_body.nodes, pinned_body.tets, rest, 1e6, 0.45,
                                    1000.0, 6, settings=preparation.ReducedSettings(
                                        basis_size=40, cubature_tets=60))
    settings = problems.SimulationSettings(h=1.0 / 24.0, density=1000.0, gravity=(0.0, 0.0, -9.81))
    sim = problems.simulation(free, problems.linear_potential(free, 1e6, 0.45), settings)
    assert sim.free
    trajectory = sim.run(12)
    masses = free.lumped_masses(1000.0)
    positions = trajectory.world_positions(free.nodes, free.deformer.basis)
    drop = (masses @ positions[-1] - masses @ positions[0]) / masses.sum()
    t = 12 / 24.0
    print(f"drop {drop[2]:.6f} m, free fall {-0.5 * 9.81 * t ** 2:.6f} m")
    np.testing.assert_allclose(drop, [0.0, 0.0, -0.5 * 9.81 * t ** 2], rtol=1e-6, atol=1e-9)
    # the reconstruction barrier evaluates q with the simulation's own (float32) deformer,
    # which keeps the pose Newton has just evaluated for it
    assert sim.potential.barrier.deformer is sim.deformer
    assert sim.deformer.dtype == np.float32 and free.deformer.dtype == np.float64


def test_a_pinned_bar_settles_where_the_full_static_solution_puts_its_tip(bar):
    """Static equilibrium of the simulation under gravity against the full-space linear FEM
    solution K u = f (scipy's sparse solve over every free node): a soft bar's tip sags by a few
    per cent of its length, which the first modes carry."""
    body, rest = bar
    youngs = 2e7
    unit = preparation.unit_stiffness_modes(body.tet_body, 0.45, 6, body.pinned_nodes)
    unit_deformer = preparation.reduced_deformer(body.tet_body, unit,
                                                 preparation.ReducedSettings())
    soft = body_module.PreparedBody(body.tet_body, preparation.modes_at(unit, youngs, 1000.0),
                                    preparation.deformer_at(unit_deformer, 1000.0))
    settings = problems.SimulationSettings(h=1.0 / 24.0, density=1000.0, gravity=(0.0, 0.0, -9.81))
    sim = problems.simulation(soft, problems.linear_potential(soft, youngs, 0.45), settings)
    sim.static_equilibrium()
    sag = (soft.deformer.basis @ sim.q).reshape(-1, 3)
    X, T = soft.nodes, soft.tets
    K = fem.stiffness_matrix(X, T, youngs, 0.45)
    f = np.zeros((len(X), 3))
    f[:, 2] = -9.81 * soft.lumped_masses(1000.0)
    free = np.setdiff1d(np.arange(3 * len(X)), (3 * soft.pinned_nodes[:, None] + np.arange(3)).ravel())
    u = np.zeros(3 * len(X))
    u[free] = spla.spsolve(K.tocsc()[free][:, free], f.ravel()[free])
    tip = np.flatnonzero(X[:, 0] > 4.0 - 1e-9)
    full, reduced_ = u.reshape(-1, 3)[tip, 2].mean(), sag[tip, 2].mean()
    print(f"tip sag: reduced {reduced_:.5f} m, full FEM {full:.5f} m")
    assert full < -0.02                                   # a real sag, a percent of the length
    assert abs(reduced_ / full - 1.0) < 0.03


def test_a_density_moves_the_unit_stages_without_changing_the_motion():
    """Prepare caches the modes and the deformer at 1 Pa and 1 kg/m^3 and moves them to the
    body's material (``preparation.modes_at``, ``deformer_at``). Two oracles: (1) rho M u'' +
    E K1 u = rho M g is E/rho K1 u + M u'' = M g, so a body of (E, rho) falls exactly as one of
    (E / rho, 1 kg/m^3), which uses the unit deformer untouched (a wrong scale of the moved one
    shows here); (2) the moved deformer gives the displacements of one trained directly on the
    modes and masses at rho (the training is sized in radians and strain, so it is the same
    up to its cubature accuracy)."""
    X, T = meshgen.box_tet_mesh(SIZE, (8, 2, 2))
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    tet_body = preparation.embedded(X, T, X)
    unit = preparation.unit_stiffness_modes(tet_body, 0.45, 6, pinned)
    unit_deformer = preparation.reduced_deformer(
        tet_body, unit, preparation.ReducedSettings(basis_size=40, cubature_tets=60))
    youngs, density = 2e6, 1000.0
    paths = []
    for e, rho in ((youngs, density), (youngs / density, 1.0)):
        body = body_module.PreparedBody(tet_body, preparation.modes_at(unit, e, rho),
                                        preparation.deformer_at(unit_deformer, rho))
        settings = problems.SimulationSettings(h=1.0 / 24.0, density=rho,
                                               gravity=(0.0, 0.0, -9.81))
        sim = problems.simulation(body, problems.linear_potential(body, e, 0.45), settings)
        paths.append(sim.run(24).world_positions(body.nodes, body.deformer.basis))
    motion = np.abs(paths[1] - paths[1][0]).max()
    print(f"tip motion {motion:.3f} m, largest difference {np.abs(paths[0] - paths[1]).max():.2e} m")
    assert motion > 0.5                                   # the bar swings down a long way
    np.testing.assert_allclose(paths[0], paths[1], rtol=0.0, atol=1e-5 * motion)  # float32 steps
    heavy = preparation.modes_at(unit, youngs, density)
    direct, _ = reduced.prepare_reduced_rs(
        X, T, tet_body.lumped_masses(density), heavy.vectors, heavy.eigenvalues,
        rs.PoissonReconstruction(X, T, pinned_nodes=pinned), max_size=40, max_tets=60)
    moved = preparation.deformer_at(unit_deformer, density)
    Z = np.random.default_rng(3).normal(size=(20, 6)) * 3.0 / np.sqrt(heavy.eigenvalues)
    expected = direct.basis @ direct.q_batch(Z).T
    np.testing.assert_allclose(moved.basis @ moved.q_batch(Z).T, expected, rtol=0.0,
                               atol=1e-3 * np.abs(expected).max())


@pytest.mark.parametrize("kind", ["STVK", "FUNG"])
def test_one_energy_cubature_serves_every_density(kind):
    """The energy cubature is trained at 1 Pa in the coordinates of the modes at 1 kg/m^3
    (``preparation.unit_energy_potential``): two bodies of other densities train the same tets
    and weights bit for bit, and moved to each (``energy_at``) it gives the energy of one
    displacement (z over sqrt(rho) is one pose) and each body's exact all-tet energy within its
    fit."""
    X, T = meshgen.box_tet_mesh(SIZE, (8, 2, 2))
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    settings = preparation.ReducedSettings(basis_size=30, cubature_tets=40)
    light, heavy = (preparation.prepare_body(X, T, X, 1e6, 0.45, rho, 5, pinned,
                                             settings=settings) for rho in (250.0, 1000.0))
    trained = [preparation.unit_energy_potential(body, kind, 0.45) for body in (light, heavy)]
    np.testing.assert_array_equal(trained[0].tets, trained[1].tets)
    np.testing.assert_array_equal(trained[0].weights, trained[1].weights)
    z = np.random.default_rng(4).normal(size=(4, 5)) * 0.3 / np.sqrt(light.linear_modes.eigenvalues)
    at_light, at_heavy = (preparation.energy_at(trained[0], body, kind, 1e6, 0.45)
                          for body in (light, heavy))
    for pose in z:
        np.testing.assert_allclose(at_heavy.energy(2.0 * pose), at_light.energy(pose), rtol=1e-10)
        for body, potential, pose_ in ((light, at_light, pose), (heavy, at_heavy, 2.0 * pose)):
            exact = materials.ReducedPotential.exact(body.material(kind, 1e6, 0.45),
                                                     body.modal_rs, body.volumes)
            assert abs(potential.energy(pose_) / exact.energy(pose_) - 1.0) < 1e-3
