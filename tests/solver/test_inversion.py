"""Tests for solver.inversion (the RS volume barrier) and dynamics' inversion check / retry.

Oracles: central finite differences of the barrier's value and gradient; the barrier's exact
zero (and so the unchanged rest Hessian) below its threshold; det F > 0 of every tet of the
full reconstruction and the total volume (sum of signed tet volumes) against the rest volume;
for the retry, a simulation with twice the substeps (the same two half steps, so the same
state to round-off) and the step lengths actually taken.

The soft column: pinned 1 x 0.1 x 0.1 m bar, 20 x 2 x 2 cells (480 tets), nu = 0.3, 8 modes,
the default reduced model (basis 80, 84 cubature tets), standing up along +x (gravity -x),
released at rest: it buckles and falls over. Measured without the barrier (Newmark, automatic
substeps, no check, 4 s at 24 fps), min det F over all tets and frames: E = 2e5 Pa: Linear
-0.044, StVK -0.141, Fung 0.322 (but its volume drops to 0.944); E = 2e4 Pa: Linear -4.8e7
(blown up), StVK -1.59, Fung -1.01. With the barrier and the check: 0.352, 0.398, 0.431 and
0.147, 0.270, 0.305. ``test_the_soft_column_inverts_without_barrier`` keeps StVK as a
control, so the column tests can fail.
"""

import functools

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from solver import dynamics, fem, inversion, materials
from test_dynamics import build_body

GRAVITY_UP = np.array([-9.81, 0.0, 0.0])      # the column stands along +x on its pinned base
FPS = 24
SECONDS = 4.0


# Barrier derivatives ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def random_barrier():
    """A barrier on 40 random tets with 5 coordinates, and an s (5,) with several tets in
    (0, J_hat), found by scaling a fixed direction until the barrier is active but finite."""
    rng = np.random.default_rng(3)
    U = rng.normal(size=(40, 6, 5))
    barrier = inversion.VolumeBarrier(U, rng.uniform(0.5, 1.5, 40), 7.0)
    direction = rng.normal(size=5)
    for scale in np.linspace(0.01, 1.0, 200):
        J = barrier.volume_ratios(scale * direction)
        if np.count_nonzero(J < barrier.j_hat) >= 4:
            break
    s = scale * direction
    assert J.min() > 0.0 and np.count_nonzero(J < barrier.j_hat) >= 4
    return barrier, s


def test_barrier_gradient_and_hessian_match_central_differences(random_barrier):
    barrier, s = random_barrier
    value, grad, hess = barrier.evaluate(s, 2, project=False)
    assert value > 0.0
    h = 1e-6
    unit = np.eye(len(s))
    fd_grad = np.array([(barrier.evaluate(s + h * e, 0)[0] - barrier.evaluate(s - h * e, 0)[0])
                        / (2 * h) for e in unit])
    fd_hess = np.array([(barrier.evaluate(s + h * e, 1)[1] - barrier.evaluate(s - h * e, 1)[1])
                        / (2 * h) for e in unit])
    assert np.allclose(fd_grad, grad, rtol=1e-6, atol=1e-8 * np.abs(grad).max())
    assert np.allclose(fd_hess, hess, rtol=1e-5, atol=1e-7 * np.abs(hess).max())


def test_projected_hessian_is_psd_and_exact_where_the_tet_hessians_are(random_barrier):
    barrier, s = random_barrier
    projected = barrier.evaluate(s, 2)[2]
    assert np.linalg.eigvalsh(projected).min() >= -1e-9 * np.abs(projected).max()
    # On a point where every active tet's 6x6 Hessian is already PSD, projecting changes nothing.
    J, dJ, d2J = inversion.stretch_determinants(np.zeros((1, 6)) - 0.5 * np.eye(6)[[0]], 2)
    _, db, d2b = inversion.barrier_function(J, barrier.j_hat)
    H = d2b[:, None, None] * dJ[:, :, None] * dJ[:, None, :] + db[:, None, None] * d2J
    assert np.linalg.eigvalsh(H[0]).min() >= 0.0 and J[0] < barrier.j_hat
    assert np.allclose(inversion._clamp_psd(H), H, atol=1e-12 * np.abs(H).max())


