"""Contact of a reduced elastic body with Blender colliders: barrier, friction and damping.

Beyond the seed papers. The body is represented by k surface samples (``surface_samples``);
each collider is a triangle mesh, static or keyed (``MeshCollider``). Their contact enters each
implicit step's objective (``dynamics``: Newton + backtracking Armijo line search on a value in
joules whose gradient is a force) as three terms of ``Contact.evaluate``:

- Barrier (Incremental Potential Contact, Li et al. 2020). Per sample p and collider c with
  signed distance d = d_pc and dhat = the collider's thickness,

      E_pc = kappa_c w_p dhat b(d),    b(d) = -(d - dhat)^2 ln(d / dhat)  for 0 < d < dhat,

  0 beyond dhat and +inf for d <= 0. b is C2 at dhat and grows without bound as d -> 0, so the
  line search can never accept a step that ends inside a collider, and a sample only feels a
  force inside the band 0 < d < dhat (Blender's outer thickness). Why a barrier and not a
  penalty or a constraint: penalties let fast bodies pass through and need a stiffness per
  scene; hard constraints need an active-set or LCP solver that the Newton solve of the reduced
  coordinates does not have. The barrier is a smooth energy that the existing Newton solve
  minimises as is. Barriers of all colliders are summed (not only the nearest one), which keeps
  the energy C2 when a sample is near two colliders; where only one is in the band that is the
  nearest.

  Stiffness: kappa_c = STIFFNESS * p_ref / dhat_c^2 [Pa/m^2 = J/m^5] with p_ref = M g0 / A the
  body's weight over its surface area (M = sum of the sample masses, A = sum of the sample
  weights, g0 = 9.81 m/s^2), so the contact pressure of a sample is
  STIFFNESS * p_ref * phi(d / dhat), phi(s) = 2 (s - 1) ln s + (s - 1)^2 / s, independent of the
  scene's units, mass and thickness. STIFFNESS = 1000 (dimensionless) trades the two demands:
  a uniform pressure p_ref rests at d = 0.98 dhat, the weight on one sixth of the area (a box
  on a face) at 0.956 dhat, the whole weight on 3 of 300 equal samples at 0.83 dhat, on one of
  them at 0.72 dhat (all inside the band); a box falling flat at 3 m/s onto dhat = 2 cm stops at
  0.53 dhat, at 5 m/s at 0.38 dhat, and all of the 3 m/s kinetic energy on one of 300 samples
  (a corner) at 1e-3 dhat (5 m/s: 5e-9 dhat). A 10 times softer barrier rests deeper (0.87
  dhat on a face) but stops that corner at 1e-30 dhat, below the round-off of world positions.
  (The numbers solve phi(s) = load share / STIFFNESS and STIFFNESS (w / A) beta(s) =
  v^2 / (2 g0 dhat), beta(s) = -(s - 1)^2 ln s, for a rigid body.) Deterministic, no adaptive
  kappa; the stiffer the contact the higher the frequency of a body bouncing in the band.

- Friction (IPC's lagged smoothed Coulomb friction). At ``begin_step`` each sample in the band
  records its normal force lambda_p = -dE/dd, the normal n and a tangent basis T (3, 2) at its
  closest collider point, and that point's displacement dc over the step (the collider's own
  motion, ``MeshCollider.displacement``). Friction acts on the sample's end-of-step velocity
  relative to the collider as the integrator defines it, v = alpha (x - x_start)/dt -
  (alpha - 1) v_start minus the collider's (alpha = 1 implicit Euler, 2 Newmark's trapezoidal
  rule), written v = alpha (x - ref) / dt with ref = x_start + dc + (alpha - 1)/alpha (dt v_start
  - dc). The step's dissipation potential is mu lambda_p f0(|u|), u = T^T (x - ref), f0 the C1
  smoothing of |u| over eps = EPS_V dt / alpha, f0(y) = -y^3/(3 eps^2) + y^2/eps + eps/3 for
  y < eps, y beyond; EPS_V = 1e-3 m/s is the slip speed below which friction acts as a stiff
  spring rather than a constant force (static friction). Its gradient is the friction force,
  of magnitude mu lambda f0'(|u|) <= mu lambda against the end slip velocity; its Hessian is
  PSD as is (eigenvalues f0'(|u|)/|u| and f0''(|u|) >= 0), so nothing needs projecting. Why the end
  velocity: with Newmark a slip measured over the step (the mean velocity) lets friction that
  stops a body within one step reverse its velocity (v_end = -v_start), and likewise damping.

- Normal damping (Blender's collision ``damping``). A linear dashpot on the same normal
  end-of-step relative velocity, dissipation potential alpha c / (2 dt) (n . (x - ref))^2 with n
  lagged, so its gradient is c (n . v) n. Mapping: damping = 1 - e, e the coefficient of
  restitution of a linear spring-dashpot contact, e = exp(-zeta pi / sqrt(1 - zeta^2)), so
  zeta = -ln e / sqrt(pi^2 + ln^2 e) in [0, 1] (damping 0 -> zeta 0, no loss; damping 1 ->
  zeta 1, critical, no bounce), and c_p = 2 zeta sqrt(m_p k_p) with the spring k_p the
  barrier's stiffness at d = dhat / 2 and the effective mass m_p = M w_p / W, W the weight of
  the samples damped this step (the patch that stops the body carries all of its mass). Damped
  this step are the samples in the band at the start or approaching it fast enough to enter it
  within the step (an impact can last less than one step). Exact only for a linear spring
  resolved in time; the barrier is stiffer near the surface and the integrator has its own
  dissipation, so it approximates the user's restitution.

Distances: libigl's AABB tree (built once per collider placement) gives the closest point;
the sign is the angle-weighted pseudonormal test (Baerentzen and Aanaes 2005) of the closest
feature (face, edge, vertex), which is exact for watertight meshes and one-sided for an open
mesh (a plane): behind it is inside, at any depth, where the point projects onto its faces;
nearest to an open boundary edge or vertex the distance is positive, so a body can pass
around the rim (a sample moving from there to behind the faces jumps to inside: rejected).
A keyed collider moved by a similarity (rotation, translation, uniform scale, mirror) keeps its
own-space tree: the points are mapped into its space and the distances scaled back; any other
placement (non-uniform scale, shear) transforms its vertices to world space and builds a new
tree (5 ms for 2,000 triangles), so distances are world metres either way. The gradient of d
is the sign times the unit (x - closest) / |x - closest|; nearest to a face's interior d and n
are its plane's distance and normal (exact to the round-off of x, not of the closest point).

Integrator note (one-off measurements with the dynamics' step objectives on a rigidly
translating body, dropped onto a plane with dhat = 2 cm): implicit Euler comes to rest without
a bounce even at damping 0 (its numerical dissipation at contact stiffness). Newmark carries
the contact force into its acceleration state, so a one-step impact kicks the next step: a
4-sample block dropped 0.3 m rebounded at 1.18 times its impact speed at dt = 1/24 and
damping 0 (0.79 at dt = 1/240), and a dashpot that stops a body within one step gives some of
it back the same way. Leaving the contact force out of the carried acceleration
(contact-stabilised Newmark, Deuflhard, Krause and Ertel 2008) lowered a point mass's rebound
at 3 m/s, dt = 1/24, damping 0 from 1.99 to 0.49 times the impact speed.

Beyond the agreed interface: ``Contact.scheme``, the dynamics' integration scheme
(``integrators``; ``dynamics.Simulation`` sets it), whose velocity factor alpha gives the
end-of-step velocity friction and damping act on, and ``Contact.max_step`` (optional) bounds a
line-search step so no sample tunnels through a thin collider. Cost (2 cores, shared):
``evaluate`` on 300 samples against a 1,984-triangle sphere, all samples inside its bounding
box, 0.5 ms; ``begin_step`` 0.6 ms (static or similarity-keyed), 7 ms for a non-uniformly
scaled keyed collider (a new tree each step).

Units: metres, kilograms, seconds, joules, newtons.
"""

