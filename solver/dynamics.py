"""Subspace dynamics in RS coordinates: SPEC.md section 6 [P15].

Generalised coordinates are the modal coordinates s (m,) of a deformer (``reduced.ReducedRS``):
RS coordinates y = (QW) s, reduced displacement coordinates q(s) (rB,), body-frame positions
``Y = Xb + B q(s)`` (N, 3) [m] with B (3N, rB) the deformer's basis (zero on pinned DOFs) and
``Xb = X - origin``. World positions are ``x = R Y + c`` for a frame (R, c):

- pinned, not moving: R = I, c = 0 (origin 0), world = the object's rest space;
- moving (``frame_motion``): (R(t), c(t)) prescribed per step, e.g. the Blender object's
  animated transform (rotation and translation only; scale belongs in X). Pinned DOFs are zero
  in B, so the pinned part follows the keys exactly and the rest lags behind;
- free (``free=True``): R and c are 6 extra unknowns, c the world position of the rest centre
  of mass ``origin`` (R = I, c = origin at the start, so world = rest space then).

Time integration (``integrator``): both schemes are one minimisation per step over s, so the
same Newton / line search solves either. World positions x (N, 3), lumped masses M, internal
step dt, gravity g (3,) [m/s^2] in world space:

- ``"newmark"`` (default): implicit Newmark average acceleration (beta = 1/4, gamma = 1/2, the
  trapezoidal rule). With velocity v_n and acceleration a_n carried as state,
  x_{n+1} = x_n + dt v_n + dt^2/4 (a_n + a_{n+1}) and M a_{n+1} = M g - grad V(x_{n+1}). So
  a_{n+1} = 4/dt^2 (x_{n+1} - x~), x~ = x_n + dt v_n + dt^2/4 a_n, and the equation of motion
  4/dt^2 M (x - x~) + grad V - M g = 0 is the stationarity condition of

      s_{n+1} = argmin  2/dt^2 |x(s) - x_hat|_M^2 + V(s),   x_hat = x~ + dt^2/4 g

  (gravity folded in by completing the square). Then a_{n+1} = 4/dt^2 (x_{n+1} - x_n - dt v_n)
  - a_n and v_{n+1} = 2/dt (x_{n+1} - x_n) - v_n. Why this scheme: it is second order and
  A-stable, and on a linear system it conserves the energy exactly at any dt (amplification
  |z| = 1), so a body rings as long as its material says; its only error is a phase lag,
  relative frequency error 1 - atan(w dt/2)/(w dt/2) ~ (w dt)^2/12 per mode. Stiff high modes
  are neither damped nor amplified at large w dt, only slowed (they alias to below the Nyquist
  rate): with dissipation coming only from the user's Rayleigh damping that is what we want,
  whereas BDF2 / TR-BDF2 would again damp the jiggle numerically (BDF2's root for an undamped
  mode keeps 97.6 % of the amplitude per period at 24 steps per period, 71 % at 7.3 steps per
  period, i.e. 3.3 Hz at 24 fps). Its known weakness is that nothing damps what it gets
  wrong: inconsistent start values and components normal to a constraint ring forever. So
  ``set_state`` solves the reduced equation of motion for the start acceleration, and the
  state is kept tangent to the RS map (below). With the nonlinear RS map and materials the
  energy is no longer exactly conserved, but it stays bounded in the tests (a jelly swinging
  past 90 degrees at one step per frame).
- ``"implicit_euler"``: x_hat = x_n + dt v_n + dt^2 g = 2 x_n - x_{n-1} + dt^2 g and the weight
  1/(2 dt^2) instead of 2/dt^2 (v_n = (x_n - x_{n-1}) / dt). First order; it damps a mode by
  about (w dt)^2 / 2 per step, more at large dt.

How it composes with the reduced RS map and the frames: the inertia term is always a mass
norm of x(s) - x_hat with x = R (Xb + B q(s)) + c, so the reduced map enters only through q(s)
and its Jacobian, exactly as for implicit Euler. Newmark's state lives in the generalised
coordinates, (s, v_s, a_s) by the trapezoidal recursion, and x_hat's velocity and acceleration
are pushed forward each step: q_dot = J v_s, q_ddot = J a_s + d^2q/ds^2 (v_s, v_s). Carrying
them in q-space or world space instead lets their components normal to the RS map ring
undamped (the trapezoidal rule never damps them), and on a jelly swinging past 90 degrees
that fed energy in until it blew up; pushed forward they stay tangent. World fields (x_hat,
velocities) have the form A Xb_k + sum_ij e_i (B_k[j] . Z[i, j]) + d with A (3, 3),
Z (3, 3, rB), d (3,) (``_Field``), closed under linear combination, so the frame terms are
contracted from precomputed mass moments (no per-vertex work per step). The free body's frame
has its own trapezoidal state (world angular velocity and acceleration, centre velocity and
acceleration) and is eliminated in closed form in each step as for implicit Euler (Procrustes
below, weight 4/dt^2). A prescribed (keyed) frame moves at its secant velocity over each step;
a change of that velocity kicks the body's relative velocity so its world momentum is kept
(``_follow_frame``): exact for keys sampled per frame, first order for smooth motion.

Rayleigh damping is a dissipation potential on the step:

    newmark:   alpha/dt |q - q_n|^2_{M_B} - alpha (M_B v_q,n).q
               + beta/dt (s - s_n)^T K0 (s - s_n) - beta (K0 v_s,n).s
    implicit Euler: alpha/(2 dt) |q - q_n|^2_{M_B} + beta/(2 dt) (s - s_n)^T K0 (s - s_n)

whose gradients are alpha M_B q_dot_{n+1} and beta K0 s_dot_{n+1} with each scheme's own
velocity (trapezoidal: 2/dt (q_{n+1} - q_n) - q_dot_n). Mass damping alpha [1/s] acts on the
body-frame velocity q_dot (so it damps elastic motion relative to the frame, never the free
fall or the spin of a free body), stiffness damping beta [s] on the strain rate through the
rest stiffness K0 = hess V(0) (= Lambda for the linear material; rigid motions have zero
strain and are not damped). Damping ratio of mode k: zeta_k = alpha/(2 w_k) + beta w_k/2
(``damping_ratio``).

Substeps: ``h`` is the sampling interval (one frame); each frame takes ``substeps`` internal
steps dt = h / substeps. ``substeps=0`` picks them from the highest retained frequency w_max
(rest stiffness against the rest reduced mass): dt w_max <= 1 (``SUBSTEP_BOUND``), where the
trapezoidal rule keeps that mode's frequency within 7.3 % and every mode below within
(w/w_max)^2 of that; capped at ``MAX_AUTO_SUBSTEPS`` because past it only the top modes lose
accuracy, never stability. Bakes then depend on the scene's fps only through the sampling.

Everything per step is reduced:

- fixed or moving frame: the inertia term is a quadratic in q whose linear term needs only the
  3x3 frame matrices contracted with precomputed mass moments of B and Xb (``H0``, ``H1``);
- free body: for given q the best frame is closed form (weighted Procrustes): c = centre of mass
  of x_hat minus R times that of Y, R the rotation maximising tr(R^T K), K = sum m (x_hat -
  x_hat_cm)(Y - Y_cm)^T, itself linear in q through the same moments. So the 6 frame
  coordinates are minimised exactly inside the objective and Newton runs on s alone; uniform
  gravity only moves c (the centre of mass then falls exactly as the scheme's recursion:
  1/2 g t^2 for Newmark, 1/2 g t^2 + 1/2 g dt t for implicit Euler).

Solver: Newton-type iterations on s, each followed by a backtracking Armijo line search on the
true objective. The first iteration, and any whose step is already below tolerance, uses the
Gauss-Newton Hessian J^T H_q J + hess V + (beta/h) K0 (J = dq/ds). Later iterations that still
move add, for a ``reduced.ReducedRS``, the curvature of the RS map itself, sum_i g_i d^2 q_i/ds^2
with g = dE/dq (``_GeometricStiffness``): Gauss-Newton converges only linearly once gravity or
inertia loads a strongly rotated pose (a small soft jelly at h = 1/24 needed 5-15 iterations, 2-3
with it), while a stiffer or larger body converges in two Gauss-Newton iterations and never pays
for the extra term. The free body's best-rotation curvature is left out. Linear systems by
Cholesky; an indefinite full Hessian (buckling, StVK in compression) falls back to
Gauss-Newton, regularised by a multiple of its diagonal if even that is indefinite. Iterations
stop once a step moves the body by less than ``tolerance`` times the bounding-box diagonal
(mass-weighted RMS) or after ``max_iterations``. The first guess is the constant-velocity
predictor s_n + dt s_dot_n.

Implicit Euler damps motion numerically, more at large dt: a free body spinning by delta
radians per step loses about delta^2 of its angular velocity per step.

Contact (``contact``, a ``contact.Contact``): its energy of the step, E_c(x) of the k surface
samples' world positions x_p = R (P_p - origin + rows_p q) + c at t_{n+1} (barrier, lagged
friction and damping), joins the step objective, and ``begin_step`` gets the samples'
positions and velocities at t_n before each internal step (Newmark's pushed-forward
velocities, implicit Euler's backward difference); the first step checks the start
(``check_start``: ValueError naming the collider). Pinned or keyed bodies know (R, c) at
t_{n+1}, so only q moves: gradient J^T rows^T R^T g, Gauss-Newton Hessian
J^T rows^T R^T H R rows J, summed only over samples whose Hessian block is nonzero. A free
body's frame is no longer eliminated (contact forces move and turn it): Newton runs jointly on
(s, phi, u) with R = exp(skew(phi)) R_it, c = c_it + u re-linearised at every iterate, the
inertia's gradient and Hessian blocks contracted from the same mass moments
(``_FramedInertia``), and the spin and drift state updated from the solved (R, c) as before;
without contact the closed-form frame is kept (same steps to solver tolerance, tested). The
start guess is the predictor (in its best frame), or the state at t_n if the predictor is
inside a collider; the barrier's +inf then keeps every accepted iterate outside. Newmark is
contact-stabilised (``_drop_contact_acceleration``): the step's contact force acts on the
velocity but is left out of the acceleration carried into the next step. Carried, a one-step
impact kicked the next step again (nothing in the trapezoidal rule damps it): a soft cube
dropped 1 m onto an undamped floor gained 1.3 m g h and climbed 0.18 m above its start; a
cube rocking after an impact at one step per frame gained a spurious spin about the vertical
axis (1.4 rad/s after 3 s, frictionless) and with friction its frame acceleration kept ringing.
Cost on a 0.2 m cube (8 modes, 60 samples, 4 substeps, a floor): 250 steps/s against 1,400
without it (``test_collisions``).
"""

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
from scipy.spatial.transform import Rotation