def test_screened_barrier_equals_the_all_tet_barrier():
    """VolumeBarrier evaluates only the tets its StrainScreen cannot clear (blocks whose
    strain bound from the last full evaluation may reach J_hat). Along a random walk in and
    out of the active region its value, gradient and Hessian must equal those of a fresh
    barrier's first (all-tet) evaluation, and the walk must take the screened path."""
    rng = np.random.default_rng(5)
    count, m = 3000, 6
    scale = np.sort(np.exp(rng.uniform(-6.0, 0.0, count)))    # neighbours strain alike
    U = rng.normal(size=(count, 6, m)) * scale[:, None, None]
    volumes = rng.uniform(0.5, 1.5, count)
    barrier = inversion.VolumeBarrier(U, volumes, 7.0)
    s, screened, active = np.zeros(m), 0, 0
    for _ in range(120):
        s = s + rng.normal(size=m) * 0.01
        near = barrier._screen.candidates(s)
        screened += near is not None and len(near) < count
        value, grad, hess = barrier.evaluate(s)
        fresh = inversion.VolumeBarrier(U, volumes, 7.0).evaluate(s)
        active += np.isfinite(fresh[0]) and fresh[0] > 0.0
        np.testing.assert_allclose(value, fresh[0], rtol=1e-12)
        np.testing.assert_allclose(grad, fresh[1], rtol=1e-12, atol=1e-300)
        np.testing.assert_allclose(hess, fresh[2], rtol=1e-12, atol=1e-300)
    print(f"screened evaluations {screened} of 120, active barrier at {active}")
    assert screened >= 20 and active >= 20


def test_barrier_is_infinite_outside_the_positive_definite_stretches():
    """J <= 0, and J > 0 with two negative eigenvalues (unreachable without passing J = 0),
    are both infeasible: the value is +inf so a line search rejects them."""
    strains = np.array([[-1.2, 0, 0, 0, 0, 0],            # S = diag(-0.2, 1, 1): J < 0
                        [-2.0, 0, 0, -2.0, 0, 0],         # S = diag(-1, -1, 1): J = +1
                        [-0.5, 0, 0, 0, 0, 0]])           # S = diag(0.5, 1, 1): feasible
    J = inversion.stretch_determinants(strains, 0)[0]
    assert J[0] < 0.0 and J[1] <= 0.0 and J[2] == pytest.approx(0.5)
    values = inversion.barrier_function(J)[0]
    assert np.isinf(values[:2]).all() and np.isfinite(values[2]) and values[2] > 0.0


# The soft column -------------------------------------------------------------------------------

@functools.lru_cache(maxsize=None)
def soft_column(youngs):
    """The soft column (module docstring) with Young's modulus ``youngs`` [Pa], built once."""
    body = build_body((1.0, 0.1, 0.1), (20, 2, 2), youngs, 0.3, num_modes=8, max_size=None,
                      max_tets=150, num_poses=80, num_snapshots=200)
    body["youngs"] = youngs
    body["volumes"] = np.abs(fem.tet_volumes(body["X"], body["T"]))
    return body


@pytest.fixture(scope="module", params=[2e5, 2e4], ids=["E2e5", "E2e4"])
def column(request):
    return soft_column(request.param)


def column_potential(body, kind, barrier=True):
    material = materials.make_material(kind, body["mu"], body["lam"])
    potential, _ = materials.prepare_potential(material, body["modal_rs"], body["volumes"],
                                               eigenvalues=body["modes"].eigenvalues)
    if barrier:
        potential = inversion.with_barrier(potential, body["modal_rs"], body["volumes"])
    return potential


def column_simulation(body, potential, check=True, substeps=0):
    return dynamics.Simulation(body["deformer"], body["X"], body["masses"], potential, 1.0 / FPS,
                               gravity=GRAVITY_UP, substeps=substeps,
                               tets=body["T"] if check else None)


def volume_ratios(body, trajectory):
    """(F, E) det F of every tet at every frame of the full reconstruction, and (F,) total
    volume / rest volume (sums of signed volumes)."""
    x = trajectory.world_positions(body["X"], body["deformer"].basis)
    T = body["T"]
    e = x[:, T[:, 1:]] - x[:, T[:, :1]]                                  # (F, E, 3, 3)
    deformed = np.linalg.det(e) / 6.0
    rest = fem.tet_volumes(body["X"], T)
    return deformed / rest, deformed.sum(axis=1) / rest.sum()


