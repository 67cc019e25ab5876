"""Body frames of the dynamics: fixed, keyed (moving) and free, and the inertia of a step in each.

A simulated body's world positions are x = R Y + c with body-frame positions
``Y = Xb + B q`` (N, 3) [m], ``Xb = X - origin``, B (3N, rB) the deformer's basis and q (rB,) its
reduced displacement coordinates (``dynamics``). The frame (R, c) is

- fixed: R = I, c = 0 (origin 0), world = the object's rest space;
- keyed (``FrameMotion``): (R(t), c(t)) prescribed, e.g. the Blender object's animated
  transform (rotation and translation only; scale belongs in X). Pinned DOFs are zero in B, so
  the pinned part follows the keys exactly and the rest lags behind;
- free: R and c are 6 extra unknowns, c the world position of the rest centre of mass
  ``origin`` (R = I, c = origin at the start, so world = rest space then).

Every integration scheme's inertia is a mass norm w/2 |x(q) - x_hat|_M^2 of the step's end
positions against a target x_hat (``integrators``). Per step nothing touches the vertices: a
world field of the form F_k = A Xb_k + sum_ij e_i (B_k[j] . Z[i, j]) + d (``Field``; positions,
velocities, accelerations and the targets made of them) is contracted with mass moments of Xb
and B computed once (``MassMoments``):

- fixed frame: a quadratic in q (``fixed_inertia``, the target as q_hat in q-space);
- keyed frame (R, c) known at the step's end: a quadratic in q whose linear term contracts
  R^T (x_hat - c) with the moments (``keyed_inertia``);
- free frame: for given q the best frame is closed form (weighted Procrustes): c = centre of
  mass of x_hat minus R times that of Y, R the rotation maximising tr(R^T K),
  K = sum m (x_hat - x_hat_cm)(Y - Y_cm)^T, itself linear in q through the same moments
  (``free_inertia``, ``best_frame``). So the 6 frame coordinates are minimised exactly inside the
  objective and Newton runs on the modal coordinates alone; uniform gravity only moves c. With
  contact the frame is explicit instead (``FramedInertia``: contact forces move and turn it).
"""

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from . import rs

LEVI_CIVITA = -np.transpose(rs.skew(np.eye(3)), (1, 2, 0))            # eps_ijk (3, 3, 3)


class FrameMotion:
    """Prescribed rigid motion of a body frame, sampled at increasing times.

    times (F,) [s]; rotations (F, 3, 3) body-to-world; translations (F, 3) [m]. Calling it at t
    returns (R (3, 3), c (3,)): slerp and linear interpolation between samples, held constant
    outside them (like Blender's constant F-curve extrapolation).
    """

    def __init__(self, times, rotations, translations):
        self.times = np.asarray(times, dtype=np.float64).reshape(-1)
        self.rotations = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
        self.translations = np.asarray(translations, dtype=np.float64).reshape(-1, 3)
        if len(self.times) == 1:
            self._slerp = None
        else:
            self._slerp = Slerp(self.times, Rotation.from_matrix(self.rotations))

    def __call__(self, t):
        t = float(np.clip(t, self.times[0], self.times[-1]))
        c = np.array([np.interp(t, self.times, self.translations[:, i]) for i in range(3)])
        if self._slerp is None:
            return self.rotations[0].copy(), c
        return self._slerp([t]).as_matrix()[0], c


def polar_decomposition(linear):
    """linear (..., 3, 3) = Q P: Q (..., 3, 3) orthogonal, P (..., 3, 3) symmetric positive
    semi-definite (the stretch: scale and shear), from the SVD U diag(s) V^T as Q = U V^T,
    P = V diag(s) V^T. det Q has the sign of det(linear): a mirroring matrix gives a reflection
    Q (det -1), which no rotation can stand for; the caller decides where the mirror goes."""
    U, s, Vt = np.linalg.svd(np.asarray(linear, dtype=np.float64))
    V = np.swapaxes(Vt, -1, -2)
    return U @ Vt, (V * s[..., None, :]) @ Vt


