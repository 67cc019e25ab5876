"""Materials on the Cauchy strain and the reduced elastic potential V(s): SPEC.md section 6 [P15].

In RS coordinates the potential depends on the strain only: tet e carries the symmetric Cauchy
strain ``eps_e = S_e - I`` (the stretch of its polar decomposition), six numbers in the RS layout
order ``[xx, xy, xz, yy, yz, zz]`` (tensor components: the off-diagonal ones appear twice in the
3x3 matrix). A material maps an (E, 6) array of strains to energy densities psi (E,) [Pa = J/m^3],
their gradients d psi / d eps (E, 6) [Pa] and Hessians (E, 6, 6) [Pa]:

- ``Linear(mu, lam)``:  psi = mu |eps|^2 + lam/2 tr(eps)^2. With eps = sym grad u this is the
  linear-elastic energy density of ``fem``, so its reduced potential is exactly 1/2 s^T Lambda s.
- ``StVK(mu, lam)`` on the Cauchy strain: E_G = eps + eps^2 / 2 (the Green strain of S = I + eps),
  psi = mu tr(E_G^2) + lam/2 tr(E_G)^2. Equal to Linear to first order at small strain; stiffer in
  tension, softer in compression.
- ``Fung(mu1, lam1, mu2, lam2, c)``: psi = psi_StVK(mu1, lam1) + c (exp(psi_StVK(mu2, lam2)) - 1);
  mu1, lam1, c in Pa, mu2, lam2 dimensionless (they scale the exponent). Its small-strain
  stiffness is that of Linear(mu1 + c mu2, lam1 + c lam2); it stiffens exponentially.

Every parameter is a number, or one value per tet (a painted body, ``fem.painted_youngs``): an
(E,) array whose rows match the rows of the strains ``evaluate`` is given. ``at(tets)`` is the
same material on a subset (or repetition) of the tets; a ``ReducedPotential`` keeps the body's
material (every tet's parameters, which the volume barriers read) and evaluates its own tets'.

Reduced potential (``ReducedPotential``): with modal coordinates s (m,) the strain is linear,
``eps_e(s) = U_e s`` (U_e the strain rows (6, m) of the modal RS coordinates ``rs.linear_rs``), so

    V(s) = sum_e w_e V_e psi(U_e s),   grad V = sum_e w_e V_e U_e^T dpsi,
    hess V = sum_e w_e V_e U_e^T d2psi U_e,

summed over all tets (w_e = 1, exact) or over an energy cubature (a few tets with weights
w_e >= 0, ``train_energy_cubature``). Everything per evaluation is (C, 6, m) array code. For
``Linear`` the Hessian is constant and precomputed, so an evaluation is one m x m product.
"""

from dataclasses import dataclass, fields, replace

import numpy as np

from . import cubature, rs, threads

# (E, 6) strain -> (E, 3, 3) matrix: entry (i, j) of the symmetric matrix is component FULL[3i+j].
_FULL = np.array([0, 1, 2, 1, 3, 4, 2, 4, 5])
# How often each component appears in the 3x3 matrix: <B_k, B_l> = diag(_MULT).
_MULT = np.array([1.0, 2.0, 2.0, 1.0, 2.0, 1.0])
_TRACE = np.array([1.0, 0.0, 0.0, 1.0, 0.0, 1.0])       # tr(eps) = _TRACE . e
_BASIS = rs.STRAIN_BASIS                                 # (6, 3, 3) d eps / d e_k


def strain_matrices(strain):
    """(E, 3, 3) symmetric strain matrices of (E, 6) components [xx, xy, xz, yy, yz, zz]."""
    strain = np.asarray(strain, dtype=np.float64)
    return strain[..., _FULL].reshape(strain.shape[:-1] + (3, 3))


def _per_tet(value, trailing):
    """A parameter ready to scale per-tet arrays with ``trailing`` more axes: a number as it is,
    an (E,) array as (E, 1, ..., 1)."""
    return value if np.ndim(value) == 0 else np.reshape(value, (-1,) + (1,) * trailing)


def _linear_tensor(mu, lam):
    """C6 with psi = 1/2 e^T C6 e for mu |eps|^2 + lam/2 tr(eps)^2: (6, 6), or (E, 6, 6) for
    per-tet (E,) parameters."""
    return 2.0 * _per_tet(mu, 2) * np.diag(_MULT) + _per_tet(lam, 2) * np.outer(_TRACE, _TRACE)


