"""Flesh on a rig: elastic motion as a deviation from linear blend skinning (issue 13).

A skinned body's rest trajectory is its rig's motion. Node i of the tet mesh, with skinning
weights w_ib over the bones (rows summing to 1), is carried to the world by the affine map
A_i(t) = sum_b w_ib T_b(t), T_b (3, 4) bone b's world-from-rest transform. The elastic motion is
a deviation u (N, 3) in the REST space, skinned with the body: x_i(t) = A_i(t) (X_i + u_i).
This is exactly what Blender's Armature modifier does to a shape-key bake (shape keys act
before every modifier), and large bone rotations stay rotations because the skinning carries
them; the deviation itself is solved by the reduced RS dynamics (``dynamics.Simulation``) in a
fixed frame, with the pinned (Follow Rig) nodes zero in the basis, so they move exactly with
the bones.

Loads (first order in u): in node i's skinned frame the flesh feels gravity and the inertia of
the rig's acceleration, a d'Alembert force pulled back through L_i = sum_b w_ib R_b (R_b the
linear part of T_b): f_i = m_i L_i^T (g - a_i), a_i = sum_b w_ib Tdd_b [X_i; 1]. Velocity
(Coriolis) and centrifugal terms in u are left out, as is the change of L_i over a step.
In the basis, f_q = B^T f (rB,); ``RigLoad`` precomputes mass moments per bone and per
overlapping bone pair so a step costs O(pairs x rB), never a pass over the nodes.

Shapes and units: X (N, 3) rest nodes [m]; weights (N, b); transforms (F, b, 3, 4) [m];
times (F,) [s], uniform; masses (N,) [kg]; B (3N, rB), node-major rows; g (3,) [m/s^2].
"""
import igl
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from . import materials


def node_values(embedding, vertex_values, X, T):
    """(N, k) fields of the render vertices' (n, k) carried to the tet nodes: the Phi^T-weighted
    average where nodes carry embedding weight, the harmonic extension (cotangent Laplacian of
    the tets, those nodes fixed) inside. Exact for fields linear in space."""
    Phi = sp.csr_matrix(embedding)
    W = np.asarray(vertex_values, dtype=np.float64).reshape(Phi.shape[0], -1)
    N = Phi.shape[1]
    carried = np.asarray(abs(Phi).sum(axis=0)).ravel()                      # (N,)
    known = carried > 1e-12
    out = np.zeros((N, W.shape[1]))
    out[known] = (Phi.T @ W)[known] / carried[known, None]
    if not known.all():
        L = sp.csr_matrix(igl.cotmatrix(np.asarray(X, dtype=np.float64),
                                        np.asarray(T, dtype=np.int64)))
        free, fixed = np.flatnonzero(~known), np.flatnonzero(known)
        rhs = L[free][:, fixed] @ out[fixed]
        out[free] = spla.splu((-L[free][:, free]).tocsc()).solve(np.ascontiguousarray(rhs))
    return out


def node_weights(embedding, vertex_weights, X, T):
    """(N, b) skinning weights of the tet nodes from the render vertices' (n, b).

    embedding: Phi (n, N) sparse, render vertices = Phi X (barycentric rows); the weights are
    carried to the nodes by ``node_values``. Rows are clipped at 0 and normalised to sum 1; a
    node whose weights are all zero
    stays zero (no bone moves it; the caller gives such vertices an identity "bone").
    """
    out = np.maximum(node_values(embedding, vertex_weights, X, T), 0.0)
    total = out.sum(axis=1)
    moved = total > 1e-12
    out[moved] /= total[moved, None]
    return out


