"""Keeping reduced RS bodies from inverting: a volume barrier on the RS strain.

In RS coordinates each tet's deformation gradient is F_e = R_e S_e with the stretch
S_e = I + eps_e, and eps_e(s) = U_e s is *linear* in the modal coordinates s (m,) (U_e (6, m)
the strain rows of ``rs.linear_rs``). So the volume ratio of the RS target,

    J_e(s) = det(I + eps_e(s)) = det F_e,

is a cubic polynomial in s that costs one (6E, m) product and a closed-form 3x3 determinant
per tet: cheap enough to evaluate over ALL tets at every Newton iteration. None of the three
materials stops J_e from reaching 0: Linear's psi = mu |eps|^2 + lam/2 tr(eps)^2 is finite at
eps = -I, and StVK on the Cauchy strain even softens in compression (its energy falls again
past S = I / sqrt(3)); Fung is StVK plus an exponential of StVK, with the same soft branch.
So a soft pinned column falling over under its own weight inverts (measured in
tests/solver/test_inversion.py: all three materials at E = 2e4 Pa, StVK at 2e5 Pa).

Method (choice and why): an IPC-style C2 log barrier (Li et al. 2020, "Incremental Potential
Contact") on the volume ratio, added to the elastic potential,

    V_b(s) = kappa sum_e V_e b(J_e(s)),
    b(J) = -(J - J_hat)^2 ln(J / J_hat)  for 0 < J < J_hat,   0 for J >= J_hat,   +inf for J <= 0,

and +inf too where S_e is not positive definite (``stretch_determinants``).

- b, b' and b'' all vanish at J_hat, so the barrier is C2 and exactly zero on every tet whose
  volume ratio is at least J_hat: the rest Hessian (small-strain stiffness, Rayleigh damping,
  automatic substeps) and every simulation that never compresses that far are unchanged.
- b -> +inf as J -> 0+: the integrator's line search rejects non-finite objectives, so no
  accepted Newton iterate has an inverted (or flat) RS stretch, and since the feasible set
  (positive-definite S_e for all e) is convex in s, no accepted step crosses J = 0 either.
- Unlike an inversion-safe rewrite of each material (e.g. Stomakhin et al. 2012's extended
  invariants, or Neo-Hookean's -mu ln J), this leaves Linear, StVK and Fung exactly as they
  are wherever they behave and works on the reduced coordinates of all three alike; unlike a
  penalty it is a true barrier. It applies to Linear too: the issue's column inverts under
  Linear as well, because the RS linear material has no volume term that grows at J -> 0.
- Tets are summed exactly (w_e = 1), not by the energy cubature: a cubature fits the energy
  of training poses and says nothing about one tet collapsing elsewhere.

Units and constants: b is dimensionless; kappa [Pa] = BARRIER_SCALE * K with K = lam + 2 mu / 3
the material's small-strain bulk modulus, so kappa V_e b [J] is a volumetric energy that scales
with the material (psi ~ K/2 (J - 1)^2 near rest) whatever E and nu. Measured on a pinned
1 x 0.1 x 0.1 m column (nu = 0.3, 8 modes, the default reduced model; tests/solver/
test_inversion.py) falling over under its own weight, 4 s at 24 fps:

- J_HAT = 0.6: the barrier acts once a tet's RS volume has lost 40 %. Ordinary motion, even
  large, stays above that, and there the barrier is exactly zero, so results are unchanged:
  a keyed 4 m prop swinging 2.5 m sideways (tests/blender/test_simulate.py) reaches RS J of
  about 0.63; with J_hat = 0.8 the barrier stiffened that swing and the test failed on some
  of its (run-to-run varying) tet meshes; at 0.6 it passed in six runs. Lower is worse: with
  J_hat = 0.5 the column's Fung run loses 5.3 % of its volume at E = 2e5, and weaker
  barriers let it invert (below).
- BARRIER_SCALE = 100: with J_hat = 0.6, kappa = 100 K kept RS J >= 0.24 and det F of the
  reconstruction >= 0.15 for all three materials at E = 2e4 and 2e5 Pa (volume within 4.3 %
  of rest at 2e5); kappa = 10 K (J_hat = 0.5) let the collapse at E = 2e4 drive tets to
  det F < 0. Near J_hat the barrier starts gently (b ~ (J_hat - J)^3 / J_hat), at J = 0.3 it
  stores 100 K * 0.062 = 6 K per unit volume, 25 times the linear material's volumetric
  energy there: deep compression becomes nearly incompressible.

The barrier controls the RS target; the reduced reconstruction x = X + B q(s) only follows it
approximately. With a coarse reduced model (basis 40, 80 cubature tets) the column still
inverted in some runs with J_hat = 0.5 - 0.6 and kappa up to 1e4 K (det F down to -0.19), and
its smallest det F was up to ~0.3 below its smallest RS volume (e.g. 0.07 against 0.34). That
is what the inversion check of ``dynamics.Simulation`` (``tets``) is for: retry, then a clear
error.

Derivatives in the six strain components e_k (eps = sum_k e_k B_k, ``rs.STRAIN_BASIS``):
dJ/de_k = <cof S, B_k>, d^2 J/de_k de_l = sum eps_ijk eps_lmn (B_k)_il (B_l)_jm S_kn (linear in
S, Levi-Civita eps). Per active tet the 6x6 Hessian b'' dJ dJ^T + b' d^2J is projected to
positive semidefinite (eigenvalues clamped at 0) as in IPC, so Newton's system stays SPD;
``project=False`` gives the exact Hessian. At an infeasible s (some J <= 0; only the
integrator's predictor s_n + dt v_s can be there) the value is +inf and the derivatives
continue b quadratically from J_FLOOR, so a Newton step from such a guess still points back
to J > 0. If none of the line search's points is feasible the step ends infeasible, with an
infinite energy: ``dynamics.Simulation`` given ``tets`` detects that and retakes the step in
halves (a shorter predictor stays feasible).
"""