class PerTetParameters:
    """Parameters that are numbers or (E,) arrays, one value per tet (module docstring)."""

    @property
    def per_tet(self):
        """True when any parameter is an array (a painted body)."""
        return any(np.ndim(getattr(self, f.name)) for f in fields(self))

    def at(self, tets):
        """The material of the tets ``tets`` (k,): each per-tet array indexed by them (numbers
        stay numbers). ``tets`` may repeat, e.g. the same tets for several poses."""
        if not self.per_tet:
            return self
        return replace(self, **{f.name: np.asarray(getattr(self, f.name))[tets]
                                for f in fields(self) if np.ndim(getattr(self, f.name))})


@dataclass(frozen=True)
class Linear(PerTetParameters):
    """psi = mu |eps|^2_F + lam/2 tr(eps)^2; mu, lam Lame parameters [Pa] (numbers or (E,))."""

    mu: float
    lam: float

    @property
    def small_strain_lame(self):
        """(mu, lam) [Pa] of the linear material this one equals at small strain."""
        return self.mu, self.lam

    def evaluate(self, strain, order=2):
        """psi (E,) [Pa], d psi/d e (E, 6) and d2 psi/d e2 (E, 6, 6) (None below ``order``)."""
        strain = np.asarray(strain, dtype=np.float64)
        C = _linear_tensor(self.mu, self.lam)
        grad = strain @ C if C.ndim == 2 else np.einsum("ek,ekl->el", strain, C)
        psi = 0.5 * np.einsum("ek,ek->e", grad, strain)
        hess = np.broadcast_to(C, strain.shape[:-1] + (6, 6)) if order >= 2 else None
        return psi, (grad if order >= 1 else None), hess


def _green_constants():
    """Constant tensors of the StVK derivatives (see ``_GreenParts``).

    half_products (9, 54): vec(S) -> [vec((B_k S + S B_k) / 2)]_k, built by applying the map
    to the nine unit matrices. symmetric_products (9, 36): vec(E) -> [<E, (B_k B_l + B_l B_k)/2>].
    """
    units = np.eye(9).reshape(9, 1, 3, 3)
    half_products = 0.5 * (_BASIS @ units + units @ _BASIS)                # (9, 6, 3, 3)
    products = _BASIS[:, None] @ _BASIS[None]                            # (6, 6, 3, 3)
    symmetric = 0.5 * (products + np.swapaxes(products, 0, 1))
    return half_products.reshape(9, 54), symmetric.reshape(36, 9).T.copy()


_HALF_PRODUCTS, _SYMMETRIC_PRODUCTS = _green_constants()
_BASIS_COLUMNS = _BASIS.reshape(6, 9).T                                 # (9, 6): vec(B_k)
_BASIS_GRAM = np.diag(_MULT)                                            # <B_k, B_l>


