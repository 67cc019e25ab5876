"""Tests for the contact integration of solver.dynamics (``Simulation(contact=...)``).

Oracles: finite differences of the free frame's inertia blocks in (q, phi, u) and of the whole
step objective's gradient in (s, phi, u) (free) and s (pinned), the per-vertex sums the mass
moments replace, the closed-form (Procrustes) frame when contact exerts no force, and exact
invariants of a free body on a test-local frictionless floor (tangential momentum).

The contact objects here are test-local implementations of the agreed interface (notes'
contract: check_start, begin_step, evaluate, points, rows, num_samples), so these tests do not
depend on solver.contact.
"""

import numpy as np
import pytest

from solver import body_contact, dynamics, frames, rs
from test_dynamics import GRAVITY, build_body


class QuadraticContact:
    """Test-local contact: value 1/2 sum_p (x_p - a_p)^T K_p (x_p - a_p) (smooth, exact Hessian
    blocks K_p) plus a frictionless penalty floor k/2 sum_p w_p (z_floor - z_p)_+^2.

    Records every begin_step call; check_start raises if a sample starts below the floor.
    """

    def __init__(self, points, rows, anchors=None, blocks=None, floor=None, stiffness=0.0,
                 weights=None):
        self.points = np.asarray(points, dtype=np.float64)
        self.rows = np.asarray(rows, dtype=np.float64)
        self.num_samples = len(self.points)
        self.anchors, self.blocks = anchors, blocks
        self.floor, self.stiffness = floor, stiffness
        self.weights = np.ones(self.num_samples) if weights is None else weights
        self.calls = []

    def check_start(self, x, t):
        if self.floor is not None and np.any(x[:, 2] <= self.floor):
            raise ValueError(f"the body starts inside collider 'floor' at t = {t:g} s")

    def begin_step(self, t_start, dt, x_start, v_start):
        self.calls.append((t_start, dt, np.array(x_start), np.array(v_start)))

    def evaluate(self, x, order=2):
        k = len(x)
        value, grad, hess = 0.0, np.zeros((k, 3)), np.zeros((k, 3, 3))
        if self.blocks is not None:
            d = x - self.anchors
            Kd = np.einsum("kij,kj->ki", self.blocks, d)
            value += 0.5 * float(np.sum(d * Kd))
            grad += Kd
            hess += self.blocks
        if self.floor is not None:
            depth = np.maximum(self.floor - x[:, 2], 0.0)
            value += 0.5 * self.stiffness * float(self.weights @ depth ** 2)
            grad[:, 2] -= self.stiffness * self.weights * depth
            hess[:, 2, 2] += self.stiffness * self.weights * (depth > 0.0)
        return value, (grad if order >= 1 else None), (hess if order >= 2 else None)


@pytest.fixture(scope="module")
def free_cube():
    """Free 0.4 x 0.2 x 0.2 m box, 4 x 2 x 2 cells, E = 1e4 Pa, 6 modes."""
    return build_body((0.4, 0.2, 0.2), (4, 2, 2), 1e4, 0.3, num_modes=6, pinned=False,
                      max_size=30, max_tets=60, num_poses=30, num_snapshots=40)


@pytest.fixture(scope="module")
def pinned_bar():
    return build_body((1.0, 0.1, 0.1), (10, 2, 2), 1e6, 0.3, num_modes=6, max_size=30,
                      max_tets=60, num_poses=30, num_snapshots=40)


def corner_samples(body):
    """Samples at the box's 8 corners and face centres: (indices, rows (3k, rB))."""
    X = body["X"]
    lo, hi = X.min(axis=0), X.max(axis=0)
    on_box = np.isclose(X, lo).any(axis=1) | np.isclose(X, hi).any(axis=1)
    idx = np.flatnonzero(on_box)[::3]
    B = body["deformer"].basis
    return idx, B.reshape(len(X), 3, -1)[idx].reshape(-1, B.shape[1])


def random_quadratic(body, rng, scale):
    idx, rows = corner_samples(body)
    G = rng.normal(size=(len(idx), 3, 3))
    blocks = scale * (G @ np.swapaxes(G, 1, 2) + np.eye(3))
    anchors = body["X"][idx] + 0.05 * rng.normal(size=(len(idx), 3))
    return QuadraticContact(body["X"][idx], rows, anchors=anchors, blocks=blocks)