import numpy as np

from . import materials, rs

J_HAT = 0.6          # volume ratio below which the barrier acts (module docstring)
BARRIER_SCALE = 100.0   # kappa / K, K the material's small-strain bulk modulus
J_FLOOR = 1e-3       # relative to J_HAT: derivatives at J <= 0 continue b from J_FLOOR J_HAT

def _levi_civita():
    eps = np.zeros((3, 3, 3))
    for i, j, k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        eps[i, j, k], eps[i, k, j] = 1.0, -1.0
    return eps


# (9, 36): vec(S) -> [d^2 det / de_k de_l]_kl, the Hessian of det is linear in S.
_DET_HESSIAN = np.einsum("pil,qjm,ijk,lmn->knpq", rs.STRAIN_BASIS, rs.STRAIN_BASIS,
                         _levi_civita(), _levi_civita()).reshape(9, 36)


def stretch_determinants(strain, order=1):
    """J (E,), dJ/de (E, 6) and d^2J/de^2 (E, 6, 6) of S = I + eps for strains (E, 6).

    Components [xx, xy, xz, yy, yz, zz] as in ``rs``; derivatives None below ``order``.
    J is replaced by min(J, 0) where S is not positive definite: a symmetric S with J > 0 may
    still have two negative eigenvalues, a stretch no continuous motion from rest reaches
    without passing J = 0. So {J > 0} here is the positive-definite cone, which is convex in
    eps and therefore in s: a line search whose end points are feasible never crosses J = 0
    in between (no step can tunnel through the barrier).
    """
    strain = np.asarray(strain, dtype=np.float64)
    a, b, c = 1.0 + strain[:, 0], strain[:, 1], strain[:, 2]
    d, e, f = 1.0 + strain[:, 3], strain[:, 4], 1.0 + strain[:, 5]
    # Cofactors of S = [[a, b, c], [b, d, e], [c, e, f]] (symmetric).
    c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
    J = a * c00 + b * c01 + c * c02
    # Sylvester: S is positive definite iff its leading minors a, ad - b^2 and J are positive.
    J = np.where((a > 0.0) & (a * d - b * b > 0.0), J, np.minimum(J, 0.0))
    if order < 1:
        return J, None, None
    grad = np.stack([c00, 2.0 * c01, 2.0 * c02, a * f - c * c, 2.0 * (b * c - a * e),
                     a * d - b * b], axis=1)                  # <cof S, B_k>
    if order < 2:
        return J, grad, None
    S9 = np.stack([a, b, c, b, d, e, c, e, f], axis=1)
    return J, grad, (S9 @ _DET_HESSIAN).reshape(-1, 6, 6)