class _GreenParts:
    """Per-tet pieces shared by StVK evaluations of one strain array (E, 6).

    With S = I + eps and E_G = (S^2 - I)/2, along strain component k: dE_k = (B_k S + S B_k)/2
    (B_k = d eps / d e_k) and d^2 E / de_k de_l = (B_k B_l + B_l B_k)/2. So for
    psi = mu tr(E_G^2) + lam/2 tr(E_G)^2, with stress Sigma = 2 mu E_G + lam tr(E_G) I:
    grad_k = <Sigma, dE_k> and hess_kl = 2 mu <dE_k, dE_l> + lam <S, B_k><S, B_l>
    + <Sigma, (B_k B_l + B_l B_k)/2> (tr dE_k = <S, B_k>). Every piece is linear in (mu, lam),
    so Fung's two StVK terms share this object; all are a few GEMMs over the tets. The
    gradient needs no dE_k: E_G is a polynomial in S, so they commute and
    <E_G, dE_k> = <E_G S, B_k> (9 numbers a tet instead of the 54 of dE_k, which only the
    Hessian's <dE_k, dE_l> needs).
    """

    def __init__(self, strain, order):
        self.order = order
        n = len(strain)
        S = strain_matrices(strain) + np.eye(3)                               # (E, 3, 3)
        # 3 x 3 products by einsum: several times faster than matmul's stacked small matrices
        green = 0.5 * (np.einsum("eij,ejk->eik", S, S) - np.eye(3))
        self.green = green.reshape(n, 9)                                      # vec E_G
        self.trace = self.green[:, 0] + self.green[:, 4] + self.green[:, 8]
        if order >= 1:
            S9 = S.reshape(n, 9)
            self.stretch = S9 @ _BASIS_COLUMNS                                # <S, B_k> (E, 6)
            self.green_stretch = (np.einsum("eij,ejk->eik", green, S).reshape(n, 9)
                                  @ _BASIS_COLUMNS)                           # <E_G, dE_k>
        if order >= 2:
            d_green = (S9 @ _HALF_PRODUCTS).reshape(n, 6, 9)                  # vec dE_k
            self.gram = d_green @ np.swapaxes(d_green, 1, 2)                  # (E, 6, 6)
            self.curvature = (self.green @ _SYMMETRIC_PRODUCTS).reshape(n, 6, 6)

    def stvk(self, mu, lam):
        """(psi, grad, hess) of mu tr(E_G^2) + lam/2 tr(E_G)^2 up to ``order`` (mu, lam numbers
        or (E,))."""
        psi = mu * np.einsum("ei,ei->e", self.green, self.green) + 0.5 * lam * self.trace ** 2
        if self.order < 1:
            return psi, None, None
        grad = (2.0 * _per_tet(mu, 1) * self.green_stretch
                + _per_tet(lam, 1) * self.trace[:, None] * self.stretch)
        if self.order < 2:
            return psi, grad, None
        hess = (2.0 * _per_tet(mu, 2) * (self.gram + self.curvature)
                + _per_tet(lam, 2) * (self.stretch[:, :, None] * self.stretch[:, None, :]
                                      + self.trace[:, None, None] * _BASIS_GRAM))
        return psi, grad, hess


@dataclass(frozen=True)
class StVK(PerTetParameters):
    """St Venant-Kirchhoff on the Cauchy strain: E_G = eps + eps^2/2, Lame mu, lam [Pa]
    (numbers or (E,))."""

    mu: float
    lam: float

    @property
    def small_strain_lame(self):
        return self.mu, self.lam

    def evaluate(self, strain, order=2):
        """psi (E,) [Pa], d psi/d e (E, 6), d2 psi/d e2 (E, 6, 6) (None below ``order``)."""
        return _GreenParts(strain, order).stvk(self.mu, self.lam)


@dataclass(frozen=True)
class Fung(PerTetParameters):
    """psi_StVK(mu1, lam1) + c (exp(psi_StVK(mu2, lam2)) - 1).

    mu1, lam1, c in Pa; mu2, lam2 dimensionless; each a number or (E,). Large strains may
    overflow the exponential to inf: the integrator's line search rejects such trial points.
    """

    mu1: float
    lam1: float
    mu2: float
    lam2: float
    c: float

    @property
    def small_strain_lame(self):
        return self.mu1 + self.c * self.mu2, self.lam1 + self.c * self.lam2

    def evaluate(self, strain, order=2):
        """psi (E,) [Pa], d psi/d e (E, 6), d2 psi/d e2 (E, 6, 6) (None below ``order``)."""
        parts = _GreenParts(strain, order)
        psi1, g1, H1 = parts.stvk(self.mu1, self.lam1)
        psi2, g2, H2 = parts.stvk(self.mu2, self.lam2)
        with np.errstate(over="ignore"):
            growth = self.c * np.exp(psi2)                                    # (E,) [Pa]
        psi = psi1 + growth - self.c
        if order < 1:
            return psi, None, None
        grad = g1 + growth[:, None] * g2
        if order < 2:
            return psi, grad, None
        hess = H1 + growth[:, None, None] * (H2 + g2[:, :, None] * g2[:, None, :])
        return psi, grad, hess


MATERIALS = ("LINEAR", "STVK", "FUNG")


def _parameter(value):
    """A number as a float, per-tet values as a float64 array."""
    return float(value) if np.ndim(value) == 0 else np.asarray(value, dtype=np.float64)


