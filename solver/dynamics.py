"""Subspace dynamics in RS coordinates: SPEC.md section 6 [P15].

Generalised coordinates are the modal coordinates s (m,) of a deformer (``reduced.ReducedRS``):
RS coordinates y = (QW) s, reduced displacement coordinates q(s) (rB,), body-frame positions
``Y = Xb + B q(s)`` (N, 3) [m] with B (3N, rB) the deformer's basis (zero on pinned DOFs) and
``Xb = X - origin``. World positions are ``x = R Y + c`` for a frame (R, c) that is fixed
(pinned, not moving), keyed (``frame_motion``, e.g. ``frames.FrameMotion``) or free
(``free=True``); ``frames`` says how each enters a step without touching the vertices.

``Simulation`` runs the steps. Each internal step dt minimises, over s (and a free frame with
contact), the inertia of the integration scheme (``integrators``: Newmark's average
acceleration by default, or implicit Euler, chosen once), the elastic potential V(s), Rayleigh
damping and the contact energy (``body_contact``), by Newton with a line search
(``newton``). What a step reads and changes is its ``State``: time, step length, pose and what
the scheme carries; a step that inverts tets or cannot start outside the colliders is undone
by restoring a copy of it and retaken in halves (``Simulation.step``).

Rayleigh damping: mass damping alpha [1/s] acts on the body-frame velocity q_dot (so it damps
elastic motion relative to the frame, never the free fall or the spin of a free body),
stiffness damping beta [s] on the strain rate through the rest stiffness K0 = hess V(0)
(= Lambda for the linear material; rigid motions have zero strain and are not damped), each a
dissipation potential on the step in the scheme's own end velocity (``integrators``). Damping
ratio of mode k: zeta_k = alpha/(2 w_k) + beta w_k/2 (``damping_ratio``).

Substeps: ``h`` is the sampling interval (one frame); each frame takes ``substeps`` internal
steps dt = h / substeps. ``substeps=0`` picks them from the highest retained frequency w_max
(rest stiffness against the rest reduced mass): dt w_max <= 1 (``SUBSTEP_BOUND``), where the
trapezoidal rule keeps that mode's frequency within 7.3 % and every mode below within
(w/w_max)^2 of that; capped at ``MAX_AUTO_SUBSTEPS`` because past it only the top modes lose
accuracy, never stability. Bakes then depend on the scene's fps only through the sampling.
"""

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from . import frames, integrators, inversion, newton
from .body_contact import BodyContact, ContactError, ContactInertia, StartsInsideError

MAX_STEP_SPLITS = 4        # a step that inverts is retaken in halves, down to dt / 2^4
MIN_VOLUME_RATIO = inversion.FLAT_J   # det F at or below this counts as inverted (flat or
                                      # turned inside out), below the reconstruction barrier
SUBSTEP_BOUND = 1.0        # largest dt * w_max of automatic substeps (module docstring)
MAX_AUTO_SUBSTEPS = 64     # automatic substeps stop here; only top-mode accuracy suffers past it
MAX_SUBSTEPS = 1000        # largest user override
SINGLE_PRECISION_TOLERANCE = 1e-6   # Newton tolerances from here up run the cubature in float32


def step_deformer(deformer, tolerance=1e-5, dtype=None):
    """The deformer a ``Simulation`` with this Newton ``tolerance`` and ``dtype`` steps with
    (its docstring): a step is mostly the cubature's (rB, 9C) products, and in float32 they
    take half as long (``reduced.ReducedRS.astype``). Potentials that evaluate q themselves
    (``inversion.ReconstructionBarrier``, ``rig.HeldPotential``) should get this same object:
    it keeps the last pose's q and dq/dz for them. A deformer without ``astype`` as it is."""
    astype = getattr(deformer, "astype", None)
    if astype is None:
        return deformer
    single = dtype is None and tolerance >= SINGLE_PRECISION_TOLERANCE
    return astype(np.float32 if single else (dtype or np.float64))


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


class _Interrupted(Exception):
    """``Simulation.step`` stopped between substeps because ``should_cancel()`` was True."""


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