def barrier_function(J, j_hat=J_HAT):
    """b(J), b'(J), b''(J) (each shaped like J), dimensionless (module docstring).

    Exact for J > 0; for J <= 0, b = +inf while b' and b'' continue b quadratically from
    J_FLOOR * j_hat (a finite, descending model for a Newton step from an infeasible guess).
    """
    J = np.asarray(J, dtype=np.float64)
    floor = J_FLOOR * j_hat
    x = np.where(J > 0.0, J, floor)
    d, log = x - j_hat, np.log(x / j_hat)
    active = J < j_hat
    value = np.where(active, -d * d * log, 0.0)
    first = np.where(active, -2.0 * d * log - d * d / x, 0.0)
    second = np.where(active, -2.0 * log - 4.0 * d / x + d * d / (x * x), 0.0)
    infeasible = J <= 0.0
    first = np.where(infeasible, first + second * (J - floor), first)
    value = np.where(infeasible, np.inf, value)
    return value, first, second


def bulk_modulus(material):
    """Small-strain bulk modulus K = lam + 2 mu / 3 [Pa] of a ``materials`` material: a number,
    or (E,) per tet for a painted body (each tet's barrier then scales with its own material)."""
    mu, lam = material.small_strain_lame
    return lam + 2.0 * mu / 3.0


class VolumeBarrier:
    """V_b(s) = kappa sum_e V_e b(det(I + U_e s)) [J] over all tets (module docstring).

    strain_modes U (E, 6, m): strain per unit s of every tet (rows 3:9 of ``rs.linear_rs``);
    volumes (E,) [m^3]; stiffness kappa [Pa], a number or (E,) per tet; j_hat in (0, 1): the
    volume ratio below which it acts. Build with ``for_material`` to get kappa = BARRIER_SCALE *
    the material's bulk modulus. ``evaluate`` computes the strains of only the tets its
    ``StrainScreen`` cannot clear (the others are exactly zero), so a step near rest or moving
    little from the last all-tet evaluation costs O(E / SCREEN_BLOCK) instead of O(E).
    """

    def __init__(self, strain_modes, volumes, stiffness, j_hat=J_HAT):
        if not 0.0 < j_hat < 1.0:
            raise ValueError(f"j_hat must lie in (0, 1), got {j_hat!r}")
        stiffness = _positive_stiffness(stiffness)
        self.strain_modes = np.ascontiguousarray(strain_modes, dtype=np.float64)
        self.num_coords = self.strain_modes.shape[2]
        self._flat = self.strain_modes.reshape(-1, self.num_coords)              # (6E, m)
        self.weights = stiffness * np.abs(np.asarray(volumes, dtype=np.float64))
        self.stiffness, self.j_hat = stiffness, float(j_hat)
        self._screen = StrainScreen(self.strain_modes, self.j_hat)

    @classmethod
    def for_material(cls, material, modal_rs, volumes, j_hat=J_HAT):
        """Barrier of all E tets: modal_rs (E, 9, m) from ``rs.linear_rs``, volumes (E,)."""
        return cls(np.asarray(modal_rs)[:, 3:, :], volumes,
                   BARRIER_SCALE * bulk_modulus(material), j_hat)

    def volume_ratios(self, s):
        """(E,) J_e = det(I + eps_e(s)) of every tet's RS stretch at s (m,)."""
        strain = (self._flat @ np.asarray(s, dtype=np.float64)).reshape(-1, 6)
        return stretch_determinants(strain, 0)[0]

    def evaluate(self, s, order=2, project=True):
        """V_b [J], grad (m,), Hessian (m, m) at s (m,) (None below ``order``).

        Only tets with J_e < j_hat contribute (the rest is exactly zero). project: clamp each
        active tet's 6x6 Hessian to positive semidefinite (False: the exact Hessian).
        """
        m, s = self.num_coords, np.asarray(s, dtype=np.float64)
        near = self._screen.candidates(s)          # the other tets are surely inactive
        if near is not None and len(near) == 0:    # every tet cleared: the common case
            return 0.0, (np.zeros(m) if order >= 1 else None), (
                np.zeros((m, m)) if order >= 2 else None)
        if near is None:                           # all tets, and a new reference
            strain = (self._flat @ s).reshape(-1, 6)
            J = stretch_determinants(strain, 0)[0]
            self._screen.refresh(s, strain, J)
            near = np.arange(len(J))
        else:
            strain = (self.strain_modes[near].reshape(-1, m) @ s).reshape(-1, 6)
            J = stretch_determinants(strain, 0)[0]
        active = near[J < self.j_hat]
        strain = strain[J < self.j_hat]
        grad = np.zeros(m) if order >= 1 else None
        hess = np.zeros((m, m)) if order >= 2 else None
        if len(active) == 0:
            return 0.0, grad, hess
        J, dJ, d2J = stretch_determinants(strain, order)
        b, db, d2b = barrier_function(J, self.j_hat)
        w = self.weights[active]
        value = float(w @ b)
        if order < 1:
            return value, None, None
        U = self.strain_modes[active]                                          # (A, 6, m)
        grad = np.einsum("ak,akm->m", (w * db)[:, None] * dJ, U)
        if order < 2:
            return value, grad, None
        H = d2b[:, None, None] * dJ[:, :, None] * dJ[:, None, :] + db[:, None, None] * d2J
        if project:
            H = _clamp_psd(H)
        HU = (w[:, None, None] * H) @ U
        hess = U.reshape(-1, m).T @ HU.reshape(-1, m)
        return value, grad, 0.5 * (hess + hess.T)


