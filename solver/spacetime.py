"""Space-time editing of elastic motion with material optimisation: SPEC.md section 5 [L14].

Unknowns: modal coordinates ``Z`` (F, r) for every frame of the edited range, h = 1/fps [s].
The deformer (``reduced.ReducedRS``, ``reduced.LinearDeformer`` or anything with the same
methods) maps its input ``zhat = S z`` (m,) to reduced coordinates ``q`` (rB,); a point set's
displacement is ``rows @ q`` with ``rows`` precomputed rows of B (tet nodes) or Phi B (render
vertices). Objective (all terms in SI units of the mass-normalised modal space)::

    J(Z, Lam, D, S) = E_f(Z, Lam, D) + gamma E_c(S, Z) + E_k(S, Z) + mu E_s(S)
                      [+ rho E_m(Lam, D, S) with material optimisation, see below]
    E_f = 1/2 sum_{i=1}^{F-2} |(z_{i+1} - 2 z_i + z_{i-1})/h^2 + D (z_{i+1} - z_{i-1})/(2h)
                               + Lam z_i|^2                 (Lam z_i: see "scheme" below)
    E_c = 1/2 sum_c w_c |rows_c q(S z_{i_c}) + rest_c - target_c|^2      (handles, metres^2)
    E_k = 1/2 sum_k w_k |S z_{i_k} - zhat_k|^2                           (full-pose keyframes)
    E_s = 1/2 sum_j (|s_j|^2 - 1)^2                                      (columns s_j of S)

Choices written down here:

- **Time discretisation** (``scheme``). "central" is SPEC 5's formula, with Lambda z_i. Its
  free motion is unstable for h sqrt(lambda) > 2 (a mode faster than the frame rate can show,
  e.g. above 7.6 Hz at 24 fps): E_f then has exponentially flat directions, the GN system is
  numerically singular and a free tail after the last constraint would explode. "average"
  evaluates the stiffness as Lambda (z_{i-1} + 2 z_i + z_{i+1}) / 4 (Newmark's average
  acceleration): the same 3-point stencil, structure and O(h^2) accuracy, but stable for every
  lambda. "auto" (default) takes "central" while h sqrt(lambda_max) <= ``CENTRAL_LIMIT`` (at
  least ~6 frames per period of the fastest mode) and "average" otherwise.
- **Start at rest** is a *hard* constraint: with ``fix_start`` (default) frames 0 and 1 are held
  at ``start_state`` (zeros unless given) and eliminated from the unknowns. Being the first two
  frames, what remains is still one contiguous banded system. An input animation (keyframes on
  the first frames) sets ``fix_start=False`` instead.
- **Gauss-Newton / Levenberg-Marquardt**: E_f and E_k are quadratic in Z, only E_c goes through
  the deformer, so the Gauss-Newton matrix is the exact E_f Hessian (pentadiagonal in time per
  mode) plus per-frame dense r x r blocks. In time-major order (unknown i r + k) that is a
  symmetric band of half-width 2r, factored by LAPACK's banded Cholesky (``cholesky_banded``,
  what ``solveh_banded`` calls, kept so the factor serves two right-hand sides). Marquardt
  damping scales the diagonal (1 + lm); lm starts at 0, so a quadratic problem is solved in
  one step. Each trial adds a second-order correction for the handles' curvature (see
  ``_gauss_newton_step``). Steps are accepted only if the true objective does not increase.
- **Elimination**: handles usually sit on a few frames, and every other frame enters J only
  through the quadratic E_f + E_k. So with the start held and at most ``ELIMINATE_LIMIT`` unknowns
  on the handles' free frames, each Z block factors that quadratic part's banded Hessian A once
  and keeps A^-1 on the handles' frames (``_Elimination``); a GN step is then a dense solve of
  that size plus one banded back-substitution. Unless pose keys couple the modes of a frame, A
  couples each mode only with itself and is factored mode by mode with bandwidth 2
  (``_BandFactor``: the 800-frame bench edit with material, 18 Z blocks, went from 1.84 to
  0.84-1.09 s). The step is the banded system's own (same objective, same iterates up to round-off
  and the Marquardt damping, which acts on the handles' unknowns only). A step's cost no longer
  grows with the frames beyond O(F r) vector work, so the default step limit is
  ``ELIMINATED_STEPS`` instead of ``GN_STEPS``, and such a run stops when the undamped GN model
  promises a decrease of at most ``tolerance`` J (g^T H^-1 g / 2, a stationarity measure) rather
  than when J's own decrease is that small: where GN converges linearly the latter stopped the
  400-frame bench edit with 6e-7 J still promised. Why: the penalised handles make a narrow curved
  valley in which GN converges linearly (measured on the bench bar, 20 modes, 5 handles keyed on 2
  frames, old stopping rule: 34 steps at 200 frames, 70 at 400, 45 at 800, the count set by the
  edit, not the length); with the banded system each step cost O(F r^3) and 400 frames ran out of
  the 50 steps. An exact Newton Hessian (the handles' curvature by differences of their Jacobians)
  was tried and did not pay: its model holds only within ~0.1 of the step in that valley, 35
  instead of 70 steps at 400 frames for 2r extra Jacobians per handle frame and step.
- **Penalty continuation**: with stiff handles (gamma far above the dynamics) the first GN step
  from rest solves the *linearised* constraints exactly, which for a large edit is a huge
  linear-modal pose; RS then lands in a poor basin (measured: a 5-handle 90 deg bend stalled
  at J ~ 4e10 against 9e5 reachable). So ``solve`` first runs GN with gamma lowered to
  ``WARM_TIGHTNESS`` (``handle_tightness``), raising it by ``WARM_FACTOR`` per stage, and starts
  the real solve from there if that lowers J (history entry "warm").
- **Out of reach**: a raise of gamma by g should cut the largest handle miss by about g
  (penalty misses go as 1/gamma once the handles hold). When a stage cuts it by less than
  sqrt(g) *and* its control energy E_f rose more than ``REACH_FORCING`` times over the last
  stage that did close in, the handles ask for a shape the modes make only by forcing the
  body. Measured on a rigged creature whose ear tip was keyed where the ear had to stretch:
  9 of 40 tet meshes (12 modes) then met the target with 110-500,000 times the control
  energy and the body thrown up to 1 m off its motion; reachable meshes rose by 1.0-1.3, a
  360/720 deg keyed twist (not closing in on a spoke, met in angle) by 2.4-3.4. The solve then
  ends at the last stage that closed in, with the handles at that (softer) gamma, and says so
  (not converged).
- **Material**: block coordinate descent, each block never increasing J: (1) Z by GN/LM;
  (2) per mode (lambda_k, d_k) by the exact two-unknown bounded least squares of
  E_f + rho E_m (``fit_material``); a mode whose motion is negligible keeps its values;
  (3) only for a rectangular S (more candidate modes m than optimised modes r, [L14]'s
  "which modes matter"), S by L-BFGS-B with the analytic gradient on J with Z *carried*
  (``carried_objective``: z_i re-fitted so S z_i keeps its value, so S can move along a stiff
  handle's valley; at fixed Z it could not, and S never moved). A square S could only mix the
  modes among themselves, which with the carried Z lowered J by ~1 % per round for 40 rounds
  without end on a 90 deg handle edit: it is left out. A round is repeated until J falls by less
  than ``round_tolerance`` (relative) over it; then Z is solved once more for the final
  material, so the free tail after the last constraint carries no control force.
- **Material regulariser**: J also has rho E_m with
  E_m = 1/2 sum_k ((lambda_k - lambda0_k)/lambda0_k)^2 + ((d_k - d0_k)/(2 sqrt(lambda0_k)))^2
  + 1/2 |S - S0|_F^2, (lambda0, d0, S0) the prepared material: to first order the change of
  log lambda (frequency) and of the damping ratio, both dimensionless. Why: a handle-only edit
  carries no information about the material, and E_f alone prefers a soft, undamped body (the
  handles then move it for free; issue 12: sqrt(lambda_1) 2.33 -> 0.64 in 10 rounds, 0.48 in 40,
  damping to 0, never converging. On top, ``material_freedom`` f is a hard bound
  (``material_bounds``): sqrt(lambda_k) within [1/f, f], d_k within [1/f, f] of prepared.
  rho = ``material_weight``, or (None) ``MATERIAL_PULL`` E_f / r chosen with mu (E_m = 0 then):
  a 20 % change of one frequency (44 % in lambda) costs about its mode's share of E_f. Data that
  do determine the material (keyframes of an input animation) may want a smaller rho.
- **mu**: E_c and E_k see only S z, so S -> a S, z -> z / a lowers E_f by a^2 for free; E_s is
  what stops that drift. ``mu=None`` (default) sets mu = ``MU_RELATIVE`` E_f / r once, after
  the first Z block and before any material block runs, so the objective stays one function for
  the whole history; with E_f = 0 there it falls back to 1.
- Weights: see ``suggest_weights``; a constraint that outweighs the per-frame dynamics by a
  factor ``tightness`` misses its target by roughly its unconstrained miss / tightness.
"""

from dataclasses import dataclass, field, replace
from typing import Optional

import numpy as np
import scipy.linalg
import scipy.optimize

LM_FIRST = 1e-9        # Marquardt factor after the first rejected step
LM_MAX = 1e12          # beyond this the step is negligible: stop
CENTRAL_LIMIT = 1.0    # "auto" uses central differences while h sqrt(lambda_max) <= this
CORRECTIONS = 2        # second-order (chord) corrections per GN trial, see _gauss_newton_step
WARM_TIGHTNESS = 10.0  # first handle weight of the penalty continuation, in tightness units
WARM_FACTOR = 1e3      # ... raised by this factor per stage until gamma
WARM_TOLERANCE = 1e-6  # relative decrease that ends a continuation stage
MU_RELATIVE = 100.0    # auto mu = MU_RELATIVE * E_f / r (S columns then stay within ~1 % of unit)
TIGHTNESS = 1e4        # default constraint/dynamics ratio of ``suggest_weights``
DEGENERATE_MOTION = 1e-12  # relative size under which a mode is "not moving" for the (lam, d) fit
MATERIAL_FREEDOM = 1.5     # default bound: each frequency and damping within this factor of prepared
MATERIAL_PULL = 10.0       # auto rho = MATERIAL_PULL * E_f / r (module doc, "Material regulariser")
ROUND_TOLERANCE = 1e-3     # a material round lowering J by less than this (relative) has converged
HANDLE_ROUNDS = 6          # method-of-multipliers rounds of ``solve(exact_handles=True)``
HANDLE_TOLERANCE = 1e-9    # ... stop once every handle is this close (relative to the handles' extent)
HANDLE_MET = 1e-4          # ... and report the handles met (converged) within this of their extent
GN_STEPS = 50             # default GN steps per Z solve (banded system)
ELIMINATED_STEPS = 200    # ... with the handles' frames eliminated (``_Elimination``)
MATERIAL_ROUNDS = 20      # default outer rounds of a solve that optimises the material
ELIMINATE_LIMIT = 240      # most unknowns on the handles' frames for ``_Elimination``
REACH_FORCING = 30.0       # E_f rise that, with the handles not closing in, means "out of reach"