def test_barrier_is_zero_near_rest_and_keeps_the_rest_hessian(column):
    """Small strain (all J >= J_hat): value, gradient and Hessian of the barrier are exactly
    zero, so the wrapped potential is unchanged there, rest Hessian included."""
    plain = column_potential(column, "STVK", barrier=False)
    wrapped = inversion.with_barrier(plain, column["modal_rs"], column["volumes"])
    assert np.array_equal(wrapped.rest_hessian, plain.rest_hessian)
    direction = np.random.default_rng(0).normal(size=plain.num_coords)
    s = direction * 0.05 / np.abs(wrapped.barrier._flat @ direction).max()   # |strain| <= 5 %
    assert wrapped.barrier.volume_ratios(s).min() >= inversion.J_HAT
    value, grad, hess = wrapped.barrier.evaluate(s, 2)
    assert value == 0.0 and not grad.any() and not hess.any()
    for a, b in zip(wrapped.evaluate(s, 2), plain.evaluate(s, 2)):
        assert np.array_equal(a, b)


@pytest.mark.parametrize("kind", ["LINEAR", "STVK", "FUNG"])
def test_the_soft_column_never_inverts(column, kind):
    """Standing column, 4 s at 24 fps with barrier and check: det F > 0 of every tet at every
    frame; at E = 2e5 the total volume stays within 5 % of rest (measured 0.957 - 1.010).
    At E = 2e4 the column folds over its base with bending strains of tens of percent; there
    these Cauchy-strain materials with nu = 0.3 themselves change volume ((1 + e)(1 - nu e)^2
    is 0.66 at e = -0.5), and the measured total volume spans 0.71 - 1.07 without any tet
    inverting, so no 5 % bound is asserted there (the barrier only acts below J = 0.6)."""
    sim = column_simulation(column, column_potential(column, kind))
    trajectory = sim.run(int(SECONDS * FPS))
    ratios, volume = volume_ratios(column, trajectory)
    assert ratios.min() > 0.0, f"min det F {ratios.min():.3f}"
    if column["youngs"] >= 2e5:
        assert np.abs(volume - 1.0).max() < 0.05, f"volume range {volume.min()}..{volume.max()}"


@pytest.mark.parametrize("youngs", [1e4, 5e3])
def test_a_softer_column_with_both_barriers_stands_its_four_seconds(youngs):
    """The column at a half and a quarter of E = 2e4 Pa, Linear, as Simulate runs it (the RS
    barrier, the reconstruction barrier and the step check): it folds until tets press
    against the reconstruction barrier, and must still run its 4 s with det F above the
    check's FLAT_J on every tet at every frame (recomputed from the trajectory in float64).
    It stopped with an InversionError (frames 36 and 46) while the barrier's wall was at 0 (a
    tet held between 0 and FLAT_J counts as flat) and the shortest retake neither restarted
    from the step's start nor watched the tets that had turned in it."""
    body = soft_column(youngs)
    stepping = dynamics.step_deformer(body["deformer"])
    potential = inversion.with_reconstruction_barrier(column_potential(body, "LINEAR"),
                                                      stepping, body["X"], body["T"])
    sim = dynamics.Simulation(stepping, body["X"], body["masses"], potential, 1.0 / FPS,
                              gravity=GRAVITY_UP, tets=body["T"])
    ratios, _ = volume_ratios(body, sim.run(int(SECONDS * FPS)))
    print(f"E = {youngs:g} Pa: min det F {ratios.min():.4f}")
    assert ratios.min() > inversion.FLAT_J


def test_the_soft_column_inverts_without_barrier(column):
    """Control: the same column without barrier or check does invert (StVK; see the module
    docstring for all three)."""
    sim = column_simulation(column, column_potential(column, "STVK", barrier=False), check=False)
    seconds = SECONDS if column["youngs"] >= 2e5 else 1.0
    ratios, _ = volume_ratios(column, sim.run(int(seconds * FPS)))
    assert ratios.min() < 0.0


# Retry and failure ---------------------------------------------------------------------------

def record_steps(sim):
    """Wrap the internal step so that every dt taken is recorded in a list (returned)."""
    taken = []
    inner = sim._take_step

    def recorded(**options):
        taken.append(sim.dt)
        return inner(**options)

    sim._take_step = recorded
    return taken