def best_rotation(K):
    """argmax over rotations of tr(R^T K) for K (3, 3), and that maximum."""
    U, sv, Vt = np.linalg.svd(K)
    sign = 1.0 if np.linalg.det(U @ Vt) >= 0.0 else -1.0
    R = (U * np.array([1.0, 1.0, sign])) @ Vt
    return R, sv[0] + sv[1] + sign * sv[2]


def axial(N):
    """(..., 3) axial vectors of (..., 3, 3): tr(skew(w) N) = -w . axial(N)."""
    return np.stack([N[..., 2, 1] - N[..., 1, 2], N[..., 0, 2] - N[..., 2, 0],
                     N[..., 1, 0] - N[..., 0, 1]], axis=-1)


class Field:
    """A world-space field over the nodes, F_k = A Xb_k + sum_ij e_i (B_k[j] . Z[i, j]) + d.

    A (3, 3), Z (3, 3, rB), d (3,); B_k[j] (rB,) is row 3k + j of the basis. Positions
    R (Xb + B q) + c are ``position(R, q, c)``; velocities and accelerations pushed forward from
    the modal coordinates, and the schemes' targets, are linear combinations of such fields, so
    they stay in this form.
    """

    __slots__ = ("A", "Z", "d")

    def __init__(self, A, Z, d):
        self.A, self.Z, self.d = A, Z, d

    @classmethod
    def position(cls, R, q, c):
        return cls(np.array(R, dtype=np.float64), R[:, :, None] * q, np.array(c, dtype=np.float64))

    @classmethod
    def constant(cls, d, basis_size):
        return cls(np.zeros((3, 3)), np.zeros((3, 3, basis_size)), np.asarray(d, dtype=np.float64))

    def __add__(self, other):
        return Field(self.A + other.A, self.Z + other.Z, self.d + other.d)

    def __sub__(self, other):
        return Field(self.A - other.A, self.Z - other.Z, self.d - other.d)

    def __rmul__(self, k):
        return Field(k * self.A, k * self.Z, k * self.d)