def make_material(kind, mu, lam, fung_stiffening=10.0):
    """Material ``kind`` (one of MATERIALS) whose small-strain Lame parameters are (mu, lam) [Pa].

    Fung splits the small-strain stiffness in half between its StVK term and its exponential
    term, and scales the exponent by the uniaxial modulus: with k = ``fung_stiffening``
    (dimensionless) and u = mu + lam/2, mu1 = mu/2, lam1 = lam/2, mu2 = k mu/u, lam2 = k lam/u,
    c = u/(2k). A uniaxial Green strain E_G then gives the exponent k E_G^2 whatever Poisson's
    ratio, so the exponential takes over around E_G = 1/sqrt(k) (k = 10: about 30 %); larger k
    stiffens sooner. mu, lam may be (E,) per tet (a painted body): so are the parameters then.
    """
    kind = str(kind).upper()
    mu, lam = _parameter(mu), _parameter(lam)
    if kind == "LINEAR":
        return Linear(mu, lam)
    if kind == "STVK":
        return StVK(mu, lam)
    if kind == "FUNG":
        k = float(fung_stiffening)
        if not k > 0.0:
            raise ValueError(f"Fung stiffening must be positive (got {k:g})")
        uniaxial = mu + 0.5 * lam
        return Fung(0.5 * mu, 0.5 * lam, k * mu / uniaxial, k * lam / uniaxial,
                    0.5 * uniaxial / k)
    raise ValueError(f"unknown material {kind!r}; expected one of {', '.join(MATERIALS)}")


# ---------------------------------------------------------------------------------------------
# Reduced potential

class PotentialAccessors:
    """energy, gradient and Hessian of anything with ``evaluate(s, order)`` -> (value, grad,
    hess): the reduced potential, and the volume barrier that wraps it (``inversion``)."""

    def energy(self, s):
        return self.evaluate(s, 0)[0]

    def gradient(self, s):
        return self.evaluate(s, 1)[1]

    def hessian(self, s):
        return self.evaluate(s, 2)[2]


