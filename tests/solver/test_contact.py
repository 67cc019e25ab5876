"""Tests for solver.contact: collider distances, surface samples, barrier, friction, damping.

Oracles: analytic signed distances of a plane, a sphere and a box (static and keyed with scale and
rotation), finite differences of the energy's gradient and Hessian, the barrier's definition
(+inf inside, exactly 0 beyond the band), total surface area, a 1-D static equilibrium solved with
scipy, and the restitution of a linear spring-dashpot integrated with scipy.
"""

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

from solver import contact, integrators


# Meshes ---------------------------------------------------------------------------------------

def plane_mesh(half=1.0):
    """Square [-half, half]^2 at z = 0, normal +z (open)."""
    V = np.array([[-half, -half, 0.0], [half, -half, 0.0], [half, half, 0.0], [-half, half, 0.0]])
    return V, np.array([[0, 1, 2], [0, 2, 3]])


def box_surface(half=(1.0, 1.0, 1.0), cells=1):
    """Closed, outward triangulated surface of the box [-h, h], each face a cells x cells grid."""
    h = np.asarray(half, dtype=float)
    verts, tris = [], []
    s = np.linspace(-1.0, 1.0, cells + 1)
    for axis in range(3):
        for side in (-1.0, 1.0):
            u, v = [a for a in range(3) if a != axis]
            base = len(verts)
            for i in range(cells + 1):
                for j in range(cells + 1):
                    p = np.zeros(3)
                    p[axis], p[u], p[v] = side, s[i], s[j]
                    verts.append(p * h)
            for i in range(cells):
                for j in range(cells):
                    a = base + i * (cells + 1) + j
                    b, c, d = a + cells + 1, a + 1, a + cells + 2
                    tris += [[a, b, d], [a, d, c]]
            # Orient outward: flip this face's triangles if their normal points inward.
            block = np.array(tris[-2 * cells * cells:])
            P = np.array(verts)
            n = np.cross(P[block[0, 1]] - P[block[0, 0]], P[block[0, 2]] - P[block[0, 0]])
            if n[axis] * side < 0:
                tris[-2 * cells * cells:] = block[:, [0, 2, 1]].tolist()
    V = np.array(verts)
    # Merge duplicate vertices along the cube's edges.
    V_unique, inverse = np.unique(np.round(V, 12), axis=0, return_inverse=True)
    return V_unique, inverse.reshape(-1)[np.array(tris)]