# |eps|_F^2 = sum_k FROBENIUS_WEIGHTS_k e_k^2 for strain components [xx, xy, xz, yy, yz, zz].
FROBENIUS_WEIGHTS = np.array([1.0, 2.0, 2.0, 1.0, 2.0, 1.0])
SCREEN_BLOCK = 64        # tets per block of ``StrainScreen``
SCREEN_REFRESH = 0.125   # share of the tets past which the screen takes a new reference


class StrainScreen:
    """The tets whose RS stretch J_e = det(I + U_e s) may be below j at s (m,), found from a
    reference pose s_ref at which every tet's strain and J are known, in O(E / SCREEN_BLOCK m)
    per call instead of the O(E m) of all strains.

    Bound: |eps_e(s) - eps_e(s_ref)|_F <= sum_k |s_k - s_ref,k| c_ek with c_ek =
    |eps(U_e[:, k])|_F (one unit of mode k), and for 3x3 S, |D|_F <= r:
    det(S + D) >= det S - r |cof S|_F - r^2 |S|_F - r^3 / sqrt(27) (expanding det by columns),
    so J_e stays >= j (and S positive definite, det never crossing 0 along the segment) while
    the change is below the margin r_e that keeps each term under a third of J_e,ref - j.
    Tets are screened in fixed blocks of SCREEN_BLOCK (bound: the block's largest c_ek per
    mode, its smallest margin). When the candidates pass SCREEN_REFRESH of all tets, the
    caller evaluates them all and ``refresh`` makes that pose the new reference.
    """

    def __init__(self, strain_modes, j):
        unit = np.sqrt(np.einsum("k,ekm->em", FROBENIUS_WEIGHTS, strain_modes ** 2))  # (E, m)
        self.num_tets, self.j = len(unit), float(j)
        self.starts = np.arange(0, self.num_tets, SCREEN_BLOCK)
        self.block_bounds = (np.maximum.reduceat(unit, self.starts, axis=0) if self.num_tets
                             else np.zeros((0, unit.shape[1])))                  # (blocks, m)
        self.reference = None
        self.block_margins = None

    def refresh(self, s, strain, J):
        """Make s (m,) the reference, with every tet's strain (E, 6) and J (E,) there."""
        a, b, c = 1.0 + strain[:, 0], strain[:, 1], strain[:, 2]
        d, e, f = 1.0 + strain[:, 3], strain[:, 4], 1.0 + strain[:, 5]
        cof2 = ((d * f - e * e) ** 2 + (a * f - c * c) ** 2 + (a * d - b * b) ** 2
                + 2.0 * ((c * e - b * f) ** 2 + (b * e - c * d) ** 2 + (b * c - a * e) ** 2))
        S2 = a * a + d * d + f * f + 2.0 * (b * b + c * c + e * e)           # |S|_F^2
        margin = _cubic_margin(J - self.j - 1e-12 * np.maximum(1.0, np.abs(J)),
                               np.sqrt(cof2), np.sqrt(S2), 1.0 / np.sqrt(27.0))
        self.block_margins = np.minimum.reduceat(margin, self.starts) * (1.0 - 1e-9)
        self.reference = np.array(s, dtype=np.float64)

    def candidates(self, s):
        """Sorted indices of the tets whose J may be below j at s (m,); None when they pass
        SCREEN_REFRESH of all tets, or there is no reference yet (evaluate all, ``refresh``)."""
        if self.reference is None:
            return None
        reach = self.block_bounds @ np.abs(s - self.reference)
        blocks = np.flatnonzero(reach >= self.block_margins)
        if len(blocks) * SCREEN_BLOCK > SCREEN_REFRESH * self.num_tets:
            return None
        rows = (blocks[:, None] * SCREEN_BLOCK + np.arange(SCREEN_BLOCK)).reshape(-1)
        return rows[rows < self.num_tets]


