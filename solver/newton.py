"""Newton / line search on one time step's objective in the modal coordinates s.

Every step of ``dynamics`` minimises inertia + V(s) + damping (+ contact) over s (m,), or over
(s, phi, u) for a free body with contact (its frame R = exp(skew(phi)) R_it, c = c_it + u
re-linearised at every iterate, ``frames.FramedInertia``). Each Newton-type iteration is
followed by a backtracking Armijo line search on the true objective; a trial point whose value
is not finite (a barrier: contact, inversion) is rejected. The first iteration, and any whose
step is already below tolerance, uses the Gauss-Newton Hessian J^T H_q J + hess V + D
(J = dq/ds, D the stiffness damping). Later iterations that still move add, for a
``reduced.ReducedRS``, the curvature of the RS map itself, sum_i g_i d^2 q_i/ds^2 with
g = dE/dq (``GeometricStiffness``): Gauss-Newton converges only linearly once gravity or
inertia loads a strongly rotated pose (a small soft jelly at h = 1/24 needed 5-15 iterations,
2-3 with it), while a stiffer or larger body converges in two Gauss-Newton iterations and never
pays for the extra term. The free body's best-rotation curvature is left out. J itself, an
(rB, 9C) x (9C, m) product over the cubature, is the costliest part of an iteration, so
``minimise`` forms it once per step: later iterations take the exact gradient J^T g from the
deformer's ``q_gradient`` (no J) with the first iterate's J in the Hessian, and form J afresh
only when that step does not already end the iterations. Linear systems by
Cholesky; an indefinite full Hessian (buckling, StVK in compression) falls back to
Gauss-Newton, regularised by a multiple of its diagonal if even that is indefinite. Iterations
stop once a step moves the body by less than a tolerance (its squared mass norm, ``step_tol2``
[kg m^2]) or after ``max_iterations``.
"""

import math
from typing import NamedTuple

import numpy as np
import scipy.linalg

from . import reduced, rs

ARMIJO = 1e-4
ROUNDING = 64 * np.finfo(float).eps  # relative rounding of a step's objective (sums of terms)
MAX_HALVINGS = 30


def newton_step(H, grad, fallback=None):
    """-H^-1 grad by Cholesky. If H is not positive definite: ``fallback`` when given, else
    H with a growing multiple of its diagonal added."""
    H = 0.5 * (H + H.T)
    step = _cholesky_solve(H, grad)
    if step is not None:
        return -step
    if fallback is not None:
        return fallback
    scale = np.diag(np.maximum(np.abs(np.diag(H)), 1e-300))
    shift = 1e-8
    for _ in range(40):
        step = _cholesky_solve(H + shift * scale, grad)
        if step is not None:
            return -step
        shift *= 10.0
    raise np.linalg.LinAlgError("Newton system could not be regularised")


def _cholesky_solve(H, b):
    """H^-1 b (m,) by LAPACK's potrf/potrs directly (the systems are m x m, tens, where
    scipy.linalg's wrappers cost several times the solve), or None if H is not positive
    definite."""
    factor, failed = scipy.linalg.lapack.dpotrf(H, lower=False, clean=False)
    return None if failed else scipy.linalg.lapack.dpotrs(factor, b, lower=False)[0]


def hidden_decrease(slope, f):
    """Whether a step's predicted decrease -slope is below the rounding of the objective's
    value f: f cannot judge such a step (``StepSolver._line_search``). Never at an infinite
    f (a start past a barrier): every finite trial is a decrease there, and the line search
    halves towards one."""
    return math.isfinite(f) and -slope <= ROUNDING * abs(f)


class Damping(NamedTuple):
    """The stiffness-damping potential of a step, 1/2 ds^T D ds - f.ds in ds = s - s_n:
    matrix D (m, m), force f (m,), start s_n (m,) (``integrators``)."""

    matrix: np.ndarray
    force: np.ndarray
    start: np.ndarray

    def value(self, s):
        ds = s - self.start
        return float(ds @ (0.5 * (self.matrix @ ds) - self.force))


