"""Flesh on a rig (solver.rig, issue 13): skinning weights of the tet nodes, the rig's motion and
its loads, and reduced RS dynamics of the deviation carried by the skinning.

Oracles: linear precision (a linear weight field is reproduced exactly, inside the body too);
second differences of a motion quadratic in time; the reduced load against a plain per-node
computation of m L^T (g - a); the external-force hook against gravity; pinned (Follow Rig)
nodes reproduce the skinned motion exactly; a bone that stops dead makes the free tip ring at
the body's first frequency, decaying by the Rayleigh damping set (theory: the damping ratio of
mode 1) and not at all without it; a bone turned 150 deg in 5 frames keeps the volume and
inverts nothing.
"""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from solver import dynamics, embed, fem, meshgen, rig
from solver.body_contact import BodyContact
from solver.frames import FrameMotion
from test_dynamics import build_body

H = 1.0 / 24.0


def surface_nodes(X, T):
    import igl
    return np.unique(igl.boundary_facets(T)[0])


def test_node_weights_reproduce_a_linear_field_inside_the_body():
    """Vertices = the surface nodes carry w = (x/4, 1 - x/4); interior nodes get it by the
    harmonic extension, which is exact for linear fields."""
    X, T = meshgen.box_tet_mesh((4.0, 1.0, 1.0), (8, 3, 3))
    surface = surface_nodes(X, T)
    assert len(surface) < len(X)                          # there are interior nodes
    V = X[surface]
    Phi = embed.embed_points(X, T, V)
    W = np.c_[V[:, 0] / 4.0, 1.0 - V[:, 0] / 4.0]
    got = rig.node_weights(Phi, W, X, T)
    np.testing.assert_allclose(got, np.c_[X[:, 0] / 4.0, 1.0 - X[:, 0] / 4.0], atol=1e-10)
    np.testing.assert_allclose(got.sum(axis=1), 1.0, atol=1e-12)


def quadratic_motion(times):
    """T(t) = T0 + t T1 + t^2 T2 for two bones (not rigid: only the algebra is tested)."""
    rng = np.random.default_rng(1)
    T0, T1, T2 = (rng.normal(size=(2, 3, 4)) for _ in range(3))
    return (T0 + times[:, None, None, None] * T1 + times[:, None, None, None] ** 2 * T2), T2