def _cubic_margin(slack, a, b, c, newton_steps=4):
    """(E,) a largest-known r >= 0 with a r + b r^2 + c r^3 <= slack (a, b, c > 0), -1 where
    slack <= 0. Safe start: each term at most slack / 3; then Newton from slack / a, which
    is above the root and descends to it on this convex function, kept where it checks."""
    with np.errstate(invalid="ignore", divide="ignore"):
        room = np.maximum(slack, 0.0)
        safe = np.minimum.reduce([room / (3.0 * a), np.sqrt(room / (3.0 * b)),
                                  np.cbrt(room / (3.0 * c))])
        r = room / a
        for _ in range(newton_steps):
            r = r - (r * (a + r * (b + r * c)) - room) / (a + r * (2.0 * b + 3.0 * c * r))
        r = r * (1.0 - 1e-9)
        r = np.where(r * (a + r * (b + r * c)) <= room, np.maximum(r, safe), safe)
    return np.where(slack > 0.0, np.nan_to_num(r, nan=-1.0), -1.0)


def _positive_stiffness(stiffness):
    """kappa as a float, or a float64 (E,) array per tet; ValueError unless every value is > 0."""
    values = np.asarray(stiffness, dtype=np.float64)
    if not np.all(values > 0.0):
        raise ValueError(f"barrier stiffness must be positive, got {stiffness!r}")
    return float(values) if values.ndim == 0 else values


def _clamp_psd(H):
    """(A, 6, 6) symmetric matrices with negative eigenvalues set to 0."""
    values, vectors = np.linalg.eigh(0.5 * (H + np.swapaxes(H, 1, 2)))
    return (vectors * np.maximum(values, 0.0)[:, None, :]) @ np.swapaxes(vectors, 1, 2)