class SolveCancelled(Exception):
    """Raised by ``solve`` when ``should_cancel()`` returned True; nothing was changed."""


# ---------------------------------------------------------------------------------------------
# Problem and result

@dataclass
class HandleConstraints:
    """c handle constraints stacked: handle position ``rows @ q(S z_frame) + rest`` -> target.

    frames (c,) int frame indices in [0, F); rows (c, 3, rB) rows of B (or Phi B) averaged over
    the handle's vertices [m per unit q]; rest (c, 3) rest centroid [m]; targets (c, 3) [m] in
    the body's rest frame; weights (c,) >= 0 dimensionless (multiplied by the problem's gamma).
    Any linear functional of the displacement fits: an orientation handle's spokes (rows of
    first moments, ``orientation_geometry``) are constraints of this same form.

    Derived on construction: ``frame_list`` (u,) the distinct constrained frames and
    ``frame_index`` (c,) into it; ``handle_rows`` (H, 3, rB) the distinct rows and
    ``handle_index`` (c,) into them. Every handle is evaluated on every constrained frame at
    once (u x H points, one batched deformer call); constraints pick their (frame, handle).
    """

    frames: np.ndarray
    rows: np.ndarray
    rest: np.ndarray
    targets: np.ndarray
    weights: np.ndarray

    def __post_init__(self):
        self.frames = np.asarray(self.frames, dtype=np.int64).reshape(-1)
        c = len(self.frames)
        rows = np.asarray(self.rows, dtype=np.float64)
        self.rows = rows.reshape(c, 3, rows.shape[-1] if rows.ndim == 3 else -1)
        self.rest = np.asarray(self.rest, dtype=np.float64).reshape(c, 3)
        self.targets = np.asarray(self.targets, dtype=np.float64).reshape(c, 3)
        self.weights = np.broadcast_to(np.asarray(self.weights, dtype=np.float64), (c,)).copy()
        if np.any(self.weights < 0.0):
            raise ValueError("handle weights must be >= 0")
        self.frame_list, self.frame_index = np.unique(self.frames, return_inverse=True)
        unique, self.handle_index = np.unique(self.rows.reshape(c, 3 * self.rows.shape[2]),
                                              axis=0, return_inverse=True)
        self.handle_index = self.handle_index.reshape(-1)
        self.handle_rows = unique.reshape(len(unique), 3, self.rows.shape[2])
        self._evaluator = (None, None)

    def __len__(self):
        return len(self.frames)

    def evaluator(self, deformer):
        """Row evaluator of all ``handle_rows`` stacked (3H, rB) for ``deformer`` (cached).

        Uses the deformer's ``row_evaluator`` (ReducedRS folds the rows into its cubature, so
        nothing of size rB is formed), else ``rows @ q`` through ``q_batch``.
        """
        if self._evaluator[0] is not deformer:
            stacked = self.handle_rows.reshape(-1, self.handle_rows.shape[2])
            make = getattr(deformer, "row_evaluator", None)
            self._evaluator = (deformer, make(stacked) if make is not None
                               else _RowsThroughQ(deformer, stacked))
        return self._evaluator[1]


class _RowsThroughQ:
    """Row evaluator for deformers without one: u = rows q(z), du/dz = rows dq/dz."""

    def __init__(self, deformer, rows):
        self.deformer, self.rows = deformer, rows

    def displacement_batch(self, Z):
        """(F, k, 3) of Z (F, m)."""
        return (np.asarray(self.deformer.q_batch(Z)) @ self.rows.T).reshape(len(Z), -1, 3)

    def jacobian_batch(self, Z):
        """(F, 3k, m) of Z (F, m)."""
        return self.rows @ np.asarray(self.deformer.q_jacobian_batch(Z))


@dataclass
class Keyframes:
    """k full-pose constraints 1/2 w |S z_frame - pose|^2.

    frames (k,) int; poses (k, m) deformer inputs zhat (e.g. from ``pose_to_modal``);
    weights (k,) >= 0 (absolute: units of E_f per (modal coordinate)^2).
    """

    frames: np.ndarray
    poses: np.ndarray
    weights: np.ndarray

    def __post_init__(self):
        self.frames = np.asarray(self.frames, dtype=np.int64).reshape(-1)
        k = len(self.frames)
        poses = np.asarray(self.poses, dtype=np.float64)
        self.poses = poses.reshape(k, poses.shape[-1] if poses.ndim == 2 else -1)
        self.weights = np.broadcast_to(np.asarray(self.weights, dtype=np.float64), (k,)).copy()
        if np.any(self.weights < 0.0):
            raise ValueError("keyframe weights must be >= 0")

    def __len__(self):
        return len(self.frames)


@dataclass
class SpaceTimeProblem:
    """One space-time edit.

    frames F >= 3 (frame 0 is the first of the range); h time step [s];
    eigenvalues (r,) initial Lambda [rad^2/s^2]; damping (r,) initial D [1/s];
    deformer: ``num_coords`` m >= r and ``q_batch`` / ``q_jacobian_batch`` (see module doc);
    handles / keyframes: optional constraints; gamma: handle weight [E_f units per m^2];
    mu: E_s weight (None: automatic, module doc); sampling (m, r) initial S (default [I; 0]);
    fix_start: hold frames 0 and 1 at start_state (2, r) (default zeros: start at rest).
    scheme: time discretisation of E_f, "central", "average" or "auto" (module doc), resolved
    on construction. material_freedom f >= 1 (dimensionless; inf: no bound): material
    optimisation keeps every sqrt(lambda_k) within [1/f, f] and d_k within [1/f, f] times the
    prepared ``eigenvalues`` / ``damping``; material_weight rho [E_f units] of the pull E_m toward
    them (None: automatic). See the module doc, "Material regulariser". external_forces (F, r):
    known modal forces per frame [modal units / s^2] that need no control, e.g. a rig's loads on
    its flesh (``rig.RigLoad.modal_forces``); not with material optimisation.
    """

    frames: int
    h: float
    eigenvalues: np.ndarray
    damping: np.ndarray
    deformer: object
    handles: Optional[HandleConstraints] = None
    keyframes: Optional[Keyframes] = None
    gamma: float = 1.0
    mu: Optional[float] = None
    sampling: Optional[np.ndarray] = None
    fix_start: bool = True
    start_state: Optional[np.ndarray] = None
    scheme: str = "auto"
    material_freedom: float = MATERIAL_FREEDOM
    material_weight: Optional[float] = None
    external_forces: Optional[np.ndarray] = None

    def __post_init__(self):
        self.frames = int(self.frames)
        self.h = float(self.h)
        self.eigenvalues = np.asarray(self.eigenvalues, dtype=np.float64).reshape(-1)
        r = len(self.eigenvalues)
        self.damping = np.broadcast_to(np.asarray(self.damping, dtype=np.float64), (r,)).copy()
        m = int(self.deformer.num_coords)
        self.sampling = (np.eye(m, r) if self.sampling is None
                         else np.asarray(self.sampling, dtype=np.float64).reshape(m, r))
        self.start_state = (np.zeros((2, r)) if self.start_state is None
                            else np.asarray(self.start_state, dtype=np.float64).reshape(2, r))
        self.scheme = resolve_scheme(self.scheme, self.h, self.eigenvalues)
        if self.external_forces is not None:
            self.external_forces = np.asarray(self.external_forces,
                                              dtype=np.float64).reshape(self.frames, r)
        self._check(m, r)

    def _check(self, m, r):
        if self.frames < 3 or self.h <= 0.0:
            raise ValueError(f"need at least 3 frames and h > 0 (got {self.frames}, {self.h})")
        if m < r:
            raise ValueError(f"the deformer takes {m} coordinates, fewer than the {r} modes")
        if not self.material_freedom >= 1.0:
            raise ValueError(f"material_freedom must be >= 1 (got {self.material_freedom})")
        if self.material_weight is not None and not self.material_weight >= 0.0:
            raise ValueError(f"material_weight must be >= 0 (got {self.material_weight})")
        for name, c in (("handle", self.handles), ("keyframe", self.keyframes)):
            if c is not None and len(c) and (c.frames.min() < 0 or c.frames.max() >= self.frames):
                raise ValueError(f"{name} frames must lie in [0, {self.frames})")
        if self.keyframes is not None and self.keyframes.poses.shape[1] != m:
            raise ValueError(f"keyframe poses have {self.keyframes.poses.shape[1]} coordinates, "
                             f"the deformer takes {m}")
        if _has(self.handles) and self.handles.rows.shape[2] != self.deformer.basis_size:
            raise ValueError(f"handle rows have {self.handles.rows.shape[2]} columns, the "
                             f"deformer's basis {self.deformer.basis_size}")

    @property
    def num_modes(self):
        return len(self.eigenvalues)

    @property
    def first_free(self):
        """Index of the first unknown frame (2 with a fixed start, else 0)."""
        return 2 if self.fix_start else 0