class ReducedPotential(PotentialAccessors):
    """V(s) = sum_c weights_c psi(U_c s): the elastic energy [J] of modal coordinates s (m,).

    material: ``Linear``, ``StVK`` or ``Fung`` of the whole body (per-tet parameters over all
    its E tets, or numbers); strain_modes U (C, 6, m): strain per unit s at each quadrature tet
    (rows 3:9 of ``rs.linear_rs``); weights (C,) [m^3]: tet volume times cubature weight (1 for
    the exact all-tet sum). Use ``exact`` or ``cubature`` to build one. ``tets`` (C,) records
    which tets these are (None: all, in order); their parameters are ``material.at(tets)``.

    For ``Linear`` the (constant) Hessian sum_c w_c U_c^T C6 U_c is precomputed at construction,
    so evaluation costs one m x m product; ``rest_hessian`` is the Hessian at s = 0 for every
    material (the linearised stiffness, used for Rayleigh stiffness damping).
    """

    def __init__(self, material, strain_modes, weights, tets=None):
        self.material = material               # the body's: the barriers read every tet's
        self.strain_modes = np.ascontiguousarray(strain_modes, dtype=np.float64)
        self.weights = np.asarray(weights, dtype=np.float64).reshape(-1)
        self.tets = None if tets is None else np.asarray(tets, dtype=np.int64)
        self._material = material if self.tets is None else material.at(self.tets)  # (C,) rows
        self.num_coords = self.strain_modes.shape[2]
        self._flat = self.strain_modes.reshape(-1, self.num_coords)            # (6C, m)
        self._quadratic = None
        if isinstance(material, Linear):
            rows = len(self.weights) if material.per_tet else 1
            rest = self._material.evaluate(np.zeros((rows, 6)))[2]
            self._quadratic = self._hessian_sum(rest if material.per_tet else rest[0])
        self.rest_hessian = (self._quadratic if self._quadratic is not None
                             else self.evaluate(np.zeros(self.num_coords))[2])

    @classmethod
    def exact(cls, material, modal_rs, volumes):
        """Sum over all E tets: modal_rs (E, 9, m) from ``rs.linear_rs``, volumes (E,) [m^3]."""
        modal_rs = np.asarray(modal_rs, dtype=np.float64)
        return cls(material, modal_rs[:, 3:, :], np.abs(volumes))

    @classmethod
    def cubature(cls, material, modal_rs, volumes, tets, weights):
        """Sum over cubature tets (C,) with weights (C,) >= 0 (see ``train_energy_cubature``)."""
        tets = np.asarray(tets, dtype=np.int64)
        modal_rs = np.asarray(modal_rs, dtype=np.float64)
        return cls(material, modal_rs[tets, 3:, :],
                   np.abs(np.asarray(volumes)[tets]) * np.asarray(weights, dtype=np.float64),
                   tets=tets)

    def to_arrays(self):
        """The quadrature as plain arrays, for a cache file: ``tets`` (C,) int64 (absent for the
        exact all-tet sum), ``weights`` (C,) [m^3] and ``strain_modes`` (C, 6, m). The material
        is not included: ``from_arrays`` takes it, so one file serves any material whose
        cubature it is."""
        arrays = dict(weights=self.weights, strain_modes=self.strain_modes)
        if self.tets is not None:
            arrays["tets"] = self.tets
        return arrays

    @classmethod
    def from_arrays(cls, arrays, material):
        """The potential of ``material`` over the quadrature saved by ``to_arrays``: evaluates
        bit for bit like the saved one (the same arrays, the same arithmetic)."""
        return cls(material, arrays["strain_modes"], arrays["weights"], tets=arrays.get("tets"))

    def for_mode_scale(self, factor):
        """This quadrature for the modes times ``factor`` > 0 (``reduced.ReducedRS.
        for_mode_scale``): the strain per unit s scales, the tets and weights are the same."""
        factor = float(factor)
        if factor == 1.0:
            return self
        return ReducedPotential(self.material, self.strain_modes * factor, self.weights,
                                tets=self.tets)

    def with_material(self, material):
        """The potential of ``material`` over this quadrature (the same arrays). A cubature
        trained for a material serves any positive multiple of it: StVK's and Fung's energies
        are proportional to Young's modulus at a fixed Poisson's ratio and stiffening."""
        return self.from_arrays(self.to_arrays(), material)

    @property
    def is_quadratic(self):
        """True for the linear material: V = 1/2 s^T K s with K = ``rest_hessian``."""
        return self._quadratic is not None

    def _hessian_sum(self, tet_hessians):
        """sum_c w_c U_c^T H_c U_c (m, m) for H (C, 6, 6) or one shared (6, 6)."""
        HU = np.matmul(tet_hessians, self.strain_modes) * self.weights[:, None, None]
        K = self._flat.T @ HU.reshape(-1, self.num_coords)
        return 0.5 * (K + K.T)

    def strains(self, s):
        """(C, 6) strains of the quadrature tets at s (m,)."""
        return (self._flat @ np.asarray(s, dtype=np.float64)).reshape(-1, 6)

    def evaluate(self, s, order=2):
        """V [J], grad (m,) [J per unit s], Hessian (m, m) at s (m,); None below ``order``."""
        s = np.asarray(s, dtype=np.float64)
        if self._quadratic is not None:
            grad = self._quadratic @ s
            return 0.5 * float(grad @ s), (grad if order >= 1 else None), (
                self._quadratic if order >= 2 else None)
        psi, dpsi, d2psi = self._material.evaluate(self.strains(s), order)
        energy = float(self.weights @ psi)
        if order < 1:
            return energy, None, None
        grad = (dpsi * self.weights[:, None]).reshape(-1) @ self._flat
        return energy, grad, (self._hessian_sum(d2psi) if order >= 2 else None)



# ---------------------------------------------------------------------------------------------
# Energy cubature

