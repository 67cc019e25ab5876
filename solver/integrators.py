"""Time integration schemes of ``dynamics``: Newmark's average acceleration and implicit Euler.

Both are one minimisation per step over the modal coordinates s, so the same Newton / line
search solves either (``newton``). World positions x (N, 3), lumped masses M, internal step dt,
gravity g (3,) [m/s^2] in world space; the step's objective is

    w/2 |x(s) - x_hat|_M^2 + V(s) + damping (+ contact),

the inertia a mass norm against a target x_hat with weight w (``frames`` turns it into a model
of the body's frame). A scheme is chosen once per simulation (``scheme``) and answers for all
that differs between the two: what a step carries to the next (``start``, ``settled``,
``advance``, ``rescaled``), the target and weight of a step, its damping potentials and first
guess (``plan``), the contact samples' velocities at t_n (``sample_velocities``), the kinetic
energy, and the velocity factor f: a scheme's end-of-step velocity is
v_{n+1} = f (x_{n+1} - x_n) / dt - (f - 1) v_n, which contact friction and damping act on
(``contact.Contact``).

- ``NewmarkScheme`` (``"newmark"``, the default): implicit Newmark average acceleration
  (beta = 1/4, gamma = 1/2, the trapezoidal rule, f = 2). With velocity v_n and acceleration
  a_n carried as state, x_{n+1} = x_n + dt v_n + dt^2/4 (a_n + a_{n+1}) and
  M a_{n+1} = M g - grad V(x_{n+1}). So a_{n+1} = 4/dt^2 (x_{n+1} - x~),
  x~ = x_n + dt v_n + dt^2/4 a_n, and the equation of motion 4/dt^2 M (x - x~) + grad V - M g = 0
  is the stationarity condition of

      s_{n+1} = argmin  2/dt^2 |x(s) - x_hat|_M^2 + V(s),   x_hat = x~ + dt^2/4 g

  (gravity folded in by completing the square; w = 4/dt^2). Then
  a_{n+1} = 4/dt^2 (x_{n+1} - x_n - dt v_n) - a_n and v_{n+1} = 2/dt (x_{n+1} - x_n) - v_n.
  Why this scheme: it is second order and A-stable, and on a linear system it conserves the
  energy exactly at any dt (amplification |z| = 1), so a body rings as long as its material
  says; its only error is a phase lag, relative frequency error
  1 - atan(w dt/2)/(w dt/2) ~ (w dt)^2/12 per mode. Stiff high modes are neither damped nor
  amplified at large w dt, only slowed (they alias to below the Nyquist rate): with dissipation
  coming only from the user's Rayleigh damping that is what we want, whereas BDF2 / TR-BDF2
  would again damp the jiggle numerically (BDF2's root for an undamped mode keeps 97.6 % of the
  amplitude per period at 24 steps per period, 71 % at 7.3 steps per period, i.e. 3.3 Hz at
  24 fps). Its known weakness is that nothing damps what it gets wrong: inconsistent start
  values and components normal to a constraint ring forever. So ``start`` solves the reduced
  equation of motion for the start acceleration, and the state is kept tangent to the RS map
  (below). With the nonlinear RS map and materials the energy is no longer exactly conserved,
  but it stays bounded in the tests (a jelly swinging past 90 degrees at one step per frame).
- ``EulerScheme`` (``"implicit_euler"``): x_hat = x_n + dt v_n + dt^2 g = 2 x_n - x_{n-1} + dt^2 g
  and w = 1/dt^2 (v_n = (x_n - x_{n-1}) / dt, f = 1), carrying the pose one step back. First
  order; it damps a mode by about (w dt)^2 / 2 per step, more at large dt: a free body spinning
  by delta radians per step loses about delta^2 of its angular velocity per step.

How Newmark composes with the reduced RS map and the frames: x = R (Xb + B q(s)) + c, so the
reduced map enters only through q(s) and its Jacobian. Newmark's state lives in the
generalised coordinates, (s, v_s, a_s) by the trapezoidal recursion, and x_hat's velocity and
acceleration are pushed forward each step: q_dot = J v_s, q_ddot = J a_s + d^2q/ds^2 (v_s, v_s)
(``NewmarkScheme.body_rates``). Carrying them in q-space or world space instead lets their
components normal to the RS map ring undamped (the trapezoidal rule never damps them), and on a
jelly swinging past 90 degrees that fed energy in until it blew up; pushed forward they stay
tangent. The world fields (x_hat, velocities) are ``frames.Field``s. The free body's frame has
its own trapezoidal state (world angular velocity and acceleration, centre velocity and
acceleration) and is eliminated in closed form in each step as for implicit Euler (so its
centre of mass falls exactly as the scheme's recursion: 1/2 g t^2 for Newmark,
1/2 g t^2 + 1/2 g dt t for implicit Euler). A keyed frame moves at its secant velocity over each
step; a change of that velocity kicks the body's relative velocity so its world momentum is
kept (``NewmarkScheme.follow_frame``): exact for keys sampled per frame, first order for smooth
motion.

Rayleigh damping (``dynamics``) is a dissipation potential on the step, in each scheme's own
end velocity (trapezoidal: 2/dt (q_{n+1} - q_n) - q_dot_n):

    newmark:   alpha/dt |q - q_n|^2_{M_B} - alpha (M_B v_q,n).q
               + beta/dt (s - s_n)^T K0 (s - s_n) - beta (K0 v_s,n).s
    implicit Euler: alpha/(2 dt) |q - q_n|^2_{M_B} + beta/(2 dt) (s - s_n)^T K0 (s - s_n)

whose gradients are alpha M_B q_dot_{n+1} and beta K0 s_dot_{n+1}. The first guess of a step is
the constant-velocity predictor s_n + dt s_dot_n.

Newmark is contact-stabilised (``STABILISED_CONTACT``, Deuflhard, Krause and Ertel 2008): the
step's contact force acts on the velocity but is left out of the acceleration carried into the
next step. Carried, a one-step impact kicked the next step again (nothing in the trapezoidal
rule damps it): a soft cube dropped 1 m onto an undamped floor gained 1.3 m g h and climbed
0.18 m above its start; a cube rocking after an impact at one step per frame gained a spurious
spin about the vertical axis (1.4 rad/s after 3 s, frictionless) and with friction its frame
acceleration kept ringing.
"""