@dataclass
class SpaceTimeResult:
    """Result of ``solve``.

    Z (F, r) modal coordinates; eigenvalues, damping (r,); sampling S (m, r); deformer inputs
    are ``Z @ S.T`` (``inputs``). objective: final J; control_energy: final E_f alone;
    handle_residuals (c,) [m] distance of each handle from its target; keyframe_residuals (k,)
    |S z - zhat|; history: list of (iteration, block, J) with block in "start", "warm", "z",
    "material", "sampling" (non-increasing); iterations: GN iterations done (continuation
    included); converged: bool, and ``reason`` (str) a sentence saying why not (or how it
    converged); mu: the E_s weight used; material_weight: rho of E_m used (0 without material
    optimisation); scheme: E_f's time discretisation (pass it to ``simulate_modal`` to continue
    the motion). ``objective`` includes rho E_m; ``control_energy`` is E_f alone.
    """

    Z: np.ndarray
    eigenvalues: np.ndarray
    damping: np.ndarray
    sampling: np.ndarray
    objective: float
    control_energy: float
    handle_residuals: np.ndarray
    keyframe_residuals: np.ndarray
    history: list = field(default_factory=list)
    iterations: int = 0
    converged: bool = False
    mu: float = 0.0
    scheme: str = "central"
    reason: str = ""
    material_weight: float = 0.0

    @property
    def inputs(self):
        """(F, m) deformer inputs zhat_i = S z_i of every frame."""
        return self.Z @ self.sampling.T

    @property
    def objective_history(self):
        """(n,) J after every recorded step."""
        return np.array([entry[2] for entry in self.history])


# ---------------------------------------------------------------------------------------------
# Control-force energy E_f (quadratic, separable per mode)

def resolve_scheme(scheme, h, eigenvalues):
    """"central" or "average" for ``scheme`` in ("auto", "central", "average") (module doc)."""
    if scheme == "auto":
        omega_h = h * np.sqrt(np.max(np.maximum(np.asarray(eigenvalues, dtype=np.float64), 0.0)))
        return "central" if omega_h <= CENTRAL_LIMIT else "average"
    if scheme not in ("central", "average"):
        raise ValueError(f"unknown time discretisation {scheme!r}: use auto, central or average")
    return scheme


def stiffness_weights(scheme):
    """(3,) weights of z_{i-1}, z_i, z_{i+1} in the stiffness term Lambda z of E_f's residual."""
    return np.array([0.0, 1.0, 0.0]) if scheme == "central" else np.array([0.25, 0.5, 0.25])


def stencil(eigenvalues, damping, h, scheme="central"):
    """(3, r) coefficients (a, b, c) of the E_f residual a z_{i-1} + b z_i + c z_{i+1} per mode.

    central: a = 1/h^2 - d/(2h), b = lambda - 2/h^2, c = 1/h^2 + d/(2h)   [1/s^2];
    average: lambda enters as (a, b, c) += lambda (1/4, 1/2, 1/4).
    """
    eigenvalues, damping = np.broadcast_arrays(np.asarray(eigenvalues, dtype=np.float64),
                                               np.asarray(damping, dtype=np.float64))
    base = np.stack([1.0 / h ** 2 - damping / (2.0 * h), np.full_like(damping, -2.0 / h ** 2),
                     1.0 / h ** 2 + damping / (2.0 * h)])
    return base + stiffness_weights(scheme)[:, None] * eigenvalues


def dynamics_residual(Z, eigenvalues, damping, h, scheme="central", external=None):
    """(F-2, r) residual of the modal equation of motion on frames 1..F-2 [modal units / s^2]:
    the control force. external (F, r): known modal forces per frame (e.g. a rig's loads,
    ``rig.RigLoad.modal_forces``), which need no control: subtracted on frames 1..F-2."""
    a, b, c = stencil(eigenvalues, damping, h, scheme)
    R = a * Z[:-2] + b * Z[1:-1] + c * Z[2:]
    return R if external is None else R - np.asarray(external)[1:-1]


def control_energy(Z, eigenvalues, damping, h, scheme="central", external=None):
    """E_f(Z) = 1/2 |dynamics_residual|^2 (float)."""
    return 0.5 * float(np.sum(dynamics_residual(Z, eigenvalues, damping, h, scheme,
                                                external) ** 2))


def control_energy_gradient(Z, eigenvalues, damping, h, scheme="central", external=None):
    """dE_f/dZ (F, r): the stencil transposed applied to the residual (the Hessian, its bands,
    does not depend on ``external``)."""
    a, b, c = stencil(eigenvalues, damping, h, scheme)
    R = dynamics_residual(Z, eigenvalues, damping, h, scheme, external)
    G = np.zeros_like(Z, dtype=np.float64)
    G[:-2] += a * R
    G[1:-1] += b * R
    G[2:] += c * R
    return G


def control_energy_bands(frames, eigenvalues, damping, h, scheme="central"):
    """E_f Hessian per mode as three diagonals: d0 (F, r), d1 (F-1, r), d2 (F-2, r).

    H_k[j, j] = d0[j, k], H_k[j+1, j] = d1[j, k], H_k[j+2, j] = d2[j, k]. Residual row i
    (1 <= i <= F-2) touches frames i-1, i, i+1 with (a, b, c), hence the masks at both ends.
    """
    a, b, c = stencil(eigenvalues, damping, h, scheme)
    row = np.zeros(frames + 2, dtype=bool)          # row[j + 1]: frame j carries a residual
    row[2:frames] = True
    at, before, after = row[1:-1, None], row[2:, None], row[:-2, None]  # rows j, j+1, j-1
    d0 = a * a * before + b * b * at + c * c * after
    d1 = (a * b * before + b * c * at)[:-1]
    d2 = (a * c * before)[:-2]
    return d0, d1, d2


def simulate_modal(eigenvalues, damping, z0, z1, frames, h, scheme="central"):
    """Free run of z'' + D z' + Lambda z = 0 with E_f's differences: (frames, r).

    z0, z1 (r,) are frames 0 and 1; each later frame solves the stencil row for z_{i+1}, so
    E_f of the output (same ``scheme``) is zero up to round-off. Vectorised over modes; the
    recurrence over frames is inherent. "central" is stable only for h sqrt(lambda) < 2;
    "average" (Newmark's average acceleration) for every lambda, d >= 0.
    """
    a, b, c = stencil(eigenvalues, damping, h, scheme)
    Z = np.zeros((int(frames), len(a)))
    Z[0], Z[1] = z0, z1
    for i in range(1, int(frames) - 1):
        Z[i + 1] = -(a * Z[i - 1] + b * Z[i]) / c
    return Z


# ---------------------------------------------------------------------------------------------
# Constraint terms

def sampling_energy(S):
    """E_s(S) = 1/2 sum_j (|s_j|^2 - 1)^2 and its gradient (m, r)."""
    excess = np.sum(S * S, axis=0) - 1.0
    return 0.5 * float(excess @ excess), 2.0 * S * excess


def handle_misses(problem, Z, S):
    """(c, 3) handle position minus target [m]; one batched deformer call for all of them."""
    handles = problem.handles
    u = handles.evaluator(problem.deformer).displacement_batch(Z[handles.frame_list] @ S.T)
    return u[handles.frame_index, handles.handle_index] + handles.rest - handles.targets



# Orientation ("rotation") handles. A handle's orientation is pinned by matching its vertices'
# first moments about the centroid: spoke k is the linear functional
#     s_k(x) = mean_v (x_v - c) (d_v . e_k) / sqrt(l_k) = mean_v x_v (d_v . e_k) / sqrt(l_k),
# d_v = rest_v - c, (e_k, l_k) the principal axes and variances of the d_v. At rest s_k =
# sqrt(l_k) e_k (a vector of the region's RMS radius along its axis); rotated rigidly by R,
# s_k = R sqrt(l_k) e_k. Being linear in x, a spoke is one more row set (3, rB) for the existing
# handle machinery (deduplicated rows, batched evaluation, GN Jacobians): a rotation handle adds
# 2-3 constraints per frame instead of one per vertex. Their zero set for a rigid handle is that
# of the per-vertex targets c + R d_v; axes with l_k ~ 0 (a flat region) are dropped, the
# other two still fix R.
# Winding: a spoke target only knows R modulo 360 deg, and E_f itself prefers the unwound pose
# (a -90 deg twist costs less control force than a 270 deg one), so sparse targets let the
# solve unwind. Measured on a pinned 4:1:1 bar twisted 360 deg over 60 frames (6 deg/frame):
# targets 45, 22.5 or 30 deg apart unwind past 180 deg; every second frame (12 deg) meets the
# targets but swings up to 157 deg between them; every frame meets 360 and 720 deg twists
# (< 0.01 deg at the keys). So an orientation handle is targeted on EVERY frame of its keyed
# span, with the rotation evaluated per frame from the keyed F-curve (``winding_span``).

FLAT_AXIS = 1e-6           # a principal variance below this times the largest is dropped


def orientation_geometry(rest_positions, basis, indices):
    """Spokes of a handle on vertices ``indices``: rows (a, 3, rB), rest spokes (a, 3) [m].

    rest_positions (N, 3) [m]; basis (3N, rB) node-major. a in {2, 3} principal axes with
    variance above FLAT_AXIS of the largest (see the comment above). Raises ValueError for a
    region of fewer than two distinct points along a line (no orientation to pin).
    """
    idx = np.asarray(indices, dtype=np.int64).reshape(-1)
    points = np.asarray(rest_positions, dtype=np.float64)[idx]
    d = points - points.mean(axis=0)
    variances, axes = np.linalg.eigh(d.T @ d / len(d))                 # ascending
    keep = variances > FLAT_AXIS * max(variances[-1], 1e-300)
    if keep.sum() < 2:
        raise ValueError("an orientation handle needs vertices spanning a plane")
    axes, variances = axes[:, keep], variances[keep]
    coeff = (d @ axes) / (len(d) * np.sqrt(variances))                 # (k, a)
    rows = np.einsum("ka,kdr->adr", coeff, np.asarray(basis).reshape(len(rest_positions), 3,
                                                                    -1)[idx])
    return rows, (np.sqrt(variances) * axes).T


def orientation_constraints(frames, rotations, rows, spokes, weights):
    """HandleConstraints fields (frames, rows, rest, targets, weights) of spoke targets.

    frames (c,) int; rotations (c, 3, 3) the handle's rotation from rest on each frame (body
    frame); rows (a, 3, rB), spokes (a, 3) from ``orientation_geometry``; weights (c,) or
    scalar. Returns arrays of c a constraints, frame-major, to concatenate with others.
    """
    frames = np.asarray(frames, dtype=np.int64).reshape(-1)
    c, a = len(frames), len(spokes)
    targets = np.einsum("cij,aj->cai", np.asarray(rotations, dtype=np.float64), spokes)
    weights = np.broadcast_to(np.asarray(weights, dtype=np.float64), (c,))
    return (np.repeat(frames, a), np.tile(rows, (c, 1, 1)), np.tile(spokes, (c, 1)),
            targets.reshape(c * a, 3), np.repeat(weights, a))