def icosphere(radius=1.0, subdivisions=3):
    """Closed outward icosphere (20 * 4^s triangles) with vertices on the sphere."""
    t = (1.0 + 5 ** 0.5) / 2
    V = [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
         [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]
    F = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
         [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
         [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    V = [np.array(v, float) / np.linalg.norm(v) for v in V]
    for _ in range(subdivisions):
        cache, F2 = {}, []

        def mid(a, b):
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = V[a] + V[b]
                V.append(m / np.linalg.norm(m))
                cache[key] = len(V) - 1
            return cache[key]
        for a, b, c in F:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            F2 += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        F = F2
    return radius * np.array(V), np.array(F)


def box_sdf(p, half):
    """Exact signed distance of points p (n, 3) to the axis-aligned box [-half, half]."""
    q = np.abs(p) - half
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def make_contact(collider, x, masses=None, weights=None, integrator="newmark"):
    """A Contact of samples at x (k, 3) (rest = x, identity rows), masses 0.5 kg, weights 0.01 m^2."""
    k = len(x)
    masses = np.full(k, 0.5) if masses is None else masses
    weights = np.full(k, 0.01) if weights is None else weights
    colliders = collider if isinstance(collider, list) else [collider]
    c = contact.Contact(colliders, x, np.eye(3 * k), weights, masses)
    c.scheme = integrators.scheme(integrator)         # as dynamics.Simulation sets it
    return c


def fd_gradient(contact_, x, h=1e-7):
    """Central differences of value w.r.t. every coordinate of x (k, 3)."""
    out = np.zeros_like(x)
    for i in range(len(x)):
        for j in range(3):
            xp, xm = x.copy(), x.copy()
            xp[i, j] += h
            xm[i, j] -= h
            out[i, j] = (contact_.evaluate(xp, 0)[0] - contact_.evaluate(xm, 0)[0]) / (2 * h)
    return out


def fd_hessian_blocks(contact_, x, h=1e-7):
    """(k, 3, 3) central differences of grad: sample i's grad w.r.t. its own position (samples
    decouple, so shifting all of them at once gives every block)."""
    out = np.zeros((len(x), 3, 3))
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        out[:, :, j] = (contact_.evaluate(x + e, 1)[1] - contact_.evaluate(x - e, 1)[1]) / (2 * h)
    return out


# Signed distance ------------------------------------------------------------------------------

def test_plane_distance_is_height_one_sided_and_positive_beyond_the_rim():
    V, F = plane_mesh(1.0)
    plane = contact.MeshCollider(V, F)
    x = np.array([[0.2, -0.3, 0.05], [0.5, 0.5, -0.02], [0.0, 0.0, -3.0], [1.5, 0.0, -0.5],
                  [0.1, 0.9, 2.0]])
    d, n, closest = plane.signed_distance(x, 0.0)
    expected = np.array([0.05, -0.02, -3.0, np.hypot(0.5, 0.5), 2.0])
    np.testing.assert_allclose(d, expected, atol=1e-12)
    np.testing.assert_allclose(n[[0, 1, 2, 4]], np.tile([0, 0, 1.0], (4, 1)), atol=1e-12)
    np.testing.assert_allclose(n[3], [0.5 ** 0.5, 0, -(0.5 ** 0.5)], atol=1e-12)
    np.testing.assert_allclose(closest[3], [1.0, 0.0, 0.0], atol=1e-12)


def test_zero_area_triangles_are_ignored():
    V, F = plane_mesh(1.0)
    V = np.vstack([V, [[0.0, 0.0, 0.0]]])
    F = np.vstack([F, [[0, 2, 4], [4, 4, 1]]])                 # on the diagonal; collapsed
    plane = contact.MeshCollider(V, F)
    assert len(plane.triangles) == 2
    d, n, _ = plane.signed_distance(np.array([[0.0, 0.0, 0.01], [0.25, 0.25, -0.01]]), 0.0)
    np.testing.assert_allclose(d, [0.01, -0.01], atol=1e-15)
    np.testing.assert_allclose(n, [[0, 0, 1.0], [0, 0, 1.0]], atol=1e-15)


def test_sphere_distance_matches_the_analytic_sphere_within_the_tessellation_sag():
    R = 0.7
    V, F = icosphere(R, 3)
    sphere = contact.MeshCollider(V, F)
    # Radially outside a vertex the vertex is the closest point: exactly r - R.
    dirs = V[::37] / R
    r = np.linspace(0.75, 1.5, len(dirs))
    d, n, _ = sphere.signed_distance(dirs * r[:, None], 0.0)
    np.testing.assert_allclose(d, r - R, atol=1e-12)
    np.testing.assert_allclose(n, dirs, atol=1e-9)
    # Anywhere else the mesh lies between the sphere and its inscribed polyhedron.
    edge = np.max(np.linalg.norm(V[F[:, 0]] - V[F[:, 1]], axis=1))
    sag = R - np.sqrt(R ** 2 - edge ** 2 / 3)      # circumradius of a triangle of side <= edge
    rng = np.random.default_rng(3)
    u = rng.normal(size=(400, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    radii = rng.uniform(0.1, 1.6, 400)
    d, _, _ = sphere.signed_distance(u * radii[:, None], 0.0)
    assert np.all(d <= radii - R + sag + 1e-12) and np.all(d >= radii - R - 1e-12)
    assert np.all(np.sign(d[np.abs(radii - R) > sag]) == np.sign(radii - R)[np.abs(radii - R) > sag])


def test_box_distance_is_exact_everywhere_including_edges_and_corners():
    half = np.array([0.5, 0.3, 0.2])
    V, F = box_surface(half, cells=2)
    box = contact.MeshCollider(V, F)
    rng = np.random.default_rng(0)
    x = rng.uniform(-1.0, 1.0, size=(600, 3)) * (2 * half)
    d, n, _ = box.signed_distance(x, 0.0)
    np.testing.assert_allclose(d, box_sdf(x, half), atol=1e-12)
    # The gradient is the unit direction of the sdf: check by central differences where smooth.
    h = 1e-6
    fd = np.stack([(box_sdf(x + h * e, half) - box_sdf(x - h * e, half)) / (2 * h) for e in np.eye(3)], 1)
    smooth = np.linalg.norm(fd, axis=1) > 1 - 1e-6
    assert smooth.sum() > 500
    np.testing.assert_allclose(n[smooth], fd[smooth], atol=1e-5)


def keyed_motion(scale):
    """Object-to-world matrices of a keyed collider: scale (3,), rotation and translation in t."""
    def motion(t):
        A = np.eye(4)
        R = Rotation.from_rotvec(np.array([0.3, -0.5, 0.8]) * (0.2 + t)).as_matrix()
        A[:3, :3] = R @ np.diag(scale)
        A[:3, 3] = [0.1, -0.2 + t, 0.3 * t]
        return A
    return motion


keyed_box_motion = keyed_motion([1.0, 2.0, 0.5])


@pytest.mark.parametrize("scale", [[1.0, 2.0, 0.5], [1.5, 1.5, 1.5], [-1.5, 1.5, 1.5], [-1.0, 2.0, 0.5]],
                         ids=["non-uniform", "uniform", "mirrored", "mirrored non-uniform"])
def test_keyed_scaled_rotated_box_distance_is_in_world_metres_at_two_times(scale):
    half = np.array([0.4, 0.25, 0.6])
    V, F = box_surface(half, cells=1)
    motion = keyed_motion(scale)
    box = contact.MeshCollider(V, F, motion=motion, name="keyed box")
    rng = np.random.default_rng(1)
    world_half = half * np.abs(scale)
    for t in (0.0, 0.75):
        A = motion(t)
        R = A[:3, :3] @ np.diag(1.0 / np.abs(scale))          # rotation (times a mirror)
        local = rng.uniform(-2.0, 2.0, size=(300, 3)) * world_half
        x = local @ R.T + A[:3, 3]
        d, n, closest = box.signed_distance(x, t)
        np.testing.assert_allclose(d, box_sdf(local, world_half), atol=1e-12)
        np.testing.assert_allclose(np.abs(d), np.linalg.norm(x - closest, axis=1), atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
        np.testing.assert_allclose(box.world_vertices(t), V @ A[:3, :3].T + A[:3, 3], atol=1e-15)


def test_a_float32_blender_matrix_is_placed_as_a_similarity_within_its_round_off():
    half = np.array([0.4, 0.25, 0.6])
    V, F = box_surface(half, cells=1)
    exact = keyed_motion([1.3, 1.3, 1.3])
    box = contact.MeshCollider(V, F, motion=lambda t: exact(t).astype(np.float32), name="float32")
    A = exact(0.4)
    rng = np.random.default_rng(4)
    local = rng.uniform(-2.0, 2.0, size=(200, 3)) * half * 1.3
    x = local @ (A[:3, :3] / 1.3).T + A[:3, 3]
    d, n, _ = box.signed_distance(x, 0.4)
    np.testing.assert_allclose(d, box_sdf(local, half * 1.3), atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    assert box.surface(0.4).__class__.__name__ == "_Similar"      # no tree rebuilt per step


def test_collider_velocity_is_the_secant_of_the_material_point():
    V, F = box_surface((0.4, 0.25, 0.6), cells=1)
    box = contact.MeshCollider(V, F, motion=keyed_box_motion)
    X = np.array([[0.4, 0.1, -0.2], [-0.1, 0.25, 0.3]])          # points of the box (own space)
    t, dt = 0.3, 0.05
    at = lambda s: X @ keyed_box_motion(s)[:3, :3].T + keyed_box_motion(s)[:3, 3]
    np.testing.assert_allclose(box.velocity(at(t), t, dt), (at(t + dt) - at(t)) / dt, atol=1e-12)
    static = contact.MeshCollider(*box_surface((1, 1, 1)))
    np.testing.assert_array_equal(static.velocity(X, t, dt), 0.0)


# Surface samples ------------------------------------------------------------------------------

def test_surface_samples_weights_sum_to_the_area_and_are_deterministic():
    V, F = box_surface((0.5, 0.3, 0.2), cells=6)
    area = 2 * (1.0 * 0.6 + 1.0 * 0.4 + 0.6 * 0.4)
    idx, w = contact.surface_samples(V, F, 50)
    assert len(idx) == 50 and len(np.unique(idx)) == 50
    np.testing.assert_allclose(w.sum(), area, rtol=1e-12)
    assert np.all(w > 0)
    idx2, w2 = contact.surface_samples(V.copy(), F.copy(), 50)
    np.testing.assert_array_equal(idx, idx2)
    np.testing.assert_array_equal(w, w2)
    # Fewer vertices than asked: every used vertex, weights = vertex areas.
    V0, F0 = box_surface((1, 1, 1), cells=1)
    idx, w = contact.surface_samples(V0, F0, 100)
    assert sorted(idx) == list(range(8))
    # Each triangle of a 2 x 2 face has area 2, a third of it per corner.
    np.testing.assert_allclose(w, np.bincount(F0.ravel(), minlength=8)[idx] * 2.0 / 3.0, rtol=1e-12)


def test_surface_samples_pick_the_corners_of_a_cube_first():
    half = np.array([0.5, 0.3, 0.2])
    V, F = box_surface(half, cells=5)
    idx, _ = contact.surface_samples(V, F, 20)
    first = V[idx[:8]]
    np.testing.assert_allclose(np.abs(first), np.tile(half, (8, 1)), atol=1e-12)
    assert len({tuple(np.sign(p)) for p in first}) == 8
    assert not np.any(np.all(np.isclose(np.abs(V[idx[8:]]), half), axis=1))


def test_surface_samples_cover_the_surface_farthest_point_first():
    V, F = icosphere(1.0, 3)
    idx, w = contact.surface_samples(V, F, 60)
    # Farthest-point sampling: each new pick's distance to the earlier ones never increases.
    gaps = [np.min(np.linalg.norm(V[idx[:i]] - V[idx[i]], axis=1)) for i in range(8, 60)]
    assert np.all(np.diff(gaps) <= 1e-12)
    np.testing.assert_allclose(w.sum(), contact.vertex_areas(V, F).sum(), rtol=1e-12)


# Barrier --------------------------------------------------------------------------------------

def test_barrier_derivatives_match_finite_differences_and_are_c2_at_dhat():
    dhat = 0.02
    d = np.linspace(0.001, 0.0199, 30)
    b, b1, b2 = contact.barrier(d, dhat)
    h = 1e-8
    np.testing.assert_allclose(b1, (contact.barrier(d + h, dhat)[0] - contact.barrier(d - h, dhat)[0]) / (2 * h),
                               rtol=1e-5, atol=1e-10)
    np.testing.assert_allclose(b2, (contact.barrier(d + h, dhat)[1] - contact.barrier(d - h, dhat)[1]) / (2 * h),
                               rtol=1e-5, atol=1e-8)
    np.testing.assert_allclose(contact.barrier(np.array([dhat]), dhat), [[0.0], [0.0], [0.0]], atol=1e-15)
    assert np.all(b > 0) and np.all(b1 < 0) and np.all(b2 > 0)


def test_energy_is_inf_inside_and_exactly_zero_beyond_the_band():
    V, F = plane_mesh(2.0)
    plane = contact.MeshCollider(V, F, thickness=0.02, friction=0.5, damping=0.5)
    x = np.array([[0.0, 0.0, 0.5], [0.3, 0.1, 0.0201], [-0.4, 0.2, 0.02]])
    c = make_contact(plane, x)
    c.begin_step(0.0, 0.01, x, np.zeros_like(x))
    value, grad, hess = c.evaluate(x)
    assert value == 0.0
    np.testing.assert_array_equal(grad, 0.0)
    np.testing.assert_array_equal(hess, 0.0)
    for z in (0.0, -1e-9, -0.5):
        y = x.copy()
        y[1, 2] = z
        assert c.evaluate(y)[0] == np.inf
        assert c.evaluate(y, order=0)[0] == np.inf


def test_barrier_gradient_and_hessian_match_finite_differences_on_a_box():
    half = np.array([1.0, 1.0, 0.5])
    V, F = box_surface(half, cells=3)
    box = contact.MeshCollider(V, F, thickness=0.05, name="box")
    # Samples in the band above faces (the distance is linear there) and one near an edge.
    x = np.array([[0.1, 0.2, 0.52], [0.3, -0.4, 0.535], [1.02, 0.1, 0.0], [-0.2, 1.04, 0.1],
                  [0.5, 0.5, 0.508]])
    c = make_contact(box, x)
    value, grad, hess = c.evaluate(x)
    assert value > 0
    np.testing.assert_allclose(grad, fd_gradient(c, x), rtol=1e-5, atol=1e-6 * np.abs(grad).max())
    np.testing.assert_allclose(hess, fd_hessian_blocks(c, x), rtol=1e-5, atol=1e-6 * np.abs(hess).max())
    np.testing.assert_allclose(c.forces(x), -grad, rtol=0, atol=0)


def test_barrier_gradient_matches_finite_differences_on_a_sphere():
    V, F = icosphere(0.5, 3)
    sphere = contact.MeshCollider(V, F, thickness=0.03)
    rng = np.random.default_rng(5)
    u = rng.normal(size=(12, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    x = u * rng.uniform(0.51, 0.525, 12)[:, None]
    c = make_contact(sphere, x)
    value, grad, hess = c.evaluate(x)
    assert np.isfinite(value) and value > 0
    np.testing.assert_allclose(grad, fd_gradient(c, x, h=1e-8), rtol=1e-5, atol=1e-6 * np.abs(grad).max())
    # Along the normal the Hessian is exact (only the NSD curvature term is left out).
    n = -grad / np.linalg.norm(grad, axis=1)[:, None]
    fd = fd_hessian_blocks(c, x, h=1e-8)
    np.testing.assert_allclose(np.einsum("ki,kij,kj->k", n, hess, n), np.einsum("ki,kij,kj->k", n, fd, n),
                               rtol=1e-4)
    assert np.all(np.linalg.eigvalsh(hess) >= -1e-9 * np.abs(hess).max())


def moving_plane(t):
    """Ground plane sliding along x and rising slowly."""
    A = np.eye(4)
    A[:3, 3] = [0.4 * t, -0.1 * t, 0.01 * t]
    return A


@pytest.mark.parametrize("integrator", ["newmark", "implicit_euler"])
@pytest.mark.parametrize("friction, damping", [(0.6, 0.0), (0.0, 0.8), (0.4, 0.5)])
def test_friction_and_damping_gradient_and_hessian_match_finite_differences(friction, damping, integrator):
    V, F = plane_mesh(3.0)
    ground = contact.MeshCollider(V, F, motion=moving_plane, thickness=0.02, friction=friction,
                                  damping=damping, name="ground")
    x0 = np.array([[0.0, 0.0, 0.012], [0.5, -0.2, 0.016], [-0.3, 0.4, 0.008], [0.2, 0.2, 0.5]])
    v0 = np.array([[0.3, 0.0, -0.2], [0.0, 0.0, 0.0], [-0.1, 0.2, -1.0], [0.0, 0.0, -0.5]])
    dt = 0.01
    c = make_contact(ground, x0, integrator=integrator)
    c.begin_step(0.2, dt, x0, v0)
    # End positions: slipping fast (beyond eps_v dt), slowly (inside it), and not in contact.
    x = x0 + np.array([[0.004, 0.0005, 0.001], [0.004 + 1e-6, -0.001 + 2e-6, 0.0001], [-0.001, 0.002, 0.0015],
                       [0.0, 0.0, -0.001]])
    x[:, 2] += 0.0001                      # the plane rises by 1e-4 over the step
    value, grad, hess = c.evaluate(x)
    assert np.isfinite(value)
    scale = np.abs(grad).max()
    np.testing.assert_allclose(grad, fd_gradient(c, x, h=1e-9), rtol=1e-4, atol=1e-5 * scale)
    np.testing.assert_allclose(hess, fd_hessian_blocks(c, x, h=1e-9), rtol=1e-4,
                               atol=1e-5 * np.abs(hess).max())
    assert np.all(np.linalg.eigvalsh(hess) >= -1e-9 * np.abs(hess).max())
    # The dissipation only adds to the barrier: the barrier alone is the contract's forces().
    barrier_only = make_contact(contact.MeshCollider(V, F, motion=moving_plane, thickness=0.02,
                                                         damping=0.0), x0)
    barrier_only.begin_step(0.2, dt, x0, v0)
    np.testing.assert_allclose(c.forces(x), -barrier_only.evaluate(x)[1], rtol=1e-12)


def test_friction_opposes_slip_relative_to_the_moving_collider_with_coulomb_magnitude():
    V, F = plane_mesh(3.0)
    mu, dt = 0.5, 0.01
    ground = contact.MeshCollider(V, F, motion=moving_plane, thickness=0.02, friction=mu, damping=0.0)
    x0 = np.array([[0.0, 0.0, 0.01]])
    c = make_contact(ground, x0)
    c.begin_step(0.0, dt, x0, np.zeros((1, 3)))
    x = x0 + [0, 0, 0.01 * dt]              # same height above the plane, which rose by 0.01 dt
    normal_force = c.forces(x)[0, 2]
    friction_force = -(c.evaluate(x)[1][0] + c.forces(x)[0])
    # The body stays while the ground slides by (0.4, -0.1) dt: it is dragged along.
    direction = np.array([0.4, -0.1]) / np.linalg.norm([0.4, -0.1])
    np.testing.assert_allclose(friction_force[:2], mu * normal_force * direction, rtol=1e-9)
    assert abs(friction_force[2]) < 1e-9 * normal_force


@pytest.mark.parametrize("integrator, alpha", [("newmark", 2.0), ("implicit_euler", 1.0)])
def test_friction_and_damping_act_on_the_schemes_end_velocity_relative_to_the_collider(integrator, alpha):
    """Newmark's end velocity is 2 (x - x0)/dt - v0, implicit Euler's (x - x0)/dt (dynamics.py):
    where it equals the collider's velocity, friction and damping vanish; otherwise the force
    opposes the relative end velocity."""
    V, F = plane_mesh(3.0)
    ground = contact.MeshCollider(V, F, motion=moving_plane, thickness=0.02, friction=0.5, damping=0.7)
    x0 = np.array([[0.0, 0.0, 0.01], [0.3, -0.2, 0.015]])
    v0 = np.array([[1.0, 0.5, -0.3], [-0.2, 0.1, -0.5]])
    dt, t0 = 0.01, 0.1
    c = make_contact(ground, x0, integrator=integrator)
    c.begin_step(t0, dt, x0, v0)
    v_collider = ground.velocity(x0 * [1, 1, 0], t0, dt)            # a translation: same everywhere
    end = lambda v_end: x0 + dt / alpha * (v_end + (alpha - 1.0) * v0)
    dissipative = lambda x: c.evaluate(x)[1] + c.forces(x)           # friction + damping gradient
    np.testing.assert_allclose(dissipative(end(v_collider)), 0.0, atol=1e-9)
    rng = np.random.default_rng(2)
    for _ in range(5):
        v_rel = rng.normal(size=(2, 3)) * 0.3
        force = -dissipative(end(v_collider + v_rel))
        assert np.all(np.einsum("kj,kj->k", force, v_rel) < 0)


def test_max_step_keeps_the_whole_segment_outside_a_thin_collider():
    half = np.array([1.0, 1.0, 0.005])                       # a 1 cm board
    V, F = box_surface(half, cells=2)
    board = contact.MeshCollider(V, F, thickness=0.02, name="board")
    x = np.array([[0.1, 0.2, 0.03], [0.5, -0.5, 0.3], [3.0, 0.0, 0.0]])
    dx = np.array([[0.02, 0.0, -0.1], [0.0, 0.0, -0.1], [0.0, 0.0, -5.0]])
    c = make_contact(board, x)
    assert c.evaluate(x + dx)[0] < np.inf                     # the full step tunnels through
    t = c.max_step(x, dx)
    assert 0.0 < t < 1.0
    path = np.linspace(0.0, t, 201)
    d = np.stack([board.signed_distance(x + s * dx, 0.0)[0] for s in path])
    assert np.all(d > 0.0)
    np.testing.assert_allclose(t, 0.9 * (0.03 - 0.005) / np.linalg.norm(dx[0]), rtol=1e-12)
    assert c.max_step(x, 0.01 * dx) == 1.0


def test_damping_ratio_gives_the_users_restitution_for_a_linear_spring_dashpot():
    m, k = 0.3, 1.0e4
    for damping in (0.0, 0.25, 0.6, 0.9):
        zeta = contact.restitution_damping_ratio(damping)
        c = 2 * zeta * np.sqrt(m * k)
        # Impact at 1 m/s on a spring-dashpot (contact while x > 0).
        hit = lambda t, y: y[0] + 1e-12 if t > 0 else 1.0
        hit.terminal, hit.direction = True, -1
        sol = solve_ivp(lambda t, y: [y[1], -(k * y[0] + c * y[1]) / m], (0, 1.0), [0.0, 1.0],
                        events=hit, rtol=1e-10, atol=1e-12, max_step=1e-4)
        out = -sol.y_events[0][0][1]
        np.testing.assert_allclose(out, 1.0 - damping, atol=2e-3)
    assert contact.restitution_damping_ratio(1.0) == 1.0


def translation(x, y, z):
    A = np.eye(4)
    A[:3, 3] = [x, y, z]
    return A


def test_check_start_names_the_collider():
    V, F = box_surface((0.5, 0.5, 0.5))
    colliders = [contact.MeshCollider(*plane_mesh(), name="Floor"),
                 contact.MeshCollider(V, F, motion=lambda t: translation(0, 0, 2 - t), name="Crate")]
    x = np.array([[0.0, 0.0, 0.5], [0.1, 0.1, 1.2]])
    c = make_contact(colliders, x)
    c.check_start(x, 0.0)                       # crate at z = 2 +- 0.5: outside
    with pytest.raises(ValueError, match="Crate"):
        c.check_start(x, 0.5)                   # crate at 1.5 +- 0.5 contains the second sample (z = 1.2)
    with pytest.raises(ValueError, match="Floor"):
        c.check_start(x - [0, 0, 0.6], 0.0)


# Small rigid-translation simulations (the dynamics' step objective on 3 unknowns) -------------

def simulate_translation(contact_, X, c0, v0, mass, dt, steps, scheme, gravity=(0.0, 0.0, -9.81)):
    """A rigid body translating by c (3,), samples at X + c, stepped by the dynamics' objective
    (dynamics.py): Newmark  2/dt^2 M |c - c_hat|^2, c_hat = c + dt v + dt^2/4 (a + g), or
    implicit Euler 1/(2 dt^2) M |c - c_hat|^2, c_hat = c + dt v + dt^2 g, plus the contact
    energy, by Newton with a backtracking Armijo line search (bounded by max_step). Returns
    (steps+1, 3) c and v. Static colliders."""
    g = np.asarray(gravity, dtype=float)
    c, v = np.array(c0, dtype=float), np.array(v0, dtype=float)
    a = g + contact_.forces(X + c).sum(axis=0) / mass          # consistent start acceleration
    W = mass * (2.0 if scheme == "newmark" else 0.5) / dt ** 2
    cs, vs = [c.copy()], [v.copy()]
    for n in range(steps):
        contact_.begin_step(n * dt, dt, X + c, np.tile(v, (len(X), 1)))
        c_hat = c + dt * v + (dt * dt / 4 * (a + g) if scheme == "newmark" else dt * dt * g)
        objective = lambda y: W * np.sum((y - c_hat) ** 2) + contact_.evaluate(X + y, 0)[0]
        y = c.copy()
        for _ in range(50):
            _, grad, hess = contact_.evaluate(X + y)
            G = 2 * W * (y - c_hat) + grad.sum(axis=0)
            step = -np.linalg.solve(2 * W * np.eye(3) + hess.sum(axis=0), G)
            t = contact_.max_step(X + y, np.tile(step, (len(X), 1)))
            f0 = objective(y)
            while objective(y + t * step) > f0 + 1e-4 * t * (G @ step) and t > 1e-12:
                t *= 0.5
            y = y + t * step
            if np.linalg.norm(t * step) < 1e-12:
                break
        if scheme == "newmark":
            a = 4 / dt ** 2 * (y - c - dt * v) - a
            v = 2 / dt * (y - c) - v
        else:
            v = (y - c) / dt
        c = y
        cs.append(c.copy())
        vs.append(v.copy())
    return np.array(cs), np.array(vs)


def four_point_block(scheme, friction, damping, mass=2.0):
    V, F = plane_mesh(5.0)
    ground = contact.MeshCollider(V, F, thickness=0.02, friction=friction, damping=damping, name="ground")
    X = np.array([[x, y, 0.0] for x in (-0.1, 0.1) for y in (-0.1, 0.1)])
    c = contact.Contact([ground], X, None, np.full(4, 0.01), np.full(4, mass / 4))
    c.scheme = integrators.scheme(scheme)
    rest = brentq(lambda z: c.forces(X + [0, 0, z])[:, 2].sum() - mass * 9.81, 1e-9, 0.02 - 1e-12)
    return c, X, rest


@pytest.mark.parametrize("scheme", ["newmark", "implicit_euler"])
def test_a_block_sliding_on_the_ground_stops_after_the_coulomb_distance(scheme):
    """Oracle: a block sliding at v with friction mu decelerates at mu g and stops after
    v^2 / (2 mu g), in v / (mu g) seconds; it keeps its rest height meanwhile."""
    mu, v, dt, mass = 0.5, 2.0, 1 / 240, 2.0
    c, X, rest = four_point_block(scheme, mu, 0.5, mass)
    cs, vs = simulate_translation(c, X, [0, 0, rest], [v, 0, 0], mass, dt, 130, scheme)
    np.testing.assert_allclose(cs[-1, 0], v ** 2 / (2 * mu * 9.81), rtol=0.02)
    np.testing.assert_allclose(np.argmax(np.abs(vs[:, 0]) < 1e-3) * dt, v / (mu * 9.81), atol=2 * dt)
    assert np.all(np.abs(vs[-10:, 0]) < 1e-4)
    np.testing.assert_allclose(cs[:, 2], rest, atol=1e-4 * 0.02)


@pytest.mark.parametrize("scheme", ["newmark", "implicit_euler"])
def test_a_dropped_block_comes_to_rest_at_the_static_equilibrium_inside_the_band(scheme):
    dt, mass = 1 / 240, 2.0
    c, X, rest = four_point_block(scheme, 0.5, 1.0, mass)
    assert 0.0 < rest < 0.02
    cs, vs = simulate_translation(c, X, [0, 0, 0.3], [0, 0, 0], mass, dt, 240, scheme)
    assert np.all(cs[:, 2] > 0.0)
    np.testing.assert_allclose(cs[-1, 2], rest, atol=1e-6)
    np.testing.assert_allclose(vs[-1], 0.0, atol=1e-4)


# Stiffness ------------------------------------------------------------------------------------

@pytest.mark.parametrize("share", [1.0, 6.0, 100.0])
def test_a_resting_sample_carries_its_load_inside_the_band(share):
    """A sample carrying `share` times its own weight (1: uniform pressure, 6: a box on one face,
    100: the body on 3 of 300 samples) rests at 0 < d < dhat where the barrier force balances it."""
    V, F = plane_mesh(2.0)
    dhat = 0.02
    ground = contact.MeshCollider(V, F, thickness=dhat)
    k = 300
    masses = np.full(k, 2.0 / k)
    weights = np.full(k, 6.0 / k)
    x = np.column_stack([np.zeros(k), np.zeros(k), np.full(k, 1.0)])
    c = make_contact(ground, x, masses, weights)
    load = share * masses[0] * 9.81
    force = lambda d: c.forces(np.array([[0.0, 0.0, d]] + [[0.0, 0.0, 1.0]] * (k - 1)))[0, 2]
    assert force(dhat) == 0.0 and force(1e-12 * dhat) > load
    d = brentq(lambda d: force(d) - load, 1e-12 * dhat, dhat, xtol=1e-15)
    assert 0.0 < d < dhat
    np.testing.assert_allclose(force(d), load, rtol=1e-9)
    # The documented rest heights of the stiffness choice.
    expected = {1.0: 0.982, 6.0: 0.956, 100.0: 0.828}[share]
    assert abs(d / dhat - expected) < 0.002