from . import frames, inversion, newton, rs

MAX_STEP_SPLITS = 4        # a step that inverts is retaken in halves, down to dt / 2^4
HOLD_MU = 1e-6             # Tikhonov weight of the held deformation (``_holding_deformation``)
HOLD_ROUNDS = 3            # fits of the held deformation, each holding the samples the last pushed in
MIN_VOLUME_RATIO = 1e-3    # det F at or below this counts as inverted (flat or turned inside out)


class InversionError(RuntimeError):
    """Raised by ``Simulation.step`` when a step inverts tets even when cut to its smallest.

    Attributes: time [s] at the start of the failed step; frame, the number of the frame being
    computed counted from the start state (1 = the first step); count of inverted tets and
    total tets; smallest det F; dt [s] of the last try; ``detail``, the message without the
    time and frame (for callers that name the frame their own way). The message is one line.
    """

    def __init__(self, time, frame, count, total, smallest, dt):
        self.time, self.frame, self.count, self.total = time, frame, count, total
        self.smallest, self.dt = smallest, dt
        if count:
            what = (f"{count} of {total} tets turned inside out or flat (smallest volume ratio "
                    f"{smallest:.3g})")
        else:
            what = "the elastic energy became infinite (a tet's strain collapsed)"
        self.detail = (f"{what} even with the time step cut to {dt:.3g} s; make the material "
                       f"stiffer, add substeps or damping, or use fewer modes")
        super().__init__(f"At t = {time:.4g} s (frame {frame} after the start): {self.detail}")
STABILISED_CONTACT = True  # Newmark leaves contact forces out of its carried acceleration


class ContactError(ValueError):
    """A contact a step cannot resolve: a collider or the keyed frame moved into the body within
    one step, even at the smallest retried step (``Simulation.step``). One readable line."""


class StartsInsideError(ContactError):
    """The body starts inside a collider (``contact.Contact.check_start``); never retried."""


class SimulationCancelled(Exception):
    """Raised by ``Simulation.run`` when ``should_cancel()`` returned True.

    ``trajectory`` holds the frames simulated so far.
    """

    def __init__(self, trajectory):
        super().__init__("simulation cancelled")
        self.trajectory = trajectory


@dataclass
class Trajectory:
    """States of a run, one row per step (the first is the state before the first step).

    times (F,) [s]; coords s (F, m); q (F, rB); rotations (F, 3, 3) and translations (F, 3) the
    frame (R, c); origin (3,) the body-frame origin in rest space (rest centre of mass for a
    free body, else 0); iterations (F,) Newton iterations per step (0 for the first row).
    World positions of frame f: R_f (X - origin + B q_f) + c_f.
    """

    times: np.ndarray
    coords: np.ndarray
    q: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    origin: np.ndarray
    iterations: np.ndarray = field(default=None)

    def body_displacements(self, rows):
        """(F, k, 3) body-frame displacements rows @ q for rows (3k, rB), e.g. B or Phi B."""
        return (self.q @ np.asarray(rows).T).reshape(len(self.q), -1, 3)

    def world_positions(self, rest_positions, rows):
        """(F, k, 3) world positions of points with rest positions (k, 3) and rows (3k, rB)."""
        body = np.asarray(rest_positions)[None] - self.origin + self.body_displacements(rows)
        return body @ np.swapaxes(self.rotations, 1, 2) + self.translations[:, None, :]


class _ContactInertia:
    """A pinned body's step model (``frames.QuadraticInertia``) plus its contact energy in the known
    frame (R, c) of the step's end: x_p = R (P_p - origin + rows_p q) + c, so the gradient
    adds rows^T R^T g and the Gauss-Newton Hessian rows^T R^T H R rows (``_contact_terms``)."""

    def __init__(self, model, sim, R, c):
        self.model, self.sim = model, sim
        self.R, self.c = np.asarray(R, dtype=np.float64), np.asarray(c, dtype=np.float64)

    def evaluate(self, q, order):
        value, grad, hess = self.model.evaluate(q, order)
        extra, g, H = self.sim._contact_terms(q, self.R, self.c, order, framed=False)
        if not np.isfinite(extra):
            return np.inf, None, None
        return (value + extra, grad + g if order >= 1 else None,
                hess + H if order >= 2 else None)


INTEGRATORS = ("newmark", "implicit_euler")
SUBSTEP_BOUND = 1.0        # largest dt * w_max of automatic substeps (module docstring)
MAX_AUTO_SUBSTEPS = 64     # automatic substeps stop here; only top-mode accuracy suffers past it
MAX_SUBSTEPS = 1000        # largest user override


def automatic_substeps(h, omega_max, bound=SUBSTEP_BOUND, cap=MAX_AUTO_SUBSTEPS):
    """Substeps n >= 1 per frame h [s] so that (h / n) omega_max [rad/s] <= bound, at most cap."""
    if not (np.isfinite(omega_max) and omega_max > 0.0):
        return 1
    return int(min(max(np.ceil(h * omega_max / bound - 1e-12), 1), cap))


def damping_ratio(mass_damping, stiffness_damping, omega):
    """Rayleigh damping alpha [1/s], beta [s] as a damping ratio at omega [rad/s] (> 0):
    zeta = alpha / (2 omega) + beta omega / 2 (works on arrays of omega too)."""
    omega = np.asarray(omega, dtype=np.float64)
    if np.any(omega <= 0.0):
        raise ValueError("the frequency of a damping ratio must be positive")
    return mass_damping / (2.0 * omega) + stiffness_damping * omega / 2.0