def winding_span(keyed):
    """(n,) every frame from the first to the last of ``keyed`` (int frames), see above."""
    keyed = np.asarray(keyed, dtype=np.int64).reshape(-1)
    return np.arange(keyed.min(), keyed.max() + 1) if len(keyed) else keyed


def _handle_terms(problem, Z, S, jacobian):
    """Weighted residuals and, optionally, Jacobians of all handle constraints.

    Returns res (c, 3) = sqrt(gamma w) (position - target) [scaled m] and Jx (c, 3, m), the
    derivative of res w.r.t. the deformer input zhat of the constraint's frame (None unless
    ``jacobian``).
    """
    handles = problem.handles
    scale = np.sqrt(problem.gamma * handles.weights)[:, None]
    res = scale * handle_misses(problem, Z, S)
    if not jacobian:
        return res, None
    J = handles.evaluator(problem.deformer).jacobian_batch(Z[handles.frame_list] @ S.T)
    J = J.reshape(len(J), -1, 3, J.shape[-1])                              # (u, H, 3, m)
    return res, scale[:, :, None] * J[handles.frame_index, handles.handle_index]


def _keyframe_terms(problem, Z, S):
    """(k, m) weighted keyframe residuals sqrt(w) (S z_i - zhat_i)."""
    keys = problem.keyframes
    return np.sqrt(keys.weights)[:, None] * (Z[keys.frames] @ S.T - keys.poses)


def _has(constraints):
    return constraints is not None and len(constraints) > 0


def objective_terms(problem, Z, eigenvalues, damping, S, mu):
    """(E_f, gamma E_c, E_k, mu E_s) as floats."""
    e_f = control_energy(Z, eigenvalues, damping, problem.h, problem.scheme,
        problem.external_forces)
    e_c = (0.5 * float(np.sum(_handle_terms(problem, Z, S, False)[0] ** 2))
           if _has(problem.handles) else 0.0)
    e_k = (0.5 * float(np.sum(_keyframe_terms(problem, Z, S) ** 2))
           if _has(problem.keyframes) else 0.0)
    return e_f, e_c, e_k, mu * sampling_energy(S)[0]


def objective(problem, Z, eigenvalues, damping, S, mu=0.0):
    """J = E_f + gamma E_c + E_k + mu E_s (float)."""
    return float(sum(objective_terms(problem, Z, eigenvalues, damping, S, mu)))


def handle_residuals(problem, Z, S):
    """(c,) distance [m] of each handle from its target (unweighted)."""
    if not _has(problem.handles):
        return np.zeros(0)
    return np.linalg.norm(handle_misses(problem, Z, S), axis=1)


# ---------------------------------------------------------------------------------------------
# Gauss-Newton system

def _block_band_indices(r):
    """(k, d) of every lower-band entry of a dense r x r block: entry (k + d, k), k + d < r."""
    return np.nonzero(np.tri(r, dtype=bool)[::-1])


def normal_equations(problem, Z, eigenvalues, damping, S):
    """Gauss-Newton system of J in Z on the free frames, lower banded form.

    Returns ab (2r + 1, n) for ``solveh_banded(ab, -g, lower=True)`` and g (n,), with
    n = (F - first_free) r unknowns in time-major order (index (i - first_free) r + k).
    The E_f part is exact; handles add Jc^T Jc, keyframes w S^T S, both per frame.
    """
    return _linearise(problem, Z, eigenvalues, damping, S)[:2]


def _linearise(problem, Z, eigenvalues, damping, S):
    """(ab, g, handle residuals (c, 3) or None, their Jacobians in z (c, 3, r) or None)."""
    s = problem.first_free
    grad, blocks = _quadratic_terms(problem, Z, eigenvalues, damping, S)
    res, Jz, handle_grad, handle_blocks = _handle_system(problem, Z, S)
    if res is not None:
        grad, blocks = grad + handle_grad, blocks + handle_blocks
    ab = _assemble_band(problem, eigenvalues, damping, blocks[s:])
    return ab, grad[s:].reshape(-1), res, Jz


def _quadratic_terms(problem, Z, eigenvalues, damping, S):
    """Gradient (F, r) of E_f + E_k at Z and the keyframes' Hessian blocks (F, r, r)."""
    F, r = problem.frames, problem.num_modes
    grad = control_energy_gradient(Z, eigenvalues, damping, problem.h, problem.scheme,
                                   problem.external_forces)
    blocks = np.zeros((F, r, r))
    if _has(problem.keyframes):
        keys = problem.keyframes
        key_res = _keyframe_terms(problem, Z, S)                             # (k, m)
        np.add.at(grad, keys.frames, np.sqrt(keys.weights)[:, None] * (key_res @ S))
        np.add.at(blocks, keys.frames, keys.weights[:, None, None] * (S.T @ S))
    return grad, blocks


def _handle_system(problem, Z, S):
    """Handles' residuals (c, 3), Jacobians in z (c, 3, r), gradient (F, r) and GN blocks
    (F, r, r) at Z; all None without handles."""
    if not _has(problem.handles):
        return None, None, None, None
    F, r = problem.frames, problem.num_modes
    res, Jx = _handle_terms(problem, Z, S, True)
    Jz = Jx @ S                                                              # (c, 3, r)
    grad, blocks = np.zeros((F, r)), np.zeros((F, r, r))
    np.add.at(grad, problem.handles.frames, np.einsum("cdr,cd->cr", Jz, res))
    np.add.at(blocks, problem.handles.frames, np.einsum("cdr,cds->crs", Jz, Jz))
    return res, Jz, grad, blocks


def _assemble_band(problem, eigenvalues, damping, blocks):
    """ab (2r + 1, n): E_f diagonals at offsets 0, r, 2r plus the per-frame blocks (nf, r, r)."""
    r, s = problem.num_modes, problem.first_free
    nf = problem.frames - s
    d0, d1, d2 = control_energy_bands(problem.frames, eigenvalues, damping, problem.h,
                                      problem.scheme)
    ab = np.zeros((2 * r + 1, nf * r))
    ab[0] = d0[s:].reshape(-1)
    ab[r, :(nf - 1) * r] = d1[s:].reshape(-1)
    ab[2 * r, :(nf - 2) * r] = d2[s:].reshape(-1)
    # ab[d, i r + k] = block_i[k + d, k]; indices broadcast over frames i (nf, 1) x pairs (P,).
    k, d = _block_band_indices(r)
    i = np.arange(nf)[:, None]
    ab[d, i * r + k] += blocks[i, k + d, k]
    return ab


def _frame_unknowns(frames, r):
    """(u r,) frame-major indices of every mode's unknown on frames (u,): j r + k for mode k
    on frames[j]."""
    return (np.asarray(frames)[:, None] * r + np.arange(r)).reshape(-1)


class _BandFactor:
    """The Cholesky factor of a banded SPD matrix A (n, n) given in ``_assemble_band``'s lower
    form ab (2r + 1, n), unknowns frame-major (frame i, mode k at i r + k).

    E_f couples each mode only with itself on the next two frames (its bands at offsets r and
    2r). Unless a frame's block couples its modes (a pose key's), A is therefore r independent
    systems of bandwidth 2, which in mode-major order are factored and solved with bandwidth 2
    instead of 2r (n 2^2 instead of n (2r)^2 for the factor, 4 n instead of 4 n r per solve).
    Otherwise the frame-major band is factored as it is."""

    def __init__(self, ab, r):
        self.r, self.n = r, ab.shape[1]
        mode_bands = [0, r, 2 * r]
        self.by_mode = not np.delete(ab, mode_bands, axis=0).any()
        if self.by_mode:                       # ab[r d, i r + k] -> row d, column k nf + i
            ab = np.ascontiguousarray(ab[mode_bands].reshape(3, -1, r).transpose(0, 2, 1)
                                      ).reshape(3, -1)
        self.factor = (scipy.linalg.cholesky_banded(ab, lower=True, check_finite=False), True)

    def frame_columns(self, frames):
        """(apply, block) for the columns X = A^-1 E (n, u r) of every unknown on ``frames``
        (u,) (column j r + k: mode k on frames[j]): apply(w (u r,)) = X w (n,), and block =
        X's rows on those unknowns (u r, u r). Mode by mode, X is zero off its column's mode:
        its nonzero part is u solves (one unit right-hand side per frame serves every mode's
        independent block) and X w costs n u instead of n u r."""
        r, frames = self.r, np.asarray(frames)
        u, nf = len(frames), self.n // r
        columns = _frame_unknowns(frames, r)
        if not self.by_mode:
            picks = np.zeros((self.n, u * r))
            picks[columns, np.arange(u * r)] = 1.0
            X = self.solve(picks)
            return (lambda w: X @ w), X[columns]
        units = np.zeros((r, nf, u))
        units[:, frames, np.arange(u)] = 1.0
        by_mode = scipy.linalg.cho_solve_banded(self.factor, units.reshape(-1, u),
                                                check_finite=False).reshape(r, nf, u)
        block = np.zeros((u, r, u, r))            # zero between different modes
        modes = np.arange(r)
        block[:, modes, :, modes] = by_mode[:, frames, :]                   # [k, j, j']
        return (lambda w: np.einsum("kij,jk->ik", by_mode, w.reshape(u, r)).reshape(-1),
                block.reshape(u * r, u * r))

    def solve(self, b):
        """A^-1 b for b (n,) or (n, k), frame-major rows."""
        if not self.by_mode:
            return scipy.linalg.cho_solve_banded(self.factor, b, check_finite=False)
        tail = b.shape[1:]
        by_mode = b.reshape((-1, self.r) + tail).swapaxes(0, 1).reshape(b.shape)
        x = scipy.linalg.cho_solve_banded(self.factor, by_mode, check_finite=False)
        return np.ascontiguousarray(x.reshape((self.r, -1) + tail).swapaxes(0, 1)).reshape(
            b.shape)