class MassMoments:
    """Mass moments of a body's Xb = X - origin and basis B (O(N rB^2) once, so that no step
    touches the vertices).

    X (N, 3) [m]; masses (N,) [kg]; B (3N, rB); free: the origin is the rest centre of mass
    (else 0); moving: also the moments a keyed or free frame needs (S0, H0, H1). Attributes:
    total_mass [kg]; mass_matrix M_B = B^T M B (rB, rB); first_moment_B F_B = sum m B_k (3, rB);
    first_moment_X m_X = sum m Xb_k (3,); S0 = sum m Xb Xb^T (3, 3); H0 [i, j, a] =
    sum m B_k[i, a] Xb_k[j] (3, 3, rB); H1 [i, j] = sum m B_k[i]^T B_k[j] (3, 3, rB, rB);
    trace_H0 = B^T M Xb (rB,); free only: com_per_q = F_B / M (3, rB), H1 centred on the centre
    of mass (centred_H1) and its trace centred_mass (rB, rB).
    """

    def __init__(self, X, masses, B, free=False, moving=False):
        n, rB = len(X), B.shape[1]
        self.basis_size = rB
        self.total_mass = float(masses.sum())
        self.origin = masses @ X / self.total_mass if free else np.zeros(3)
        Xb = X - self.origin
        Bk = B.reshape(n, 3, rB)
        self.mass_matrix = B.T @ (np.repeat(masses, 3)[:, None] * B)             # M_B (rB, rB)
        self.mass_matrix = 0.5 * (self.mass_matrix + self.mass_matrix.T)
        self.first_moment_B = np.einsum("k,kia->ia", masses, Bk)                # (3, rB)
        self.first_moment_X = masses @ Xb                                       # (3,)
        if not (free or moving):
            return
        mB = masses[:, None, None] * Bk
        self.S0 = Xb.T @ (masses[:, None] * Xb)                                  # (3, 3)
        self.H0 = np.einsum("kia,kj->ija", mB, Xb)                              # (3, 3, rB)
        self.H1 = np.empty((3, 3, rB, rB))               # [i, j] = sum m B_k[i]^T B_k[j]
        for i in range(3):                               # nine GEMMs, no loop over vertices
            for j in range(3):
                self.H1[i, j] = mB[:, i, :].T @ Bk[:, j, :]
        self.trace_H0 = np.einsum("iia->a", self.H0)                            # B^T M Xb
        if free:
            D = self.first_moment_B / self.total_mass                           # COM per unit q
            self.com_per_q = D
            self.centred_H1 = self.H1 - self.total_mass * D[:, None, :, None] * D[None, :, None, :]
            self.centred_mass = np.einsum("iiab->ab", self.centred_H1)

    def project(self, R, field):
        """B^T M R^T F (rB,) for a world field F."""
        RA = R.T @ field.A
        RZ = np.einsum("il,ija->lja", R, field.Z)
        return (RA.reshape(-1) @ self.H0.reshape(9, -1) + np.einsum("ljab,ljb->a", self.H1, RZ)
                + self.first_moment_B.T @ (R.T @ field.d))

    def field_norm2(self, field):
        """sum_k m_k |F_k|^2 for a ``Field`` F."""
        A, Z, d = field.A, field.Z, field.d
        return float(np.sum(A * (A @ self.S0)) + np.einsum("ija,jlab,ilb->", Z, self.H1, Z)
                     + 2.0 * np.einsum("il,jla,ija->", A, self.H0, Z)
                     + 2.0 * d @ (A @ self.first_moment_X)
                     + 2.0 * np.einsum("i,ja,ija->", d, self.first_moment_B, Z)
                     + self.total_mass * d @ d)

    def cross_moment(self, qa, qb):
        """sum_k m_k Z_a,k Z_b,k^T (3, 3), Z = Xb for q None, else B q."""
        if qa is None and qb is None:
            return self.S0
        if qa is None:
            return (self.H0 @ qb).T
        if qb is None:
            return self.H0 @ qa
        return np.einsum("a,ijab,b->ij", qa, self.H1, qb)

    def mass_norm2(self, terms, d):
        """sum_k m_k |sum_p L_p Z_p,k + d|^2 for terms [(L_p (3, 3), q_p or None)]."""
        total = self.total_mass * float(d @ d)
        for L, qa in terms:
            first = self.first_moment_X if qa is None else self.first_moment_B @ qa
            total += 2.0 * float(d @ (L @ first))
            for L2, qb in terms:
                total += float(np.sum(L * (L2 @ self.cross_moment(qb, qa))))
        return total

    def mass_metric(self, q, R):
        """sum_k m_k (dx_k/dz)^T dx_k/dz (rB + 6, rB + 6) for z = (q, phi, u), x = R Y + c with
        R = exp(skew(phi)) R, c + u at phi = u = 0 (``FramedInertia``)."""
        rB, FB = self.basis_size, self.first_moment_B
        mq = self.first_moment_X + FB @ q
        H0q = self.H0 @ q
        P = self.H0 + self.H1 @ q                         # [j, m, a] = sum m B_k[j, a] Y_k[m]
        S = self.S0 + H0q + H0q.T + np.einsum("a,ijab,b->ij", q, self.H1, q)
        mass = np.zeros((rB + 6, rB + 6))
        mass[:rB, :rB] = self.mass_matrix
        mass[:rB, rB + 3:] = FB.T @ R.T
        mass[:rB, rB:rB + 3] = (R @ -np.einsum("ijm,jma->ia", LEVI_CIVITA, P)).T
        mass[rB:rB + 3, rB:rB + 3] = R @ (np.trace(S) * np.eye(3) - S) @ R.T
        mass[rB:rB + 3, rB + 3:] = rs.skew(R @ mq)
        mass[rB + 3:, rB + 3:] = self.total_mass * np.eye(3)
        return np.triu(mass) + np.triu(mass, 1).T


class QuadraticInertia:
    """kappa/2 q^T M_B q - b.q: fixed or keyed frame (the inertia and mass damping)."""

    def __init__(self, kappa, mass_matrix, b):
        self.hess = kappa * mass_matrix
        self.b = b

    def evaluate(self, q, order):
        grad = self.hess @ q - self.b
        value = 0.5 * float((grad - self.b) @ q)
        return value, grad, (self.hess if order >= 2 else None)