class StepSolver:
    """Newton / line search of a step (module docstring) for one body.

    deformer: s -> q(s) (rB,) and its Jacobian (rB, m); potential: V(s) with ``evaluate``;
    mass_matrix M_B (rB, rB); step_tol2 [kg m^2]: a step whose squared mass norm is below it
    ends the iterations; max_iterations per step. A step's inertia is a ``model`` with
    ``evaluate(q, order)`` in q, or a ``frames.FramedInertia`` in (q, phi, u).
    """

    def __init__(self, deformer, potential, mass_matrix, step_tol2, max_iterations):
        self.deformer, self.potential, self.mass_matrix = deformer, potential, mass_matrix
        self.step_tol2, self.max_iterations = step_tol2, max_iterations
        self.geometric = (GeometricStiffness(deformer)
                          if isinstance(deformer, reduced.ReducedRS) else None)

    def objective(self, model, s, q, damping):
        value = model.evaluate(q, 0)[0] + self.potential.evaluate(s, 0)[0]
        return value + damping.value(s)

    def minimise(self, model, s, damping, max_iterations=None, q=None, jacobian=None,
                 feasible=None):
        """Newton / line search on s from the guess s (q: q(s), jacobian: dq/ds there, if
        known); returns (s, q(s), iterations).

        feasible: a start (s, q(s)) whose objective is known to be finite, e.g. the step's
        start state. A barrier (inversion, contact) makes the objective infinite at a guess
        past it, such as a predictor that overshoots; Newton from there moves by a finite model
        of the barrier and may find no finite point at all, and would then end where it began,
        past the barrier. It is then restarted from ``feasible``, inside the barrier, where the
        line search keeps every iterate (an interior-point start). The iterations of both runs
        are counted."""
        s, q, iterations, f = self._minimise_from(model, s, damping, max_iterations, q,
                                                  jacobian)
        if feasible is None or math.isfinite(f):
            return s, q, iterations
        s, q, more, _ = self._minimise_from(model, feasible[0], damping, max_iterations,
                                            feasible[1], None)
        return s, q, iterations + more

    def _minimise_from(self, model, s, damping, max_iterations, q, jacobian):
        """``minimise`` from one start; returns (s, q(s), iterations, objective there)."""
        q = self.deformer.q(s) if q is None else q
        f = self.objective(model, s, q, damping)
        iterations, J, known = 0, None, jacobian
        for iterations in range(1, (max_iterations or self.max_iterations) + 1):
            _, gq, Hq = model.evaluate(q, 2)
            _, gV, HV = self.potential.evaluate(s, 2)
            own = gV + damping.matrix @ (s - damping.start) - damping.force
            fresh = J is None
            if fresh:                                 # the step's first iterate
                J = self.deformer.q_jacobian(s) if known is None else known
                grad, inertia = J.T @ gq + own, J.T @ (Hq @ J)
            else:                                     # the exact gradient, without dq/ds
                grad = self._q_gradient(s, gq) + own
                if Hq is not used:                    # e.g. contact: its Hessian moved
                    inertia = J.T @ (Hq @ J)
            used = Hq
            if not grad.any():
                break
            step = newton_step(inertia + HV + damping.matrix, grad)
            small = self._moved2(J, step) <= self.step_tol2
            if not small and not fresh:
                # Not converged in one step: refresh dq/ds here (the Hessian above used the
                # first iterate's) and, for a ReducedRS, take the true Newton step, since
                # Gauss-Newton converges only linearly here (kept Gauss-Newton if that
                # Hessian is indefinite).
                J = self.deformer.q_jacobian(s)
                inertia = J.T @ (Hq @ J)
                gauss_newton = inertia + HV + damping.matrix
                step = newton_step(gauss_newton, grad)
                small = self._moved2(J, step) <= self.step_tol2
                if not small and self.geometric is not None:
                    step = newton_step(gauss_newton + self.geometric(s, gq), grad, step)
            slope = float(grad @ step)
            s_new, q_new, f_new = self._line_search(model, s, f, step, slope, damping,
                                                    small, hidden_decrease(slope, f))
            if s_new is None:                      # no decrease possible: at round-off level
                break
            s, q, f = s_new, q_new, f_new
            if small:
                break
        return s, q, iterations, f

    def _q_gradient(self, s, g):
        """(dq/ds)^T g (m,) at s: the deformer's own product where it has one
        (``reduced.ReducedRS.q_gradient``), else through its Jacobian."""
        product = getattr(self.deformer, "q_gradient", None)
        return product(s, g) if product is not None else self.deformer.q_jacobian(s).T @ g

    def _moved2(self, J, step):
        """Squared mass norm [kg m^2] of the motion J step (rB,) of a step in s."""
        moved = J @ step
        return float(moved @ (self.mass_matrix @ moved))

    def _line_search(self, model, s, f, step, slope, damping, converged=False, hidden=False):
        """Backtracking Armijo; (s, q, f) of the accepted point or (None, None, None).

        converged: the step is below the tolerance, so its decrease can be below the rounding
        of f (the deformer's float32 products round q to ~1e-7 of its nonlinear part): it is
        tried whole, once, and not halved against that noise (the iterate is converged).
        hidden: the step's predicted decrease is below f's own rounding, so f cannot judge it
        (halving would only shrink it below the resolution of s): it is taken whole unless f
        rises by more than that rounding; the gradient, exact where f is not, goes on."""
        alpha, allowance = 1.0, ROUNDING * abs(f) if hidden else 0.0
        for _ in range(1 if converged or hidden else MAX_HALVINGS):
            s_try = s + alpha * step
            q_try = self.deformer.q(s_try)
            f_try = self.objective(model, s_try, q_try, damping)
            if np.isfinite(f_try) and f_try <= f + ARMIJO * alpha * slope + allowance:
                return s_try, q_try, f_try
            alpha *= 0.5
        return None, None, None

    # -- a free body with contact: (s, phi, u) --------------------------------------------------

    def framed_objective(self, model, s, q, R, c, damping, contact):
        """The step objective of a free body with contact; ``contact(q, R, c, order)`` gives
        the contact's (value, gradient, Gauss-Newton Hessian) in (q, phi, u)."""
        value = contact(q, R, c, 0)[0]
        if not np.isfinite(value):
            return np.inf
        value += model.value(q, R, c) + self.potential.evaluate(s, 0)[0]
        return value + damping.value(s)

    def minimise_framed(self, model, start, damping, contact):
        """Newton / line search on (s, phi, u) from start = (s, R, c), re-linearised at each
        iterate. As ``minimise``: Gauss-Newton first, the exact Hessian (inertia's and the RS
        map's curvature) on later iterations that still move. Returns (s, q, R, c,
        iterations)."""
        s, R, c = start
        q = self.deformer.q(s)
        f = self.framed_objective(model, s, q, R, c, damping, contact)
        iterations = 0
        for iterations in range(1, self.max_iterations + 1):
            grad, gauss_newton, exact, moved = self.framed_system(model, s, q, R, c, damping,
                                                                  contact)
            if not grad.any():
                break
            step = newton_step(gauss_newton, grad)
            small = moved(step) <= self.step_tol2
            if not small and iterations > 1:
                step = newton_step(exact(), grad, step)
            slope = float(grad @ step)
            trial = self._framed_line_search(model, s, R, c, f, step, slope, damping, contact,
                                             hidden_decrease(slope, f))
            if trial is None:                      # no decrease possible: at round-off level
                break
            s, q, R, c, f = trial
            if small:
                break
        return s, q, R, c, iterations

    def framed_system(self, model, s, q, R, c, damping, contact):
        """The step objective's derivatives in (s, phi, u) (m + 6,) at phi = u = 0: gradient,
        Gauss-Newton Hessian, a callable giving the exact one (inertia and RS map curvature;
        contact stays Gauss-Newton) and a callable giving a step's squared mass norm [kg m^2].
        q = q(s) enters through T = diag(J, I6)."""
        m, rB = len(s), len(q)
        T = np.zeros((rB + 6, m + 6))
        T[:rB, :m] = self.deformer.q_jacobian(s)
        T[rB:, m:] = np.eye(6)
        g, exact, gauss_newton, mass = model.derivatives(q, R, c)
        _, gc, Hc = contact(q, R, c, 2)
        g = g + gc
        _, gV, HV = self.potential.evaluate(s, 2)
        grad = T.T @ g
        grad[:m] += gV + damping.matrix @ (s - damping.start) - damping.force
        own = np.zeros((m + 6, m + 6))
        own[:m, :m] = HV + damping.matrix

        def exact_hessian():
            full = T.T @ (exact + Hc) @ T + own
            if self.geometric is not None:
                full[:m, :m] += self.geometric(s, g[:rB])
            return full

        def moved(step):
            z = T @ step
            return float(z @ (mass @ z))
        return grad, T.T @ (gauss_newton + Hc) @ T + own, exact_hessian, moved

    def _framed_line_search(self, model, s, R, c, f, step, slope, damping, contact,
                            hidden=False):
        """Backtracking Armijo along (s + a ds, exp(a skew(dphi)) R, c + a du); hidden: as
        ``_line_search``'s."""
        m, alpha = len(s), 1.0
        allowance = ROUNDING * abs(f) if hidden else 0.0
        for _ in range(1 if hidden else MAX_HALVINGS):
            s_try = s + alpha * step[:m]
            R_try = rs.exp_rotation(alpha * step[None, m:m + 3])[0] @ R
            c_try = c + alpha * step[m + 3:]
            q_try = self.deformer.q(s_try)
            f_try = self.framed_objective(model, s_try, q_try, R_try, c_try, damping, contact)
            if np.isfinite(f_try) and f_try <= f + ARMIJO * alpha * slope + allowance:
                return s_try, q_try, R_try, c_try, f_try
            alpha *= 0.5
        return None