from dataclasses import dataclass

import numpy as np
import scipy.linalg
from scipy.spatial.transform import Rotation

from . import newton, rs
from .frames import Field

STABILISED_CONTACT = True  # Newmark leaves contact forces out of its carried acceleration


@dataclass
class Pose:
    """A body's pose: modal coordinates s (m,), q = q(s) (rB,), the frame's rotation R (3, 3)
    and translation c (3,) [m]."""

    coords: np.ndarray
    q: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray

    def copy(self):
        return Pose(*(np.array(value) for value in
                      (self.coords, self.q, self.rotation, self.translation)))


@dataclass
class Rates:
    """What Newmark carries: v_s and a_s (m,); kick (m,) and kick_q = J kick (rB,), the velocity
    change a keyed frame's last change of velocity gave; a keyed frame's secant velocity
    (R' (3, 3), c' (3,)) over the step; a free frame's world angular velocity and acceleration
    (spin (2, 3)) and its centre's velocity and acceleration (drift (2, 3))."""

    velocity: np.ndarray
    acceleration: np.ndarray
    kick: np.ndarray
    kick_q: np.ndarray
    frame_velocity: tuple = None
    spin: np.ndarray = None
    drift: np.ndarray = None

    def copy(self):
        frame = None if self.frame_velocity is None else tuple(map(np.array, self.frame_velocity))
        return Rates(self.velocity.copy(), self.acceleration.copy(), self.kick.copy(),
                     self.kick_q.copy(), frame, *(None if x is None else x.copy()
                                                  for x in (self.spin, self.drift)))