class _Elimination:
    """The frames no handle touches, eliminated once per Z block (module doc, "Elimination").

    Only E_f and E_k see those frames, and both are quadratic in Z with a Hessian A (banded,
    fixed while the material and S are). With the u r unknowns on the handles' free frames
    picked by E (n, u r), X = A^-1 E (n, u r) and K = (E^T A^-1 E)^-1 (u r, u r), the Schur
    complement of A on those frames: for a GN step whose handle part lives on them, the
    minimiser of the model is dZ = -A^-1 g_q + X K (v + (A^-1 g_q)_c), v its handle-frame part
    solving (K + Jc^T Jc) v = -K (A^-1 g_q)_c - g_c. The same step as the banded system's; what
    the frame count costs is one banded factor and u r right-hand sides per block.
    Raises np.linalg.LinAlgError when A is not positive definite (e.g. no start held).
    """

    def __init__(self, problem, eigenvalues, damping, S):
        s, r = problem.first_free, problem.num_modes
        frames = problem.handles.frame_list
        self.frames = frames[frames >= s]
        Z = np.zeros((problem.frames, r))
        blocks = _quadratic_terms(problem, Z, eigenvalues, damping, S)[1]
        A = _assemble_band(problem, eigenvalues, damping, blocks[s:])
        factor = _BandFactor(A, r)
        self.solve = factor.solve                                 # A^-1 of (n,) or (n, k)
        self.columns = _frame_unknowns(self.frames - s, r)
        self._apply_X, inverse = factor.frame_columns(self.frames - s)       # X, (A^-1)_cc
        inverse = 0.5 * (inverse + inverse.T)
        self.K = scipy.linalg.cho_solve(scipy.linalg.cho_factor(inverse), np.eye(len(inverse)))
        self.K = 0.5 * (self.K + self.K.T)

    def expand(self, v):
        """(n,) step on every free frame of a handle-frame part v (u r,) of a model with no
        quadratic gradient: X K v."""
        return self._apply_X(self.K @ v)


def _elimination(state):
    """An ``_Elimination`` for the state's Z block, or None where the banded solve is used:
    no handles, no start held (A singular), or more than ``ELIMINATE_LIMIT`` handle unknowns."""
    problem = state.problem
    if not _elimination_applies(problem):
        return None
    try:
        return _Elimination(problem, state.eigenvalues, state.damping, state.S)
    except np.linalg.LinAlgError:
        return None


def _elimination_applies(problem):
    """Handles on at most ``ELIMINATE_LIMIT`` / r free frames, and the start held."""
    if not _has(problem.handles) or not problem.fix_start:
        return False
    frames = problem.handles.frame_list
    return np.count_nonzero(frames >= problem.first_free) * problem.num_modes <= ELIMINATE_LIMIT


def _eliminated_step(state, tolerance, elimination):
    """``_gauss_newton_step`` with the other frames eliminated (``_Elimination``)."""
    problem, s = state.problem, state.problem.first_free
    grad, _ = _quadratic_terms(problem, state.Z, state.eigenvalues, state.damping, state.S)
    res, Jz, handle_grad, handle_blocks = _handle_system(problem, state.Z, state.S)
    frames = elimination.frames
    free = elimination.solve(grad[s:].reshape(-1))                          # A^-1 g_q
    H = elimination.K + scipy.linalg.block_diag(*handle_blocks[frames])
    rhs = -elimination.K @ free[elimination.columns] - handle_grad[frames].reshape(-1)

    def solve_with(factor):
        def solve(rhs_frames):                    # (F, r) handle-frame rhs -> (n,) step
            return elimination.expand(scipy.linalg.cho_solve(
                factor, rhs_frames[frames].reshape(-1), check_finite=False))
        return solve

    def trial(factor):
        v = scipy.linalg.cho_solve(factor, rhs, check_finite=False)
        return -free + elimination.expand(v + free[elimination.columns])

    def factorise(damped):
        return scipy.linalg.cho_factor(damped, lower=True, check_finite=False)

    def scale_diagonal(damped, lm):
        damped[np.diag_indices(len(damped))] *= 1.0 + lm

    # The undamped model's decrease g^T H^-1 g / 2 (the Newton decrement of the GN model):
    # where GN converges linearly J's own decrease per step understates what is left.
    predicted = 0.5 * float(rhs @ scipy.linalg.cho_solve(factorise(H), rhs, check_finite=False))
    return _damped_steps(state, tolerance, H, trial, solve_with, res, Jz, factorise,
                         scale_diagonal, predicted)


# ---------------------------------------------------------------------------------------------
# Blocks of the descent

class _State:
    """Mutable solve state: Z, Lambda, D, S, mu, Marquardt factor, history."""

    def __init__(self, problem, Z, mu):
        self.problem = problem
        self.Z, self.S = Z, problem.sampling.copy()
        self.eigenvalues, self.damping = problem.eigenvalues.copy(), problem.damping.copy()
        self.mu, self.lm, self.iterations = mu, 0.0, 0
        self.rho = 0.0                       # weight of E_m; set by _choose_weights
        self.value = self.evaluate()
        self.history = [(0, "start", self.value)]
        self.progress = None                 # the solve's ``SolveProgress``, if it reports

    def evaluate(self, Z=None, S=None):
        """J + rho E_m at the state, with Z or S replaced if given."""
        value = objective(self.problem, self.Z if Z is None else Z, self.eigenvalues,
                          self.damping, self.S if S is None else S, self.mu)
        if self.rho > 0.0:
            value += self.rho * (material_energy(self.eigenvalues, self.damping,
                                                 self.problem.eigenvalues, self.problem.damping)
                                 + sampling_change(self.S if S is None else S,
                                                   self.problem.sampling)[0])
        return value

    def record(self, iteration, block, callback):
        self.history.append((iteration, block, self.value))
        if callback is not None:
            callback(iteration, self.value)


def _gauss_newton_step(state, tolerance):
    """One accepted (or failed) LM step on Z. Returns True when converged or stuck.

    Each trial factors the damped GN matrix once (``cholesky_banded``, the factorisation
    ``solveh_banded`` does) and reuses it for up to ``CORRECTIONS`` second-order corrections:
    the handle residual's curvature along the step, e = r(z + dz) - r(z) - J dz, is fed back as
    the chord step -H^-1 J^T e. Penalised handles make a narrow curved valley (gamma is large);
    straight GN steps leave it quadratically and get rejected or shortened, the corrections
    follow it. The best of the trial points is kept if it does not increase J.
    """
    problem = state.problem
    ab, g, res, Jz = _linearise(problem, state.Z, state.eigenvalues, state.damping, state.S)
    s = problem.first_free

    def solve_with(factor):
        def solve(rhs_frames):
            return scipy.linalg.cho_solve_banded(factor, rhs_frames[s:].reshape(-1),
                                                 check_finite=False)
        return solve

    def scale_diagonal(damped, lm):
        damped[0] *= 1.0 + lm

    def factorise(damped):
        return scipy.linalg.cholesky_banded(damped, lower=True, check_finite=False), True

    def trial(factor):
        return scipy.linalg.cho_solve_banded(factor, -g, check_finite=False)

    return _damped_steps(state, tolerance, ab, trial, solve_with, res, Jz, factorise,
                         scale_diagonal)


def _damped_steps(state, tolerance, H, trial, solve_with, res, Jz, factorise, scale_diagonal,
                  predicted=None):
    """The LM loop of a GN step: damp H's diagonal by (1 + lm), factorise, take the step
    ``trial(factor)`` (n,) and its chord corrections (``solve_with(factor)``), accept the best
    if J does not increase, else raise lm. Returns True when converged or stuck: J fell by at
    most ``tolerance`` J (relative), or ``predicted`` (the decrease the undamped GN model
    promised, if given) is at most that, or the step was that small relative to Z."""
    s = state.problem.first_free
    while state.lm <= LM_MAX:
        damped = H.copy()
        scale_diagonal(damped, state.lm)
        try:
            factor = factorise(damped)
        except np.linalg.LinAlgError:       # round-off made the GN matrix indefinite: damp more
            state.lm = max(10.0 * state.lm, LM_FIRST)
            continue
        Z, value = _corrected_trials(state, solve_with(factor), trial(factor), res, Jz)
        if value <= state.value:
            decrease = state.value - value
            small_step = (np.linalg.norm(Z - state.Z)
                          <= tolerance * (np.linalg.norm(Z[s:]) + 1e-300))
            state.Z, state.value, state.lm = Z, value, state.lm / 10.0
            state.lm = 0.0 if state.lm < LM_FIRST else state.lm
            # The undamped GN model's promise overstates what is left where GN converges
            # linearly (a damped step takes about half of it each time), so a step that lowered J
            # by at most the tolerance also ends the run, as it always did.
            promised = decrease if predicted is None else min(decrease, predicted)
            return promised <= tolerance * max(value, 1e-300) or small_step
        state.lm = max(10.0 * state.lm, LM_FIRST)
    return True


def _corrected_trials(state, solve, step, res, Jz):
    """Best (Z, J) among Z + step and its chord corrections (see ``_gauss_newton_step``)."""
    problem, s, r = state.problem, state.problem.first_free, state.problem.num_modes
    Z = state.Z.copy()
    Z[s:] += step.reshape(-1, r)
    best = (Z, state.evaluate(Z=Z))
    if res is None:                          # everything else is quadratic: GN is exact
        return best
    frames = problem.handles.frames
    for _ in range(CORRECTIONS):
        linear = res + np.einsum("cdr,cr->cd", Jz, (Z - state.Z)[frames])   # r(z) + J dz
        error = _handle_terms(problem, Z, state.S, False)[0] - linear
        rhs = np.zeros_like(Z)
        np.add.at(rhs, frames, np.einsum("cdr,cd->cr", Jz, error))
        Z = Z.copy()
        Z[s:] -= solve(rhs).reshape(-1, r)
        value = state.evaluate(Z=Z)
        if value >= best[1]:
            break
        best = (Z, value)
    return best