class BarrierPotential(materials.PotentialAccessors):
    """A reduced elastic potential plus a ``VolumeBarrier``, with the interface ``dynamics``
    uses from ``materials.ReducedPotential``: evaluate(s, order), energy / gradient / hessian,
    rest_hessian, num_coords; other attributes (material, tets, strain_modes, weights, ...)
    are the wrapped potential's. The barrier vanishes near rest, so ``rest_hessian`` (and with
    it Rayleigh damping and automatic substeps) is the wrapped potential's; the sum is never
    quadratic (``is_quadratic`` False)."""

    is_quadratic = False

    def __init__(self, potential, barrier):
        if barrier.num_coords != potential.num_coords:
            raise ValueError("the barrier and the potential have different modal coordinates")
        self.potential, self.barrier = potential, barrier
        self.num_coords = potential.num_coords
        self.rest_hessian = potential.rest_hessian

    def __getattr__(self, name):            # only called for attributes not found above
        if name in ("potential", "barrier"):
            raise AttributeError(name)
        return getattr(self.potential, name)

    def watch_volumes(self, ratios, keep=False):
        """Pass every tet's det F (E,) at the step's start to the reconstruction barriers
        (``ReconstructionBarrier.watch``), here and in the wrapped potentials."""
        if hasattr(self.barrier, "watch"):
            self.barrier.watch(ratios, keep)
        inner = getattr(self.potential, "watch_volumes", None)
        if inner is not None:
            inner(ratios, keep)

    def evaluate(self, s, order=2):
        """V + V_b [J], grad (m,), Hessian (m, m) (barrier Hessian PSD-projected)."""
        energy, grad, hess = self.potential.evaluate(s, order)
        b_energy, b_grad, b_hess = self.barrier.evaluate(s, order)
        return (energy + b_energy, None if grad is None else grad + b_grad,
                None if hess is None else hess + b_hess)


def with_barrier(potential, modal_rs, volumes, j_hat=J_HAT):
    """``potential`` (a ``materials.ReducedPotential``) plus the volume barrier of all tets.

    modal_rs (E, 9, m) from ``rs.linear_rs`` and volumes (E,) [m^3] of the full mesh (the
    potential itself may hold only cubature tets); kappa = BARRIER_SCALE * its bulk modulus.
    """
    return BarrierPotential(potential, VolumeBarrier.for_material(potential.material, modal_rs,
                                                                  volumes, j_hat))


FLAT_J = 1e-3                 # det F at or below this counts as flat or inverted (the step
                              # check's bound, ``dynamics.MIN_VOLUME_RATIO``)
RECONSTRUCTION_WALL = 2e-3    # det F where the reconstruction barrier is infinite: above FLAT_J
                              # by far more than the float32 check's rounding (1e-5)
RECONSTRUCTION_J_HAT = 0.25   # det F of the reconstruction below which its barrier acts
WATCH_J = 0.6                 # tets at or below this det F at a step's start are watched