# -- the RS map's curvature -------------------------------------------------------------------

_SERIES_BELOW = 0.1     # rad: below, the Rodrigues coefficients use their series
_SKEW_UNITS = rs.skew(np.eye(3))                                        # (3, 3, 3): E_i
_STRAIN_COLUMNS = rs.STRAIN_BASIS.reshape(6, 9).T                       # (9, 6): vec(B_k)


def _rodrigues_derivatives(t2):
    """(a, b, c, d, e, f) (n,) of R = I + aK + bK^2: c = a'/t, d = b'/t, e = c'/t, f = d'/t.

    t = |omega|, t2 = t^2; three-term series below 0.1 rad (truncation < 1e-11 relative).
    """
    small = t2 < _SERIES_BELOW ** 2
    t2s = np.where(small, 1.0, t2)
    t = np.sqrt(t2s)
    a, b = np.sin(t) / t, (1.0 - np.cos(t)) / t2s
    c = (np.cos(t) - a) / t2s
    d = (a - 2.0 * b) / t2s
    return (np.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, a),
            np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, b),
            np.where(small, -1.0 / 3.0 + t2 / 30.0 - t2 * t2 / 840.0, c),
            np.where(small, -1.0 / 12.0 + t2 / 180.0 - t2 * t2 / 6720.0, d),
            np.where(small, 1.0 / 15.0 - t2 / 210.0 + t2 * t2 / 7560.0, (-a - 3.0 * c) / t2s),
            np.where(small, 1.0 / 90.0 - t2 / 1680.0 + t2 * t2 / 75600.0, (c - 4.0 * d) / t2s))