def _optimise_z(state, iterations, tolerance, outer, callback, should_cancel, part=None):
    """Up to ``iterations`` GN/LM steps on Z (None: ``_step_limit``); records each. Returns
    True if converged. part: which run of the solve's ``SolveProgress`` this is (None: it
    does not report)."""
    elimination = _elimination(state) if iterations is None or iterations > 0 else None
    limit = _step_limit(state, iterations, elimination)
    progress = state.progress if part is not None else None
    if progress is not None:
        progress.run(part, limit, tolerance, state.value)
    for _ in range(limit):
        _check_cancel(should_cancel)
        done = (_gauss_newton_step(state, tolerance) if elimination is None
                else _eliminated_step(state, tolerance, elimination))
        state.iterations += 1
        state.record(outer if outer is not None else state.iterations, "z", callback)
        if progress is not None:
            progress.step(state.value)
        if done:
            return True
    return False


class SolveProgress:
    """How far a ``solve`` has come, for a progress bar: report(fraction, text) after every
    Gauss-Newton step, the fraction in [0, 0.99] and never going back.

    A solve is a sequence of GN runs on Z (the continuation's stages, the motion; with material
    optimisation one per round and a final one), each given an equal share of the bar. Within a
    run the share follows its convergence: the relative decrease of J per step, on a log scale
    from the run's first step down to the tolerance that ends it (where GN converges linearly
    it falls steadily), or the steps taken against the run's limit where that is further. Step
    counts alone left the bar near 0 through the continuation and at a few percent when a
    200-step limit was met in 15 steps.
    """

    def __init__(self, report, runs):
        self.report, self.runs = report, max(int(runs), 1)
        self.fraction, self.total_steps = 0.0, 0
        self.run(0, 1, 1.0, 0.0)

    def run(self, part, limit, tolerance, value):
        """Begin run ``part`` (0-based) of at most ``limit`` steps, ending at relative decrease
        ``tolerance``, from J = value."""
        self.part = min(int(part), self.runs - 1)
        self.limit, self.tolerance = max(int(limit), 1), float(tolerance)
        self.steps, self.first_decrease, self.value = 0, None, float(value)

    def step(self, value):
        """One step of the current run reached J = value: report."""
        self.steps += 1
        self.total_steps += 1
        within = self.steps / self.limit
        if value < self.value:
            decrease = max((self.value - value) / max(abs(value), 1e-300), self.tolerance)
            if self.first_decrease is None:
                self.first_decrease = decrease
            if self.first_decrease > self.tolerance:
                within = max(within, np.log(self.first_decrease / decrease)
                             / np.log(self.first_decrease / self.tolerance))
        self.value = float(value)
        self.fraction = max(self.fraction, min((self.part + min(within, 1.0)) / self.runs, 0.99))
        self.report(self.fraction, f"step {self.total_steps}, objective {value:.4g}")


def _step_limit(state, iterations, elimination=False):
    """``step_limit`` of a Z solve; elimination: its ``_Elimination`` or None (False: whether
    the problem allows one)."""
    eliminated = None if elimination is False else elimination is not None
    return step_limit(state.problem, iterations, eliminated=eliminated)


def step_limit(problem, iterations=None, optimise_material=False, eliminated=None):
    """The most steps ``solve`` records for ``iterations`` (None: its defaults): Gauss-Newton
    steps of the motion, ``GN_STEPS`` or ``ELIMINATED_STEPS`` where the handles' frames are
    eliminated (``eliminated``; None: where ``_elimination`` applies; such steps cost no more
    with the frame count), or ``MATERIAL_ROUNDS`` with ``optimise_material``."""
    if iterations is not None:
        return int(iterations)
    if optimise_material:
        return MATERIAL_ROUNDS
    if eliminated is None:
        eliminated = _elimination_applies(problem)
    return ELIMINATED_STEPS if eliminated else GN_STEPS


def material_bounds(eigenvalues, damping, freedom):
    """(lower (2, r), upper (2, r)) of (lambda, d) around prepared values (r,) for factor f.

    lambda in [lambda0 / f^2, lambda0 f^2] (frequency within a factor f), d in [d0 / f, d0 f];
    f = inf gives [0, inf) for both. A prepared value of 0 stays 0 unless f is infinite.
    """
    prepared = np.stack([eigenvalues, damping]).astype(np.float64)
    factor = np.array([freedom ** 2, freedom], dtype=np.float64)[:, None]
    if np.isinf(freedom):
        return np.zeros_like(prepared), np.full_like(prepared, np.inf)
    return prepared / factor, prepared * factor


def material_scales(eigenvalues):
    """(2, r) divisors turning (lambda - lambda0, d - d0) into E_m's residuals: (lambda0,
    2 sqrt(lambda0)), i.e. the change of log lambda and of the damping ratio to first order."""
    lam = np.maximum(np.asarray(eigenvalues, dtype=np.float64), 1e-300)
    return np.stack([lam, 2.0 * np.sqrt(lam)])


def material_energy(eigenvalues, damping, prepared_eigenvalues, prepared_damping):
    """E_m = 1/2 sum_k ((lambda_k - lambda0_k) / lambda0_k)^2 + ((d_k - d0_k) / 2 sqrt(lambda0_k))^2
    (dimensionless float; module doc, "Material regulariser")."""
    change = np.stack([eigenvalues, damping]) - np.stack([prepared_eigenvalues, prepared_damping])
    return 0.5 * float(np.sum((change / material_scales(prepared_eigenvalues)) ** 2))


def sampling_change(S, S0):
    """1/2 |S - S0|_F^2 (E_m's mode-shape part, dimensionless) and its gradient (m, r)."""
    return 0.5 * float(np.sum((S - S0) ** 2)), S - S0


def fit_material(Z, h, eigenvalues, damping, scheme="central", prepared=None, weight=0.0,
                 freedom=np.inf):
    """Per mode the exact minimiser of E_f + weight E_m over (lambda_k, d_k) in their bounds.

    E_f of mode k is 1/2 |[s, v] (lambda, d) + acc|^2 over frames 1..F-2, with s = z_i
    ("central") or (z_{i-1} + 2 z_i + z_{i+1}) / 4 ("average"), v = (z_{i+1} - z_{i-1}) / 2h,
    acc = (z_{i+1} - 2 z_i + z_{i-1}) / h^2; E_m (``material_energy``, about ``prepared`` =
    (lambda0 (r,), d0 (r,)), default the given values) adds two rows, so each mode is a
    two-column bounded least-squares problem (``material_bounds`` with factor ``freedom``;
    default [0, inf): plain NNLS), solved exactly by BVLS with columns scaled to unit norm. A
    column that is negligible (relative ``DEGENERATE_MOTION`` to the largest of its kind), or a
    parameter whose bounds coincide, keeps the value in ``eigenvalues`` / ``damping`` (r,)
    (clipped to its bounds). Returns (lambda (r,), d (r,)).
    """
    w = stiffness_weights(scheme)
    stiffness = w[0] * Z[:-2] + w[1] * Z[1:-1] + w[2] * Z[2:]
    columns = np.stack([stiffness, (Z[2:] - Z[:-2]) / (2.0 * h)], axis=1)   # (F-2, 2, r)
    acc = (Z[2:] - 2.0 * Z[1:-1] + Z[:-2]) / h ** 2                        # (F-2, r)
    norms = np.linalg.norm(columns, axis=0)                                # (2, r)
    used = norms > DEGENERATE_MOTION * np.maximum(norms.max(axis=1, keepdims=True), 1e-300)
    origin = (np.stack([eigenvalues, damping]) if prepared is None
              else np.stack(prepared)).astype(np.float64)                  # (2, r)
    lower, upper = material_bounds(origin[0], origin[1], freedom)
    used &= upper > lower
    params = np.clip(np.stack([eigenvalues, damping]).astype(np.float64), lower, upper)
    pull = np.sqrt(weight) / material_scales(origin[0])                    # (2, r)
    for k in np.flatnonzero(used.any(axis=0)):       # r <= ~40 tiny bounded problems
        use = used[:, k]
        rhs = np.concatenate([-acc[:, k] - columns[:, ~use, k] @ params[~use, k],
                              pull[use, k] * origin[use, k]])
        scale = norms[use, k]
        A = np.concatenate([columns[:, use, k], np.diag(pull[use, k])]) / scale
        x = scipy.optimize.lsq_linear(A, rhs, bounds=(lower[use, k] * scale,
                                                      upper[use, k] * scale),
                                      method="bvls").x
        params[use, k] = np.clip(x / scale, lower[use, k], upper[use, k])
    return params[0], params[1]


def _optimise_material(state, outer, callback):
    """Block (2): exact bounded (lambda, d) of E_f + rho E_m; kept only if J does not increase."""
    problem = state.problem
    lam, dmp = fit_material(state.Z, problem.h, state.eigenvalues, state.damping,
                            problem.scheme, (problem.eigenvalues, problem.damping),
                            state.rho, problem.material_freedom)
    old = state.eigenvalues, state.damping
    state.eigenvalues, state.damping = lam, dmp
    value = state.evaluate()
    if value <= state.value:
        state.value = value
    else:                                     # round-off only: the fit is exact
        state.eigenvalues, state.damping = old
    state.record(outer, "material", callback)


def sampling_objective(problem, Z, S, mu):
    """gamma E_c + E_k + mu E_s as a function of S (m, r), and its gradient (m, r).

    d/dS of 1/2 |res(S z_i)|^2 is (Jx^T res) z_i^T summed over constraints; E_s as in
    ``sampling_energy``. One batched deformer call (values and Jacobians) per evaluation.
    """
    value, grad = sampling_energy(S)
    value, grad = mu * value, mu * grad
    if _has(problem.handles):
        res, Jx = _handle_terms(problem, Z, S, True)
        value += 0.5 * float(np.sum(res ** 2))
        grad = grad + np.einsum("cdm,cd,cr->mr", Jx, res, Z[problem.handles.frames])
    if _has(problem.keyframes):
        res = _keyframe_terms(problem, Z, S)
        value += 0.5 * float(np.sum(res ** 2))
        weights = np.sqrt(problem.keyframes.weights)[:, None]
        grad = grad + res.T @ (weights * Z[problem.keyframes.frames])
    return value, grad


def z_gradient(problem, Z, eigenvalues, damping, S):
    """dJ/dZ (F, r) at fixed material and S (E_f, handles and keyframes; E_s does not see Z)."""
    grad = control_energy_gradient(Z, eigenvalues, damping, problem.h, problem.scheme,
        problem.external_forces)
    if _has(problem.handles):
        res, Jx = _handle_terms(problem, Z, S, True)
        np.add.at(grad, problem.handles.frames, np.einsum("cdm,cd,mr->cr", Jx, res, S))
    if _has(problem.keyframes):
        keys = problem.keyframes
        np.add.at(grad, keys.frames,
                  np.sqrt(keys.weights)[:, None] * (_keyframe_terms(problem, Z, S) @ S))
    return grad