def test_a_rejected_step_is_retaken_as_two_half_steps():
    """Force the first check to fail: the frame is then taken as two steps of dt/2 from the
    restored state, exactly like a simulation with twice the substeps (same state to round-off:
    the undo restored everything), and the next frame is back to the nominal dt. Both start
    at rest (a start velocity would make Newmark's start acceleration depend on dt through
    the finite-difference curvature of ``NewmarkScheme.body_rates``)."""
    column = soft_column(2e5)
    potential = column_potential(column, "LINEAR")
    sim = column_simulation(column, potential, substeps=1)
    reference = column_simulation(column, potential, substeps=2)
    taken = record_steps(sim)
    force_failed_checks(sim, 1)
    sim.step()
    reference.step()
    h = 1.0 / FPS
    assert taken == [h, h / 2, h / 2] and sim.dt == h and sim.time == pytest.approx(h)
    scale = np.abs(reference.coords).max()
    assert np.allclose(sim.coords, reference.coords, atol=1e-10 * scale)
    v_s, reference_v_s = sim.state.carried.velocity, reference.state.carried.velocity
    assert np.allclose(v_s, reference_v_s, atol=1e-9 * np.abs(reference_v_s).max())
    sim.step()
    assert taken[3:] == [h]


def force_failed_checks(sim, count, turned=None):
    """Make the first ``count`` checks of ``sim`` report one inverted tet (with ``turned``, that
    tet's det F at -0.5 among the real ones); later checks are real."""
    real_check, forced = sim._inverted_tets, []

    def check():
        if len(forced) >= count:
            return real_check()
        forced.append(True)
        ratios = real_check()[3]
        if turned is None:
            return 1, -1.0, True, ratios
        ratios = ratios.copy()
        ratios[turned] = -0.5
        return 1, -0.5, True, ratios

    sim._inverted_tets = check


def test_only_the_shortest_retake_restarts_from_the_steps_start():
    """A step retaken down to dt / 2^MAX_STEP_SPLITS (its checks forced to fail) hands Newton
    the state it starts from as a feasible restart there, and only there: longer retakes keep
    halving (their trajectories unchanged), and the restart can only turn the shortest
    retake's failure into a step (``newton.StepSolver.minimise``'s ``feasible``)."""
    column = soft_column(2e5)
    sim = column_simulation(column, column_potential(column, "LINEAR"), substeps=1)
    force_failed_checks(sim, dynamics.MAX_STEP_SPLITS)
    calls, minimise = [], sim.solver.minimise

    def recorded(model, s, damping, *args, feasible=None, **kwargs):
        start = (sim.state.pose.coords.copy(), sim.state.pose.q.copy())
        calls.append((sim.dt, start, feasible))
        return minimise(model, s, damping, *args, feasible=feasible, **kwargs)

    sim.solver.minimise = recorded
    sim.step()
    h, shortest = 1.0 / FPS, 1.0 / FPS / 2 ** dynamics.MAX_STEP_SPLITS
    assert [dt for dt, _, _ in calls[:dynamics.MAX_STEP_SPLITS + 1]] == pytest.approx(
        [h / 2 ** k for k in range(dynamics.MAX_STEP_SPLITS + 1)])
    for dt, start, feasible in calls:
        if dt > 1.5 * shortest:
            assert feasible is None
        else:
            assert all(np.array_equal(a, b) for a, b in zip(feasible, start))
    assert sum(dt < 1.5 * shortest for dt, _, _ in calls) == 2     # the two shortest steps
    assert sim.time == pytest.approx(h)


def test_each_frame_counts_its_steps_at_the_shortest_retake_length():
    """``shortest_steps`` (what a bake reports as slow frames) counts, per frame, the internal
    steps taken at dt / 2^MAX_STEP_SPLITS: none while the checks pass, the two shortest halves
    on the frame whose checks are forced to fail down to there, and nothing more after it."""
    column = soft_column(2e5)
    sim = column_simulation(column, column_potential(column, "LINEAR"), substeps=1)
    sim.step()
    assert sim.shortest_steps == {}
    force_failed_checks(sim, dynamics.MAX_STEP_SPLITS)
    sim.step()
    assert sim.shortest_steps == {2: 2}
    sim.step()
    assert sim.shortest_steps == {2: 2}