class GeometricStiffness:
    """sum_i g_i d^2 q_i / ds^2 (m, m) of a ReducedRS for a fixed vector g (rB,).

    The Gauss-Newton Hessian J^T H_q J misses this term; with it the step is a true Newton
    step and converges quadratically where the RS map curves (large rotations under load).
    ReducedRS's q is linear in s plus sum_C w_e P_e vec(b_e(y_e)), y_e = U_e s, so the term is
    sum_e U_e^T G_e U_e with G_e (9, 9) the Hessian of <lam_e, b_e(y)>, lam_e = w_e P_e^T g
    (3, 3), b = R(omega) S - I, S = I + eps. It has no eps-eps block;
    omega-eps: <lam B_k, dR_i> = <B_k, lam^T dR_i>, with dR_i = a E_i + b (omega e_i^T +
    e_i omega^T - 2 omega_i I) + omega_i (c K + d K^2);
    omega-omega: the Hessian of <L, R(omega)> = tr L + a p + b r, L = lam S, p = omega.vee(L),
    r = omega^T A omega, A = sym(L) - tr(L) I, i.e.
    (c p + d r) I + (e p + f r) omega omega^T + c (omega v^T + v omega^T)
    + 2 d (omega u^T + u omega^T) + 2 b A, v = vee(L), u = A omega.
    Only a Hessian model: the gradient always comes from ``q_jacobian``.
    """

    def __init__(self, deformer):
        self.weighted = deformer.weighted_projections            # (rB, 9C), entry-major
        self.U = deformer.modal_rs_cubature                                    # (C, 9, m)
        self.flat = self.U.reshape(-1, self.U.shape[2])

    def __call__(self, s, g):
        y = self.U @ s
        n = len(y)
        omega = y[:, :3]
        a, b, c, d, e, f = _rodrigues_derivatives(np.einsum("ci,ci->c", omega, omega))
        K = rs.skew(omega)
        K2 = K @ K
        S = (y[:, 3:] @ rs.STRAIN_BASIS.reshape(6, 9)).reshape(n, 3, 3) + np.eye(3)
        lam = g.astype(self.weighted.dtype, copy=False) @ self.weighted   # (9C,) entry-major
        lam = lam.astype(np.float64, copy=False).reshape(9, n).T.reshape(n, 3, 3)
        G = np.zeros((n, 9, 9))
        G[:, :3, :3] = self._omega_omega(omega, lam @ S, a, b, c, d, e, f)
        G[:, :3, 3:] = self._omega_eps(omega, K, K2, lam, a, b, c, d)
        G[:, 3:, :3] = np.swapaxes(G[:, :3, 3:], 1, 2)
        H = self.flat.T @ (G @ self.U).reshape(-1, self.U.shape[2])
        return 0.5 * (H + H.T)

    @staticmethod
    def _omega_omega(omega, L, a, b, c, d, e, f):
        """Hessian of <L, R(omega)> (n, 3, 3) (class docstring)."""
        flat = L.reshape(-1, 9)
        v = flat[:, [7, 2, 3]] - flat[:, [5, 6, 1]]                          # vee(L)
        trace = flat[:, 0] + flat[:, 4] + flat[:, 8]
        A = 0.5 * (L + np.swapaxes(L, 1, 2)) - trace[:, None, None] * np.eye(3)
        u = np.einsum("nij,nj->ni", A, omega)
        p, r = np.einsum("ni,ni->n", omega, v), np.einsum("ni,ni->n", omega, u)
        cross = c[:, None, None] * v[:, :, None] + 2.0 * d[:, None, None] * u[:, :, None]
        cross = cross * omega[:, None, :]
        return ((c * p + d * r)[:, None, None] * np.eye(3) + cross + np.swapaxes(cross, 1, 2)
                + (e * p + f * r)[:, None, None] * omega[:, :, None] * omega[:, None, :]
                + 2.0 * b[:, None, None] * A)

    @staticmethod
    def _omega_eps(omega, K, K2, lam, a, b, c, d):
        """<lam B_k, dR_i> (n, 3, 6) through lam^T dR_i projected on the strain basis."""
        n = len(omega)
        eye = np.eye(3)
        dR = (a[:, None, None, None] * _SKEW_UNITS
              + b[:, None, None, None] * (omega[:, None, :, None] * eye[None, :, None, :]
                                          + eye[None, :, :, None] * omega[:, None, None, :]
                                          - 2.0 * omega[:, :, None, None] * eye)
              + omega[:, :, None, None] * (c[:, None, None] * K + d[:, None, None] * K2)[:, None])
        M = np.swapaxes(lam, 1, 2)[:, None] @ dR                                # (n, 3, 3, 3)
        return M.reshape(n, 3, 9) @ _STRAIN_COLUMNS