def carried_z(problem, Z, S, S_new):
    """(F, r) Z' with S_new z'_i the least-squares fit of the inputs S z_i (start frames kept)."""
    first = problem.first_free
    carried = Z.copy()
    carried[first:] = np.linalg.lstsq(S_new, S @ Z[first:].T, rcond=None)[0].T
    return carried


def carried_objective(problem, Z, S, eigenvalues, damping, mu, S_new):
    """J(Z'(S_new), S_new) with Z' = ``carried_z`` (deformer inputs held), and d/dS_new (m, r).

    With P = (S'^T S')^-1 S'^T, Z' = Zhat P^T (Zhat = Z S^T fixed), dP = -P dS' P
    + (S'^T S')^-1 dS'^T (I - S' P); with A = G_Z^T Zhat (G_Z = dJ/dZ' on the free frames) the
    gradient is G_S - P^T A P^T + (I - S' P) A^T (S'^T S')^-1, G_S = dJ/dS' at fixed Z'.
    Holding the inputs lets S move along the handles' valley instead of across it: at fixed Z
    a stiff handle pins S z and S barely moves per block.
    """
    first = problem.first_free
    Zc = carried_z(problem, Z, S, S_new)
    value, grad_s = sampling_objective(problem, Zc, S_new, mu)
    value += control_energy(Zc, eigenvalues, damping, problem.h, problem.scheme,
        problem.external_forces)
    G = z_gradient(problem, Zc, eigenvalues, damping, S_new)[first:]            # (n, r)
    gram_inv = np.linalg.pinv(S_new.T @ S_new)      # (r, r); pinv: L-BFGS may try a singular S
    P = gram_inv @ S_new.T                                                      # (r, m)
    A = G.T @ (Z[first:] @ S.T)                                                 # (r, m)
    Q = np.eye(len(S_new)) - S_new @ P
    return value, grad_s - P.T @ A @ P.T + Q @ A.T @ gram_inv


def _optimise_sampling(state, iterations, outer, callback):
    """Block (3): S by L-BFGS-B on J with Z carried (``carried_objective``), kept if J fell."""
    problem, shape = state.problem, state.S.shape

    def fun(flat):
        S = flat.reshape(shape)
        value, grad = carried_objective(problem, state.Z, state.S, state.eigenvalues,
                                        state.damping, state.mu, S)
        pull, pull_grad = sampling_change(S, problem.sampling)
        return value + state.rho * pull, (grad + state.rho * pull_grad).reshape(-1)

    found = scipy.optimize.minimize(fun, state.S.reshape(-1), jac=True, method="L-BFGS-B",
                                    options=dict(maxiter=iterations))
    S = found.x.reshape(shape)
    if np.all(np.isfinite(S)) and np.linalg.matrix_rank(S) == shape[1]:
        Z = carried_z(problem, state.Z, state.S, S)
        value = state.evaluate(Z=Z, S=S)
        if value < state.value:
            state.Z, state.S, state.value = Z, S, value
    state.record(outer, "sampling", callback)


def _check_cancel(should_cancel):
    if should_cancel is not None and should_cancel():
        raise SolveCancelled("space-time solve cancelled")


# ---------------------------------------------------------------------------------------------
# Driver

def solve(problem, optimise_material=False, iterations=None, gn_iterations=5,
          sampling_iterations=30, tolerance=1e-9, initial=None, continuation=True,
          callback=None, should_cancel=None, round_tolerance=ROUND_TOLERANCE,
          exact_handles=False, progress=None):
    """Minimise J over Z (and, with ``optimise_material``, over Lambda, D and S).

    iterations: GN steps per Z solve (default ``GN_STEPS``, ``ELIMINATED_STEPS`` where the handles'
    frames are eliminated, module doc) without material optimisation; outer block-descent rounds
    (default ``MATERIAL_ROUNDS``) with it, each round = up to ``gn_iterations`` GN steps, the
    (lambda, d) fit and, for a rectangular S only (module doc), up to ``sampling_iterations``
    L-BFGS-B iterations on S with Z carried; after the last round Z is solved again (default step
    limit) for the final material, so no control force is left that the material change made
    unnecessary. tolerance: relative decrease of J (and relative step size) under which a GN run
    stops; round_tolerance: relative decrease of J over a round under which the material descent
    has converged. initial: (F, r) starting Z (default zeros; start frames are overwritten by
    start_state). continuation: run the penalty continuation for stiff handles first (module doc).
    callback(iteration, J) after every recorded step; progress(fraction, text) after every GN
    step, stages included (``SolveProgress``); should_cancel() -> bool polled between steps,
    raising ``SolveCancelled``. exact_handles (without material optimisation only): after the
    penalty solve, meet the handles by the method of multipliers (``_meet_handles``); the result
    then minimises E_f + E_k subject to the handles rather than J, so its ``objective`` (J) may be
    above the history's last value.
    Returns ``SpaceTimeResult`` (``converged`` and ``reason`` say whether each stage converged).
    """
    Z = np.zeros((problem.frames, problem.num_modes)) if initial is None else \
        np.array(initial, dtype=np.float64).reshape(problem.frames, problem.num_modes)
    if problem.fix_start:
        Z[:2] = problem.start_state
    if optimise_material and problem.external_forces is not None:
        raise ValueError("material optimisation with external forces (a rig's loads) is not "
                         "supported: the forces are in the prepared modes' coordinates")
    state = _State(problem, Z, 0.0 if problem.mu is None else float(problem.mu))
    gn_cap = None if iterations is None or optimise_material else int(iterations)
    rounds = MATERIAL_ROUNDS if iterations is None else int(iterations)
    stages = len(_stage_gammas(problem) or []) if continuation else 0
    if progress is not None:     # runs: the stages, then the motion or (material) 1 + rounds + 1
        state.progress = SolveProgress(progress, stages + (rounds + 2 if optimise_material
                                                           else 1))
    reach = _warm_start(state, gn_cap, tolerance, callback, should_cancel) if continuation \
        else None
    if not optimise_material:
        if reach is None or not reach.stalled:
            done = _optimise_z(state, gn_cap, tolerance, None, callback, should_cancel,
                               part=stages)
            if reach is not None:
                reach = reach.judge(state)
        if reach is not None and reach.stalled:
            return reach.give_up(state, callback)
        worst = _meet_handles(state, gn_cap, tolerance, should_cancel) if exact_handles \
            else None
        if worst is not None:       # the multipliers decide: are the handles met?
            met = worst <= HANDLE_MET
            return _result(state, met, f"handles met to {worst:.1e} of their extent" if met
                           else f"the handles stay up to {worst:.1e} of their extent from "
                                f"their targets: they may ask for the impossible")
        return _result(state, done, "converged" if done else
                       f"Gauss-Newton did not converge in {_step_limit(state, gn_cap)} steps")

    out_of_reach = []
    if reach is not None and reach.stalled:     # go on with the handles at the stage that held
        out_of_reach.append(reach.give_up(state, callback).reason)
    _optimise_z(state, gn_iterations, tolerance, 0, callback, should_cancel, part=stages)
    _choose_weights(state)
    rounds_done, change = False, np.inf
    for outer in range(1, 1 + rounds):
        before = state.value
        _optimise_z(state, gn_iterations, tolerance, outer, callback, should_cancel,
                    part=stages + outer)
        _check_cancel(should_cancel)
        _optimise_material(state, outer, callback)
        _check_cancel(should_cancel)
        if state.S.shape[0] > state.S.shape[1]:     # square S could only mix the modes
            _optimise_sampling(state, sampling_iterations, outer, callback)
        change = (before - state.value) / max(state.value, 1e-300)
        rounds_done = change <= round_tolerance
        if rounds_done:
            break
    _check_cancel(should_cancel)
    z_done = _optimise_z(state, None, tolerance, rounds + 1, callback, should_cancel,
                         part=stages + rounds + 1)
    reasons = out_of_reach + ([] if rounds_done else
               [f"the material still lowered the objective by {change:.1e} (relative) in "
                f"round {rounds} of {rounds}: allow more iterations"])
    if not z_done:
        reasons.append("the motion for the final material did not converge in "
                       f"{_step_limit(state, None)} Gauss-Newton steps")
    return _result(state, rounds_done and z_done and not out_of_reach, "; ".join(reasons) or
                   f"converged in {outer} material rounds")


def _warm_start(state, iterations, tolerance, callback, should_cancel):
    """Penalty continuation for stiff handles (module doc); kept only if it lowers J.

    Stages gamma_k = gamma (WARM_TIGHTNESS / t) WARM_FACTOR^k below gamma, t the problem's
    equivalent tightness (``handle_tightness``); each is solved by GN from the previous one.
    A stage that forced the body without closing in on the targets ends the continuation
    (module doc, "Out of reach"). Returns the ``_Reach`` (None without handles).
    """
    problem = state.problem
    gammas = _stage_gammas(problem)
    if gammas is None:
        return None
    Z, reach = state.Z, None
    for stage, gamma in enumerate(gammas):
        staged = _State(replace(problem, gamma=gamma), Z.copy(), state.mu)
        staged.progress = state.progress
        _optimise_z(staged, iterations, max(tolerance, WARM_TOLERANCE), None, None,
                    should_cancel, part=stage)
        state.iterations += staged.iterations
        reach = _Reach(staged) if reach is None else reach.judge(staged)
        if reach.stalled:
            break
        Z = staged.Z
    value = state.evaluate(Z=Z)
    if Z is not state.Z and value < state.value:
        state.Z, state.value = Z, value
        state.record(0, "warm", callback)
    return reach


def _stage_gammas(problem):
    """The handle weights of the continuation's stages (``_warm_start``), below gamma; None
    without handles."""
    if not _has(problem.handles) or problem.gamma <= 0.0:
        return None
    gamma, gammas = problem.gamma * WARM_TIGHTNESS / handle_tightness(problem), []
    while gamma < problem.gamma:
        gammas.append(gamma)
        gamma *= WARM_FACTOR
    return gammas