class RigMotion:
    """Bones' world-from-rest transforms sampled at uniform times, and their accelerations.

    times (F,) [s] uniform (F >= 2); transforms (F, b, 3, 4). Between samples the transforms
    and the accelerations are interpolated linearly; outside the range they are held (the rig
    stands still before and after). Accelerations at the samples are central second
    differences (T_{f+1} - 2 T_f + T_{f-1}) / h^2, so a bone keyed to stop dead at frame f
    decelerates over the frames around f; the end samples take their neighbour's value.
    """

    def __init__(self, times, transforms):
        self.times = np.asarray(times, dtype=np.float64)
        self.transforms = np.asarray(transforms, dtype=np.float64)
        if len(self.times) < 2 or self.transforms.shape[0] != len(self.times):
            raise ValueError("a rig motion needs at least two samples, one transform set each")
        self.h = float(self.times[1] - self.times[0])
        acc = np.zeros_like(self.transforms)
        if len(self.times) >= 3:
            acc[1:-1] = (self.transforms[2:] - 2.0 * self.transforms[1:-1]
                         + self.transforms[:-2]) / self.h ** 2
            acc[0], acc[-1] = acc[1], acc[-2]
        self.accelerations = acc

    def _blend(self, samples, t):
        u = np.clip((float(t) - self.times[0]) / self.h, 0.0, len(self.times) - 1.0)
        k = min(int(np.floor(u)), len(self.times) - 2)
        f = u - k
        return (1.0 - f) * samples[k] + f * samples[k + 1]

    def at(self, t):
        """(b, 3, 4) transforms at time t [s]."""
        return self._blend(self.transforms, t)

    def acceleration(self, t):
        """(b, 3, 4) second time derivative of the transforms at t [1/s^2]."""
        return self._blend(self.accelerations, t)

    def placement(self, t, weights):
        """(A (k, 3, 3), b (k, 3)): the blended affine maps x = A X + b at time t [s] of k
        points with weights (k, b) (``dynamics.Simulation``'s ``sample_placement``)."""
        blend = np.einsum("kb,bij->kij", np.asarray(weights, dtype=np.float64), self.at(t))
        return blend[:, :, :3], blend[:, :, 3]

    def skin(self, t, weights, points):
        """(k, 3) world positions of rest points (k, 3) with weights (k, b) at time t."""
        A, b = self.placement(t, weights)
        return np.einsum("kij,kj->ki", A, np.asarray(points)) + b


class RigLoad:
    """The generalised force B^T f(t) (rB,) of a rig's loads on its flesh (module docstring).

    motion: ``RigMotion``; weights (N, b) node skinning weights (``node_weights``); masses
    (N,) [kg]; basis B (3N, rB) (zero on pinned DOFs); gravity (3,) world [m/s^2].
    Precomputed: per bone c, G_c = sum_i m_i w_ic B_i^T (rB, 3); per bone pair (c, b) whose
    weights overlap, H_cb = sum_i m_i w_ic w_ib B_i^T [X_i; 1]^T (rB, 3, 4). Then
    f_q(t) = sum_c G_c R_c^T g - sum_cb H_cb : (R_c^T Tdd_b).
    """

    def __init__(self, motion, weights, masses, basis, X, gravity=(0.0, 0.0, -9.81)):
        self.motion = motion
        W = np.asarray(weights, dtype=np.float64)
        m = np.asarray(masses, dtype=np.float64)
        B3 = np.asarray(basis, dtype=np.float64).reshape(len(m), 3, -1)      # (N, 3, rB)
        Xh = np.c_[np.asarray(X, dtype=np.float64), np.ones(len(m))]         # (N, 4)
        self.gravity = np.asarray(gravity, dtype=np.float64).reshape(3)
        self.gravity_moments = np.einsum("ic,ikr->ckr", m[:, None] * W, B3)  # (b, 3, rB)
        pairs, moments = [], []
        for c in range(W.shape[1]):
            for b in range(W.shape[1]):
                share = m * W[:, c] * W[:, b]
                nodes = np.flatnonzero(share)
                if len(nodes):
                    pairs.append((c, b))
                    moments.append(np.einsum("i,ikr,il->rkl", share[nodes], B3[nodes],
                                             Xh[nodes]))
        self.pairs = np.array(pairs, dtype=np.int64).reshape(-1, 2)
        self.pair_moments = (np.array(moments) if moments
                             else np.zeros((0, B3.shape[2], 3, 4)))          # (P, rB, 3, 4)

    def force(self, t):
        """(rB,) generalised force at time t [s]."""
        T = self.motion.at(t)                                                 # (b, 3, 4)
        R = T[:, :, :3]
        out = np.einsum("ckr,ck->r", self.gravity_moments, R.transpose(0, 2, 1) @ self.gravity)
        if len(self.pairs):
            acc = self.motion.acceleration(t)
            c, b = self.pairs[:, 0], self.pairs[:, 1]
            pulled = np.einsum("pjk,pjl->pkl", R[c], acc[b])                  # R_c^T Tdd_b
            out -= np.einsum("prkl,pkl->r", self.pair_moments, pulled)
        return out

    def modal_forces(self, times, jacobian):
        """(len(times), m) f_q(t) @ J for a fixed (rB, m) Jacobian (e.g. dq/dz at rest)."""
        return np.array([self.force(t) for t in np.asarray(times, dtype=np.float64)]) @ \
            np.asarray(jacobian, dtype=np.float64)