def simulation(body, h, **kwargs):
    return dynamics.Simulation(body["deformer"], body["X"], body["masses"], body["potential"],
                               h, **kwargs)


def chart(R, c, z, m):
    """(s-offset, R, c) of chart coordinates z = (ds, phi, u) around (R, c)."""
    return z[:m], rs.exp_rotation(z[None, m:m + 3])[0] @ R, c + z[m + 3:]


def central_gradient(f, n, h):
    E = np.eye(n)
    return np.array([(f(h * E[i]) - f(-h * E[i])) / (2.0 * h) for i in range(n)])


# 1. The free frame's inertia in (q, phi, u) ----------------------------------------------------

def test_framed_inertia_blocks_match_finite_differences(free_cube):
    """Gradient and every exact Hessian block (qq, q phi, q u, phi phi, phi u, uu) of
    ``_FramedInertia`` against central differences of its value in the chart R =
    exp(skew(phi)) R0, c = c0 + u; the unscaled Gauss-Newton metric against the per-vertex sum
    sum m (dx/dz)^T dx/dz it replaces."""
    rng = np.random.default_rng(3)
    sim = simulation(free_cube, 1.0 / 24.0, gravity=GRAVITY, free=True)
    rB = sim.basis_size
    target = frames.Field(rs.exp_rotation(np.array([[0.2, 0.1, -0.3]]))[0],
                          0.01 * rng.normal(size=(3, 3, rB)), rng.normal(size=3))
    model = frames.FramedInertia(sim.moments, 4.0 * 24.0 ** 2, target,
                                 0.3 * sim.moments.mass_matrix, rng.normal(size=rB))
    q = 0.05 * rng.normal(size=rB)
    R0, c0 = rs.exp_rotation(np.array([[0.5, -0.2, 0.1]]))[0], rng.normal(size=3)
    n = rB + 6

    def value(z):
        return model.value(q + z[:rB], rs.exp_rotation(z[None, rB:rB + 3])[0] @ R0,
                           c0 + z[rB + 3:])

    def errors():
        """(gradient error, {block: Hessian error}) relative to the largest entry."""
        grad, exact, _, _ = model.derivatives(q, R0, c0)
        fd_grad = central_gradient(value, n, 1e-5)
        fd_hess = np.array([central_gradient(lambda z: value(z + e), n, 1e-4)
                            - central_gradient(lambda z: value(z - e), n, 1e-4)
                            for e in 1e-4 * np.eye(n)]) / 2e-4
        blocks = {"q": slice(0, rB), "phi": slice(rB, rB + 3), "u": slice(rB + 3, n)}
        scale = np.abs(exact).max()
        return np.abs(fd_grad - grad).max() / np.abs(grad).max(), {
            f"{a}{b}": np.abs(fd_hess[blocks[a], blocks[b]] - exact[blocks[a], blocks[b]]).max()
            / scale for a in blocks for b in blocks}

    grad_error, errors_centred = errors()
    mass = model.derivatives(q, R0, c0)[3]
    Xb = free_cube["X"] - sim.origin
    Bk = free_cube["deformer"].basis.reshape(len(Xb), 3, rB)
    r = (Xb + Bk @ q) @ R0.T
    dx = np.concatenate([np.einsum("ij,kja->kia", R0, Bk), -rs.skew(r),
                         np.broadcast_to(np.eye(3), (len(Xb), 3, 3))], axis=2)
    per_vertex = np.einsum("k,kia,kib->ab", free_cube["masses"], dx, dx)
    mass_error = np.abs(per_vertex - mass).max() / np.abs(mass).max()
    # A free body's basis carries almost no first moment (F_B ~ 0, m_X = 0), which leaves the
    # q-u and phi-u blocks near zero: the algebra is checked again with made-up moments.
    moments = sim.moments
    moments.first_moment_X = 0.1 * moments.total_mass * np.array([1.0, -2.0, 0.5])
    moments.first_moment_B = moments.first_moment_B + rng.normal(size=moments.first_moment_B.shape)
    model = frames.FramedInertia(moments, model.scale, target, model.D, model.e)
    grad_error_moved, errors_moved = errors()
    print(f"framed inertia vs central differences: gradient {grad_error:.1e} "
          f"({grad_error_moved:.1e} with first moments); Hessian blocks "
          + ", ".join(f"{k} {v:.1e}/{errors_moved[k]:.1e}" for k, v in errors_centred.items())
          + f" (of the largest entry); mass metric vs per-vertex sum {mass_error:.1e}")
    assert max(grad_error, grad_error_moved) < 1e-8
    assert max(max(errors_centred.values()), max(errors_moved.values())) < 1e-6
    assert np.abs(model.derivatives(q, R0, c0)[1][rB:rB + 3, rB + 3:]).max() > 1.0
    assert mass_error < 1e-12