import numpy as np
import igl

STIFFNESS = 1000.0
"""Dimensionless barrier stiffness: contact pressure = STIFFNESS * (M g0 / A) * phi(d / dhat)."""
STANDARD_GRAVITY = 9.81
"""g0 [m/s^2]: only sets the stiffness scale, not the scene's gravity."""
EPS_V = 1e-3
"""Friction smoothing slip speed [m/s]: below it friction is a stiff spring (static friction)."""
MIN_THICKNESS = 1e-3
"""[m] Barrier band used for a collider whose thickness is below it (thickness 0 has no band)."""
DAMPING_SPRING_POINT = 0.5
"""d / dhat at which the barrier's stiffness defines the damping's spring."""
_BARY_TOL = 1e-10


# Barrier --------------------------------------------------------------------------------------

def barrier(d, dhat):
    """b, b' [m], b'' [1] of b(d) = -(d - dhat)^2 ln(d / dhat) for d (n,) [m] in (0, dhat)."""
    r = d - dhat
    log = np.log(d / dhat)
    b = -r * r * log
    b1 = -2.0 * r * log - r * r / d
    b2 = -2.0 * log - 4.0 * r / d + r * r / (d * d)
    return b, b1, b2


def restitution_damping_ratio(damping):
    """zeta in [0, 1] of a linear spring-dashpot whose restitution is 1 - damping (damping in [0, 1])."""
    e = 1.0 - min(max(float(damping), 0.0), 1.0)
    if e <= 0.0:
        return 1.0
    log_e = np.log(e)
    return float(-log_e / np.sqrt(np.pi ** 2 + log_e ** 2))