def test_the_shortest_retake_is_taken_once_more_watching_what_turned():
    """A failing shortest retake is taken once more at its own length, watching the tets
    that turned in it (a tet above WATCH_J at its start had no reconstruction barrier there):
    with checks forced to fail down to and including the first shortest step the frame still
    completes, the extra step at dt / 16 sees the turned tets in the watch; one more forced
    failure and it is an InversionError, with the state as before the frame."""
    column = soft_column(2e5)
    shortest = dynamics.MAX_STEP_SPLITS
    for failures, completes in ((shortest + 1, True), (shortest + 2, False)):
        potential = inversion.with_reconstruction_barrier(
            column_potential(column, "LINEAR"), column["deformer"], column["X"], column["T"])
        sim = column_simulation(column, potential, substeps=1)
        force_failed_checks(sim, failures, turned=7)
        check, watched = sim._inverted_tets, []

        def observed(check=check, watched=watched, potential=potential):
            watched.append(7 in potential.barrier.watched)
            return check()

        sim._inverted_tets = observed
        taken = record_steps(sim)
        h = 1.0 / FPS
        if completes:
            sim.step()
            assert taken[:shortest + 2] == pytest.approx(
                [h / 2 ** k for k in range(shortest + 1)] + [h / 2 ** shortest])
            assert watched[shortest + 1]                # the extra step's check
            assert not watched[0]
            assert sim.time == pytest.approx(h)
        else:
            start = sim.coords.copy()
            with pytest.raises(dynamics.InversionError):
                sim.step()
            assert len(taken) == shortest + 2 and np.array_equal(sim.coords, start)


def test_implicit_euler_retry_keeps_a_free_bodys_velocities():
    """Implicit Euler keeps velocities as backward differences over one step, so halving the
    step must rescale them (frame rotation included). A spinning, drifting free body retried
    in halves matches a run with twice the substeps to round-off, and afterwards its history
    is back to differences over the nominal dt (twice the half-step turn)."""
    body = build_body((0.3, 0.1, 0.1), (6, 2, 2), 1e5, 0.3, num_modes=6, pinned=False,
                      max_size=30, max_tets=40, num_poses=30, num_snapshots=30)
    sims = [dynamics.Simulation(body["deformer"], body["X"], body["masses"], body["potential"],
                                1.0 / FPS, gravity=(0.0, 0.0, -9.81), free=True,
                                integrator="implicit_euler", substeps=n, tets=body["T"])
            for n in (1, 2)]
    for sim in sims:
        sim.set_state(np.zeros(6), 0.5 * np.ones(6), linear_velocity=(1.0, 0.0, 0.0),
                      angular_velocity=(0.0, 2.0, 3.0))
    retried, reference = sims
    force_failed_checks(retried, 1)
    taken = record_steps(retried)
    retried.step()
    reference.step()
    h = 1.0 / FPS
    assert taken == [h, h / 2, h / 2]
    assert np.allclose(retried.coords, reference.coords, rtol=1e-9, atol=1e-12)
    assert np.allclose(retried.rotation, reference.rotation, atol=1e-12)
    assert np.allclose(retried.translation, reference.translation, atol=1e-12)
    turn = lambda sim: Rotation.from_matrix(sim.state.carried.rotation
                                            @ sim.rotation.T).as_rotvec()
    assert np.allclose(turn(retried), 2.0 * turn(reference), atol=1e-12)
    assert np.allclose(retried.coords - retried.state.carried.coords,
                       2.0 * (reference.coords - reference.state.carried.coords), atol=1e-12)


def test_inversion_error_when_even_the_smallest_step_inverts():
    """No barrier on the E = 2e4 column (it inverts, see the control test): the check halves
    down to dt / 2^MAX_STEP_SPLITS, then raises one readable InversionError, and the state is
    the last good one (no inverted tet)."""
    column = soft_column(2e4)
    sim = column_simulation(column, column_potential(column, "STVK", barrier=False))
    taken = record_steps(sim)
    with pytest.raises(dynamics.InversionError) as caught:
        sim.run(int(SECONDS * FPS))
    error = caught.value
    assert isinstance(error, RuntimeError) and error.count > 0 and error.total == 480
    assert error.smallest <= dynamics.MIN_VOLUME_RATIO and error.frame >= 1
    assert min(taken) == pytest.approx(sim.h / sim.substeps / 2 ** dynamics.MAX_STEP_SPLITS)
    message = str(error)
    assert "\n" not in message and f"frame {error.frame}" in message and "stiffer" in message
    ratios = inversion.DeformedVolumes(column["X"], column["T"], column["deformer"].basis)
    assert ratios.ratios(sim.q).min() > dynamics.MIN_VOLUME_RATIO


# The reconstruction barrier ---------------------------------------------------------------------