@dataclass
class StepPlan:
    """One step's objective as a scheme makes it: inertia weight w [1/s^2] and target (a world
    ``frames.Field`` x_hat, or q_hat (rB,) in a fixed frame, which adds its loads itself); mass
    damping (k [1/s], e (rB,)) as k/2 q^T M_B q + e.q; the stiffness damping
    (``newton.Damping``); the first guess s (m,); Newmark's pushed-forward q_dot (rB,) and
    q(guess) (rB,) and dq/ds (rB, m) there when the scheme has them at hand (None: the solver
    evaluates them)."""

    weight: float
    target: object
    mass_damping: tuple
    damping: newton.Damping
    guess: np.ndarray
    body_velocity: np.ndarray = None
    guess_q: np.ndarray = None
    guess_jacobian: np.ndarray = None


def _q_rows(deformer, s, shifts, jacobian_at=None):
    """(q(s + shift) (k, rB) for shifts [(m,)...], dq/ds (rB, m) at shift ``jacobian_at`` or
    None), in one ``q_batch`` call where the deformer has one (the per-call overhead of the
    cubature's RS map is paid once), the Jacobian in the same product where it has
    ``q_batch_and_jacobian``."""
    if not shifts:
        return [], None
    points = s + np.array(shifts)
    fused = getattr(deformer, "q_batch_and_jacobian", None)
    if jacobian_at is not None and fused is not None:
        return fused(points, jacobian_at)
    batch = getattr(deformer, "q_batch", None)
    return (batch(points) if batch is not None else [deformer.q(p) for p in points]), None


def trapezoidal(rates, delta, dt):
    """Newmark average acceleration update of (velocity, acceleration) rates (2, ...) given the
    displacement delta over dt: a' = 4/dt^2 (delta - dt v) - a, v' = 2/dt delta - v."""
    v, a = rates
    return np.array([2.0 / dt * delta - v, 4.0 / dt ** 2 * (delta - dt * v) - a])