def _f0_terms(y, eps):
    """f0(y), g = f1(y) / y and dg/dy of IPC's friction smoothing for slips y (n,) >= 0 [m]."""
    inside = y < eps
    safe = np.where(inside, 1.0, y)
    f0 = np.where(inside, -y ** 3 / (3 * eps ** 2) + y ** 2 / eps + eps / 3, y)
    g = np.where(inside, 2.0 / eps - y / eps ** 2, 1.0 / safe)
    dg = np.where(inside, -1.0 / eps ** 2, -1.0 / safe ** 2)
    return f0, g, dg


def _tangent_basis(n):
    """(k, 3, 2) orthonormal tangents of unit normals n (k, 3)."""
    helper = np.zeros_like(n)
    use_y = np.abs(n[:, 0]) > 0.9
    helper[~use_y, 0] = 1.0
    helper[use_y, 1] = 1.0
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1)[:, None]
    t2 = np.cross(n, t1)
    return np.stack([t1, t2], axis=2)


# Colliders ------------------------------------------------------------------------------------

class _Topology:
    """Edges of a triangle mesh: face_edges (F, 3) (edge opposite corner j), open boundary flags."""

    def __init__(self, triangles, num_vertices):
        F = triangles
        pairs = np.stack([F[:, [1, 2]], F[:, [2, 0]], F[:, [0, 1]]], axis=1).reshape(-1, 2)
        edges, inverse, counts = np.unique(np.sort(pairs, axis=1), axis=0, return_inverse=True,
                                           return_counts=True)
        self.face_edges = inverse.reshape(-1, 3)
        self.num_edges = len(edges)
        self.boundary_edge = counts == 1
        self.is_open = bool(self.boundary_edge.any())
        self.boundary_vertex = np.zeros(num_vertices, dtype=bool)
        self.boundary_vertex[edges[self.boundary_edge].ravel()] = True