@functools.lru_cache(maxsize=None)
def coarse_column():
    """The soft column at E = 2e4 with a coarse reduced model (basis 40, 80 cubature tets),
    whose reconstruction strays furthest from its RS target."""
    body = build_body((1.0, 0.1, 0.1), (20, 2, 2), 2e4, 0.3, num_modes=8, max_size=40,
                      max_tets=80, num_poses=80, num_snapshots=200)
    body["volumes"] = np.abs(fem.tet_volumes(body["X"], body["T"]))
    return body


def reconstruction_barrier(body, watch_all=True):
    plain = column_potential(body, "LINEAR", barrier=False)
    stiffness = inversion.BARRIER_SCALE * inversion.bulk_modulus(plain.material)
    barrier = inversion.ReconstructionBarrier(body["deformer"], body["X"], body["T"], stiffness)
    if watch_all:
        barrier.watch(np.zeros(len(body["T"])))
    return barrier


def test_reconstruction_barrier_gradient_matches_central_differences():
    """At a pose (a fixed direction scaled) where a few tets of the reconstruction are in
    (0, j_hat): the value is positive, its gradient matches central differences of the value,
    and the Gauss-Newton Hessian is symmetric PSD and matches sum w b'' g g^T of the
    differenced per-tet gradients g (an independent sum)."""
    body = coarse_column()
    barrier = reconstruction_barrier(body)
    ratios = inversion.DeformedVolumes(body["X"], body["T"], body["deformer"].basis)
    direction = np.random.default_rng(5).normal(size=barrier.num_coords)
    for scale in np.geomspace(1e-3, 1e2, 400):
        J = ratios.ratios(body["deformer"].q(scale * direction))
        if J.min() < barrier.j_hat:
            break
    s = scale * direction
    assert 0.0 < J.min() < barrier.j_hat
    value, grad, hess = barrier.evaluate(s, 2)
    assert value > 0.0
    h = 1e-6 * max(1.0, np.abs(s).max())
    unit = np.eye(len(s))
    fd = np.array([(barrier.evaluate(s + h * e, 0)[0] - barrier.evaluate(s - h * e, 0)[0])
                   / (2 * h) for e in unit])
    assert np.allclose(fd, grad, rtol=1e-5, atol=1e-7 * np.abs(grad).max())
    active = np.flatnonzero(J < barrier.j_hat)
    g = np.array([(ratios.ratios(body["deformer"].q(s + h * e))[active]
                   - ratios.ratios(body["deformer"].q(s - h * e))[active]) / (2 * h)
                  for e in unit]).T                                         # (A, m)
    wall = inversion.RECONSTRUCTION_WALL
    _, _, d2b = inversion.barrier_function(J[active] - wall, barrier.j_hat - wall)
    expected = g.T @ ((barrier.weights[active] * d2b)[:, None] * g)
    assert np.allclose(hess, expected, rtol=1e-4, atol=1e-6 * np.abs(expected).max())
    assert np.allclose(hess, hess.T) and np.linalg.eigvalsh(hess).min() >= -1e-9 * hess.max()


def test_deformed_volumes_match_determinants_of_the_positions_in_both_precisions():
    """DeformedVolumes.ratios against np.linalg.det of the deformed edge matrices (an independent
    recipe, from world positions) on poses from rest to inverting ones, the body 1,000 m from
    the origin: float64 to round-off, float32 (the step check's) within 1e-5 of the largest
    ratio, the bound its docstring gives."""
    body = coarse_column()
    far = body["X"] + np.array([1000.0, -500.0, 200.0])
    T, B = body["T"], body["deformer"].basis
    exact = inversion.DeformedVolumes(far, T, B)
    single = inversion.DeformedVolumes(far, T, B, dtype=np.float32)
    direction = np.random.default_rng(7).normal(size=body["deformer"].num_coords)
    smallest = []
    for scale in (0.0, 0.3, 3.0, 30.0):
        q = body["deformer"].q(scale * direction)
        x = body["X"] + (B @ q).reshape(-1, 3)
        reference = (np.linalg.det(x[T[:, 1:]] - x[T[:, :1]])
                     / np.linalg.det(body["X"][T[:, 1:]] - body["X"][T[:, :1]]))
        size = np.abs(reference).max()
        np.testing.assert_allclose(exact.ratios(q), reference, rtol=0, atol=1e-10 * size)
        got = single.ratios(q)
        assert single._coordinate_basis.dtype == np.float32
        np.testing.assert_allclose(got, reference, rtol=0, atol=1e-5 * size)
        smallest.append(reference.min())
    print("smallest det F per pose:", np.round(smallest, 3))
    assert smallest[0] == pytest.approx(1.0) and min(smallest) < 0.0   # rest to inverted