class NewmarkScheme:
    """Newmark average acceleration (module docstring); carries ``Rates``."""

    name = "newmark"
    velocity_factor = 2.0

    def start(self, sim, coords_velocity, angular_velocity, linear_velocity):
        """Rates at the current pose: v_s = ds/dt and the acceleration a_s consistent with the
        equation of motion; a keyed frame's velocity from its motion over the last dt; a free
        frame spinning uniformly at world ``angular_velocity`` (3,) [rad/s] and falling with g
        from ``linear_velocity`` (3,) [m/s]."""
        state, pose = sim.state, sim.state.pose
        m, rB = sim.num_coords, sim.moments.basis_size
        rates = Rates(coords_velocity.copy(), np.zeros(m), np.zeros(m), np.zeros(rB))
        if sim.frame_motion is not None:            # carried along at the frame's velocity
            R, c = sim.frame_motion(state.time - state.dt)
            rates.frame_velocity = ((pose.rotation - R) / state.dt,
                                    (pose.translation - c) / state.dt)
        if sim.free:
            rates.spin = np.array([np.asarray(angular_velocity, float), np.zeros(3)])
            rates.drift = np.array([np.asarray(linear_velocity, float), sim.gravity])
        J = sim.deformer.q_jacobian(pose.coords)
        v_q, a_q = self.body_rates(sim, pose, rates, J)   # a_q = curvature alone while a_s = 0
        if sim.fixed_frame:
            force = sim.fixed_load(state.time)
        else:
            R = np.asarray(pose.rotation, float)
            R1, R2, _, c2 = self.frame_rates(sim, pose, rates)
            external = Field.constant(sim.gravity, rB)          # a free fall cancels
            frame = Field(R2, R2[:, :, None] * pose.q + 2.0 * R1[:, :, None] * v_q, c2)
            force = sim.moments.project(R, external - frame)
        M = sim.moments.mass_matrix
        mass = J.T @ M @ J
        rhs = (J.T @ (force - M @ (a_q + sim.alpha * v_q))
               - sim.potential.evaluate(pose.coords, 1)[1]
               - sim.beta * (sim.potential.rest_hessian @ rates.velocity))
        rates.acceleration = scipy.linalg.solve(0.5 * (mass + mass.T), rhs, assume_a="pos")
        return rates

    def settled(self, sim):
        """Rates of a body at rest in its frame at the current pose."""
        return self.start(sim, np.zeros(sim.num_coords), np.zeros(3), np.zeros(3))

    def body_rates(self, sim, pose, rates, J=None, with_guess=False):
        """(v_q, a_q) (rB,): q_dot = J v_s and q_ddot = J a_s + kappa at the pose,
        kappa = d^2 q/ds^2 (v_s, v_s) the curvature of the RS map along the motion.

        Pushing forward from s keeps v and a tangent to the RS map: carried in q-space, their
        components normal to it would ring undamped (the trapezoidal rule never damps them) and
        feed energy into large rotations. Without J: by central differences of q(s), over
        s +- dt v_s (J v_s and kappa, errors O(dt^2) like the scheme's) and s +- dt^2/4 a_s
        (J a_s, the displacement a_s makes in x_hat): four q evaluations cost a fraction of one
        Jacobian, and they are exact for a linear map. with_guess: also return q at the
        predictor s + dt v_s (evaluated here anyway), the step's first Newton iterate, and
        dq/ds there if the deformer gives it with the same evaluation (else None).
        """
        s, q, v, a, dt = pose.coords, pose.q, rates.velocity, rates.acceleration, sim.dt
        eps = 0.25 * dt ** 2
        shifts = ([eps * a, -eps * a] if J is None and a.any() else []) + (
            [dt * v, -dt * v] if v.any() else [])
        ahead = len(shifts) - 2 if with_guess and v.any() else None
        at, guess_jacobian = _q_rows(sim.deformer, s, shifts, ahead)   # one batched evaluation
        if J is not None:
            v_q, a_q = J @ v, J @ a
        else:
            v_q, a_q = np.zeros(len(q)), np.zeros(len(q))
            if a.any():
                a_q = (at[0] - at[1]) / (2 * eps)
        if v.any():
            ahead, behind = at[-2], at[-1]
            a_q = a_q + (ahead - 2.0 * q + behind) / dt ** 2
            if J is None:
                v_q = (ahead - behind) / (2.0 * dt)
        if with_guess:
            return v_q, a_q, (at[-2] if v.any() else q), guess_jacobian
        return v_q, a_q

    def frame_rates(self, sim, pose, rates):
        """(R', R'', c', c'') of a keyed or free frame at the pose: a free frame's from its
        rates; a keyed one moves at its secant velocity over each step, without acceleration
        within it (``follow_frame``)."""
        R = np.asarray(pose.rotation, float)
        if sim.free:
            W, A = rs.skew(rates.spin)
            return W @ R, (A + W @ W) @ R, rates.drift[0], rates.drift[1]
        R1, c1 = rates.frame_velocity
        return R1, np.zeros((3, 3)), c1, np.zeros(3)

    def follow_frame(self, sim, R, c):
        """A keyed frame about to move to (R, c) over the next step: its velocity becomes
        the secant over that step. A change of frame velocity is an impulse on the body: the
        world momentum of its elastic part is kept (projected onto the reduced space in the
        mass metric), so the body lags and swings. Keys sampled per frame (piecewise linear)
        change velocity only at frames, and this is then exact; smooth motion gets its
        fictitious forces as impulses (kick, then trapezoidal drift). The damping of that step
        sees the velocity half way through the kick, so a steady acceleration gives the exact
        static lag (the kick and the damping stay symmetric)."""
        pose, rates, dt = sim.state.pose, sim.state.carried, sim.dt
        R_n = np.asarray(pose.rotation, float)
        R1, c1 = (R - R_n) / dt, (c - pose.translation) / dt
        old_R1, old_c1 = rates.frame_velocity
        rates.frame_velocity = (R1, c1)
        dR, dc = R1 - old_R1, c1 - old_c1
        rates.kick, rates.kick_q = np.zeros(sim.num_coords), np.zeros(len(pose.q))
        if not (dR.any() or dc.any()):
            return
        J = sim.deformer.q_jacobian(pose.coords)
        jump = sim.moments.project(R_n, Field(dR, dR[:, :, None] * pose.q, dc))
        mass = J.T @ sim.moments.mass_matrix @ J
        rates.kick = -scipy.linalg.solve(0.5 * (mass + mass.T), J.T @ jump, assume_a="pos")
        rates.kick_q = J @ rates.kick
        rates.velocity = rates.velocity + rates.kick

    def plan(self, sim, end):
        """The step's objective (``StepPlan``); end: the keyed frame's (R, c) at its end."""
        pose, rates, dt = sim.state.pose, sim.state.carried, sim.dt
        if sim.frame_motion is not None:
            self.follow_frame(sim, *end)
        v_q, a_q, guess_q, guess_jacobian = self.body_rates(sim, pose, rates, with_guess=True)
        v_damped = rates.velocity - 0.5 * rates.kick     # the velocity the damping sees
        damped_q = v_q - 0.5 * rates.kick_q
        if sim.fixed_frame:
            target = pose.q + dt * v_q + 0.25 * dt * dt * a_q
        else:
            target = self.target(sim, pose, rates, v_q, a_q)
        M, k, K0 = sim.moments.mass_matrix, 2.0 * sim.alpha / dt, sim.potential.rest_hessian
        damping = newton.Damping(2.0 * sim.beta / dt * K0, sim.beta * (K0 @ v_damped),
                                 pose.coords)
        return StepPlan(4.0 / dt ** 2, target, (k, -(M @ (k * pose.q + sim.alpha * damped_q))),
                        damping, pose.coords + dt * rates.velocity, v_q, guess_q, guess_jacobian)

    def target(self, sim, pose, rates, v_q, a_q):
        """x_hat = x_n + dt v_n + dt^2/4 (a_n + g) as a world field, v and a pushed forward:
        v = R' Y + R B v_q + c', a = R'' Y + 2 R' B v_q + R B a_q + c''."""
        dt, q = sim.dt, pose.q
        R = np.asarray(pose.rotation, float)
        R1, R2, c1, c2 = self.frame_rates(sim, pose, rates)
        x = Field.position(R, q, np.asarray(pose.translation, float))
        v = Field(R1, R1[:, :, None] * q + R[:, :, None] * v_q, c1)
        a = Field(R2, R2[:, :, None] * q + 2.0 * R1[:, :, None] * v_q + R[:, :, None] * a_q,
                  c2 + sim.gravity)
        return x + dt * v + (0.25 * dt * dt) * a

    def advance(self, sim, plan, s, q, R, c):
        """The rates after the step solved (s, q, R, c): the trapezoidal recursion, the free
        frame's too; with contact, stabilised (``drop_contact_acceleration``)."""
        pose, rates, dt = sim.state.pose, sim.state.carried, sim.dt
        if sim.free:
            turn = Rotation.from_matrix(R @ np.asarray(pose.rotation, float).T).as_rotvec()
            rates.spin = trapezoidal(rates.spin, turn, dt)
            rates.drift = trapezoidal(rates.drift, c - pose.translation, dt)
        rates.velocity, rates.acceleration = trapezoidal(
            np.array([rates.velocity, rates.acceleration]), s - pose.coords, dt)
        if sim.contact is not None and STABILISED_CONTACT:
            self.drop_contact_acceleration(sim, rates, s, q, R, c)
        return rates

    def drop_contact_acceleration(self, sim, rates, s, q, R, c):
        """Contact-stabilised Newmark (Deuflhard, Krause and Ertel 2008): the contact force of
        the step (barrier, friction, damping) changes the velocity through the trapezoidal
        rule, but is left out of the acceleration carried into the next step,
        a_{n+1} <- a_{n+1} - M^-1 f_c, f_c = -dE_c/dz, M the generalised mass of the unknowns
        z (s, or (s, phi, u) of a free body: J^T M_B J or T^T mass T). Carried, a one-step
        impact kicks the next step again (the barrier's acceleration is huge and the
        trapezoidal rule never damps it): a soft cube dropped 1 m onto an undamped floor at
        one step per frame gained 1.3 m g h within 2 s (``test_collisions``); left out, the
        next step predicts without it and the barrier acts again only if still needed. At rest
        the barrier then carries twice the weight at the step's end (its mean over the step is
        the weight), so bodies rest a little deeper in the band."""
        _, g, _ = sim.contact.terms(q, R, c, 1, sim.free)
        if not g.any():
            return
        m, rB = sim.num_coords, len(q)
        J = sim.deformer.q_jacobian(s)
        if sim.free:
            T = np.zeros((rB + 6, m + 6))
            T[:rB, :m] = J
            T[rB:, m:] = np.eye(6)
            mass = T.T @ sim.moments.mass_metric(q, R) @ T
            change = scipy.linalg.solve(0.5 * (mass + mass.T), T.T @ g, assume_a="pos")
            rates.spin[1] = rates.spin[1] + change[m:m + 3]
            rates.drift[1] = rates.drift[1] + change[m + 3:]
        else:
            mass = J.T @ sim.moments.mass_matrix @ J
            change = scipy.linalg.solve(0.5 * (mass + mass.T), J.T @ g, assume_a="pos")
        rates.acceleration = rates.acceleration + change[:m]

    def rescaled(self, sim, dt):
        """Rates carried into a step of another length: velocities and accelerations do not
        depend on dt."""
        return sim.state.carried

    def sample_velocities(self, sim, plan, x, start):
        """(k, 3) [m/s] world velocities at t_n of the contact samples at x (k, 3), pushed
        forward: v = R' Y + R B v_q + c', plus a placement's secant rate over the step (start:
        the placement at t_n, or None)."""
        pose, dt = sim.state.pose, sim.dt
        R, c = np.asarray(pose.rotation, float), np.asarray(pose.translation, float)
        rate = sim.contact.velocities(plan.body_velocity)
        if start is not None:     # fixed frame (R = I, c = 0): the placement's own rate
            moved = sim.contact.positions(pose.q, R, c, sim.contact.end_placement)
            rate = np.einsum("kij,kj->ki", start[0], rate) + (moved - x) / dt
        v = rate @ R.T
        if not sim.fixed_frame:
            R1, _, c1, _ = self.frame_rates(sim, pose, sim.state.carried)
            v += (x - c) @ (R1 @ R.T).T + c1
        return v

    def kinetic_energy(self, sim):
        """1/2 sum m |v|^2 [J] with Newmark's carried velocities."""
        pose, rates = sim.state.pose, sim.state.carried
        v_q = self.body_rates(sim, pose, rates)[0]
        if sim.fixed_frame:
            return 0.5 * float(v_q @ (sim.moments.mass_matrix @ v_q))
        R = np.asarray(pose.rotation, float)
        R1, _, c1, _ = self.frame_rates(sim, pose, rates)
        velocity = Field(R1, R1[:, :, None] * pose.q + R[:, :, None] * v_q, c1)
        return 0.5 * sim.moments.field_norm2(velocity)