class ReconstructionBarrier:
    """V_r(s) = kappa sum_e V_e b(det F_e(s)) [J]: the barrier ``b`` on the volume ratio of
    the *reconstruction* x = X + B q(s), the positions the user sees, over the watched tets.

    Why a second barrier: ``VolumeBarrier`` keeps the RS stretch of every tet positive, but
    the reduced reconstruction only approximates its RS target (module docstring), so a few
    tets of it can still turn over, e.g. under a contact that stops part of a soft body, or in
    a coarse reduced model (tests/solver/test_inversion.py: a Linear column with a 40-column
    basis inverted at frame 51 and the step check gave up; with this barrier its smallest
    det F stays at 0.03). With it, the line search of every implicit step rejects a
    reconstruction that turns a tet inside out, as it rejects one inside a collider. det F is
    invariant under the body's frame, so body-frame positions suffice. j_hat 0.25
    (RECONSTRUCTION_J_HAT): below what ordinary motion reaches, so results elsewhere are
    unchanged (the barrier is exactly zero above j_hat).

    Watched tets: evaluating det F of every tet at every Newton iterate would cost a (3N, rB)
    product each time (a 32k-tet rig shot took 2.6 times as long). ``dynamics.Simulation``
    already computes every tet's det F once per step for its inversion check, and hands them
    to ``watch``: the tets at or below WATCH_J then carry the barrier during the next step
    (a tet above 0.6 at a step's start that reaches 0 within it is caught by the check, which
    adds it to the watch and retakes the step in halves). Nothing is watched until then.

    Its wall is at det F = RECONSTRUCTION_WALL, not 0: the barrier is b(J - wall) with
    j_hat - wall for j_hat, so what it admits the step check (``dynamics``, which counts
    det F <= FLAT_J as flat, in float32) passes. With its wall at 0, a tet pressed against it
    ended between 0 and FLAT_J, and the check undid the step down to its shortest retake and
    stopped the simulation (the shared cow, pinned at its feet at E = 5e4 Pa under gravity,
    at frame 18); with its wall at FLAT_J itself, the check's rounding counted a tet held at
    1.00001e-3 as 0.000999 (the soft column at E = 1e4 Pa).

    deformer: ``reduced.ReducedRS`` or ``LinearDeformer`` with its basis B (3N, rB);
    rest_positions X (N, 3) [m]; tets (E, 4); stiffness kappa [Pa] (a number or (E,)).
    Derivatives: the gradient is exact, sum_e w_e b'(J_e) dq/ds^T B_e^T dJ_e/dx_e; the Hessian
    is the Gauss-Newton part sum_e w_e b''(J_e) g_e g_e^T (g_e = dJ_e/ds; b'' > 0 below j_hat,
    so it is PSD), without b' d^2J/ds^2 (indefinite; the line search makes up for it).
    """

    def __init__(self, deformer, rest_positions, tets, stiffness, j_hat=RECONSTRUCTION_J_HAT):
        if not 0.0 < j_hat < 1.0:
            raise ValueError(f"j_hat must lie in (0, 1), got {j_hat!r}")
        self.deformer = deformer
        self.volumes = DeformedVolumes(rest_positions, tets, deformer.basis)
        self.num_coords = deformer.num_coords
        stiffness = _positive_stiffness(stiffness)
        self.weights = stiffness * np.abs(self.volumes.rest_determinants) / 6.0
        self.stiffness, self.j_hat = stiffness, float(j_hat)
        self._node_basis = self.volumes.basis.reshape(len(self.volumes.rest), 3, -1)
        self.watched = np.empty(0, dtype=np.int64)

    def watch(self, ratios, keep=False):
        """Watch the tets whose det F ``ratios`` (E,) are at or below WATCH_J (with ``keep``,
        in addition to those already watched)."""
        low = np.flatnonzero(np.asarray(ratios) <= WATCH_J)
        self.watched = np.union1d(self.watched, low) if keep else low

    def evaluate(self, s, order=2):
        """V_r [J], grad (m,), Hessian (m, m) at s (m,) over the watched tets (None below
        ``order``)."""
        m = self.num_coords
        grad = np.zeros(m) if order >= 1 else None
        hess = np.zeros((m, m)) if order >= 2 else None
        if len(self.watched) == 0:
            return 0.0, grad, hess
        q = self.deformer.q(s)
        tets = self.volumes.tets[self.watched]
        node_basis = self._node_basis[tets]                                     # (W, 4, 3, rB)
        x = self.volumes.rest[tets] + node_basis @ q                            # (W, 4, 3)
        e1, e2, e3 = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]
        rest = self.volumes.rest_determinants[self.watched]
        J = np.einsum("ei,ei->e", e1, np.cross(e2, e3)) / rest
        active = np.flatnonzero(J < self.j_hat)
        if len(active) == 0:
            return 0.0, grad, hess
        b, db, d2b = barrier_function(J[active] - RECONSTRUCTION_WALL,
                                      self.j_hat - RECONSTRUCTION_WALL)
        w = self.weights[self.watched[active]]
        value = float(w @ b)
        if order < 1:
            return value, None, None
        e1, e2, e3 = e1[active], e2[active], e3[active]
        cof = np.stack([np.cross(e2, e3), np.cross(e3, e1), np.cross(e1, e2)], axis=1)
        dJ_dx = np.concatenate([-cof.sum(axis=1, keepdims=True), cof], axis=1)    # (A, 4, 3)
        dJ_dx /= rest[active][:, None, None]
        dJ_dq = np.einsum("anc,ancr->ar", dJ_dx, node_basis[active])              # (A, rB)
        g = dJ_dq @ self.deformer.q_jacobian(s)                                   # (A, m)
        grad = g.T @ (w * db)
        if order < 2:
            return value, grad, None
        return value, grad, g.T @ ((w * d2b)[:, None] * g)