class FreeInertia:
    """Free body: inertia with the frame (R, c) minimised in closed form (module docstring).

    value(q) = scale/2 (q^T M_c q + 2 a.q - 2 sigma(K0 + Kq q)) + 1/2 q^T D q + e.q,
    sigma(K) = max_R tr(R^T K). scale = w, the scheme's inertia weight; Kq (9, rB); M_c the
    centred mass matrix of B; D (rB, rB) and e (rB,) the mass-damping terms.
    """

    def __init__(self, scale, centred_mass, damping_matrix, damping_linear, a, K0, Kq):
        self.scale, self.K0, self.Kq = scale, K0, Kq
        self.quad = scale * centred_mass + damping_matrix
        self.lin = scale * a + damping_linear

    def rotation(self, q):
        return best_rotation(self.K0 + (self.Kq @ q).reshape(3, 3))

    def evaluate(self, q, order):
        R, sigma = self.rotation(q)
        Mq = self.quad @ q
        value = 0.5 * float(Mq @ q) + float(self.lin @ q) - self.scale * sigma
        if order < 1:
            return value, None, None
        grad = Mq + self.lin - self.scale * (R.reshape(-1) @ self.Kq)
        return value, grad, (self.quad if order >= 2 else None)


class FramedInertia:
    """Free body with its frame explicit (used with contact): in the unknowns (q, phi, u),
    R = exp(skew(phi)) R_ref, c = c_ref + u, linearised at phi = u = 0 (the current iterate),

        E = scale/2 sum_k m_k |R Y_k(q) + c - x_hat_k|^2 + 1/2 q^T D q + e.q,   Y = Xb + B q.

    Expanded with the mass moments (R orthogonal, constants dropped):

        E = scale (1/2 q^T M_B q + a.q + M/2 |c|^2 - c.X + tr(R^T W)) + 1/2 q^T D q + e.q,
        W(q, c) = c m(q)^T - G(q),  m(q) = sum m Y = m_X + F_B q,  G(q) = sum m x_hat Y^T = G0 + Gq q,

    a = B^T M Xb, X = sum m x_hat (3,), M the total mass; for x_hat = A Xb + (Z : B) + d
    (``Field``): X = A m_X + Z : F_B + M d, G0 = A S0 + Z : H0 + d m_X^T,
    Gq = A H0^T + Z : H1 + d F_B (contractions as in ``free_inertia``, with H1 not
    centred). With tr(exp(-skew(phi)) N) = tr N + phi.axial(N) + 1/2 phi^T (sym N - tr N I) phi
    + O(phi^3) for N = W R_ref^T (``axial``), the gradient at phi = u = 0 is

        q:   scale (M_B q + a + F_B^T R^T c - Gq^T vec R) + D q + e
        phi: scale axial(N)
        u:   scale (M c + R m(q) - X)           (= scale sum m (x - x_hat))

    and the Hessian blocks (N linear in q and c):

        qq: scale M_B + D;   qu: scale F_B^T R^T;   uu: scale M I;
        phi phi: scale (sym N - tr N I);   phi u: scale skew(R m(q));
        phi q_b: scale axial((c F_B[:, b]^T - Gq[:, :, b]) R^T).

    Gauss-Newton (scale sum m (dx/dz)^T dx/dz, always PSD, x = R Y + c) differs only in
    phi phi: scale R (tr S I - S) R^T with S = sum m Y Y^T = S0 + H0 q + (H0 q)^T + q^T H1 q,
    and phi q: scale R sum m skew(Y_k) B_k. Its unscaled form is the mass metric of a step
    (``MassMoments.mass_metric``), which measures how far a step moves the body. Everything is
    contracted from the moments (O(rB^2) per evaluation, no per-vertex work).
    """

    def __init__(self, moments, scale, target, damping_matrix, damping_linear):
        self.moments, self.scale = moments, scale
        self.D, self.e = damping_matrix, damping_linear
        A, Z, d = target.A, target.Z, target.d
        mX, FB = moments.first_moment_X, moments.first_moment_B
        self.X = A @ mX + np.einsum("ija,ja->i", Z, FB) + moments.total_mass * d
        self.G0 = A @ moments.S0 + np.einsum("ija,jla->il", Z, moments.H0) + np.outer(d, mX)
        self.Gq = (np.einsum("ij,ljb->ilb", A, moments.H0)
                   + np.einsum("ija,jlab->ilb", Z, moments.H1) + d[:, None, None] * FB[None])

    def value(self, q, R, c):
        mo = self.moments
        W = np.outer(c, mo.first_moment_X + mo.first_moment_B @ q) - self.G0 - self.Gq @ q
        inertia = (0.5 * q @ (mo.mass_matrix @ q) + mo.trace_H0 @ q
                   + 0.5 * mo.total_mass * c @ c - c @ self.X + np.sum(R * W))
        return float(self.scale * inertia + 0.5 * q @ (self.D @ q) + self.e @ q)

    def derivatives(self, q, R, c):
        """(grad (rB+6,), exact Hessian, Gauss-Newton Hessian (rB+6, rB+6), unscaled mass
        metric (rB+6, rB+6)) in (q, phi, u) at phi = u = 0 (class docstring)."""
        mo, k = self.moments, self.scale
        rB, FB, M_B = mo.basis_size, mo.first_moment_B, mo.mass_matrix
        mq = mo.first_moment_X + FB @ q
        N = (np.outer(c, mq) - self.G0 - self.Gq @ q) @ R.T
        grad = np.concatenate([
            k * (M_B @ q + mo.trace_H0 + FB.T @ (R.T @ c) - self.Gq.reshape(9, -1).T @ R.ravel())
            + self.D @ q + self.e,
            k * axial(N),
            k * (mo.total_mass * c + R @ mq - self.X)])
        mass = mo.mass_metric(q, R)
        gauss_newton = k * mass
        gauss_newton[:rB, :rB] += self.D
        exact = gauss_newton.copy()
        dN = np.einsum("i,lb->ilb", c, FB) - self.Gq                          # dW/dq_b
        exact[rB:rB + 3, :rB] = k * axial(np.einsum("ilb,jl->bij", dN, R)).T
        exact[:rB, rB:rB + 3] = exact[rB:rB + 3, :rB].T
        exact[rB:rB + 3, rB:rB + 3] = k * (0.5 * (N + N.T) - np.trace(N) * np.eye(3))
        return grad, exact, gauss_newton, mass