def test_rig_motion_acceleration_is_exact_for_a_quadratic_motion():
    times = np.arange(10) * H
    transforms, T2 = quadratic_motion(times)
    motion = rig.RigMotion(times, transforms)
    for t in (0.0, 3 * H, 4.5 * H, 9 * H, 12 * H):
        np.testing.assert_allclose(motion.acceleration(t), 2.0 * T2, rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(motion.at(3 * H), transforms[3], atol=1e-14)
    np.testing.assert_allclose(motion.at(3.5 * H), 0.5 * (transforms[3] + transforms[4]),
                               atol=1e-14)


def turning(times, axis, degrees, start, frames, offset=(0.0, 0.0, 0.0)):
    """(F, 3, 4) rigid transforms turning by ``degrees`` about ``axis`` through ``offset``,
    linearly from frame ``start`` over ``frames`` frames, held before and after."""
    fraction = np.clip((np.arange(len(times)) - start) / frames, 0.0, 1.0)
    R = Rotation.from_rotvec(np.radians(degrees) * fraction[:, None] * np.asarray(axis)).as_matrix()
    o = np.asarray(offset)
    return np.concatenate([R, (o - R @ o)[:, :, None]], axis=2)


def test_reduced_load_matches_a_per_node_computation():
    X, T = meshgen.box_tet_mesh((2.0, 0.5, 0.5), (6, 2, 2))
    masses = fem.lumped_masses(X, T, 900.0)
    rng = np.random.default_rng(2)
    W = rng.random((len(X), 3)) * (rng.random((len(X), 3)) > 0.3)
    W[W.sum(axis=1) == 0, 0] = 1.0
    W /= W.sum(axis=1)[:, None]
    B = rng.normal(size=(3 * len(X), 7))
    times = np.arange(12) * H
    transforms = np.stack([turning(times, (0, 0, 1), 80, 2, 6, (0.5, 0, 0)),
                           turning(times, (1, 0, 0), -60, 3, 5, (1.5, 0.2, 0)),
                           turning(times, (0, 1, 0), 30, 0, 11)], axis=1)
    transforms[:, 1, :, 3] += np.outer(times ** 2, [0.3, -0.2, 0.1])    # and translating
    motion = rig.RigMotion(times, transforms)
    g = np.array([0.0, -1.0, -9.81])
    load = rig.RigLoad(motion, W, masses, B, X, gravity=g)
    for t in (1.5 * H, 4 * H, 7.25 * H):
        A, acc = motion.at(t), motion.acceleration(t)
        f = np.zeros((len(X), 3))
        for i in range(len(X)):                      # the plain formula, one node at a time
            L = sum(W[i, b] * A[b, :, :3] for b in range(3))
            a = sum(W[i, b] * acc[b] @ np.r_[X[i], 1.0] for b in range(3))
            f[i] = masses[i] * L.T @ (g - a)
        expected = B.T @ f.ravel()
        np.testing.assert_allclose(load.force(t), expected, rtol=1e-10,
                                   atol=1e-10 * np.abs(expected).max())


@pytest.fixture(scope="module")
def bar():
    """Pinned 1 x 0.1 x 0.1 bar (root at x = 0), E = 2e5 Pa, 6 modes, ReducedRS."""
    return build_body((1.0, 0.1, 0.1), (10, 1, 1), 2.0e5, 0.3, num_modes=6)


def test_external_force_hook_is_gravity_when_it_is_gravitys_force(bar):
    g = np.array([0.0, 0.0, -9.81])
    steps = 12
    with_gravity = dynamics.Simulation(bar["deformer"], bar["X"], bar["masses"],
                                       bar["potential"], H, gravity=g).run(steps)
    simulation = dynamics.Simulation(bar["deformer"], bar["X"], bar["masses"], bar["potential"],
                                     H, external_force=None)
    force = simulation.moments.first_moment_B.T @ g
    hooked = dynamics.Simulation(bar["deformer"], bar["X"], bar["masses"], bar["potential"], H,
                                 external_force=lambda t: force).run(steps)
    np.testing.assert_allclose(hooked.coords, with_gravity.coords, atol=1e-9)
    assert np.abs(with_gravity.coords).max() > 1e-3                  # it did move


def rig_run(body, transforms, frames, weights=None, **kwargs):
    """Simulate the body's deviation on a rig: (motion, world positions (F, N, 3), deviations
    u (F, N, 3), total energy after each step (F - 1,) [J])."""
    X = body["X"]
    times = np.arange(len(transforms)) * H
    motion = rig.RigMotion(times, transforms)
    weights = np.ones((len(X), transforms.shape[1])) / transforms.shape[1] if weights is None \
        else weights
    load = rig.RigLoad(motion, weights, body["masses"], body["deformer"].basis, X,
                       gravity=kwargs.pop("gravity", (0.0, 0.0, 0.0)))
    simulation = dynamics.Simulation(body["deformer"], X, body["masses"], body["potential"], H,
                                     external_force=load.force, substeps=0, **kwargs)
    energies = []
    trajectory = simulation.run(frames - 1, callback=lambda *_: energies.append(
        simulation.energy()["total"]))
    u = trajectory.body_displacements(body["deformer"].basis)                # (F, N, 3)
    world = np.array([motion.skin(k * H, weights, X + u[k]) for k in range(frames)])
    return motion, world, u, np.array(energies)


def test_pinned_nodes_follow_the_skinned_motion_exactly(bar):
    """Two bones blended over the bar's middle; the elbow turns 90 deg in 10 frames."""
    X = bar["X"]
    times = np.arange(24) * H
    blend = np.clip((X[:, 0] - 0.4) / 0.2, 0.0, 1.0)
    weights = np.c_[1.0 - blend, blend]
    transforms = np.stack([turning(times, (0, 0, 1), 0, 0, 1),
                           turning(times, (0, 0, 1), 90, 2, 10, (0.5, 0.05, 0.05))], axis=1)
    motion, world, u, _ = rig_run(bar, transforms, 24, weights=weights)
    pins = bar["pins"]
    skinned = np.array([motion.skin(k * H, weights[pins], X[pins]) for k in range(24)])
    assert np.abs(u[:, pins]).max() == 0.0
    np.testing.assert_allclose(world[:, pins], skinned, atol=1e-14)
    assert np.abs(u).max() > 1e-3                       # the free part did lag


def first_mode_direction(body):
    """Unit (3,) direction of the first mode's tip motion (on a coarse square bar the two
    bending directions are not exactly y and z, and their frequencies differ)."""
    tip = body["X"][:, 0] > 1.0 - 1e-9
    d = body["modes"].vectors[:, 0].reshape(len(body["X"]), 3)[tip].mean(axis=0)
    return d / np.linalg.norm(d)


def sideways_stop(frames, stop, direction, distance=0.05):
    """One bone moving the bar along ``direction`` with a smooth start, stopping dead at
    frame ``stop``."""
    t = np.arange(frames) / stop
    d = distance * np.where(t < 1.0, t * t * (2.0 - t), 1.0)   # velocity ramps up, then 0 at once
    transforms = np.zeros((frames, 1, 3, 4))
    transforms[:, 0, :, :3] = np.eye(3)
    transforms[:, 0, :, 3] = d[:, None] * direction
    return transforms


def tip_after_stop(bar, damping, frames=260, stop=12):
    """Tip deviation (F',) along the first mode's direction after the stop, and the energy
    (F',) [J] of the flesh over the same frames."""
    direction = first_mode_direction(bar)
    _, _, u, energy = rig_run(bar, sideways_stop(frames, stop, direction), frames,
                              mass_damping=damping)
    tip = bar["X"][:, 0] > 1.0 - 1e-9
    return u[stop + 2:, tip].mean(axis=1) @ direction, energy[stop + 1:]


def crossings(signal):
    """Sub-frame times of the sign changes of a sampled signal (linear interpolation)."""
    i = np.flatnonzero(np.diff(np.sign(signal)) != 0)
    return i + signal[i] / (signal[i] - signal[i + 1])


def peaks(signal):
    inner = (signal[1:-1] > signal[:-2]) & (signal[1:-1] >= signal[2:]) & (signal[1:-1] > 0)
    return np.flatnonzero(inner) + 1


def test_a_bone_that_stops_dead_rings_the_tip_at_the_first_frequency(bar):
    omega1 = float(np.sqrt(bar["modes"].eigenvalues[0]))
    free, after = tip_after_stop(bar, 0.0)
    frequency = 1.0 / (2.0 * np.mean(np.diff(crossings(free))) * H)
    print(f"ringing at {frequency:.4f} Hz, first mode {omega1 / (2 * np.pi):.4f} Hz")
    assert frequency == pytest.approx(omega1 / (2.0 * np.pi), rel=0.05)
    # No integrator damping: once the bone stands still the flesh keeps its energy, up to the
    # slow drift the nonlinear reduced RS map gives Newmark on this coarse bar (measured 2.8 %
    # over 10 s; the same bar released from its first mode without a rig drifts alike).
    print(f"energy after the stop: {after.min() / after[0]:.5f}-{after.max() / after[0]:.5f} "
          "of its value at the stop")
    assert np.abs(after / after[0] - 1.0).max() < 0.035
    zeta = 0.05
    alpha = 2.0 * zeta * omega1                           # mass damping for zeta_1 = 5 %
    damped, _ = tip_after_stop(bar, alpha)
    top = damped[peaks(damped)][1:]        # the first still carries the stop's transient
    per_period = (top[-1] / top[0]) ** (1.0 / (len(top) - 1))
    expected = np.exp(-2.0 * np.pi * zeta / np.sqrt(1.0 - zeta ** 2))
    print(f"damped peaks {np.round(top / top[0], 4)}: {per_period:.4f} per period, "
          f"theory {expected:.4f}")
    assert len(top) >= 3 and abs(per_period / expected - 1.0) < 0.05


def test_a_bone_turned_150_degrees_in_5_frames_keeps_volume_and_inverts_nothing():
    """A stiffer bar (E = 5e6 Pa, first mode about 2 Hz): the rig carries the 150 deg turn as a
    rotation; the flesh lags and swings back (a deviation of several centimetres)."""
    bar = build_body((1.0, 0.1, 0.1), (10, 1, 1), 5.0e6, 0.3, num_modes=6)
    X, T = bar["X"], bar["T"]
    transforms = turning(np.arange(30) * H, (0, 0, 1), 150, 2, 5)[:, None]
    _, world, u, _ = rig_run(bar, transforms, 30, gravity=(0.0, 0.0, -9.81))
    rest = np.abs(fem.tet_volumes(X, T)).sum()
    volumes = np.array([fem.tet_volumes(x, T) for x in world])                 # (F, E)
    ratio = volumes.sum(axis=1) / rest
    print(f"volume {ratio.min():.4f}-{ratio.max():.4f}, smallest tet "
          f"{(volumes / fem.tet_volumes(X, T)).min():.3f} of its rest volume, "
          f"largest deviation {np.abs(u).max():.3f} m")
    assert np.abs(ratio - 1.0).max() < 0.03
    assert (volumes / fem.tet_volumes(X, T)).min() > 0.0
    assert np.abs(u).max() > 1e-3


# Partly-following flesh: springs to the skinned pose (rig.follow_stiffness, rig.HeldPotential)

def test_follow_springs_hold_the_flesh_as_their_stiffness_says():
    """Linear modes (q = s, B = W), exact linear potential: the static sag under gravity with
    the springs is the solution of (H + W^T K_f W) s = W^T M g (a direct solve); weight 0 adds
    nothing; the spring matrix is B^T diag(k) B with k = m omega^2 w / (1 - w) node by node."""
    from solver import materials, modes, reduced, rs
    X, T = meshgen.box_tet_mesh((1.0, 0.1, 0.1), (10, 1, 1))
    masses = fem.lumped_masses(X, T, 1000.0)
    pins = np.flatnonzero(X[:, 0] < 1e-9)
    result = modes.linear_modes(fem.stiffness_matrix(X, T, 2e5, 0.3), masses, 6, pins)
    W = result.vectors
    deformer = reduced.LinearDeformer(6, W)
    mu, lam = fem.lame_parameters(2e5, 0.3)
    potential = materials.ReducedPotential.exact(materials.Linear(mu, lam),
                                                 rs.linear_rs(rs.rs_operator(X, T), W),
                                                 fem.tet_volumes(X, T))
    follow = np.clip(X[:, 0], 0.0, 0.4)                 # stiffer springs towards the tip
    omega = float(np.sqrt(result.eigenvalues[-1]))
    K_f = rig.follow_stiffness(follow, masses, W, omega)
    k = masses * omega ** 2 * follow / (1.0 - follow)
    expected = W.T @ (np.repeat(k, 3)[:, None] * W)
    np.testing.assert_allclose(K_f, expected, rtol=1e-10, atol=1e-12 * np.abs(expected).max())
    assert np.abs(rig.follow_stiffness(np.zeros(len(X)), masses, W, omega)).max() == 0.0
    g = np.array([0.0, 0.0, -9.81])
    held = rig.HeldPotential(potential, deformer, K_f)
    sags = []
    for pot in (potential, held):
        simulation = dynamics.Simulation(deformer, X, masses, pot, H, gravity=g)
        sags.append(simulation.static_equilibrium())
    load = W.T @ (np.repeat(masses, 3) * np.tile(g, len(X)))
    np.testing.assert_allclose(sags[1], np.linalg.solve(potential.rest_hessian + K_f, load),
                               rtol=1e-6)
    np.testing.assert_allclose(held.rest_hessian, potential.rest_hessian + K_f, rtol=1e-12)
    print(f"tip sag {np.abs(W @ sags[0]).max():.4f} m free, {np.abs(W @ sags[1]).max():.4f} m "
          "held")
    assert np.abs(W @ sags[1]).max() < 0.5 * np.abs(W @ sags[0]).max()


def test_flesh_on_a_turning_bone_meets_a_wall_as_a_keyed_body_does():
    """Contact on a rig (``sample_placement``: the samples skinned to the world). A 1 m bar,
    pinned at x = 0, all weight on one bone that turns 60 deg about z in 1 s (smoothstep), runs
    into a wall at y = 0.5 (x in [0.75, 1.4]). Oracles: without the wall the samples pass
    y = 0.5; with it none gets behind the wall; and the skinned flesh moves as the same bar
    keyed on a frame with the same turn (``FrameMotion``, the other code path) within 1 cm,
    with or without the wall."""
    from test_collisions import body_contact, build_body as collision_body, quad
    body = collision_body((1.0, 0.1, 0.1), (20, 2, 2), 1e7, pinned=True, samples=80)
    X, idx, frames = body["X"], body["idx"], 36
    times = np.arange(frames) * H
    ease = np.clip(times, 0.0, 1.0)
    turns = Rotation.from_rotvec(np.radians(60.0) * (3 * ease ** 2 - 2 * ease ** 3)[:, None]
                                 * np.array([0.0, 0.0, 1.0])).as_matrix()
    transforms = np.concatenate([turns, np.zeros((frames, 3, 1))], axis=2)[:, None]
    motion = rig.RigMotion(times, transforms)
    y_wall = 0.5
    wall = quad([[0.75, y_wall, -0.5], [1.4, y_wall, -0.5], [1.4, y_wall, 0.5],
                 [0.75, y_wall, 0.5]], thickness=0.02)
    sample_weights = np.ones((len(idx), 1))
    common = dict(substeps=4, stiffness_damping=0.002)

    def rigged(colliders):
        load = rig.RigLoad(motion, np.ones((len(X), 1)), body["masses"], body["deformer"].basis,
                           X, gravity=(0.0, 0.0, 0.0))
        extra = {} if colliders is None else dict(
            contact=body_contact(body, colliders),
            sample_placement=lambda t: motion.placement(t, sample_weights))
        u = dynamics.Simulation(body["deformer"], X, body["masses"], body["potential"], H,
                                external_force=load.force, **common, **extra) \
            .run(frames - 1).body_displacements(body["rows"])
        return np.array([motion.skin(k * H, sample_weights, X[idx] + u[k])
                         for k in range(frames)])

    def keyed(colliders):
        frame = FrameMotion(times, turns, np.zeros((frames, 3)))
        extra = {} if colliders is None else dict(contact=body_contact(body, colliders))
        return dynamics.Simulation(body["deformer"], X, body["masses"], body["potential"], H,
                                   frame_motion=frame, **common, **extra) \
            .run(frames - 1).world_positions(X[idx], body["rows"])

    free, walled = rigged(None), rigged([wall])
    reference_free, reference_walled = keyed(None), keyed([wall])
    under_wall = walled[:, :, 0] > 0.75
    print(f"rig and wall: free samples reach y = {free[:, :, 1].max():.3f} m, walled ones "
          f"{walled[:, :, 1][under_wall].max():.4f} m under the wall; off the keyed body by "
          f"{np.abs(free - reference_free).max():.1e} m free, "
          f"{np.abs(walled - reference_walled).max():.1e} m walled")
    assert free[:, :, 1].max() > y_wall + 0.2
    assert walled[:, :, 1][under_wall].max() < y_wall
    assert np.abs(free - reference_free).max() < 0.01
    assert np.abs(walled - reference_walled).max() < 0.01


@pytest.mark.parametrize("carrier", ["rig", "keyed frame"])
def test_a_body_carried_into_a_wall_it_touches_starts_each_step_outside_it(carrier, monkeypatch):
    """A 1 m bar pinned at x = 0 rests 3 mm under a wall (y, x in [0.75, 1.4]; band 1 cm) until
    frame 2, then its bone (or keyed frame) turns it into the wall at 2 rad/s: 8 cm a frame at
    the tip. Neither the predictor nor s_n is outside the wall once the turn starts, so without
    ``_holding_deformation`` the step has no start guess (the control: ContactError, with step
    halving switched off so that every step must stand alone). With it, every step of 24 frames
    starts outside and no sample gets behind the wall, while the free bone would carry the tip
    to y = 0.98 m."""
    from test_collisions import body_contact, build_body as collision_body, quad
    monkeypatch.setattr(dynamics, "MAX_STEP_SPLITS", 0)
    body = collision_body((1.0, 0.1, 0.1), (20, 2, 2), 1e6, pinned=True, samples=80)
    X, idx, frames = body["X"], body["idx"], 24
    times = np.arange(frames) * H
    angle = np.where(times > 2 * H, 2.0 * (times - 2 * H), 0.0)
    turns = Rotation.from_rotvec(angle[:, None] * np.array([0.0, 0.0, 1.0])).as_matrix()
    y_wall = X[:, 1].max() + 0.003
    wall = quad([[0.75, y_wall, -0.5], [1.4, y_wall, -0.5], [1.4, y_wall, 0.5],
                 [0.75, y_wall, 0.5]], thickness=0.01)
    weights = np.ones((len(idx), 1))
    motion = rig.RigMotion(times, np.concatenate([turns, np.zeros((frames, 3, 1))],
                                                 axis=2)[:, None])

    def samples_over_time():
        """(F, k, 3) world positions of the contact samples."""
        common = dict(substeps=1, contact=body_contact(body, [wall]))
        if carrier == "keyed frame":
            frame = FrameMotion(times, turns, np.zeros((frames, 3)))
            return dynamics.Simulation(body["deformer"], X, body["masses"], body["potential"], H,
                                       frame_motion=frame, **common) \
                .run(frames - 1).world_positions(X[idx], body["rows"])
        load = rig.RigLoad(motion, np.ones((len(X), 1)), body["masses"], body["deformer"].basis,
                           X, gravity=(0.0, 0.0, 0.0))
        u = dynamics.Simulation(body["deformer"], X, body["masses"], body["potential"], H,
                                external_force=load.force,
                                sample_placement=lambda t: motion.placement(t, weights),
                                **common).run(frames - 1).body_displacements(body["rows"])
        return np.array([motion.skin(k * H, weights, X[idx] + u[k]) for k in range(frames)])

    x = samples_over_time()
    under_wall = x[:, :, 0] > 0.75
    print(f"{carrier}: samples under the wall reach y = {x[:, :, 1][under_wall].max():.4f} m "
          f"(wall {y_wall:.4f} m); free tip y {np.sin(angle[-1]):.2f} m")
    assert x[:, :, 1][under_wall].max() < y_wall
    assert np.sin(angle).max() > 0.9
    monkeypatch.setattr(BodyContact, "holding_deformation", lambda self, state, R, c: None)
    with pytest.raises(dynamics.ContactError, match="moved into the body"):
        samples_over_time()


def test_sample_placement_needs_contact_in_a_fixed_frame(bar):
    with pytest.raises(ValueError, match="sample placement"):
        dynamics.Simulation(bar["deformer"], bar["X"], bar["masses"], bar["potential"], H,
                            sample_placement=lambda t: None)


def test_a_settled_start_includes_the_external_force_and_stays_put(bar):
    """``static_equilibrium`` counts the external force (a rig's loads): with the force equal to
    gravity's B^T M g it is the gravity equilibrium (the same Newton problem by another road),
    and started there an undamped simulation stays there (a fixed point of the dynamics)."""
    g = np.array([0.0, 0.0, -9.81])
    settled = dynamics.Simulation(bar["deformer"], bar["X"], bar["masses"], bar["potential"], H,
                                  gravity=g).static_equilibrium()
    probe = dynamics.Simulation(bar["deformer"], bar["X"], bar["masses"], bar["potential"], H)
    force = probe.moments.first_moment_B.T @ g
    # float64 products: in float32 (the default) q's rounding alone moves the body by 1e-6 of
    # the sag over these frames on some CPUs (OpenBLAS's kernels differ), not the dynamics
    hooked = dynamics.Simulation(bar["deformer"], bar["X"], bar["masses"], bar["potential"], H,
                                 external_force=lambda t: force, dtype=np.float64)
    start = hooked.static_equilibrium()
    np.testing.assert_allclose(start, settled, atol=1e-10 * np.abs(settled).max())
    assert np.abs(settled).max() > 1e-3                                    # it did sag
    drift = np.abs(hooked.run(24).coords - start).max() / np.abs(start).max()
    print(f"settled start: largest drift over 24 frames {drift:.1e} of the sag")
    assert drift < 1e-6