# 2. The whole step objective ------------------------------------------------------------------

@pytest.mark.parametrize("integrator", ["newmark", "implicit_euler"])
def test_free_step_gradient_matches_finite_differences(free_cube, integrator):
    """A free body moving and deforming, one step taken, then the next step's objective
    (inertia + elastic + damping + contact) in (s, phi, u) around a perturbed iterate: its
    gradient against central differences of the value; the contact's (q, u) Hessian blocks are
    exact for the quadratic contact, so the Gauss-Newton Hessian's u-u block must match too."""
    rng = np.random.default_rng(5)
    contact = random_quadratic(free_cube, rng, 50.0)
    sim = simulation(free_cube, 1.0 / 24.0, gravity=GRAVITY, free=True, contact=contact,
                     mass_damping=0.5, stiffness_damping=0.01, integrator=integrator,
                     dtype=np.float64)        # q smooth to round-off for the differences
    s0 = 0.2 * rng.normal(size=6)
    sim.set_state(s0, linear_velocity=[0.3, 0.0, 0.1], angular_velocity=[0.5, 1.0, -0.2])
    sim.step()
    # The next step's model, built as the step does.
    plan = sim.scheme.plan(sim, None)
    model, damping = sim._framed_inertia(plan), plan.damping
    sim._begin_contact(plan)
    s = sim.coords + 0.05 * rng.normal(size=6)
    R = rs.exp_rotation(np.array([[0.1, -0.2, 0.3]]))[0] @ sim.rotation
    c = sim.translation + 0.02 * rng.normal(size=3)
    q = sim.deformer.q(s)
    grad, gauss_newton, _, _ = sim.solver.framed_system(model, s, q, R, c, damping,
                                                       sim.contact.framed_terms)

    def value(z):
        ds, R1, c1 = chart(R, c, z, 6)
        return sim.solver.framed_objective(model, s + ds, sim.deformer.q(s + ds), R1, c1, damping,
                                           sim.contact.framed_terms)

    fd = central_gradient(value, 12, 1e-6)
    error = np.abs(fd - grad).max() / np.abs(grad).max()
    fd_uu = np.array([central_gradient(lambda z: value(z + e), 12, 1e-5)[9:]
                      - central_gradient(lambda z: value(z - e), 12, 1e-5)[9:]
                      for e in 1e-5 * np.eye(12)[9:]]) / 2e-5
    uu_error = np.abs(fd_uu - gauss_newton[9:, 9:]).max() / np.abs(gauss_newton[9:, 9:]).max()
    print(f"{integrator}: step objective gradient in (s, phi, u) vs central differences "
          f"{error:.1e}; u-u Hessian {uu_error:.1e}")
    assert error < 1e-6
    assert uu_error < 1e-6


def test_pinned_step_gradient_matches_finite_differences(pinned_bar):
    """A pinned bar on a moving frame: the step model with contact (``_ContactInertia``) chained
    to s, J^T dE/dq, against central differences of the objective in s; its q-Hessian (exact for
    the quadratic contact, x linear in q) against differences of its q-gradient."""
    rng = np.random.default_rng(7)
    contact = random_quadratic(pinned_bar, rng, 20.0)
    motion = frames.FrameMotion([0.0, 1.0], rs.exp_rotation(np.array([[0, 0, 0],
                                                                      [0.3, 0, 0.6]])),
                                [[0, 0, 0], [0.1, 0.2, 0.0]])
    sim = simulation(pinned_bar, 1.0 / 24.0, gravity=GRAVITY, frame_motion=motion,
                     contact=contact, dtype=np.float64)
    R, c = motion(0.3)
    base = sim._inertia(sim.scheme.plan(sim, (R, c)), (R, c))
    model = body_contact.ContactInertia(base, sim.contact, R, c)
    s = 0.3 * rng.normal(size=6) / np.sqrt(np.maximum(pinned_bar["modes"].eigenvalues[:6], 1))
    J = sim.deformer.q_jacobian(s)
    grad = J.T @ model.evaluate(sim.deformer.q(s), 1)[1]
    fd = central_gradient(lambda ds: model.evaluate(sim.deformer.q(s + ds), 0)[0], 6, 1e-7)
    q = sim.deformer.q(s)
    rB = sim.basis_size
    fd_hess = np.array([model.evaluate(q + e, 1)[1] - model.evaluate(q - e, 1)[1]
                        for e in 1e-6 * np.eye(rB)]) / 2e-6
    hess = model.evaluate(q, 2)[2]
    error = np.abs(fd - grad).max() / np.abs(grad).max()
    hess_error = np.abs(fd_hess - hess).max() / np.abs(hess).max()
    print(f"pinned: gradient in s vs central differences {error:.1e}; q-Hessian {hess_error:.1e}")
    assert error < 1e-6
    assert hess_error < 1e-8