def fixed_inertia(moments, weight, q_hat, damping, load):
    """Fixed frame: w/2 |q - q_hat|^2_{M_B} - load.q plus the mass damping k/2 q^T M_B q + e.q
    (damping = (k, e)), as kappa/2 q^T M_B q - b.q: kappa = w + k, b = w M_B q_hat - e + load."""
    k, linear = damping
    b = weight * (moments.mass_matrix @ q_hat) - linear + load
    return QuadraticInertia(weight + k, moments.mass_matrix, b)


def keyed_inertia(moments, weight, target, R, c, damping):
    """Keyed frame (R, c) at the step's end: w/2 |Y(q) - R^T (x_hat - c)|^2_M plus the mass
    damping (k, e), the target a ``Field`` contracted with the moments."""
    k, linear = damping
    shifted = target - Field.constant(c, moments.basis_size)
    b = weight * (moments.project(R, shifted) - moments.trace_H0) - linear
    return QuadraticInertia(weight + k, moments.mass_matrix, b)


def free_inertia(moments, weight, target, damping):
    """Free frame, minimised in closed form (``FreeInertia``, weight w): K(q) =
    sum m (x_hat - x_hat_cm)(Y(q) - Y_cm)^T = K0 + Kq q from the target's (A, Z) and the
    moments; mass damping (k, e)."""
    A, Z = target.A, target.Z
    K0 = A @ moments.S0 + np.einsum("ija,jla->il", Z, moments.H0)
    Kq = np.einsum("ij,ljb->ilb", A, moments.H0) + np.einsum("ija,jlab->ilb", Z, moments.centred_H1)
    k, linear = damping
    return FreeInertia(weight, moments.centred_mass, k * moments.mass_matrix, linear,
                       moments.trace_H0, K0, Kq.reshape(9, -1))


def best_frame(moments, model, target, q):
    """A free frame (R, c) for q: the Procrustes rotation of ``model`` (a ``FreeInertia``) and
    the centre of mass on the target's."""
    R, _ = model.rotation(q)
    c = (np.einsum("ija,ja->i", target.Z, moments.com_per_q) + target.d
         - R @ (moments.com_per_q @ q))
    return R, c