class _Surface:
    """A collider's triangle mesh placed in world space: AABB tree and sign pseudonormals."""

    def __init__(self, vertices, triangles, topology, flip=False):
        """flip: the vertices were mirrored (negative determinant), so the triangles' winding now
        points inward and the normals are reversed to keep the inside inside."""
        self.V = np.ascontiguousarray(vertices, dtype=np.float64)
        self.F = triangles
        self.topology = topology
        self.tree = igl.AABB()
        self.tree.init(self.V, self.F)
        self.lower = self.V.min(axis=0)
        self.upper = self.V.max(axis=0)
        a, b, c = (self.V[self.F[:, j]] for j in range(3))
        cross = np.cross(b - a, c - a)
        norm = np.linalg.norm(cross, axis=1)
        self.face_normal = cross / np.where(norm > 0, norm, 1.0)[:, None]
        if flip:
            self.face_normal = -self.face_normal
        # Angle-weighted vertex and summed edge pseudonormals; only their direction is used.
        corners = np.stack([a, b, c], axis=1)
        u = np.roll(corners, -1, axis=1) - corners
        v = np.roll(corners, -2, axis=1) - corners
        cos = np.einsum("fjk,fjk->fj", u, v) / np.maximum(
            np.linalg.norm(u, axis=2) * np.linalg.norm(v, axis=2), 1e-300)
        angle = np.arccos(np.clip(cos, -1.0, 1.0))
        self.vertex_normal = np.zeros_like(self.V)
        for j in range(3):
            np.add.at(self.vertex_normal, self.F[:, j], angle[:, j, None] * self.face_normal)
        self.edge_normal = np.zeros((topology.num_edges, 3))
        for j in range(3):
            np.add.at(self.edge_normal, topology.face_edges[:, j], self.face_normal)

    def box_distance(self, x):
        """(k,) [m] distance of points x (k, 3) to the mesh's bounding box (0 inside it)."""
        gap = np.maximum(self.lower - x, 0.0) + np.maximum(x - self.upper, 0.0)
        return np.linalg.norm(gap, axis=1)

    def query(self, x):
        """Signed distance d (k,) [m], its gradient n (k, 3) (unit), closest points (k, 3), faces."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        sq, face, closest = self.tree.squared_distance(self.V, self.F, x)
        dist = np.sqrt(sq)
        feature_normal, on_boundary, on_face = self._feature(face, closest)
        diff = x - closest
        sign = np.where(np.einsum("kj,kj->k", diff, feature_normal) < 0.0, -1.0, 1.0)
        sign[on_boundary] = 1.0
        d = sign * dist
        off = dist > 0.0
        n = self.face_normal[face].copy()
        n[off] = sign[off, None] * diff[off] / dist[off, None]
        # Closest to a face's interior: the distance to its plane, accurate to round-off of x
        # itself (the closest point's round-off would tilt n by 1e-16 / d).
        fn = self.face_normal[face[on_face]]
        d[on_face] = np.einsum("kj,kj->k", x[on_face] - self.V[self.F[face[on_face], 0]], fn)
        n[on_face] = fn
        return d, n, closest, face

    def _feature(self, face, closest):
        """Pseudonormal (k, 3) of the closest feature, whether that is on an open boundary, and
        whether it is a face's interior (k,) bools."""
        tri = self.F[face]
        a, b, c = (self.V[tri[:, j]] for j in range(3))
        e0, e1, ep = b - a, c - a, closest - a
        d00 = np.einsum("kj,kj->k", e0, e0)
        d01 = np.einsum("kj,kj->k", e0, e1)
        d11 = np.einsum("kj,kj->k", e1, e1)
        d20 = np.einsum("kj,kj->k", ep, e0)
        d21 = np.einsum("kj,kj->k", ep, e1)
        den = d00 * d11 - d01 * d01
        den = np.where(den > 0, den, 1.0)
        beta = (d11 * d20 - d01 * d21) / den
        gamma = (d00 * d21 - d01 * d20) / den
        bary = np.stack([1.0 - beta - gamma, beta, gamma], axis=1)
        zero = bary <= _BARY_TOL
        count = zero.sum(axis=1)
        normal = self.face_normal[face].copy()
        boundary = np.zeros(len(face), dtype=bool)
        rows = np.arange(len(face))
        on_edge = count == 1
        if on_edge.any():
            edge = self.topology.face_edges[face[on_edge], np.argmax(zero[on_edge], axis=1)]
            normal[on_edge] = self.edge_normal[edge]
            boundary[on_edge] = self.topology.boundary_edge[edge]
        on_vertex = count >= 2
        if on_vertex.any():
            vertex = tri[rows[on_vertex], np.argmax(bary[on_vertex], axis=1)]
            normal[on_vertex] = self.vertex_normal[vertex]
            boundary[on_vertex] = self.topology.boundary_vertex[vertex]
        return normal, boundary, count == 0


class _Similar:
    """A collider's own-space surface placed by a similarity x = s R X + T (R orthogonal, possibly
    a reflection): queries map the points into its own space, so its tree is built only once."""

    def __init__(self, local, linear, translation, scale):
        self.local = local
        self.topology = local.topology
        self.inverse = np.linalg.inv(linear)
        self.rotation = linear / scale
        self.linear, self.translation, self.scale = linear, translation, scale

    def box_distance(self, x):
        return self.scale * self.local.box_distance((x - self.translation) @ self.inverse.T)

    def query(self, x):
        d, n, closest, face = self.local.query((x - self.translation) @ self.inverse.T)
        # d_world(x) = s d(L^-1 (x - T)): its gradient s L^-T n = R n (renormalised for a
        # float32 R).
        n = n @ self.rotation.T
        n /= np.linalg.norm(n, axis=1)[:, None]
        return self.scale * d, n, closest @ self.linear.T + self.translation, face