PIN_THRESHOLD = 0.5   # follow weights from this up are pins (the body's pin rule)


def follow_stiffness(follow, masses, basis, omega_hold):
    """(rB, rB) stiffness K_f = B^T diag(k) B of the springs that hold partly-following nodes.

    follow (N,) Follow Rig weights of the nodes (``node_values`` of the vertex group): 0 is
    free flesh, from ``PIN_THRESHOLD`` up a node is pinned (zero in B). In between, node i is
    held to its skinned place by a spring k_i = m_i omega_hold^2 w/(1 - w) [N/m]: its own
    frequency on the spring rises from 0 with the weight to omega_hold [rad/s] at the pin
    threshold (e.g. the body's fastest mode, so the step to a pin is a small one).
    """
    w = np.clip(np.asarray(follow, dtype=np.float64), 0.0, PIN_THRESHOLD)
    k = np.where(w < PIN_THRESHOLD, np.asarray(masses) * omega_hold ** 2 * w / (1.0 - w), 0.0)
    B3 = np.asarray(basis, dtype=np.float64).reshape(len(w), 3, -1)
    held = np.flatnonzero(k > 0.0)
    return np.einsum("i,ikr,iks->rs", k[held], B3[held], B3[held])


class HeldPotential(materials.PotentialAccessors):
    """A reduced potential (``materials.ReducedPotential`` or a ``BarrierPotential``) plus the
    follow springs 1/2 q(s)^T K_f q(s) of a deformer (rest space: q = 0 is the skinned pose).

    evaluate(s, order) -> (V [J], grad (m,), Hessian (m, m), Gauss-Newton J^T K_f J for the
    springs); ``rest_hessian`` includes J0^T K_f J0, so Rayleigh stiffness damping and the
    automatic substeps see the springs. Other attributes are the wrapped potential's.
    """

    is_quadratic = False

    def __init__(self, potential, deformer, stiffness):
        self.potential, self.deformer = potential, deformer
        self.stiffness = np.asarray(stiffness, dtype=np.float64)
        self.num_coords = potential.num_coords
        J0 = np.asarray(deformer.q_jacobian(np.zeros(self.num_coords)))
        self.rest_hessian = potential.rest_hessian + J0.T @ self.stiffness @ J0

    def __getattr__(self, name):            # only called for attributes not found above
        if name in ("potential", "deformer", "stiffness"):
            raise AttributeError(name)
        return getattr(self.potential, name)

    def evaluate(self, s, order=2):
        energy, grad, hess = self.potential.evaluate(s, order)
        q = np.asarray(self.deformer.q(s))
        Kq = self.stiffness @ q
        energy = energy + 0.5 * float(q @ Kq)
        if order >= 1:
            J = np.asarray(self.deformer.q_jacobian(s))
            grad = grad + J.T @ Kq
            if order >= 2:
                hess = hess + J.T @ self.stiffness @ J
        return energy, grad, hess