def prepare_potential(material, modal_rs, volumes, eigenvalues=None, num_poses=200,
                      max_tets=200, tol=1e-4, max_rotation=np.pi / 2, seed=0, progress=None):
    """The reduced potential a simulation should use: returns (potential, info).

    Linear: the exact all-tet quadratic form (precomputed, no cubature needed). StVK / Fung:
    an energy cubature (``train_energy_cubature``) on ``num_poses`` random poses from
    ``cubature.training_poses`` with per-tet rotations up to ``max_rotation`` [rad] (90 deg
    by default: poses far beyond what a simulation reaches spend tets on strains it never
    sees). modal_rs (E, 9, m), volumes (E,) [m^3], eigenvalues (m,) weight the modes of mixed
    poses; seed makes the result reproducible. info: ``tets``, ``weights``,
    ``relative_residual`` (empty for Linear). progress: as for ``train_energy_cubature``.

    What the cubature depends on (a cache key needs all of it): the modes (modal_rs, volumes,
    eigenvalues), the training settings and every parameter of the material. Young's modulus
    only scales StVK and Fung, and each pose's fit is normalised, yet it still changes the
    rounding, and with it which of two mirror-image tets of equal score a pick takes: train at
    one modulus (``preparation.energy_potential``: 1 Pa) and move the result to another with
    ``ReducedPotential.with_material``.
    """
    if isinstance(material, Linear):
        return ReducedPotential.exact(material, modal_rs, volumes), {}
    modal_rs = np.asarray(modal_rs, dtype=np.float64)
    rng = np.random.default_rng(seed)
    poses = cubature.training_poses(modal_rs.shape[2], eigenvalues, num_poses, rng,
                                    max_rotation=max_rotation, modal_rs=modal_rs)
    tets, weights, info = train_energy_cubature(material, modal_rs, volumes, poses, tol=tol,
                                                max_tets=max_tets, rng=rng, progress=progress)
    potential = ReducedPotential.cubature(material, modal_rs, volumes, tets, weights)
    return potential, dict(tets=tets, weights=weights, relative_residual=info["relative_residual"])


STORED_COLUMNS = 64_000_000   # training matrices up to this many entries (256 MB in float32)
                              # are computed once, and every tet is scored at every pick
COLUMN_CHUNK = 512            # tets whose columns are computed at once (bounds temporaries)


def train_energy_cubature(material, modal_rs, volumes, poses, tol=1e-2, max_tets=300,
                          candidates=500, rng=None, progress=None, picks_per_block=1):
    """Cubature (tets, weights) for V(s) of ``material``, trained on forces and energies.

    modal_rs (E, 9, m), volumes (E,) [m^3]; poses (F, m) training modal coordinates (e.g.
    ``cubature.training_poses``: random, up to large rotations). Per pose t the target is the
    exact reduced force grad V(s_t) (m,) and energy V(s_t), each divided by its own norm so
    every pose and both kinds count alike (An et al. 2008 fit forces; the energy row keeps the
    line search's objective consistent with them). Tet e's column holds its own contribution
    V_e [U_e^T dpsi_e, psi_e] under the same scaling; ``cubature.greedy_nnls`` picks the tets.

    Where the training matrix (F (m + 1), E) has at most STORED_COLUMNS entries, every column
    is computed once (one material evaluation per tet and pose, which also sums to the exact
    targets) and kept in float32, and each pick scores every unpicked tet against the residual
    with one product (``cubature.StoredScreen``); the best few are formed exactly. A body of
    more tets draws ``candidates`` random tets per block and forms their columns, as An et al.
    do: a column costs F material evaluations, so on the 12k-tet bar (200 poses, about 200
    picks) blocks of 500 took 13.6 s for StVK, the stored columns 5.0 s, and they choose each
    pick among all tets (``bench/run_bench.py``, dynamics). ``picks_per_block`` picks from
    one scoring; one by default (with random blocks, 12 a block trained StVK in a sixth of the
    time but raised Fung's residual fourfold: its exponential puts a bent pose's energy in a
    few tets; with the stored columns, 2 and 4 a block saved 1 and 1.8 s of 4.7 and raised
    StVK's mean held-out force error from 0.011 to 0.014 and 0.018).
    progress: optional callable(fraction, message), called between chunks of tets or poses
    and between blocks of picks; an exception it raises (a cancel) stops the training.

    Returns tets (C,), weights (C,) > 0 and info dict (``history``, ``relative_residual``).
    """
    modal_rs = np.asarray(modal_rs, dtype=np.float64)
    volumes = np.abs(np.asarray(volumes, dtype=np.float64))
    Z = np.atleast_2d(np.asarray(poses, dtype=np.float64))
    strain_modes = modal_rs[:, 3:, :]
    num_tets, num_rows = len(volumes), len(Z) * (strain_modes.shape[2] + 1)
    if num_rows * num_tets <= STORED_COLUMNS:
        stored, rows = _all_columns(material, strain_modes, volumes, Z, progress)
    else:
        stored, rows = None, _exact_rows(material, modal_rs, volumes, Z, progress)
    scale = np.concatenate([np.repeat(np.maximum(np.linalg.norm(rows[:, :-1], axis=1), 1e-300)
                                      [:, None], rows.shape[1] - 1, axis=1),
                            np.maximum(np.abs(rows[:, -1:]), 1e-300)], axis=1)
    target = (rows / scale).reshape(-1)

    def columns(tets):
        return _tet_columns(material, tets, strain_modes[tets], volumes[tets], Z, scale)

    screen = None
    if stored is not None:
        stored /= scale.reshape(-1, 1).astype(np.float32)
        screen, candidates = cubature.StoredScreen(stored), None
    inner = None if progress is None else (lambda f, msg: progress(0.1 + 0.9 * f, msg))
    tets, weights, history = cubature.greedy_nnls(columns, target, tol=tol, max_picks=max_tets,
                                                  candidates=candidates, rng=rng,
                                                  num_columns=num_tets, progress=inner,
                                                  picks_per_block=picks_per_block,
                                                  screen=screen)
    return tets, weights, dict(history=history, relative_residual=history[-1])