# 3. Steps ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("integrator", ["newmark", "implicit_euler"])
def test_force_free_contact_matches_the_closed_form_frame(free_cube, integrator):
    """A contact that never touches (zero energy): the joint Newton over (s, phi, u) takes the
    same steps as the closed-form Procrustes frame, for a spinning, vibrating, thrown body."""
    idx, rows = corner_samples(free_cube)
    far = QuadraticContact(free_cube["X"][idx], rows, floor=-100.0, stiffness=1e6)
    runs = []
    for contact in (None, far):
        sim = simulation(free_cube, 1.0 / 24.0, gravity=GRAVITY, free=True, contact=contact,
                         integrator=integrator, tolerance=1e-10)
        s0 = np.zeros(6)
        s0[0] = 0.3
        sim.set_state(s0, linear_velocity=[1.0, 0.0, 0.0], angular_velocity=[0.0, 2.0, 1.0])
        runs.append(sim.run(24))
    a, b = runs
    scale = np.abs(a.coords).max()
    print(f"{integrator}: joint vs closed-form frame over 1 s: |ds| {np.abs(a.coords - b.coords).max():.1e}"
          f" (|s| {scale:.2f}), |dR| {np.abs(a.rotations - b.rotations).max():.1e}, "
          f"|dc| {np.abs(a.translations - b.translations).max():.1e} m")
    # 1e-10 both (1e-8 to 1e-6 when a step the objective's rounding could not judge was
    # halved away: ``newton.hidden_decrease``)
    assert np.abs(a.coords - b.coords).max() < 1e-8 * scale
    assert np.abs(a.rotations - b.rotations).max() < 1e-8
    assert np.abs(a.translations - b.translations).max() < 1e-7
    assert len(far.calls) == 24 * sim.substeps


def test_free_body_on_frictionless_floor_keeps_tangential_momentum(free_cube):
    """Thrown sideways with spin onto a frictionless penalty floor: the floor pushes only along
    z, so the centre of mass moves exactly x0 + v0 t in x and y (the u-gradient is the momentum
    balance), while in z it bounces (the floor did act)."""
    X = free_cube["X"]
    idx, rows = corner_samples(free_cube)
    mass = free_cube["masses"].sum()
    floor = X[:, 2].min() - 0.05
    contact = QuadraticContact(X[idx], rows, floor=floor, stiffness=2e4 * mass / len(idx))
    v0 = np.array([0.8, -0.3, 0.0])
    sim = simulation(free_cube, 1.0 / 24.0, gravity=GRAVITY, free=True, contact=contact,
                     substeps=4, tolerance=1e-10, stiffness_damping=0.005)
    sim.set_state(np.zeros(6), linear_velocity=v0, angular_velocity=[0.0, 1.0, 2.0])
    trajectory = sim.run(24)
    x = trajectory.world_positions(X, free_cube["deformer"].basis)
    com = np.einsum("k,fki->fi", free_cube["masses"], x) / mass
    t = trajectory.times
    drift = np.abs(com[:, :2] - (com[0, :2] + v0[:2] * t[:, None])).max()
    lowest = trajectory.world_positions(X[idx], rows)[:, :, 2].min()
    rise = np.diff(com[:, 2]).max()
    print(f"frictionless floor 1 s: |com_xy - (x0 + v0 t)| {drift:.1e} m; lowest sample "
          f"{1e3 * (lowest - floor):+.1f} mm from the floor; largest com rise per frame "
          f"{1e3 * rise:.1f} mm")
    assert lowest < floor                        # it reached the floor ...
    assert rise > 0.0                            # ... and was pushed back up
    assert drift < 1e-7