class _Reach:
    """The last continuation stage that held the handles (module doc, "Out of reach").

    Holds that stage's gamma, Z, largest miss [m] and control energy E_f; ``judge`` compares
    a stage solved at a higher gamma with it, ``give_up`` ends the solve there.
    """

    def __init__(self, staged):
        self.gamma, self.Z = staged.problem.gamma, staged.Z.copy()
        self.miss = _largest_miss(staged.problem, staged.Z, staged.S)
        self.energy = _stage_energy(staged)
        self.stalled = False

    def judge(self, staged):
        """The reach after ``staged`` (solved at a higher gamma): moved on to it if it closed in
        on the targets, kept if it did not but cost little, stalled if it forced the body."""
        miss = _largest_miss(staged.problem, staged.Z, staged.S)
        met = HANDLE_MET * _handle_extent(staged.problem.handles)
        if self.miss <= met or miss * np.sqrt(staged.problem.gamma / self.gamma) <= self.miss:
            return _Reach(staged)
        self.stalled = _stage_energy(staged) > REACH_FORCING * self.energy
        return self

    def give_up(self, state, callback):
        """Set state to the held stage (handles at its gamma); the not-converged result.

        J is now that of the softer gamma, so the history restarts at this entry ("reach").
        """
        state.problem = replace(state.problem, gamma=self.gamma)
        state.Z = self.Z.copy()
        state.value = state.evaluate()
        state.history = []
        state.record(0, "reach", callback)
        extent = _handle_extent(state.problem.handles)
        return _result(state, False,
                       f"the handles ask for a shape the {state.problem.num_modes} modes make "
                       f"only by forcing the body: they stay up to {self.miss:.2g} m "
                       f"({self.miss / extent:.1e} of their extent) from their targets; "
                       "raise Modes and Prepare again, or move the targets")


def _stage_energy(staged):
    """Control energy E_f of a state's Z (its eigenvalues, damping and external forces)."""
    problem = staged.problem
    return control_energy(staged.Z, staged.eigenvalues, staged.damping, problem.h,
                          problem.scheme, problem.external_forces)


def _handle_extent(handles):
    """Largest coordinate span of the handles' rest points and targets [m] (> 0)."""
    points = np.vstack([handles.rest, handles.targets])
    return max(float(np.ptp(points, axis=0).max()), 1e-300)


def _largest_miss(problem, Z, S):
    """Largest handle miss |position - target| over the handles [m]."""
    return float(np.linalg.norm(handle_misses(problem, Z, S), axis=1).max())


def _meet_handles(state, iterations, tolerance, should_cancel):
    """Method of multipliers (augmented Lagrangian in penalty form) on the handles.

    A penalty solve leaves each handle short of its target by about its force / gamma; on a
    rigged body, whose loads push back, that was up to 1e-3 of the diagonal, and GN creeps
    along the stiff valley a larger gamma makes. Each round moves every handle's target by
    minus its current miss (targets t + s, s <- s - miss: the multiplier lambda = -gamma w s)
    and solves Z again by GN from the current Z, at the same gamma. A round is kept only if it
    brings the largest miss down; the rounds stop at HANDLE_ROUNDS or once every handle is
    within HANDLE_TOLERANCE of the handles' extent. state.Z and state.value (J of the original
    problem) are updated; the history is not (J is not what the rounds lower). Returns the
    largest miss over the handles' extent (a float), or None without handles.
    """
    problem = state.problem
    if not _has(problem.handles) or problem.gamma <= 0.0:
        return None
    handles = problem.handles
    extent = _handle_extent(handles)
    goal = HANDLE_TOLERANCE * extent
    misses = handle_misses(problem, state.Z, state.S)
    shift = np.zeros_like(handles.targets)
    for _ in range(HANDLE_ROUNDS):
        worst = np.abs(misses).max()
        if worst <= goal:
            break
        shift = shift - misses
        moved = HandleConstraints(handles.frames, handles.rows, handles.rest,
                                  handles.targets + shift, handles.weights)
        shifted = _State(replace(problem, handles=moved), state.Z.copy(), state.mu)
        _optimise_z(shifted, iterations, tolerance, None, None, should_cancel)
        state.iterations += shifted.iterations
        trial = handle_misses(problem, shifted.Z, state.S)
        if np.abs(trial).max() >= worst:
            break
        state.Z, misses = shifted.Z, trial
    state.value = state.evaluate()
    return float(np.abs(misses).max()) / extent


def handle_tightness(problem):
    """gamma mean(sigma^2) / dynamics_scale: how much the handles outweigh a frame's dynamics.

    sigma: largest singular value of each handle's rows dq/dzhat(0) S (see ``suggest_weights``).
    """
    sigma2 = _handle_curvature(problem.deformer, problem.handles.rows, problem.sampling)
    return problem.gamma * float(np.mean(problem.handles.weights * sigma2)) / dynamics_scale(
        problem.h, problem.eigenvalues, problem.damping, problem.scheme)


def _handle_curvature(deformer, rows, S):
    """(c,) sigma^2: squared largest singular value of rows (c, 3, rB) dq/dzhat(0) S (m, r)."""
    dq = np.asarray(deformer.q_jacobian(np.zeros(deformer.num_coords)))      # (rB, m)
    return np.linalg.norm(np.asarray(rows) @ (dq @ S), ord=2, axis=(1, 2)) ** 2


def _choose_weights(state):
    """Automatic mu and rho from E_f after the first Z block (module doc).

    S and the material have not moved yet, so mu E_s(S0) is one constant for every entry so
    far (0 for the default [I; 0]) and rho E_m is 0: adding them keeps the history one function
    of the unknowns.
    """
    problem = state.problem
    e_f = control_energy(state.Z, state.eigenvalues, state.damping, problem.h, problem.scheme,
        problem.external_forces)
    per_mode = e_f / problem.num_modes
    if problem.mu is None:
        state.mu = MU_RELATIVE * per_mode if e_f > 0.0 else 1.0
    state.rho = (float(problem.material_weight) if problem.material_weight is not None
                 else MATERIAL_PULL * per_mode if e_f > 0.0 else 1.0)
    shift = state.evaluate() - state.value
    state.history = [(i, block, value + shift) for i, block, value in state.history]
    state.value += shift


def _result(state, converged, reason):
    problem = state.problem
    keys = problem.keyframes
    key_res = (np.linalg.norm(state.Z[keys.frames] @ state.S.T - keys.poses, axis=1)
               if _has(keys) else np.zeros(0))
    return SpaceTimeResult(
        Z=state.Z, eigenvalues=state.eigenvalues, damping=state.damping, sampling=state.S,
        objective=state.value,
        control_energy=control_energy(state.Z, state.eigenvalues, state.damping, problem.h,
                                      problem.scheme,
        problem.external_forces),
        handle_residuals=handle_residuals(problem, state.Z, state.S),
        keyframe_residuals=key_res, history=state.history, iterations=state.iterations,
        converged=bool(converged), mu=state.mu, scheme=problem.scheme, reason=reason,
        material_weight=state.rho)


# ---------------------------------------------------------------------------------------------
# Helpers for callers

def pose_to_modal(modal_rs, volumes, y):
    """Deformer input zhat = argmin |V^(1/2) (QW z - y)| of RS coordinates.

    modal_rs (E, 9, m) = ``rs.linear_rs(Q, W)``; volumes (E,) [m^3]; y (E, 9) one pose or
    (K, E, 9) several (e.g. from ``rs.pose_to_rs``). Returns (m,) or (K, m).
    """
    modal_rs = np.asarray(modal_rs, dtype=np.float64)
    E, _, m = modal_rs.shape
    root = np.sqrt(np.asarray(volumes, dtype=np.float64))
    A = (root[:, None, None] * modal_rs).reshape(9 * E, m)
    y = np.asarray(y, dtype=np.float64)
    B = (root[:, None] * y.reshape(-1, E, 9)).reshape(-1, 9 * E).T           # (9E, K)
    z = np.linalg.lstsq(A, B, rcond=None)[0].T                              # (K, m)
    return z[0] if y.ndim == 2 else z


def handle_geometry(rest_positions, basis, indices):
    """A handle on vertices ``indices``: rows (3, rB) = mean of their basis rows, rest (3,).

    rest_positions (N, 3) [m]; basis (3N, rB) node-major (B, or Phi B for render vertices).
    """
    idx = np.asarray(indices, dtype=np.int64).reshape(-1)
    rows = np.asarray(basis).reshape(len(rest_positions), 3, -1)[idx].mean(axis=0)
    return rows, np.asarray(rest_positions, dtype=np.float64)[idx].mean(axis=0)


def rayleigh_damping(eigenvalues, alpha_mass, alpha_stiffness):
    """(r,) modal damping D = alpha_m + alpha_k lambda_k [1/s]."""
    return alpha_mass + alpha_stiffness * np.asarray(eigenvalues, dtype=np.float64)


def dynamics_scale(h, eigenvalues, damping, scheme="auto"):
    """Largest diagonal entry of the E_f Hessian, max_k a_k^2 + b_k^2 + c_k^2 [1/s^4]."""
    scheme = resolve_scheme(scheme, h, eigenvalues)
    return float(np.max(np.sum(stencil(eigenvalues, damping, h, scheme) ** 2, axis=0)))


def suggest_weights(h, eigenvalues, damping, deformer=None, handle_rows=None, sampling=None,
                    tightness=TIGHTNESS, scheme="auto"):
    """(gamma, keyframe_weight) so constraints outweigh one frame's dynamics by ``tightness``.

    A frame's E_f curvature is at most ``dynamics_scale``; a handle's at rest is gamma sigma^2,
    sigma the mean largest singular value of rows (c, 3, rB) dq/dzhat(0) S; a keyframe's is w
    (unit columns of S). A constraint then misses by about its unconstrained miss / tightness
    (less, since motion spreads over neighbouring frames).
    """
    scale = tightness * dynamics_scale(h, eigenvalues, damping, scheme)
    if deformer is None or handle_rows is None or len(handle_rows) == 0:
        return scale, scale
    r = len(np.atleast_1d(eigenvalues))
    S = np.eye(deformer.num_coords, r) if sampling is None else np.asarray(sampling)
    return scale / float(np.mean(_handle_curvature(deformer, handle_rows, S))), scale