def _exact_rows(material, modal_rs, volumes, Z, progress):
    """[grad V(s_t), V(s_t)] (F, m + 1) of poses Z (F, m), one all-tet evaluation each."""
    exact = ReducedPotential.exact(material, modal_rs, volumes)
    rows = np.empty((len(Z), exact.num_coords + 1))
    for t, z in enumerate(Z):       # report (and cancel) between poses
        if progress is not None:
            progress(0.1 * t / len(Z), f"exact forces of training pose {t + 1}/{len(Z)}")
        rows[t] = _pose_row(exact, z)
    return rows


def _all_columns(material, strain_modes, volumes, Z, progress):
    """Every tet's unscaled column (F (m + 1), E) in float32, and their sum in float64, the
    exact rows [grad V(s_t), V(s_t)] (F, m + 1): COLUMN_CHUNK tets per call on threads, a
    fixed split and sums added in order, so the result is the same on any number of them."""
    num_tets, (F, m) = len(volumes), Z.shape
    stored = np.empty((F * (m + 1), num_tets), dtype=np.float32)
    rows = np.zeros(F * (m + 1))
    unit = np.ones((F, m + 1))

    def fill(part):
        tets = np.arange(part.start, part.stop)
        block = _tet_columns(material, tets, strain_modes[tets], volumes[tets], Z, unit)
        stored[:, part] = block
        return block.sum(axis=1)

    chunks = threads.fixed_parts(num_tets, COLUMN_CHUNK)
    group = 2 * threads.worker_count()
    for first in range(0, len(chunks), group):      # report (and cancel) between groups
        if progress is not None:
            progress(0.1 * first / len(chunks), f"training columns of tets "
                                                f"{chunks[first].start + 1}-{num_tets}")
        for sums in threads.ordered_map(fill, chunks[first:first + group]):
            rows += sums
    return stored, rows.reshape(F, m + 1)


def _pose_row(potential, s):
    """[grad V(s), V(s)] (m + 1,) of one pose."""
    energy, grad, _ = potential.evaluate(s, 1)
    return np.append(grad, energy)


def _tet_columns(material, tets, strain_modes, volumes, Z, scale):
    """(F (m + 1), k) per-tet [V_e U_e^T dpsi, V_e psi] of the tets (k,) at poses Z (F, m),
    divided by scale; material is the body's (its per-tet parameters repeat for every pose)."""
    k, _, m = strain_modes.shape
    strains = np.einsum("kim,fm->fki", strain_modes, Z)                      # (F, k, 6)
    psi, dpsi, _ = material.at(np.tile(tets, len(Z))).evaluate(strains.reshape(-1, 6), 1)
    # U_e^T dpsi per tet, batched over the tets (a third of the einsum's time)
    forces = np.matmul(dpsi.reshape(len(Z), k, 6).transpose(1, 0, 2), strain_modes)  # (k, F, m)
    forces = forces.transpose(1, 0, 2)
    cols = np.concatenate([forces, psi.reshape(len(Z), k, 1)], axis=2) * volumes[None, :, None]
    cols /= scale[:, None, :]
    return cols.transpose(0, 2, 1).reshape(-1, k)