class EulerScheme:
    """Implicit Euler (module docstring); carries the ``Pose`` one step dt back."""

    name = "implicit_euler"
    velocity_factor = 1.0

    def start(self, sim, coords_velocity, angular_velocity, linear_velocity):
        """The pose one step back whose backward differences are the given velocities: ds/dt
        (m,), a free frame's world ``angular_velocity`` [rad/s] and ``linear_velocity`` [m/s]
        (3,); a keyed frame's from its motion."""
        state, pose, dt = sim.state, sim.state.pose, sim.dt
        coords = pose.coords - dt * coords_velocity
        q = sim.deformer.q(coords) if coords_velocity.any() else pose.q.copy()
        if sim.free:
            R = rs.exp_rotation(-dt * np.asarray(angular_velocity, float)[None])[0]
            c = pose.translation - dt * np.asarray(linear_velocity, float)
        elif sim.frame_motion is not None:
            R, c = sim.frame_motion(state.time - dt)
        else:
            R, c = np.eye(3), np.zeros(3)
        return Pose(coords, q, R, c)

    def settled(self, sim):
        """The pose of a body at rest in its frame (the frame at rest too)."""
        pose = sim.state.pose
        return Pose(pose.coords.copy(), pose.q.copy(), pose.rotation, pose.translation)

    def plan(self, sim, end):
        """The step's objective (``StepPlan``): x_hat = 2 x_n - x_{n-1} + dt^2 g."""
        pose, previous, dt = sim.state.pose, sim.state.carried, sim.dt
        if sim.fixed_frame:
            target = 2.0 * pose.q - previous.q
        else:
            position = lambda p: Field.position(np.asarray(p.rotation, float), p.q,  # noqa: E731
                                                np.asarray(p.translation, float))
            target = (2.0 * position(pose) - position(previous)
                      + Field.constant(dt * dt * sim.gravity, len(pose.q)))
        k = sim.alpha / dt
        damping = newton.Damping(sim.beta / dt * sim.potential.rest_hessian,
                                 np.zeros(sim.num_coords), pose.coords)
        return StepPlan(1.0 / dt ** 2, target, (k, -k * (sim.moments.mass_matrix @ pose.q)),
                        damping, 2.0 * pose.coords - previous.coords)

    def advance(self, sim, plan, s, q, R, c):
        """The pose before the step becomes the one carried."""
        return sim.state.pose

    def rescaled(self, sim, dt):
        """The pose one step back rescaled to a step dt [s], keeping the velocities (backward
        differences): the modal coordinates and the centre linearly, the turn by its angle."""
        pose, previous = sim.state.pose, sim.state.carried
        ratio = dt / sim.dt
        coords = pose.coords - ratio * (pose.coords - previous.coords)
        translation = pose.translation - ratio * (pose.translation - previous.translation)
        R = np.asarray(pose.rotation, float)
        turn = Rotation.from_matrix(np.asarray(previous.rotation, float) @ R.T).as_rotvec()
        return Pose(coords, sim.deformer.q(coords),             # on the RS map, as ``start``
                    Rotation.from_rotvec(ratio * turn).as_matrix() @ R, translation)

    def sample_velocities(self, sim, plan, x, start):
        """(k, 3) [m/s] backward differences (x_n - x_{n-1}) / dt of the contact samples."""
        previous, time, dt = sim.state.carried, sim.state.time, sim.dt
        before = sim.contact.positions(previous.q, previous.rotation, previous.translation,
                                       sim.contact.placed_at(time - dt))
        return (x - before) / dt

    def kinetic_energy(self, sim):
        """1/2 sum m |v|^2 [J] with v = (x_n - x_{n-1}) / dt."""
        pose, previous = sim.state.pose, sim.state.carried
        h2 = sim.dt * sim.dt
        if sim.fixed_frame:
            dq = pose.q - previous.q
            return 0.5 * float(dq @ (sim.moments.mass_matrix @ dq)) / h2
        dR = pose.rotation - previous.rotation
        terms = [(dR, None), (pose.rotation, pose.q), (-previous.rotation, previous.q)]
        return 0.5 * sim.moments.mass_norm2(terms, pose.translation - previous.translation) / h2


SCHEMES = {scheme.name: scheme for scheme in (NewmarkScheme(), EulerScheme())}
INTEGRATORS = tuple(SCHEMES)


def scheme(integrator):
    """The scheme for "newmark" or "implicit_euler", or the scheme object given."""
    if isinstance(integrator, str) or integrator is None:
        if integrator not in SCHEMES:
            raise ValueError(f"unknown integrator {integrator!r}; expected one of "
                             f"{', '.join(INTEGRATORS)}")
        return SCHEMES[integrator]
    return integrator