def rayleigh_from_damping_ratio(zeta, omega, stiffness_share=0.0):
    """(alpha [1/s], beta [s]) giving damping ratio zeta at omega [rad/s]; stiffness_share in
    [0, 1] is the part of zeta carried by beta (0: mass damping only, every mode slowed alike;
    1: stiffness damping only, faster modes damped more)."""
    if not omega > 0.0 or not zeta >= 0.0 or not 0.0 <= stiffness_share <= 1.0:
        raise ValueError("need omega > 0, zeta >= 0 and a stiffness share in [0, 1]")
    return 2.0 * zeta * omega * (1.0 - stiffness_share), 2.0 * zeta * stiffness_share / omega


class Simulation:
    """Time integration in the reduced RS space of a deformer (module docstring).

    deformer: ``reduced.ReducedRS`` (or any object with ``num_coords``, ``basis`` (3N, rB),
      ``q(s)`` (rB,) and ``q_jacobian(s)`` (rB, m)); rest_positions X (N, 3) [m]; masses (N,)
      lumped node masses [kg]; potential: ``materials.ReducedPotential`` over the same modal
      coordinates; h: sampling interval [s] (one frame: ``run`` records one row per h).
    gravity (3,) [m/s^2]: in world space (= rest space when there is no frame motion).
    mass_damping alpha [1/s], stiffness_damping beta [s]: Rayleigh damping, see above.
    free: the body has no pins and gets a floating frame. frame_motion: callable t -> (R, c)
      (e.g. ``FrameMotion``) for a moving pinned body; not with ``free``.
    start_time t0 [s]; tolerance: Newton stops when a step moves the body by less than this
      fraction of the bounding-box diagonal (RMS); max_iterations per step.
    integrator: "newmark" (default) or "implicit_euler". substeps: internal steps per h (>= 1),
      or 0 for automatic (``automatic_substeps`` of the highest rest frequency); dt = h /
      substeps. ``omega`` (m,) holds the rest frequencies [rad/s], ascending.
    tets (E, 4): the body's tet mesh (rest_positions are its nodes). Given, every internal step
      is checked (``step``): det F of all tets of x = X + B q must stay above
      ``MIN_VOLUME_RATIO`` and the elastic energy finite, else the step is undone and retaken
      as two half steps (recursively, ``MAX_STEP_SPLITS`` levels); ``InversionError`` if even
      the smallest inverts. Each check's det F also goes to the potential's
      ``watch_volumes`` if it has one (``inversion.with_reconstruction_barrier``). None: no
      check (the step is taken as it comes).
    contact: a ``contact.Contact`` of this body's surface samples (its rows over the same
      basis B, its points in rest space), or None. Its energy joins every step's objective
      (module docstring, Contact); a start inside a collider raises ValueError at the first step.
      Its optional ``proximity`` lets a step carried into a collider start outside it
      (``_holding_deformation``).
    external_force: callable t [s] -> (rB,) generalised force in q-space [N m per unit q],
      e.g. ``rig.RigLoad.force`` (a rig's accelerations and gravity felt by its flesh), added
      to gravity's B^T M g wherever that enters (each step at t_{n+1}, the start acceleration
      at t0); fixed frame only (no ``free``, no ``frame_motion``).
    sample_placement: callable t [s] -> (A (k, 3, 3), b (k, 3)) that carries the contact
      samples from the body's space to the world, x_p = A_p(t) Y_p + b_p, before the frame
      (e.g. ``rig.RigMotion.placement``: the skinning of a rig's flesh, which the simulation
      solves in rest space); None is the identity. Fixed frame only, and only with contact.

    The body starts at rest in its frame at s = 0 (``set_state`` changes that); a moving frame's
    velocity at t0 comes from frame_motion around t0, so a frame already moving at t0 carries
    the body along. State attributes: time, coords (s), q, rotation, translation; ``iterations``
    of the last frame (summed over its substeps).
    """

    def __init__(self, deformer, rest_positions, masses, potential, h, gravity=(0.0, 0.0, 0.0),
                 mass_damping=0.0, stiffness_damping=0.0, free=False, frame_motion=None,
                 start_time=0.0, tolerance=1e-5, max_iterations=20, integrator="newmark",
                 substeps=1, tets=None, contact=None, external_force=None,
                 sample_placement=None):
        if free and frame_motion is not None:
            raise ValueError("a free body cannot also follow a prescribed frame motion")
        if external_force is not None and (free or frame_motion is not None):
            raise ValueError("an external force is for a body in a fixed frame (e.g. the "
                             "flesh of a rig, solver.rig), not a free or moving one")
        self.external_force = external_force
        if sample_placement is not None and (free or frame_motion is not None or contact is None):
            raise ValueError("a sample placement carries the contact samples of a body in a "
                             "fixed frame; it needs a contact and no free or moving frame")
        self._placement = sample_placement
        self._end_placement = None
        if deformer.basis is None:
            raise ValueError("the deformer has no basis B; build it with its basis")
        if integrator not in INTEGRATORS:
            raise ValueError(f"unknown integrator {integrator!r}; expected one of "
                             f"{', '.join(INTEGRATORS)}")
        if int(substeps) != substeps or not 0 <= substeps <= MAX_SUBSTEPS:
            raise ValueError(f"substeps must be an integer in [0, {MAX_SUBSTEPS}] (0 = "
                             f"automatic), got {substeps!r}")
        self.deformer, self.potential = deformer, potential
        self.h, self.free, self.frame_motion = float(h), bool(free), frame_motion
        if not self.h > 0.0:
            raise ValueError(f"time step must be positive (got {h!r})")
        self.gravity = np.asarray(gravity, dtype=np.float64).reshape(3)
        self.alpha, self.beta = float(mass_damping), float(stiffness_damping)
        if self.alpha < 0.0 or self.beta < 0.0:
            raise ValueError("damping coefficients must be non-negative")
        self.integrator, self.newmark = integrator, integrator == "newmark"
        self.tolerance, self.max_iterations = float(tolerance), int(max_iterations)
        self.num_coords = deformer.num_coords
        self._precompute(np.asarray(rest_positions, dtype=np.float64),
                         np.asarray(masses, dtype=np.float64))
        self.omega = self._rest_frequencies()
        self.substeps = int(substeps) or automatic_substeps(self.h, self.omega[-1])
        self.dt = self.h / self.substeps
        # (beta/dt) K0 for Newmark, (beta/(2 dt)) K0 for implicit Euler, as 1/2 ds^T D ds.
        scale = (2.0 if self.newmark else 1.0) * self.beta / self.dt
        self._damping = scale * potential.rest_hessian                             # (m, m)
        self.time = float(start_time)
        self._start_time = self.time
        self._volumes = (None if tets is None else
                         inversion.DeformedVolumes(rest_positions, tets, deformer.basis))
        self._setup_contact(contact)
        self.set_state(np.zeros(self.num_coords))

    # -- precomputation -----------------------------------------------------------------------

    def _precompute(self, X, masses):
        """Mass moments of Xb and B (``frames.MassMoments``) and the Newton solver."""
        B = np.asarray(self.deformer.basis, dtype=np.float64)
        self.moments = frames.MassMoments(X, masses, B, self.free, self.frame_motion is not None)
        self.basis_size, self.origin = self.moments.basis_size, self.moments.origin
        self.diagonal = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))
        self._step_tol2 = (self.tolerance * self.diagonal) ** 2 * self.moments.total_mass
        self.solver = newton.StepSolver(self.deformer, self.potential, self.moments.mass_matrix,
                                        self._step_tol2, self.max_iterations)

    def _rest_frequencies(self):
        """(m,) rest frequencies [rad/s]: K0 w = omega^2 J0^T M_B J0 w at s = 0, ascending."""
        J0 = self.deformer.q_jacobian(np.zeros(self.num_coords))
        mass = J0.T @ self.moments.mass_matrix @ J0
        values = scipy.linalg.eigh(self.potential.rest_hessian, 0.5 * (mass + mass.T),
                                   eigvals_only=True)
        return np.sqrt(np.maximum(values, 0.0))

    # -- state --------------------------------------------------------------------------------

    def set_state(self, coords, coords_velocity=None, linear_velocity=None,
                  angular_velocity=None):
        """Set s (m,) and its velocity ds/dt (m,) at the current time (default at rest).

        Free bodies: the frame starts at R = I, c = origin, moving with ``linear_velocity``
        (3,) [m/s] and world ``angular_velocity`` (3,) [rad/s]. Implicit Euler keeps them as
        backward differences over one step dt; Newmark as velocities, with the start
        acceleration from the reduced equation of motion (``_start_newmark``).
        """
        dt = self.dt
        self.coords = np.array(coords, dtype=np.float64).reshape(self.num_coords)
        velocity = (np.zeros(self.num_coords) if coords_velocity is None
                    else np.asarray(coords_velocity, dtype=np.float64).reshape(self.num_coords))
        w = np.zeros(3) if angular_velocity is None else np.asarray(angular_velocity, float)
        v = np.zeros(3) if linear_velocity is None else np.asarray(linear_velocity, float)
        self.coords_prev = self.coords - dt * velocity
        self.q = self.deformer.q(self.coords)
        self.q_prev = self.deformer.q(self.coords_prev) if velocity.any() else self.q.copy()
        if self.free:
            self.rotation, self.translation = np.eye(3), self.origin.copy()
            self.rotation_prev = rs.exp_rotation(-dt * w[None])[0]
            self.translation_prev = self.translation - dt * v
        elif self.frame_motion is not None:
            self.rotation, self.translation = self.frame_motion(self.time)
            self.rotation_prev, self.translation_prev = self.frame_motion(self.time - dt)
        else:
            self.rotation, self.translation = np.eye(3), np.zeros(3)
            self.rotation_prev, self.translation_prev = np.eye(3), np.zeros(3)
        self.iterations = 0
        self._contact_checked = False                 # the first step checks the new start
        if self.newmark:
            self._start_newmark(velocity, w, v)
        if self._volumes is not None:
            self._watch(self._volumes.ratios(self.q))

    def _start_newmark(self, s_dot, angular_velocity, linear_velocity):
        """Newmark's state in generalised coordinates: v_s = s_dot and the acceleration a_s
        consistent with the equation of motion; a free frame's world angular velocity and
        acceleration and its centre's velocity and acceleration (spinning uniformly, falling
        with g). The world fields are pushed forward from these each step (``_body_rates``,
        ``_frame_rates``)."""
        self._v_s, self._impulse = s_dot.copy(), np.zeros(self.num_coords)
        self._impulse_q = np.zeros(self.basis_size)
        if self.frame_motion is not None:            # carried along at the frame's velocity
            R, c = self.frame_motion(self.time - self.dt)
            self._frame_velocity = ((self.rotation - R) / self.dt,
                                    (self.translation - c) / self.dt)
        if self.free:
            self._spin = np.array([np.asarray(angular_velocity, float), np.zeros(3)])
            self._drift = np.array([np.asarray(linear_velocity, float), self.gravity])
        J = self.deformer.q_jacobian(self.coords)
        self._a_s = np.zeros(self.num_coords)
        v_q, a_q = self._body_rates(J)                   # a_q = curvature alone while a_s = 0
        if not (self.free or self.frame_motion is not None):
            force = self._fixed_load(self.time)
        else:
            R = np.asarray(self.rotation, float)
            R1, R2, _, c2 = self._frame_rates()
            external = frames.Field.constant(self.gravity, self.basis_size)   # a free fall cancels
            frame = frames.Field(R2, R2[:, :, None] * self.q + 2.0 * R1[:, :, None] * v_q, c2)
            force = self.moments.project(R, external - frame)
        mass = J.T @ self.moments.mass_matrix @ J
        rhs = (J.T @ (force - self.moments.mass_matrix @ (a_q + self.alpha * v_q))
               - self.potential.evaluate(self.coords, 1)[1]
               - self.beta * (self.potential.rest_hessian @ self._v_s))
        self._a_s = scipy.linalg.solve(0.5 * (mass + mass.T), rhs, assume_a="pos")

    def _body_rates(self, J=None):
        """(v_q, a_q) (rB,): q_dot = J v_s and q_ddot = J a_s + kappa at the current state,
        kappa = d^2 q/ds^2 (v_s, v_s) the curvature of the RS map along the motion.

        Pushing forward from s keeps v and a tangent to the RS map: carried in q-space, their
        components normal to it would ring undamped (the trapezoidal rule never damps them) and
        feed energy into large rotations. Without J: by central differences of q(s), over
        s +- dt v_s (J v_s and kappa, errors O(dt^2) like the scheme's) and s +- dt^2/4 a_s
        (J a_s, the displacement a_s makes in x_hat): four q evaluations cost a fraction of one
        Jacobian, and they are exact for a linear map.
        """
        s, q, v, a = self.coords, self.q, self._v_s, self._a_s
        if J is not None:
            v_q, a_q = J @ v, J @ a
        else:
            v_q, a_q = np.zeros(self.basis_size), np.zeros(self.basis_size)
            if a.any():
                eps = 0.25 * self.dt ** 2
                a_q = (self.deformer.q(s + eps * a) - self.deformer.q(s - eps * a)) / (2 * eps)
        if v.any():
            ahead, behind = self.deformer.q(s + self.dt * v), self.deformer.q(s - self.dt * v)
            a_q = a_q + (ahead - 2.0 * q + behind) / self.dt ** 2
            if J is None:
                v_q = (ahead - behind) / (2.0 * self.dt)
        return v_q, a_q

    def _frame_rates(self):
        """(R', R'', c', c'') of the frame at the current time: a free frame's from its state;
        a prescribed one moves at its secant velocity over each step, without acceleration
        within it (``_follow_frame``)."""
        R = np.asarray(self.rotation, float)
        if self.free:
            W, A = rs.skew(self._spin)
            return W @ R, (A + W @ W) @ R, self._drift[0], self._drift[1]
        R1, c1 = self._frame_velocity
        return R1, np.zeros((3, 3)), c1, np.zeros(3)

    def _follow_frame(self, R, c):
        """A prescribed frame about to move to (R, c) over the next step: its velocity becomes
        the secant over that step. A change of frame velocity is an impulse on the body: the
        world momentum of its elastic part is kept (projected onto the reduced space in the
        mass metric), so the body lags and swings. Keys sampled per frame (piecewise linear)
        change velocity only at frames, and this is then exact; smooth motion gets its
        fictitious forces as impulses (kick, then trapezoidal drift). The damping of that step
        sees the velocity half way through the kick, so a steady acceleration gives the exact
        static lag (the kick and the damping stay symmetric)."""
        R_n = np.asarray(self.rotation, float)
        R1, c1 = (R - R_n) / self.dt, (c - self.translation) / self.dt
        old_R1, old_c1 = self._frame_velocity
        self._frame_velocity = (R1, c1)
        dR, dc = R1 - old_R1, c1 - old_c1
        self._impulse, self._impulse_q = np.zeros(self.num_coords), np.zeros(self.basis_size)
        if not (dR.any() or dc.any()):
            return
        J = self.deformer.q_jacobian(self.coords)
        jump = self.moments.project(R_n, frames.Field(dR, dR[:, :, None] * self.q, dc))
        mass = J.T @ self.moments.mass_matrix @ J
        self._impulse = -scipy.linalg.solve(0.5 * (mass + mass.T), J.T @ jump, assume_a="pos")
        self._impulse_q = J @ self._impulse
        self._v_s = self._v_s + self._impulse

    # -- one frame ----------------------------------------------------------------------------

    def step(self):
        """Advance one frame h (``substeps`` steps dt); returns the Newton iterations taken.

        With ``tets``, each internal step is checked for inverted tets and a non-finite energy
        (an RS strain past the volume barrier of ``inversion``, e.g. from a predictor that
        overshot); a failing step is undone (``_snapshot`` / ``_restore``: state, Newmark
        rates, frame state, time) and retaken as two steps of half the length, recursively
        down to dt / 2^MAX_STEP_SPLITS; past that ``InversionError``. Why halving: the
        predictor s_n + dt v_s and every Newton iterate move less, so the barrier's line search
        can hold them, and most of the frame keeps its nominal dt.
        """
        total = 0
        frame = int(round((self.time - self._start_time) / self.h)) + 1
        try:
            for _ in range(self.substeps):
                total += self._checked_step(self.h / self.substeps, 0, frame)
        finally:
            self._set_step(self.h / self.substeps)
        self.iterations = total
        return total

    def _checked_step(self, dt, splits, frame):
        """One internal step of length dt [s], retaken in halves if it inverts or if no start
        guess of it is outside the colliders (a fast collider or keyed frame; ``step``)."""
        if self._volumes is None and self.contact is None:
            return self._newmark_step() if self.newmark else self._euler_step()
        snapshot = self._snapshot()
        self._set_step(dt)
        blocked = None
        try:
            iterations = self._newmark_step() if self.newmark else self._euler_step()
        except StartsInsideError:
            raise
        except ContactError as exc:
            blocked = exc
        if blocked is None:
            if self._volumes is None:
                return iterations
            count, smallest, finite, ratios = self._inverted_tets()
            if count == 0 and finite:
                self._watch(ratios)
                return iterations
            self._watch(ratios, keep=True)     # the retried halves see the tets that turned
        self._restore(snapshot)
        if splits >= MAX_STEP_SPLITS:
            if blocked is not None:
                raise blocked
            raise InversionError(self.time, frame, count, self._volumes.num_tets, smallest, dt)
        if blocked is not None:
            iterations = 0
        for _ in range(2):
            iterations += self._checked_step(0.5 * dt, splits + 1, frame)
        return iterations

    def _inverted_tets(self):
        """(count of tets with det F <= MIN_VOLUME_RATIO, smallest det F, energy finite?,
        every tet's det F (E,))."""
        ratios = self._volumes.ratios(self.q)
        finite = bool(np.isfinite(self.potential.evaluate(self.coords, 0)[0]))
        return (int(np.count_nonzero(ratios <= MIN_VOLUME_RATIO)), float(ratios.min()), finite,
                ratios)

    def _watch(self, ratios, keep=False):
        """Hand every tet's det F to a potential with a reconstruction barrier
        (``inversion.ReconstructionBarrier.watch``)."""
        watch = getattr(self.potential, "watch_volumes", None)
        if watch is not None:
            watch(ratios, keep)

    def _snapshot(self):
        """The whole integrator state: every attribute (a step rebinds its state attributes,
        so attributes added by other features are covered too), arrays copied so that even an
        in-place update could not leak into the restored state. Shared objects (deformer,
        potential) are kept by reference: they hold no step state."""
        return {name: (value.copy() if isinstance(value, np.ndarray) else value)
                for name, value in self.__dict__.items()}

    def _restore(self, snapshot):
        self.__dict__.update(snapshot)

    def _set_step(self, dt):
        """Make the internal step dt [s]: the stiffness damping's 1/dt factor, and implicit
        Euler's history (backward differences over one step) rescaled so that its velocities
        are kept. Newmark carries velocities and accelerations, which do not depend on dt."""
        if dt == self.dt:
            return
        ratio = dt / self.dt
        if not self.newmark:
            self.coords_prev = self.coords - ratio * (self.coords - self.coords_prev)
            self.q_prev = self.deformer.q(self.coords_prev)     # on the RS map, as set_state
            self.translation_prev = (self.translation
                                     - ratio * (self.translation - self.translation_prev))
            R = np.asarray(self.rotation, float)
            turn = Rotation.from_matrix(np.asarray(self.rotation_prev, float) @ R.T).as_rotvec()
            self.rotation_prev = Rotation.from_rotvec(ratio * turn).as_matrix() @ R
        self.dt = dt
        scale = (2.0 if self.newmark else 1.0) * self.beta / dt      # as in the constructor
        self._damping = scale * self.potential.rest_hessian

    def _advance(self, s, q, R, c):
        self.coords_prev, self.q_prev = self.coords, self.q
        self.rotation_prev, self.translation_prev = self.rotation, self.translation
        self.coords, self.q, self.rotation, self.translation = s, q, R, c
        self.time += self.dt

    # -- Newmark average acceleration -----------------------------------------------------------

    def _newmark_step(self):
        """One trapezoidal step dt (module docstring); returns the Newton iterations."""
        dt = self.dt
        if self.frame_motion is not None:
            R, c = (np.asarray(x, float) for x in self.frame_motion(self.time + dt))
            self._follow_frame(R, c)
        v_q, a_q = self._body_rates()
        v_damped = self._v_s - 0.5 * self._impulse       # the velocity the damping sees
        damped_q = v_q - 0.5 * self._impulse_q
        if self.frame_motion is not None or self.free:
            target = self._newmark_target(v_q, a_q)
        if self.frame_motion is not None:
            model = self._newmark_moving_inertia(R, c, target, damped_q)
        elif self.free:
            model = self._newmark_free_inertia(target, damped_q)
        else:
            R, c = self.rotation, self.translation
            model = self._newmark_fixed_inertia(v_q, a_q, damped_q)
        damping = newton.Damping(self._damping, self.beta * (self.potential.rest_hessian @ v_damped),
                                 self.coords)
        guess = self.coords + dt * self._v_s
        if self.contact is None:
            s, q, iterations = self.solver.minimise(model, guess, damping)
            if self.free:
                R, c = self._best_frame(model, target, q)
        else:
            self._begin_contact(v_q)
            if self.free:
                framed = frames.FramedInertia(self.moments, 4.0 / dt ** 2, target,
                                        *self._mass_damping_terms(damped_q))
                start = self._feasible_guess(self._framed_guesses(model, target, guess), True)
                s, q, R, c, iterations = self.solver.minimise_framed(framed, start, damping,
                                                                     self._framed_contact)
            else:
                s, q, iterations = self._minimise_with_contact(model, R, c, guess, damping)
        if self.free:
            turn = Rotation.from_matrix(R @ np.asarray(self.rotation, float).T).as_rotvec()
            self._spin = _trapezoidal(self._spin, turn, dt)
            self._drift = _trapezoidal(self._drift, c - self.translation, dt)
        self._v_s, self._a_s = _trapezoidal(np.array([self._v_s, self._a_s]),
                                            s - self.coords, dt)
        if self.contact is not None and STABILISED_CONTACT:
            self._drop_contact_acceleration(s, q, R, c)
        self._advance(s, q, R, c)
        return iterations

    def _drop_contact_acceleration(self, s, q, R, c):
        """Contact-stabilised Newmark (Deuflhard, Krause and Ertel 2008): the contact force of
        the step (barrier, friction, damping) changes the velocity through the trapezoidal
        rule, but is left out of the acceleration carried into the next step,
        a_{n+1} <- a_{n+1} - M^-1 f_c, f_c = -dE_c/dz, M the generalised mass of the unknowns
        z (s, or (s, phi, u) of a free body: J^T M_B J or T^T mass T). Carried, a one-step
        impact kicks the next step again (the barrier's acceleration is huge and the
        trapezoidal rule never damps it): a soft cube dropped 1 m onto an undamped floor at
        one step per frame gained 1.3 m g h within 2 s (``test_collisions``); left out, the
        next step predicts without it and the barrier acts again only if still needed. At rest the
        barrier then carries twice the weight at the step's end (its mean over the step is the
        weight), so bodies rest a little deeper in the band."""
        _, g, _ = self._contact_terms(q, R, c, 1, self.free)
        if not g.any():
            return
        m, rB = self.num_coords, self.basis_size
        J = self.deformer.q_jacobian(s)
        if self.free:
            T = np.zeros((rB + 6, m + 6))
            T[:rB, :m] = J
            T[rB:, m:] = np.eye(6)
            mass = T.T @ self.moments.mass_metric(q, R) @ T
            change = scipy.linalg.solve(0.5 * (mass + mass.T), T.T @ g, assume_a="pos")
            self._spin[1] = self._spin[1] + change[m:m + 3]
            self._drift[1] = self._drift[1] + change[m + 3:]
        else:
            mass = J.T @ self.moments.mass_matrix @ J
            change = scipy.linalg.solve(0.5 * (mass + mass.T), J.T @ g, assume_a="pos")
        self._a_s = self._a_s + change[:m]

    def _best_frame(self, model, target, q):
        """A free frame (R, c) for q: Procrustes rotation, centre of mass on x_hat's."""
        R, _ = model.rotation(q)
        c = (np.einsum("ija,ja->i", target.Z, self.moments.com_per_q) + target.d
             - R @ (self.moments.com_per_q @ q))
        return R, c

    def _framed_guesses(self, model, target, guess):
        """Start guesses (s, R, c) of a free body with contact: the predictor in its best
        frame, else the state at t_n (outside the colliders by the previous step)."""
        R, c = self._best_frame(model, target, self.deformer.q(guess))
        return [(guess, R, c), (self.coords, np.asarray(self.rotation, float),
                                np.asarray(self.translation, float))]

    def _minimise_with_contact(self, model, R, c, guess, damping):
        """``_minimise`` of a pinned body's step with its contact in the known frame (R, c),
        from the first start guess outside the colliders (``_contact_guesses``)."""
        R, c = np.asarray(R, float), np.asarray(c, float)
        start, _, _ = self._feasible_guess(self._contact_guesses(guess, R, c), False)
        return self.solver.minimise(_ContactInertia(model, self, R, c), start, damping)

    def _contact_guesses(self, guess, R, c):
        """Start guesses (s, R, c) of a step with contact in the known end frame (R, c), made
        lazily: the predictor, s_n, then both plus ``_holding_deformation``. A keyed frame or a
        rig that carries the body towards a collider can put both of the first inside it when
        the body already touches it (a flicked ear pressed on a box while the creature lands);
        the held deformation keeps the touching samples where they were at t_n."""
        yield guess, R, c
        yield self.coords, R, c
        hold = self._holding_deformation(R, c)
        if hold is not None:
            yield guess + hold, R, c
            yield self.coords + hold, R, c

    def _holding_deformation(self, R, c, rounds=HOLD_ROUNDS):
        """ds (m,) that holds the contact samples near a collider at the step's end where they
        were at t_n, to first order, while the frame (R, c) and the placement move the body:
        min |G ds - (x_n - x)|^2 + mu ds^T K ds over the held samples, x their end positions
        with s_n, G = dx/ds = R A rows J (3 per sample, m), K the rest Hessian, mu = HOLD_MU
        tr(G^T G) / tr(K) (the least elastic energy among near-equal fits). Samples the
        correction moves into a collider join the held ones, up to ``rounds`` fits. None if no
        sample is near a collider, or if the contact has no ``proximity`` (it is optional)."""
        proximity = getattr(self.contact, "proximity", None)
        if proximity is None:
            return None
        q = self.q
        start = self._sample_positions(q, self.rotation, self.translation,
                                       self._placed_at(self.time))
        end = self._sample_positions(q, R, c, self._end_placement)
        held = proximity(end)[1]
        if not held.any():
            return None
        rows = self._sample_rows.reshape(-1, 3, self.basis_size)
        to_world = np.broadcast_to(R, (len(rows), 3, 3)) if self._end_placement is None \
            else R @ self._end_placement[0]
        G = np.einsum("kij,kja->kia", to_world, rows) @ self.deformer.q_jacobian(self.coords)
        K = self.potential.rest_hessian
        for _ in range(rounds):
            Gh = G[held].reshape(-1, self.num_coords)
            normal = Gh.T @ Gh
            mu = HOLD_MU * np.trace(normal) / max(np.trace(K), 1e-300)
            ds = scipy.linalg.solve(normal + mu * K, Gh.T @ (start - end)[held].ravel(),
                                    assume_a="sym")
            moved = self._sample_positions(self.deformer.q(self.coords + ds), R, c,
                                           self._end_placement)
            inside = proximity(moved)[0] & ~held
            if not inside.any():
                break
            held |= inside
        return ds

    def _newmark_target(self, v_q, a_q):
        """x_hat = x_n + dt v_n + dt^2/4 (a_n + g) as a world field, v and a pushed forward:
        v = R' Y + R B v_q + c', a = R'' Y + 2 R' B v_q + R B a_q + c''."""
        dt, q = self.dt, self.q
        R = np.asarray(self.rotation, float)
        R1, R2, c1, c2 = self._frame_rates()
        x = frames.Field.position(R, q, np.asarray(self.translation, float))
        v = frames.Field(R1, R1[:, :, None] * q + R[:, :, None] * v_q, c1)
        a = frames.Field(R2, R2[:, :, None] * q + 2.0 * R1[:, :, None] * v_q + R[:, :, None] * a_q,
                   c2 + self.gravity)
        return x + dt * v + (0.25 * dt * dt) * a

    def _mass_damping_terms(self, v_q):
        """Newmark's alpha/dt |q - q_n|^2_M - alpha (M v_q).q as (matrix, linear term)."""
        M, k = self.moments.mass_matrix, 2.0 * self.alpha / self.dt
        return k * M, -(M @ (k * self.q + self.alpha * v_q))

    def _newmark_fixed_inertia(self, v_q, a_q, damped_q):
        """R = I, c = 0: 2/dt^2 |q - q_hat|^2_M - B^T M g.q + mass damping, with
        q_hat = q_n + dt v_q + dt^2/4 a_q."""
        dt, M = self.dt, self.moments.mass_matrix
        q_hat = self.q + dt * v_q + 0.25 * dt * dt * a_q
        _, linear = self._mass_damping_terms(damped_q)
        b = (4.0 / dt ** 2) * (M @ q_hat) - linear + self._fixed_load(self.time + dt)
        return frames.QuadraticInertia(4.0 / dt ** 2 + 2.0 * self.alpha / dt, M, b)

    def _fixed_load(self, t):
        """(rB,) B^T M g plus the external force at time t [s] (fixed frame)."""
        load = self.moments.first_moment_B.T @ self.gravity
        if self.external_force is not None:
            load = load + np.asarray(self.external_force(t), dtype=np.float64)
        return load

    def _newmark_moving_inertia(self, R, c, target, v_q):
        """Prescribed frame (R, c) at t_{n+1}: 2/dt^2 |Y(q) - R^T (x_hat - c)|^2_M + damping."""
        dt = self.dt
        shifted = target - frames.Field.constant(c, self.basis_size)
        _, linear = self._mass_damping_terms(v_q)
        b = (4.0 / dt ** 2) * (self.moments.project(R, shifted) - self.moments.trace_H0) - linear
        return frames.QuadraticInertia(4.0 / dt ** 2 + 2.0 * self.alpha / dt, self.moments.mass_matrix, b)

    def _newmark_free_inertia(self, target, v_q):
        """Free body: K(q) = sum m (x_hat - x_hat_cm)(Y(q) - Y_cm)^T = K0 + Kq q from the
        field's (A, Z) and the mass moments; weight 4/dt^2."""
        A, Z = target.A, target.Z
        K0 = A @ self.moments.S0 + np.einsum("ija,jla->il", Z, self.moments.H0)
        Kq = np.einsum("ij,ljb->ilb", A, self.moments.H0) + np.einsum("ija,jlab->ilb", Z, self.moments.centred_H1)
        damping, linear = self._mass_damping_terms(v_q)
        return frames.FreeInertia(4.0 / self.dt ** 2, self.moments.centred_mass, damping, linear,
                            self.moments.trace_H0, K0, Kq.reshape(9, -1))

    # -- implicit Euler -------------------------------------------------------------------------

    def _euler_step(self):
        """One implicit Euler step dt; returns the Newton iterations."""
        if self.frame_motion is not None:
            R, c = self.frame_motion(self.time + self.dt)
            model = self._moving_inertia(np.asarray(R, float), np.asarray(c, float))
        elif self.free:
            model = self._free_inertia()
        else:
            R, c = self.rotation, self.translation
            model = self._fixed_inertia()
        predictor = 2.0 * self.coords - self.coords_prev
        damping = newton.Damping(self._damping, np.zeros(self.num_coords), self.coords)
        if self.contact is None:
            s, q, iterations = self.solver.minimise(model, predictor, damping)
            if self.free:
                R, _ = model.rotation(q)
                c = self._free_translation(R, q)
        else:
            self._begin_contact(None)
            if self.free:
                q_guess = self.deformer.q(predictor)
                R, _ = model.rotation(q_guess)
                guesses = [(predictor, R, self._free_translation(R, q_guess)),
                           (self.coords, np.asarray(self.rotation, float),
                            np.asarray(self.translation, float))]
                s, q, R, c, iterations = self.solver.minimise_framed(
                    self._euler_framed_inertia(), self._feasible_guess(guesses, True), damping,
                    self._framed_contact)
            else:
                s, q, iterations = self._minimise_with_contact(model, R, c, predictor, damping)
        self._advance(s, q, R, c)
        return iterations

    def _fixed_inertia(self):
        """R = I, c = 0: b = M_B (2 q_n - q_{n-1}) / dt^2 + B^T M g + alpha/dt M_B q_n."""
        h, M = self.dt, self.moments.mass_matrix
        b = (M @ ((2.0 + self.alpha * h) * self.q - self.q_prev)) / (h * h)
        b += self._fixed_load(self.time + h)
        return frames.QuadraticInertia(1.0 / (h * h) + self.alpha / h, M, b)

    def _moving_inertia(self, R, c):
        """Prescribed frame (R, c) at t_{n+1}: target Y~ = R^T (x_hat - c) in the body frame.

        Y~_k = C_n Y_n,k + C_p Y_{n-1},k + e with C_n = 2 R^T R_n, C_p = -R^T R_{n-1},
        e = R^T (2 c_n - c_{n-1} + dt^2 g - c); B^T M (Y~ - Xb) is contracted from H0, H1.
        """
        h = self.dt
        Cn = 2.0 * R.T @ self.rotation
        Cp = -R.T @ self.rotation_prev
        e = R.T @ (2.0 * self.translation - self.translation_prev + h * h * self.gravity - c)
        contract = lambda C, A: C.reshape(-1) @ A.reshape(9, -1)               # noqa: E731
        rhs = (contract(Cn + Cp - np.eye(3), self.moments.H0) + contract(Cn, self.moments.H1 @ self.q)
               + contract(Cp, self.moments.H1 @ self.q_prev) + self.moments.first_moment_B.T @ e)
        b = rhs / (h * h) + (self.alpha / h) * (self.moments.mass_matrix @ self.q)
        return frames.QuadraticInertia(1.0 / (h * h) + self.alpha / h, self.moments.mass_matrix, b)

    def _free_inertia(self):
        """Free body: K(q) = sum_p A_p P_p(q), A_n = 2 R_n, A_{n-1} = -R_{n-1}, with the
        centred cross moments P_p(q) = sum m Y'_p Y'(q)^T (linear in q)."""
        K0, Kq = np.zeros((3, 3)), np.zeros((3, 3, self.basis_size))
        for A, qp in ((2.0 * self.rotation, self.q), (-self.rotation_prev, self.q_prev)):
            const = self.moments.S0 + self.moments.H0 @ qp                                     # (3, 3)
            lin = np.swapaxes(self.moments.H0, 0, 1) + qp @ self.moments.centred_H1                  # (3, 3, rB)
            K0 += A @ const
            Kq += np.einsum("ki,ijb->kjb", A, lin)
        h, M = self.dt, self.moments.mass_matrix
        return frames.FreeInertia(1.0 / h ** 2, self.moments.centred_mass, (self.alpha / h) * M,
                            -(self.alpha / h) * (M @ self.q), self.moments.trace_H0, K0,
                            Kq.reshape(9, -1))

    def _euler_framed_inertia(self):
        """Free body with contact: 1/(2 dt^2) |x - x_hat|^2_M, x_hat = 2 x_n - x_{n-1} + dt^2 g,
        with the frame explicit (``_FramedInertia``), plus mass damping alpha/(2 dt) |q - q_n|^2_M."""
        h, M, rB = self.dt, self.moments.mass_matrix, self.basis_size
        target = (2.0 * frames.Field.position(np.asarray(self.rotation, float), self.q,
                                        np.asarray(self.translation, float))
                  - frames.Field.position(np.asarray(self.rotation_prev, float), self.q_prev,
                                    np.asarray(self.translation_prev, float))
                  + frames.Field.constant(h * h * self.gravity, rB))
        return frames.FramedInertia(self.moments, 1.0 / h ** 2, target, (self.alpha / h) * M,
                              -(self.alpha / h) * (M @ self.q))

    def _free_translation(self, R, q):
        """c = centre of mass of x_hat - R (centre of mass of Y(q))."""
        D = self.moments.com_per_q
        x_hat_cm = (2.0 * self.rotation @ (D @ self.q) - self.rotation_prev @ (D @ self.q_prev)
                    + 2.0 * self.translation - self.translation_prev
                    + self.dt * self.dt * self.gravity)
        return x_hat_cm - R @ (D @ q)

    # -- contact --------------------------------------------------------------------------------

    def _setup_contact(self, contact):
        """Keep the samples' rest positions relative to the origin and their rows (k, 3, rB)."""
        self.contact = contact
        self._contact_checked = False
        if contact is None:
            return
        expected = 2.0 if self.newmark else 1.0             # the contact's end-velocity factor
        if getattr(contact, "alpha", expected) != expected:
            raise ValueError(f"the contact was built for another integrator than {self.integrator!r}")
        k = int(contact.num_samples)
        rows = np.asarray(contact.rows, dtype=np.float64)
        if rows.shape != (3 * k, self.basis_size):
            raise ValueError(f"contact rows have shape {rows.shape}, expected "
                             f"{(3 * k, self.basis_size)} (3 rows per sample over the basis B)")
        self._sample_rest = np.asarray(contact.points, dtype=np.float64).reshape(k, 3) - self.origin
        self._sample_rows = rows

    def _placed_at(self, t):
        """The samples' placement (A (k, 3, 3), b (k, 3)) at time t, or None (identity)."""
        if self._placement is None:
            return None
        A, b = self._placement(t)
        return np.asarray(A, dtype=np.float64), np.asarray(b, dtype=np.float64)

    def _sample_positions(self, q, R, c, placement=None):
        """(k, 3) world positions R (A (P - origin + rows q) + b) + c of the contact samples,
        placement (A, b) or None for the identity."""
        body = self._sample_rest + (self._sample_rows @ q).reshape(-1, 3)
        if placement is not None:
            body = np.einsum("kij,kj->ki", placement[0], body) + placement[1]
        return body @ np.asarray(R, dtype=np.float64).T + np.asarray(c, dtype=np.float64)

    def _begin_contact(self, v_q):
        """``contact.begin_step`` at t_n with the samples' world positions and velocities:
        Newmark's pushed-forward v = R' Y + R B v_q + c' (v_q from ``_body_rates``) plus a
        placement's secant rate over the step, implicit Euler's backward difference. The first
        step checks the start (``check_start``). Keeps the placement at the step's end."""
        R, c = np.asarray(self.rotation, float), np.asarray(self.translation, float)
        start = self._placed_at(self.time)
        self._end_placement = self._placed_at(self.time + self.dt)
        x = self._sample_positions(self.q, R, c, start)
        if not self._contact_checked:
            try:
                self.contact.check_start(x, self.time)
            except ValueError as exc:
                raise StartsInsideError(str(exc)) from None
            self._contact_checked = True
        if self.newmark:
            rate = (self._sample_rows @ v_q).reshape(-1, 3)
            if start is not None:     # fixed frame (R = I, c = 0): the placement's own rate
                moved = self._sample_positions(self.q, R, c, self._end_placement)
                rate = np.einsum("kij,kj->ki", start[0], rate) + (moved - x) / self.dt
            v = rate @ R.T
            if self.free or self.frame_motion is not None:
                R1, _, c1, _ = self._frame_rates()
                v += (x - c) @ (R1 @ R.T).T + c1
        else:
            v = (x - self._sample_positions(self.q_prev, self.rotation_prev,
                                            self.translation_prev,
                                            self._placed_at(self.time - self.dt))) / self.dt
        self.contact.begin_step(self.time, self.dt, x, v)

    def _contact_terms(self, q, R, c, order, framed):
        """Contact value [J], gradient and Gauss-Newton Hessian in q (rB,), or in (q, phi, u)
        (rB + 6,) for a free frame R = exp(skew(phi)) R, c + u at phi = u = 0.

        dx_p/dq = R A_p rows_p (A_p the step end's sample placement, I without one),
        dx_p/dphi = -skew(x_p - c), dx_p/du = I; the Hessian
        sum_p J_p^T H_p J_p only over samples whose block H_p is nonzero."""
        A = None if self._end_placement is None else self._end_placement[0]
        r = self._sample_positions(q, R, c, self._end_placement) - c
        value, g, H = self.contact.evaluate(r + c, order)
        if order == 0 or not np.isfinite(value):
            return value, None, None
        pulled = g @ R if A is None else np.einsum("kij,ki->kj", A, g @ R)     # A^T R^T g
        grad = self._sample_rows.T @ pulled.ravel()
        if framed:
            grad = np.concatenate([grad, np.cross(r, g).sum(axis=0), g.sum(axis=0)])
        if order < 2:
            return value, grad, None
        n = len(grad)
        active = np.flatnonzero(np.abs(H).reshape(len(H), 9).max(axis=1) > 0.0)
        if len(active) == 0:
            return value, grad, np.zeros((n, n))
        rows = self._sample_rows.reshape(-1, 3, self.basis_size)[active]
        to_world = np.broadcast_to(R, (len(active), 3, 3)) if A is None else R @ A[active]
        Jp = np.einsum("kij,kja->kia", to_world, rows)                        # (a, 3, rB)
        if framed:
            eye = np.broadcast_to(np.eye(3), (len(active), 3, 3))
            Jp = np.concatenate([Jp, -rs.skew(r[active]), eye], axis=2)
        HJ = H[active] @ Jp
        return value, grad, Jp.reshape(-1, n).T @ HJ.reshape(-1, n)

    def _framed_contact(self, q, R, c, order):
        return self._contact_terms(q, R, c, order, True)

    def _feasible_guess(self, guesses, framed):
        """The first of (s, R, c) guesses whose samples are outside every collider."""
        for s, R, c in guesses:
            q = self.deformer.q(s)
            x = self._sample_positions(q, R, c, self._end_placement)
            if np.isfinite(self.contact.evaluate(x, 0)[0]):
                return s, R, c
        raise ContactError(f"at t = {self.time:.4g} s a collider or the keyed motion moved into "
                           "the body within one step; add substeps")

    # -- statics, runs, energy ----------------------------------------------------------------

    def static_equilibrium(self, s=None, max_iterations=200):
        """Minimise V(s) - (R^T g).(sum m Y) - f_ext(t).q in the current frame (f_ext the
        ``external_force`` at the current time, e.g. a rig's loads); sets the state at rest
        there.

        For pinned bodies (not free). Same Newton / line search as ``step`` with the elastic
        Hessian alone (so it converges linearly where q(s) curves). s: first guess (default
        rest). Returns s (m,).
        """
        if self.free:
            raise ValueError("a free body has no static equilibrium under gravity")
        b = self.moments.first_moment_B.T @ (self.rotation.T @ self.gravity)
        if self.external_force is not None:
            b = b + np.asarray(self.external_force(self.time), dtype=np.float64)
        model = frames.QuadraticInertia(0.0, self.moments.mass_matrix, b)
        guess = np.zeros(self.num_coords) if s is None else np.asarray(s, dtype=np.float64)
        no_damping = newton.Damping(np.zeros((self.num_coords, self.num_coords)),
                                    np.zeros(self.num_coords), self.coords)
        s, q, self.iterations = self.solver.minimise(model, guess, no_damping, max_iterations)
        self.coords, self.coords_prev, self.q, self.q_prev = s, s.copy(), q, q.copy()
        self.rotation_prev, self.translation_prev = self.rotation, self.translation
        if self.newmark:
            self._start_newmark(np.zeros(self.num_coords), np.zeros(3), np.zeros(3))
        return s

    def run(self, num_steps, callback=None, should_cancel=None):
        """Take ``num_steps`` steps; returns a ``Trajectory`` of num_steps + 1 rows.

        callback(step, num_steps) after each step; should_cancel() -> bool before each step:
        True raises ``SimulationCancelled`` carrying the frames so far.
        """
        rows = [self._record()]
        for k in range(int(num_steps)):
            if should_cancel is not None and should_cancel():
                raise SimulationCancelled(self._trajectory(rows))
            self.step()
            rows.append(self._record())
            if callback is not None:
                callback(k + 1, int(num_steps))
        return self._trajectory(rows)

    def _record(self):
        return (self.time, self.coords.copy(), self.q.copy(), np.array(self.rotation),
                np.array(self.translation), self.iterations)

    def _trajectory(self, rows):
        t, s, q, R, c, it = (np.array(column) for column in zip(*rows))
        return Trajectory(times=t, coords=s, q=q, rotations=R, translations=c,
                          origin=self.origin.copy(), iterations=it)

    def world_positions(self, rest_positions, rows=None):
        """(k, 3) current world positions R (X - origin + rows q) + c; rows default B."""
        rows = self.deformer.basis if rows is None else rows
        body = np.asarray(rest_positions) - self.origin + (np.asarray(rows) @ self.q).reshape(-1, 3)
        return body @ self.rotation.T + self.translation

    def energy(self):
        """dict of kinetic, elastic, gravity and total energy [J] of the current state.

        Kinetic 1/2 sum m |v|^2 with the integrator's own world velocities (Newmark's v_n;
        implicit Euler's (x_n - x_{n-1}) / dt), elastic V(s_n), gravity -sum m g.x_n (zero at
        the rest pose in the rest frame).
        """
        h2 = self.dt * self.dt
        if self.newmark and (self.free or self.frame_motion is not None):
            R, v_q = np.asarray(self.rotation, float), self._body_rates()[0]
            R1, _, c1, _ = self._frame_rates()
            velocity = frames.Field(R1, R1[:, :, None] * self.q + R[:, :, None] * v_q, c1)
            kinetic = 0.5 * self.moments.field_norm2(velocity)
        elif self.newmark:
            v_q = self._body_rates()[0]
            kinetic = 0.5 * float(v_q @ (self.moments.mass_matrix @ v_q))
        elif self.free or self.frame_motion is not None:
            dR = self.rotation - self.rotation_prev
            terms = [(dR, None), (self.rotation, self.q), (-self.rotation_prev, self.q_prev)]
            kinetic = 0.5 * self.moments.mass_norm2(terms, self.translation - self.translation_prev) / h2
        else:
            dq = self.q - self.q_prev
            kinetic = 0.5 * float(dq @ (self.moments.mass_matrix @ dq)) / h2
        moment = self.rotation @ (self.moments.first_moment_B @ self.q)
        moment += (self.rotation - np.eye(3)) @ self.moments.first_moment_X
        moment += self.moments.total_mass * (self.translation - (self.origin if self.free else 0.0))
        gravity = -float(self.gravity @ moment)
        elastic = self.potential.evaluate(self.coords, 0)[0]
        return dict(kinetic=kinetic, elastic=elastic, gravity=gravity,
                    total=kinetic + elastic + gravity)

def _trapezoidal(rates, delta, dt):
    """Newmark average acceleration update of (velocity, acceleration) rates (2, ...) given the
    displacement delta over dt: a' = 4/dt^2 (delta - dt v) - a, v' = 2/dt delta - v."""
    v, a = rates
    return np.array([2.0 / dt * delta - v, 4.0 / dt ** 2 * (delta - dt * v) - a])