def test_begin_step_receives_world_positions_and_velocities(free_cube):
    """begin_step gets, per internal step, t_n, dt and the samples' world positions and
    velocities at t_n: a free body thrown with spin, its positions from the trajectory; its
    velocities Newmark's v = w x (x - c) + c' (rigid start), implicit Euler's backward
    difference (x_n - x_{n-1}) / dt."""
    idx, rows = corner_samples(free_cube)
    w, v = np.array([0.0, 0.0, 2.0]), np.array([1.0, 0.0, 0.5])
    for integrator in ("newmark", "implicit_euler"):
        probe = QuadraticContact(free_cube["X"][idx], rows, floor=-100.0, stiffness=0.0)
        sim = simulation(free_cube, 1.0 / 24.0, gravity=GRAVITY, free=True, contact=probe,
                         integrator=integrator, substeps=2)
        sim.set_state(np.zeros(6), linear_velocity=v, angular_velocity=w)
        trajectory = sim.run(2)
        positions = trajectory.world_positions(free_cube["X"][idx], rows)
        times = [call[0] for call in probe.calls]
        assert np.allclose(times, np.arange(4) / 48.0) and all(
            call[1] == pytest.approx(1.0 / 48.0) for call in probe.calls)
        assert np.allclose(probe.calls[2][2], positions[1], atol=1e-12)
        first = probe.calls[0]
        if integrator == "newmark":
            expected = np.cross(w, first[2] - sim.origin) + v
        else:
            expected = (first[2] - ((first[2] - sim.origin) @ rs.exp_rotation(
                -w[None] / 48.0)[0].T + sim.origin - v / 48.0)) * 48.0
        print(f"{integrator}: begin_step velocity error {np.abs(first[3] - expected).max():.1e}")
        assert np.allclose(first[3], expected, atol=1e-12)


def test_a_start_inside_a_collider_fails_clearly(free_cube):
    idx, rows = corner_samples(free_cube)
    floor = QuadraticContact(free_cube["X"][idx], rows, floor=free_cube["X"][:, 2].min() + 0.01,
                             stiffness=1.0)
    sim = simulation(free_cube, 1.0 / 24.0, gravity=GRAVITY, free=True, contact=floor)
    with pytest.raises(dynamics.StartsInsideError, match="inside collider 'floor'"):
        sim.step()
    with pytest.raises(ValueError, match="rows"):
        simulation(free_cube, 0.1, free=True,
                   contact=QuadraticContact(free_cube["X"][idx], rows[:, :3]))
    # The simulation gives the contact its own scheme, so the two cannot disagree.
    euler_contact = QuadraticContact(free_cube["X"][idx], rows)
    simulation(free_cube, 0.1, free=True, contact=euler_contact, integrator="implicit_euler")
    assert euler_contact.scheme.velocity_factor == 1.0


def test_a_frame_keyed_into_a_collider_within_one_step_fails_clearly(pinned_bar):
    """A pinned bar whose keyed frame drops it 1 m through a floor 5 cm below it in one frame:
    neither start guess of that step is outside, even cut to 1/16 of the frame (6 cm per step),
    so the step raises instead of passing through."""
    idx, rows = corner_samples(pinned_bar)
    floor = QuadraticContact(pinned_bar["X"][idx], rows, floor=pinned_bar["X"][:, 2].min() - 0.05,
                             stiffness=1.0)
    floor.evaluate_penalty = floor.evaluate

    def inside_is_infinite(x, order=2):
        if np.any(x[:, 2] <= floor.floor):
            return np.inf, None, None
        return floor.evaluate_penalty(x, order)
    floor.evaluate = inside_is_infinite
    motion = frames.FrameMotion([0.0, 1.0 / 24.0], np.stack([np.eye(3)] * 2),
                                [[0, 0, 0], [0, 0, -1.0]])
    sim = simulation(pinned_bar, 1.0 / 24.0, frame_motion=motion, contact=floor)
    with pytest.raises(dynamics.ContactError, match="moved into the body within one step"):
        sim.step()