def with_reconstruction_barrier(potential, deformer, rest_positions, tets,
                                j_hat=RECONSTRUCTION_J_HAT):
    """``potential`` plus a ``ReconstructionBarrier`` of the full mesh (kappa = BARRIER_SCALE *
    the material's bulk modulus, as the RS volume barrier). Give the result to a
    ``dynamics.Simulation`` with the same ``tets``: its step check feeds the barrier's watch."""
    stiffness = BARRIER_SCALE * bulk_modulus(potential.material)
    return BarrierPotential(potential, ReconstructionBarrier(deformer, rest_positions, tets,
                                                             stiffness, j_hat))


class DeformedVolumes:
    """Volume ratios det F_e of every tet of the full reconstruction x = X + B q.

    rest_positions X (N, 3) [m]; tets (E, 4); basis B (3N, rB) [m per unit q]. det F is
    invariant under a rigid frame, so body-frame positions suffice. ``ratios(q)`` (E,) costs one
    (3N, rB) product and E 3x3 determinants, all vectorised: each tet's deformed edges are its
    rest edges plus differences of displacements, so no rounding of the absolute positions
    enters. dtype float32 halves the memory the product reads (the all-tet check after every
    step of ``dynamics.Simulation``): displacements then carry a relative error of about 1e-7
    of the largest, so a ratio is off by about 1e-7 times |u| / edge length (1e-5 for a 4 m
    swing of 6 cm tets), far inside the check's threshold.
    """

    def __init__(self, rest_positions, tets, basis, dtype=np.float64):
        self.rest = np.asarray(rest_positions, dtype=np.float64)
        self.tets = np.asarray(tets, dtype=np.int64).reshape(-1, 4)
        self.basis = np.asarray(basis, dtype=np.float64)
        self.dtype = np.dtype(dtype)
        if self.basis.shape[0] != self.rest.size or self.tets.max(initial=0) >= len(self.rest):
            raise ValueError("tets, rest positions and basis do not describe the same mesh")
        self.rest_determinants = _edge_determinants(self.rest, self.tets)       # (E,) 6 V_e
        if np.any(self.rest_determinants == 0.0):
            raise ValueError("the tet mesh has degenerate (zero-volume) tets")
        self._coordinate_basis = None       # B in ``dtype``, made by the first ``ratios``
        self._corners = np.ascontiguousarray(self.tets.T)                        # (4, E)
        # rest edges x_k - x_0 (3, 3, E): edge k's coordinate i in row [k, i]
        self._rest_edges = (self.rest[self.tets[:, 1:]] - self.rest[self.tets[:, :1]]
                            ).transpose(1, 2, 0).astype(self.dtype)

    @property
    def num_tets(self):
        return len(self.tets)

    def ratios(self, q):
        """(E,) det F_e = deformed / rest signed volume at reduced coordinates q (rB,)."""
        if self._coordinate_basis is None:
            # rows coordinate-major (3 N, rB), so B q is (3, N), one contiguous row per
            # coordinate for one np.take of every corner (several times faster than fancy
            # indexing of (N, 3) rows)
            self._coordinate_basis = np.ascontiguousarray(
                self.basis.reshape(len(self.rest), 3, -1).transpose(1, 0, 2),
                dtype=self.dtype).reshape(self.basis.shape)
        u = (self._coordinate_basis @ np.asarray(q, dtype=self.dtype)).reshape(3, -1)
        corners = np.take(u, self._corners, axis=1)          # (3, 4, E): [coordinate, corner]
        edges = self._rest_edges + (corners[:, 1:] - corners[:, :1]).transpose(1, 0, 2)
        return _column_determinants(*edges) / self.rest_determinants


def _edge_determinants(x, tets):
    """(E,) det [x_b - x_a, x_c - x_a, x_d - x_a] (6 times the signed volume)."""
    a = x[tets[:, 0]]
    return _column_determinants(*((x[tets[:, k]] - a).T for k in (1, 2, 3)))


def _column_determinants(e1, e2, e3):
    """(E,) det [e1, e2, e3] of E 3x3 matrices whose columns are given by coordinate, each
    (3, E) or a sequence of three (E,) arrays."""
    (x1, y1, z1), (x2, y2, z2), (x3, y3, z3) = e1, e2, e3
    return x1 * (y2 * z3 - z2 * y3) + y1 * (z2 * x3 - x2 * z3) + z1 * (x2 * y3 - y2 * x3)