class MeshCollider:
    """A Blender collider: a triangle mesh, static or keyed, with contact thickness, friction, damping."""

    def __init__(self, vertices, triangles, motion=None, thickness=0.02, friction=0.0, damping=0.1,
                 name="collider"):
        """vertices (V, 3) [m] in the collider's own space, triangles (F, 3) int.
        motion: None (vertices are already world positions, static collider) or a callable
          t [s] -> (4, 4) affine object-to-world matrix (a keyed collider; may include scale).
        thickness [m] >= 0: Blender's Collision `thickness_outer`, the distance from the surface at which
          contact acts (the body is kept outside the surface, within this band when resting).
          Below MIN_THICKNESS the band is MIN_THICKNESS (a barrier needs a band).
        friction: Coulomb coefficient mu >= 0. damping in [0, 1]: Blender's Collision `damping`,
          the share of the normal approach velocity removed by an impact (0 = no loss, 1 = no bounce).
        Closed meshes (box, sphere, any watertight mesh): inside is negative distance. Open meshes (a plane):
          one-sided by the face normals, i.e. behind the plane is inside.
        Zero-area triangles are dropped (they have no normal to sign a distance with)."""
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64).reshape(-1, 3)
        F = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        V = self.vertices
        area2 = np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
        extent = np.ptp(V, axis=0).max() if len(V) else 0.0
        self.triangles = np.ascontiguousarray(F[area2 > 1e-14 * extent ** 2])
        if len(self.triangles) == 0:
            raise ValueError(f"collider '{name}' has no triangles")
        self.motion = motion
        self.thickness = float(thickness)
        self.dhat = max(self.thickness, MIN_THICKNESS)
        self.friction = float(friction)
        self.damping = float(damping)
        self.name = str(name)
        self._topology = _Topology(self.triangles, len(self.vertices))
        self._placed = {}            # t -> placed surface, the last two placements of a keyed collider
        self._local = None           # the own-space surface, for static and similarity placements

    def matrix(self, t):
        """(4, 4) object-to-world matrix at time t [s] (identity for a static collider)."""
        if self.motion is None:
            return np.eye(4)
        return np.asarray(self.motion(float(t)), dtype=np.float64).reshape(4, 4)

    def world_vertices(self, t):
        """(V, 3) [m] world positions of the vertices at time t [s]."""
        if self.motion is None:
            return self.vertices
        A = self.matrix(t)
        return self.vertices @ A[:3, :3].T + A[:3, 3]

    def surface(self, t):
        """The mesh placed at time t. A static collider's, or a keyed one's moved by a similarity
        (rotation, translation, uniform scale, mirror) reuses the own-space tree; any other
        placement (non-uniform scale, shear) builds a tree of the world vertices. The last two
        placements are cached (a step's start and end)."""
        # Rounded so that a step's end time and the next step's start time, summed differently
        # by the caller, share one placement.
        key = None if self.motion is None else round(float(t), 9)
        if key not in self._placed:
            if len(self._placed) >= 2:
                self._placed.pop(next(iter(self._placed)))
            self._placed[key] = self._place(t)
        return self._placed[key]

    def _own_space(self):
        if self._local is None:
            self._local = _Surface(self.vertices, self.triangles, self._topology)
        return self._local

    def _place(self, t):
        if self.motion is None:
            return self._own_space()
        A = self.matrix(t)
        L = A[:3, :3]
        det = np.linalg.det(L)
        scale = abs(det) ** (1.0 / 3.0)
        # Blender's matrices are float32: a similarity up to 1e-6 is taken as one (the distance
        # error is then ~1e-6 of the collider's size).
        if scale > 0 and np.allclose(L.T @ L, scale ** 2 * np.eye(3), rtol=0, atol=1e-6 * scale ** 2):
            return _Similar(self._own_space(), L, A[:3, 3], scale)
        return _Surface(self.world_vertices(t), self.triangles, self._topology, flip=det < 0)

    def signed_distance(self, x, t):
        """Signed distance d (k,) [m] of world points x (k, 3) at time t, its unit gradient n (k, 3),
        closest surface points (k, 3) [m]. Inside a closed mesh / behind an open one is negative."""
        d, n, closest, _ = self.surface(t).query(np.asarray(x, dtype=np.float64).reshape(-1, 3))
        return d, n, closest

    def displacement(self, points, t0, t1):
        """(k, 3) [m] displacement from t0 to t1 of the collider's material points at world
        positions points (k, 3) at time t0 (zero for a static collider)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if self.motion is None:
            return np.zeros_like(points)
        step = self.matrix(t1) @ np.linalg.inv(self.matrix(t0))
        return points @ step[:3, :3].T + step[:3, 3] - points

    def velocity(self, points, t, dt):
        """(k, 3) [m/s] secant velocity over [t, t + dt] of the collider's material points at world
        positions points (k, 3) at time t."""
        return self.displacement(points, t, t + dt) / dt


# Surface samples ------------------------------------------------------------------------------

_SEED_DIRECTIONS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)],
                            dtype=np.float64)


def vertex_areas(vertices, triangles):
    """(n,) [m^2] a third of the area of each incident triangle (0 for unused vertices)."""
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(triangles, dtype=np.int64)
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    out = np.zeros(len(V))
    for j in range(3):
        np.add.at(out, F[:, j], area / 3.0)
    return out


def surface_samples(vertices, triangles, count):
    """Deterministic contact cubature on a triangle surface: (indices (k,) of chosen vertices,
    weights (k,) [m^2] = the surface area each represents, summing to the total area). k = min(count, n),
    n the number of vertices used by the triangles.

    Picks: first the support vertices in the 8 diagonal directions (+-1, +-1, +-1) of the rest
    space (the body's extreme corners, the first points to touch a collider; lowest index on
    ties, duplicates skipped), then farthest-point sampling in Euclidean distance. Weights: each
    vertex's area (a third of its triangles') goes to its nearest sample."""
    V = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    used = np.unique(np.asarray(triangles, dtype=np.int64).ravel())
    P = V[used]
    k = min(int(count), len(used))
    if k <= 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    seeds = list(dict.fromkeys(int(i) for i in np.argmax(P @ _SEED_DIRECTIONS.T, axis=0)))
    picked = []
    nearest_dist = np.full(len(P), np.inf)
    nearest = np.zeros(len(P), dtype=np.int64)
    for s in range(k):
        i = seeds[s] if s < len(seeds) else int(np.argmax(nearest_dist))
        picked.append(i)
        dist = np.linalg.norm(P - P[i], axis=1)
        closer = dist < nearest_dist
        nearest_dist[closer] = dist[closer]
        nearest[closer] = s
    weights = np.bincount(nearest, weights=vertex_areas(V, triangles)[used], minlength=k)
    return used[np.array(picked, dtype=np.int64)], weights


# Contact --------------------------------------------------------------------------------------

class _Lagged:
    """One collider's lagged terms for one step: samples idx (a,), normals (a, 3), reference
    positions ref (a, 3) [m] (the end-of-step relative velocity is alpha (x - ref) / dt), friction
    mu lambda (a,) [N] and tangents (a, 3, 2), dashpots c (a,) [N s/m]."""

    def __init__(self, idx, normal, ref, friction, tangents, dashpot):
        self.idx, self.normal, self.ref = idx, normal, ref
        self.friction, self.tangents, self.dashpot = friction, tangents, dashpot


class Contact:
    """Barrier, lagged friction and normal damping of one body's surface samples against colliders."""

    def __init__(self, colliders, points, rows, weights, masses):
        """colliders: list of MeshCollider. points (k, 3) [m]: rest positions of the samples in the body's
        rest space; rows (3k, rB): their displacement rows (sample displacement = (rows @ q).reshape(k, 3));
        weights (k,) [m^2]; masses (k,) [kg]: each sample's share of the body's mass.
        Attributes used by dynamics: .points, .rows, .num_samples; it sets .scheme, the integration
        scheme (``integrators``) whose end-of-step velocity alpha (x - x_n) / dt - (alpha - 1) v_n
        (alpha its ``velocity_factor``) friction and damping act on; steps need it."""
        self.scheme = None
        self.colliders = list(colliders)
        self.points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        self.rows = rows
        self.weights = np.asarray(weights, dtype=np.float64).reshape(-1)
        self.masses = np.asarray(masses, dtype=np.float64).reshape(-1)
        self.num_samples = len(self.points)
        self.total_mass = float(self.masses.sum())
        area = float(self.weights.sum())
        self.reference_pressure = self.total_mass * STANDARD_GRAVITY / area if area > 0 else 0.0
        # kappa_c [Pa/m^2]; per-sample coefficient kappa_c w_p dhat_c [N/m^2] of b(d).
        self.kappa = np.array([STIFFNESS * self.reference_pressure / c.dhat ** 2
                               for c in self.colliders])
        self._coef = [k * self.weights * c.dhat for k, c in zip(self.kappa, self.colliders)]
        self._t_end = 0.0
        self._dt = None
        self._lagged = []

    # Queries ----------------------------------------------------------------------------------

    def _distances(self, surface, dhat, x):
        """Signed distances (k,) [m] and unit gradients (k, 3) of x to a placed collider; for a
        closed mesh, samples farther than dhat from its bounding box are skipped (d = inf, n = 0).
        An open mesh's inside (behind it) reaches beyond its bounding box: all are queried."""
        if surface.topology.is_open:
            d, n, _, _ = surface.query(x)
            return d, n
        d = np.full(len(x), np.inf)
        n = np.zeros_like(x)
        near = np.flatnonzero(surface.box_distance(x) < dhat)
        if len(near):
            d[near], n[near], _, _ = surface.query(x[near])
        return d, n

    def check_start(self, x, t):
        """Raise ValueError naming the collider if any sample (k, 3) world positions at time t is inside
        (distance <= 0) a collider."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        for c in self.colliders:
            d, _, _ = c.signed_distance(x, t)
            if np.any(d <= 0.0):
                worst = int(np.argmin(d))
                raise ValueError(
                    f"the body starts inside collider '{c.name}' at t = {t:g} s: {int(np.sum(d <= 0))} "
                    f"of {len(x)} contact samples, the deepest {-d[worst]:.4g} m; move the body or the "
                    f"collider apart")

    def begin_step(self, t_start, dt, x_start, v_start):
        """Before each internal step [t_start, t_start + dt]: world positions x_start (k, 3) [m] and
        velocities v_start (k, 3) [m/s] at t_start. Places keyed colliders at t_start + dt, lags the friction
        normal forces and tangent frames (IPC-style) and the damping set for this step."""
        if self.scheme is None:
            raise ValueError("the contact has no integration scheme: give it to a "
                             "dynamics.Simulation, or set its scheme (solver.integrators)")
        alpha = self.scheme.velocity_factor
        x0 = np.asarray(x_start, dtype=np.float64).reshape(-1, 3)
        v0 = np.asarray(v_start, dtype=np.float64).reshape(-1, 3)
        self._dt = float(dt)
        self._t_end = float(t_start) + self._dt
        found = []
        for c, coef in zip(self.colliders, self._coef):
            surf = c.surface(t_start)
            c.surface(self._t_end)          # placed now, so evaluate only queries
            d = np.full(len(x0), np.inf)
            reach = c.dhat + np.linalg.norm(v0, axis=1) * dt
            near = np.flatnonzero((surf.box_distance(x0) < reach) | surf.topology.is_open)
            n = np.zeros_like(x0)
            closest = np.zeros_like(x0)
            if len(near):
                d[near], n[near], closest[near], _ = surf.query(x0[near])
            dc = c.displacement(closest, t_start, self._t_end)
            approach = np.einsum("kj,kj->k", v0 - dc / dt, n)
            # Damped: in the band, or reaching it within the step at the start's approach speed.
            damped = (d > 0) & (d + np.minimum(approach, 0.0) * dt < c.dhat)
            in_band = (d > 0) & (d < c.dhat)
            found.append((c, coef, d, n, dc, in_band, damped))
        damped_weight = sum(float(self.weights[f[6]].sum()) for f in found)
        self._lagged = []
        for c, coef, d, n, dc, in_band, damped in found:
            active = in_band & (c.friction > 0) | damped & (c.damping > 0)
            idx = np.flatnonzero(active)
            lam = np.zeros(len(idx))
            band = in_band[idx]
            if band.any():
                _, b1, _ = barrier(d[idx][band], c.dhat)
                lam[band] = -coef[idx][band] * b1
            _, _, b2_ref = barrier(np.array([DAMPING_SPRING_POINT * c.dhat]), c.dhat)
            spring = coef[idx] * b2_ref[0]
            zeta = restitution_damping_ratio(c.damping)
            m_eff = self.total_mass * self.weights[idx] / max(damped_weight, 1e-300)
            dashpot = np.where(damped[idx], 2.0 * zeta * np.sqrt(m_eff * spring), 0.0)
            # End velocity relative to the collider: alpha (x - ref) / dt with this reference.
            ref = x0[idx] + dc[idx] + (alpha - 1.0) / alpha * (v0[idx] * dt - dc[idx])
            self._lagged.append(_Lagged(idx, n[idx], ref, c.friction * lam,
                                        _tangent_basis(n[idx]) if len(idx) else np.zeros((0, 3, 2)),
                                        dashpot))

    # Energy -----------------------------------------------------------------------------------

    def evaluate(self, x, order=2):
        """Contact energy of this step for world sample positions x (k, 3) [m] at t_start + dt:
        (value [J], grad (k, 3) [N] = d value / d x, hess (k, 3, 3) [N/m] per-sample blocks, positive
        semidefinite). value is +inf if any sample is inside a collider (so a line search rejects the step);
        grad and hess are then None. grad/hess None below `order`. Includes the barrier (conservative),
        the lagged friction dissipation potential and the normal damping dissipation potential of this
        step (none before the first begin_step)."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        value, grad, hess = self._barrier(x, self._t_end, order)
        if not np.isfinite(value):
            return np.inf, None, None
        if self._dt is not None:
            for lag in self._lagged:
                value += self._dissipation(lag, x, grad, hess, order)
        return value, grad, hess

    def proximity(self, x):
        """(inside, near): (k,) bools of world sample positions x (k, 3) [m] at the step's end:
        inside (distance <= 0) some collider, and inside or within its barrier band dhat."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        inside = np.zeros(len(x), dtype=bool)
        near = np.zeros(len(x), dtype=bool)
        for c in self.colliders:
            d, _ = self._distances(c.surface(self._t_end), c.dhat, x)
            inside |= d <= 0.0
            near |= d < c.dhat
        return inside, near

    def max_step(self, x, dx, margin=0.1):
        """Optional line-search bound (not part of the agreed interface): the largest fraction
        t in [0, 1] (a float) such that no sample moves by more than (1 - margin) times its
        current distance to the nearest collider along x + t dx (x, dx (k, 3) [m], world, at the
        step's end time). The distance is 1-Lipschitz, so the whole segment stays outside every
        collider: no sample can tunnel through a thin collider in one trial (a conservative
        stand-in for continuous collision detection). Samples farther than their move are not
        limited. x must be outside all colliders."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        move = np.linalg.norm(np.asarray(dx, dtype=np.float64).reshape(-1, 3), axis=1)
        nearest = np.full(len(x), np.inf)
        for c in self.colliders:
            surface = c.surface(self._t_end)
            near = np.arange(len(x)) if surface.topology.is_open else np.flatnonzero(
                surface.box_distance(x) < move)
            if len(near):
                d, _, _, _ = surface.query(x[near])
                nearest[near] = np.minimum(nearest[near], d)
        limited = move > (1.0 - margin) * nearest
        if not limited.any():
            return 1.0
        return float(np.clip(np.min((1.0 - margin) * nearest[limited] / move[limited]), 0.0, 1.0))

    def forces(self, x):
        """(k, 3) [N] contact force on each sample at positions x (for reports/tests): -grad of the barrier.
        Colliders at the end of the current step (at t = 0 before the first begin_step)."""
        value, grad, _ = self._barrier(np.asarray(x, dtype=np.float64).reshape(-1, 3), self._t_end, 1)
        if not np.isfinite(value):
            raise ValueError("a contact sample is inside a collider: the contact force is unbounded")
        return -grad

    def _barrier(self, x, t, order):
        """Summed barrier value [J], grad (k, 3), hess (k, 3, 3) (or None) of x against colliders at t."""
        k = len(x)
        grad = np.zeros((k, 3)) if order >= 1 else None
        hess = np.zeros((k, 3, 3)) if order >= 2 else None
        value = 0.0
        for c, coef in zip(self.colliders, self._coef):
            d, n = self._distances(c.surface(t), c.dhat, x)
            if np.any(d <= 0.0):
                return np.inf, None, None
            band = np.flatnonzero(d < c.dhat)
            if len(band) == 0:
                continue
            b, b1, b2 = barrier(d[band], c.dhat)
            w = coef[band]
            value += float(np.dot(w, b))
            if order >= 1:
                grad[band] += (w * b1)[:, None] * n[band]
            if order >= 2:
                # b''(d) n n^T only: the curvature term b'(d) (I - n n^T) / r of an edge or vertex
                # closest point is negative semidefinite (b' < 0 in the band) and left out.
                hess[band] += (w * b2)[:, None, None] * np.einsum("ki,kj->kij", n[band], n[band])
        return value, grad, hess

    def _dissipation(self, lag, x, grad, hess, order):
        """Add one collider's friction and damping gradient / Hessian in place; return their value [J]."""
        if len(lag.idx) == 0:
            return 0.0
        dt = self._dt
        alpha = self.scheme.velocity_factor
        rel = x[lag.idx] - lag.ref         # (a, 3) = dt / alpha * the end relative velocity
        value = 0.0
        # Friction: mu lambda f0(|u|), u = T^T rel, smoothed below the slip speed EPS_V.
        u = np.einsum("aji,aj->ai", lag.tangents, rel)
        y = np.linalg.norm(u, axis=1)
        f0, g, dg = _f0_terms(y, EPS_V * dt / alpha)
        value += float(np.dot(lag.friction, f0))
        # Damping: alpha c / (2 dt) (n . rel)^2, whose gradient is c times the normal end velocity.
        a = np.einsum("aj,aj->a", lag.normal, rel)
        value += alpha * float(np.dot(lag.dashpot, a * a)) / (2.0 * dt)
        if order >= 1:
            gu = (lag.friction * g)[:, None] * u                              # (a, 2)
            grad[lag.idx] += np.einsum("aij,aj->ai", lag.tangents, gu)
            grad[lag.idx] += (alpha * lag.dashpot * a / dt)[:, None] * lag.normal
        if order >= 2:
            # d(g u)/du = g I + g'(y) y uu^T/|u|^2: PSD for IPC's f0 (eigenvalues g and f1'(y) >= 0).
            unit = u / np.maximum(y, 1e-300)[:, None]
            Hu = g[:, None, None] * np.eye(2) + (dg * y)[:, None, None] * np.einsum(
                "ai,aj->aij", unit, unit)
            Hu *= lag.friction[:, None, None]
            hess[lag.idx] += np.einsum("aik,akl,ajl->aij", lag.tangents, Hu, lag.tangents)
            hess[lag.idx] += (alpha * lag.dashpot / dt)[:, None, None] * np.einsum(
                "ai,aj->aij", lag.normal, lag.normal)
        return value