@dataclass
class State:
    """What a step reads and changes, so all that ``Simulation.step`` restores to retake one:
    time t_n [s], the internal step dt [s], the pose at t_n (``integrators.Pose``), what the
    scheme carries to the next step (``integrators.Rates``, or implicit Euler's pose one step
    back) and whether the contact has checked this start."""

    time: float
    dt: float
    pose: integrators.Pose = None
    carried: object = None
    contact_checked: bool = False

    def copy(self):
        return State(self.time, self.dt, self.pose.copy(), self.carried.copy(),
                     self.contact_checked)


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
      (e.g. ``frames.FrameMotion``) for a moving pinned body; not with ``free``.
    start_time t0 [s]; tolerance: Newton stops when a step moves the body by less than this
      fraction of the bounding-box diagonal (RMS); max_iterations per step.
    integrator: "newmark" (default), "implicit_euler", or a scheme (``integrators``), chosen
      once (``scheme``; ``integrator`` keeps its name). substeps: internal steps per h (>= 1),
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
      (``body_contact``); a start inside a collider raises ``StartsInsideError`` (a ValueError)
      at the first step. The simulation gives it its scheme (``contact.scheme``): friction and
      damping act on the scheme's end velocity. Its optional ``proximity`` lets a step carried
      into a collider start outside it (``body_contact.BodyContact.holding_deformation``).
    external_force: callable t [s] -> (rB,) generalised force in q-space [N m per unit q],
      e.g. ``rig.RigLoad.force`` (a rig's accelerations and gravity felt by its flesh), added
      to gravity's B^T M g wherever that enters (each step at t_{n+1}, the start acceleration
      at t0); fixed frame only (no ``free``, no ``frame_motion``).
    sample_placement: callable t [s] -> (A (k, 3, 3), b (k, 3)) that carries the contact
      samples from the body's space to the world, x_p = A_p(t) Y_p + b_p, before the frame
      (e.g. ``rig.RigMotion.placement``: the skinning of a rig's flesh, which the simulation
      solves in rest space); None is the identity. Fixed frame only, and only with contact.
    dtype: of the deformer's cubature products (``reduced.ReducedRS.astype``; ``deformer`` is
      then that copy); None: float32 unless ``tolerance`` is below
      ``SINGLE_PRECISION_TOLERANCE`` (float32's rounding of q, about 1e-7 of its nonlinear
      part, would stall Newton there). float64 where q must be smooth to round-off (finite
      differences).

    The body starts at rest in its frame at s = 0 (``set_state`` changes that); a moving frame's
    velocity at t0 comes from frame_motion around t0, so a frame already moving at t0 carries
    the body along. ``state`` (``State``) is all a step changes; time, dt, coords (s), q,
    rotation and translation read it. ``iterations``: Newton iterations of the last frame
    (summed over its substeps); ``shortest_steps``: frame -> internal steps retaken down to
    the shortest length in it (slow frames; empty while none was).
    """

    def __init__(self, deformer, rest_positions, masses, potential, h, gravity=(0.0, 0.0, 0.0),
                 mass_damping=0.0, stiffness_damping=0.0, free=False, frame_motion=None,
                 start_time=0.0, tolerance=1e-5, max_iterations=20, integrator="newmark",
                 substeps=1, tets=None, contact=None, external_force=None,
                 sample_placement=None, dtype=None):
        _check_arguments(deformer, h, mass_damping, stiffness_damping, free, frame_motion,
                         substeps, contact, external_force, sample_placement)
        deformer = step_deformer(deformer, tolerance, dtype)
        self.scheme = integrators.scheme(integrator)
        self.integrator = self.scheme.name
        self.deformer, self.potential, self.external_force = deformer, potential, external_force
        self.h, self.free, self.frame_motion = float(h), bool(free), frame_motion
        self.fixed_frame = not (self.free or frame_motion is not None)
        self.gravity = np.asarray(gravity, dtype=np.float64).reshape(3)
        self.alpha, self.beta = float(mass_damping), float(stiffness_damping)
        self.tolerance, self.max_iterations = float(tolerance), int(max_iterations)
        self.num_coords = deformer.num_coords
        X = np.asarray(rest_positions, dtype=np.float64)
        self.moments = frames.MassMoments(X, np.asarray(masses, dtype=np.float64),
                                          np.asarray(deformer.basis, dtype=np.float64),
                                          self.free, frame_motion is not None)
        self.basis_size, self.origin = self.moments.basis_size, self.moments.origin
        self.diagonal = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))
        self.solver = newton.StepSolver(
            deformer, potential, self.moments.mass_matrix,
            (self.tolerance * self.diagonal) ** 2 * self.moments.total_mass, self.max_iterations)
        self.omega = self._rest_frequencies()
        self.substeps = int(substeps) or automatic_substeps(self.h, self.omega[-1])
        self.state = State(float(start_time), self.h / self.substeps)
        self._start_time = self.time
        # float32: the check after every step reads B once; its error is far inside
        # MIN_VOLUME_RATIO (``inversion.DeformedVolumes``)
        self._volumes = (None if tets is None else
                         inversion.DeformedVolumes(rest_positions, tets, deformer.basis,
                                                   dtype=np.float32))
        # frame (1-based, as ``InversionError`` counts) -> internal steps it took at the
        # shortest retake length, dt / 2^MAX_STEP_SPLITS: a body that needs them on frame after
        # frame bakes slowly (every such step is 2^MAX_STEP_SPLITS times the work), which the
        # caller can say why
        self.shortest_steps = {}
        self.contact = None
        if contact is not None:    # the contact's friction and damping act on our end velocity
            contact.scheme = self.scheme
            self.contact = BodyContact(contact, deformer, potential.rest_hessian, self.origin,
                                       sample_placement)
        self.set_state(np.zeros(self.num_coords))

    def _rest_frequencies(self):
        """(m,) rest frequencies [rad/s]: K0 w = omega^2 J0^T M_B J0 w at s = 0, ascending."""
        J0 = self.deformer.q_jacobian(np.zeros(self.num_coords))
        mass = J0.T @ self.moments.mass_matrix @ J0
        values = scipy.linalg.eigh(self.potential.rest_hessian, 0.5 * (mass + mass.T),
                                   eigvals_only=True)
        return np.sqrt(np.maximum(values, 0.0))

    # -- state --------------------------------------------------------------------------------

    time = property(lambda self: self.state.time, doc="t_n [s]")
    dt = property(lambda self: self.state.dt, doc="the internal step [s]")
    coords = property(lambda self: self.state.pose.coords, doc="s (m,)")
    q = property(lambda self: self.state.pose.q, doc="q(s) (rB,)")
    rotation = property(lambda self: self.state.pose.rotation, doc="the frame's R (3, 3)")
    translation = property(lambda self: self.state.pose.translation, doc="the frame's c (3,)")

    def set_state(self, coords, coords_velocity=None, linear_velocity=None,
                  angular_velocity=None):
        """Set s (m,) and its velocity ds/dt (m,) at the current time (default at rest).

        Free bodies: the frame starts at R = I, c = origin, moving with ``linear_velocity``
        (3,) [m/s] and world ``angular_velocity`` (3,) [rad/s]. What the scheme carries starts
        from these (``integrators``: Newmark also solves for the start acceleration).
        """
        m = self.num_coords
        coords = np.array(coords, dtype=np.float64).reshape(m)
        velocity = (np.zeros(m) if coords_velocity is None
                    else np.asarray(coords_velocity, dtype=np.float64).reshape(m))
        w = np.zeros(3) if angular_velocity is None else np.asarray(angular_velocity, float)
        v = np.zeros(3) if linear_velocity is None else np.asarray(linear_velocity, float)
        if self.free:
            R, c = np.eye(3), self.origin.copy()
        elif self.frame_motion is not None:
            R, c = self.frame_motion(self.time)
        else:
            R, c = np.eye(3), np.zeros(3)
        self.state = State(self.time, self.dt,
                           integrators.Pose(coords, self.deformer.q(coords), R, c))
        self.state.carried = self.scheme.start(self, velocity, w, v)
        self.iterations = 0
        if self._volumes is not None:
            self._watch(self._volumes.ratios(self.q))

    def fixed_load(self, t):
        """(rB,) B^T M g plus the external force at time t [s] (fixed frame)."""
        load = self.moments.first_moment_B.T @ self.gravity
        if self.external_force is not None:
            load = load + np.asarray(self.external_force(t), dtype=np.float64)
        return load

    # -- one frame ----------------------------------------------------------------------------

    def step(self, should_cancel=None):
        """Advance one frame h (``substeps`` steps dt); returns the Newton iterations taken.

        should_cancel() -> bool before each substep: True raises ``_Interrupted`` with the frame
        part-way (``run`` turns it into ``SimulationCancelled`` with the whole frames so far), so
        a cancel waits for one substep, not a whole frame.

        With ``tets``, each internal step is checked for inverted tets and a non-finite energy
        (an RS strain past the volume barrier of ``inversion``, e.g. from a predictor that
        overshot); a failing step is undone (the ``State`` copied before it is restored) and
        retaken as two steps of half the length, recursively down to dt / 2^MAX_STEP_SPLITS,
        where a step whose Newton ends past a barrier is solved again from its start
        (``_take_step``'s restart) and a failed one is taken once more with the tets that
        turned in it watched (``_checked_step``); past that ``InversionError``. Why halving:
        the predictor s_n + dt v_s and every Newton iterate move less, so the barrier's line
        search can hold them, and most of the frame keeps its nominal dt. A step with contact
        none of whose start guesses is outside the colliders is retaken the same way
        (``ContactError`` past the smallest).
        """
        total = 0
        frame = int(round((self.time - self._start_time) / self.h)) + 1
        try:
            for _ in range(self.substeps):
                if should_cancel is not None and should_cancel():
                    raise _Interrupted()
                total += self._checked_step(self.h / self.substeps, 0, frame)
        finally:
            self._set_step(self.h / self.substeps)
        self.iterations = total
        return total

    def _checked_step(self, dt, splits, frame, rewatched=False):
        """One internal step of length dt [s], retaken in halves if it inverts or if no start
        guess of it is outside the colliders (a fast collider or keyed frame; ``step``). The
        shortest is retaken once more at its own length (``rewatched``), now with the tets
        that turned in it watched by the reconstruction barrier: a tet that went from above
        WATCH_J to inside out within it had no barrier there."""
        if self._volumes is None and self.contact is None:
            return self._take_step()
        snapshot = self.state.copy()
        self._set_step(dt)
        if splits >= MAX_STEP_SPLITS:
            self.shortest_steps[frame] = self.shortest_steps.get(frame, 0) + 1
        blocked = None
        try:
            iterations = self._take_step(restart=splits >= MAX_STEP_SPLITS)
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
        self.state = snapshot
        if splits >= MAX_STEP_SPLITS:
            if blocked is None and not rewatched:
                return iterations + self._checked_step(dt, splits, frame, rewatched=True)
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

    def _set_step(self, dt):
        """Make the internal step dt [s], what the scheme carries rescaled to it."""
        if dt != self.state.dt:
            self.state.carried = self.scheme.rescaled(self, dt)
            self.state.dt = dt

    def _take_step(self, restart=False):
        """One internal step dt from the current state; returns the Newton iterations.

        restart: if Newton ends past a barrier (from a predictor past it), solve the step
        again from its start state, inside the barriers (``newton.StepSolver.minimise``'s
        ``feasible``). Only for the shortest retake of a step (``_checked_step``): longer
        ones are retaken in halves, whose predictors move less."""
        state = self.state
        end = self._end_frame()
        plan = self.scheme.plan(self, end)
        model = self._inertia(plan, end)
        if self.contact is None:
            s, q, iterations = self.solver.minimise(
                model, plan.guess, plan.damping, q=plan.guess_q, jacobian=plan.guess_jacobian,
                feasible=(state.pose.coords, state.pose.q) if restart else None)
            R, c = frames.best_frame(self.moments, model, plan.target, q) if self.free else end
        elif self.free:
            self._begin_contact(plan)
            start = self.contact.feasible(self._framed_guesses(model, plan), self.time)
            s, q, R, c, iterations = self.solver.minimise_framed(
                self._framed_inertia(plan), start, plan.damping, self.contact.framed_terms)
        else:
            self._begin_contact(plan)
            R, c = end
            guesses = self.contact.guesses(state, plan.guess, R, c)
            start, _, _ = self.contact.feasible(guesses, self.time)
            s, q, iterations = self.solver.minimise(ContactInertia(model, self.contact, R, c),
                                                    start, plan.damping)
        state.carried = self.scheme.advance(self, plan, s, q, R, c)
        state.pose = integrators.Pose(s, q, R, c)
        state.time += state.dt
        return iterations

    def _begin_contact(self, plan):
        """The contact's ``begin_step`` at t_n, with the scheme's sample velocities."""
        self.contact.begin(self.state, lambda x, start: self.scheme.sample_velocities(
            self, plan, x, start))

    def _end_frame(self):
        """The frame (R, c) at the step's end: a keyed one's motion, a fixed one's (I, 0);
        None for a free one (solved with the step)."""
        if self.free:
            return None
        if self.frame_motion is not None:
            return tuple(np.asarray(x, float) for x in self.frame_motion(self.time + self.dt))
        return self.rotation, self.translation

    def _inertia(self, plan, end):
        """The step's inertia and mass damping in q in this body's frame (``frames``)."""
        if self.free:
            return frames.free_inertia(self.moments, plan.weight, plan.target, plan.mass_damping)
        if self.frame_motion is not None:
            return frames.keyed_inertia(self.moments, plan.weight, plan.target, *end,
                                        plan.mass_damping)
        return frames.fixed_inertia(self.moments, plan.weight, plan.target, plan.mass_damping,
                                    self.fixed_load(self.time + self.dt))

    def _framed_inertia(self, plan):
        """A free body's inertia with its frame explicit (with contact)."""
        k, linear = plan.mass_damping
        return frames.FramedInertia(self.moments, plan.weight, plan.target,
                                    k * self.moments.mass_matrix, linear)

    def _framed_guesses(self, model, plan):
        """Start guesses (s, R, c) of a free body with contact: the predictor in its best
        frame, else the state at t_n (outside the colliders by the previous step)."""
        R, c = frames.best_frame(self.moments, model, plan.target, self.deformer.q(plan.guess))
        return [(plan.guess, R, c), (self.coords, np.asarray(self.rotation, float),
                                     np.asarray(self.translation, float))]

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
        pose, m = self.state.pose, self.num_coords
        b = self.moments.first_moment_B.T @ (pose.rotation.T @ self.gravity)
        if self.external_force is not None:
            b = b + np.asarray(self.external_force(self.time), dtype=np.float64)
        model = frames.QuadraticInertia(0.0, self.moments.mass_matrix, b)
        guess = np.zeros(m) if s is None else np.asarray(s, dtype=np.float64)
        no_damping = newton.Damping(np.zeros((m, m)), np.zeros(m), pose.coords)
        s, q, self.iterations = self.solver.minimise(model, guess, no_damping, max_iterations)
        self.state.pose = integrators.Pose(s, q, pose.rotation, pose.translation)
        self.state.carried = self.scheme.settled(self)
        return s

    def run(self, num_steps, callback=None, should_cancel=None):
        """Take ``num_steps`` steps; returns a ``Trajectory`` of num_steps + 1 rows.

        callback(step, num_steps) after each step; should_cancel() -> bool before each step:
        True raises ``SimulationCancelled`` carrying the frames so far.
        """
        rows = [self._record()]
        for k in range(int(num_steps)):
            try:
                self.step(should_cancel)
            except _Interrupted:
                raise SimulationCancelled(self._trajectory(rows)) from None
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

        Kinetic 1/2 sum m |v|^2 with the scheme's own world velocities (Newmark's v_n;
        implicit Euler's (x_n - x_{n-1}) / dt), elastic V(s_n), gravity -sum m g.x_n (zero at
        the rest pose in the rest frame).
        """
        kinetic = self.scheme.kinetic_energy(self)
        mo, R = self.moments, self.rotation
        moment = R @ (mo.first_moment_B @ self.q) + (R - np.eye(3)) @ mo.first_moment_X
        moment += mo.total_mass * (self.translation - (self.origin if self.free else 0.0))
        gravity = -float(self.gravity @ moment)
        elastic = self.potential.evaluate(self.coords, 0)[0]
        return dict(kinetic=kinetic, elastic=elastic, gravity=gravity,
                    total=kinetic + elastic + gravity)


def _check_arguments(deformer, h, mass_damping, stiffness_damping, free, frame_motion, substeps,
                     contact, external_force, sample_placement):
    """ValueError for arguments of ``Simulation`` that do not go together or are out of range
    (the integrator's name is checked by ``integrators.scheme``)."""
    if free and frame_motion is not None:
        raise ValueError("a free body cannot also follow a prescribed frame motion")
    if external_force is not None and (free or frame_motion is not None):
        raise ValueError("an external force is for a body in a fixed frame (e.g. the "
                         "flesh of a rig, solver.rig), not a free or moving one")
    if sample_placement is not None and (free or frame_motion is not None or contact is None):
        raise ValueError("a sample placement carries the contact samples of a body in a "
                         "fixed frame; it needs a contact and no free or moving frame")
    if deformer.basis is None:
        raise ValueError("the deformer has no basis B; build it with its basis")
    if int(substeps) != substeps or not 0 <= substeps <= MAX_SUBSTEPS:
        raise ValueError(f"substeps must be an integer in [0, {MAX_SUBSTEPS}] (0 = "
                         f"automatic), got {substeps!r}")
    if not float(h) > 0.0:
        raise ValueError(f"time step must be positive (got {h!r})")
    if float(mass_damping) < 0.0 or float(stiffness_damping) < 0.0:
        raise ValueError("damping coefficients must be non-negative")