def test_reconstruction_barrier_is_zero_unwatched_and_near_rest_and_infinite_inverted():
    body = coarse_column()
    barrier = reconstruction_barrier(body, watch_all=False)
    s = np.full(barrier.num_coords, 1e3)                 # far out: the reconstruction inverts
    assert barrier.evaluate(s, 2)[0] == 0.0              # nothing watched: nothing to see
    barrier.watch(np.zeros(len(body["T"])))
    small = np.full(barrier.num_coords, 1e-4)
    value, grad, hess = barrier.evaluate(small, 2)
    assert value == 0.0 and not grad.any() and not hess.any()
    ratios = inversion.DeformedVolumes(body["X"], body["T"], body["deformer"].basis)
    assert ratios.ratios(body["deformer"].q(s)).min() <= 0.0
    assert np.isinf(barrier.evaluate(s, 0)[0])


def test_reconstruction_barrier_wall_is_above_where_the_step_check_counts_a_tet_flat():
    """Along a direction from rest, the poses where the smallest det F of the reconstruction
    is half of FLAT_J (a tet the step check counts as flat, though not inverted) and half way
    from FLAT_J to the wall are infinite for the barrier, and the one just past the wall is
    finite and positive: what the barrier admits, the check passes, with a margin far above
    its float32 rounding (bisection on the scale for each)."""
    body = coarse_column()
    barrier = reconstruction_barrier(body)
    ratios = inversion.DeformedVolumes(body["X"], body["T"], body["deformer"].basis)
    direction = np.random.default_rng(5).normal(size=barrier.num_coords)
    smallest = lambda scale: ratios.ratios(body["deformer"].q(scale * direction)).min()
    scales = np.geomspace(1e-3, 1e2, 400)
    outside = scales[np.argmax([smallest(scale) <= 0.0 for scale in scales])]
    assert smallest(outside) <= 0.0
    flat, wall = inversion.FLAT_J, inversion.RECONSTRUCTION_WALL
    assert dynamics.MIN_VOLUME_RATIO == flat and wall - flat >= 100 * 1e-5
    for wanted in (0.5 * flat, 0.5 * (flat + wall), 1.01 * wall):
        low, high = 0.0, outside                          # smallest(low) > wanted >= at high
        for _ in range(60):
            middle = 0.5 * (low + high)
            low, high = (middle, high) if smallest(middle) > wanted else (low, middle)
        J = smallest(high)
        assert 0.0 < J <= wanted and J == pytest.approx(wanted, rel=1e-3)
        value = barrier.evaluate(high * direction, 0)[0]
        assert (np.isinf(value) if wanted < wall else 0.0 < value < np.inf)


def test_reconstruction_barrier_keeps_a_coarse_models_column_from_inverting():
    """The coarse column, Linear, with the RS barrier and the step check: without the
    reconstruction barrier its reconstruction turns tets over and the check gives up
    (InversionError, the control); with it the fall completes, det F > 0 on every tet at every
    frame (recomputed from the trajectory), and the simulation's watch holds exactly the tets
    at or below WATCH_J at the end."""
    body = coarse_column()
    steps = int(SECONDS * FPS)
    control = column_simulation(body, column_potential(body, "LINEAR"))
    with pytest.raises(dynamics.InversionError):
        control.run(steps)
    potential = inversion.with_reconstruction_barrier(column_potential(body, "LINEAR"),
                                                      body["deformer"], body["X"], body["T"])
    sim = column_simulation(body, potential)
    ratios, volume = volume_ratios(body, sim.run(steps))
    print(f"coarse column with the reconstruction barrier: min det F {ratios.min():.4f}, "
          f"volume {volume.min():.3f}-{volume.max():.3f}")
    assert ratios.min() > dynamics.MIN_VOLUME_RATIO
    final = inversion.DeformedVolumes(body["X"], body["T"], body["deformer"].basis)
    np.testing.assert_array_equal(potential.barrier.watched,
                                  np.flatnonzero(final.ratios(sim.q) <= inversion.WATCH_J))
