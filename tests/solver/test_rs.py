"""Tests for solver.rs: rotation-strain coordinates and Poisson reconstruction (SPEC.md 3 and 8).

Oracles: exact affine / rigid / P1 fields, scipy's rotation exponential, central finite
differences, libigl's cotangent Laplacian, signed tet volumes.
"""

import igl
import numpy as np
import pytest
import scipy.sparse.linalg as spla
from scipy.spatial.transform import Rotation

from solver import fem, meshgen, modes, rs

DEG = np.pi / 180.0


def distorted_box(size=(2.0, 1.0, 1.5), cells=(4, 3, 3), seed=0):
    """Box tet mesh with randomly moved interior nodes (no axis-aligned special cases)."""
    X, T = meshgen.box_tet_mesh(size, cells)
    rng = np.random.default_rng(seed)
    h = min(s / c for s, c in zip(size, cells))
    interior = np.all((X > 1e-9) & (X < np.array(size) - 1e-9), axis=1)
    X = X.copy()
    X[interior] += rng.uniform(-0.15 * h, 0.15 * h, (interior.sum(), 3))
    return X, fem.orient_tets(X, T)


def diagonal(X):
    return float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))


def unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def reconstruct_free(X, T, x, reference=None):
    """Psi(y(x)) for a free body, mean displacement taken from x; returns (x_rec, y)."""
    recon = rs.PoissonReconstruction(X, T)
    y, _ = rs.pose_to_rs(X, T, x, reference=reference)
    u = recon.reconstruct(y, mean_displacement=recon.weighted_mean(x - X))
    return X + u, y


def central_differences(f, y, h=1e-6):
    """(E, out, 9) central differences of f: (E, 9) -> (E, out) w.r.t. each y_k."""
    columns = []
    for k in range(y.shape[1]):
        step = np.zeros_like(y)
        step[:, k] = h
        columns.append((f(y + step) - f(y - step)) / (2.0 * h))
    return np.stack(columns, axis=-1)


# 1. Linear operator Q ------------------------------------------------------------------------

def test_rs_operator_of_affine_displacement_is_axial_skew_and_sym():
    X, T = distorted_box()
    rng = np.random.default_rng(1)
    A, c = rng.normal(size=(3, 3)), rng.normal(size=3)
    u = X @ A.T + c
    y = (rs.rs_operator(X, T) @ u.reshape(-1)).reshape(len(T), 9)
    skew_part, sym_part = 0.5 * (A - A.T), 0.5 * (A + A.T)
    omega = np.array([skew_part[2, 1], skew_part[0, 2], skew_part[1, 0]])
    strain = sym_part[[0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]
    np.testing.assert_allclose(y, np.broadcast_to(np.r_[omega, strain], y.shape), atol=1e-12)
    np.testing.assert_allclose(rs.skew(omega), skew_part, atol=1e-15)


# 2. Rigid motions ----------------------------------------------------------------------------

@pytest.mark.parametrize("axis, degrees", [((0, 0, 1), 30.0), ((1, 2, -0.5), 90.0),
                                           ((1, 1, 1), 170.0), ((-0.3, 1, 0.2), 170.0)])
def test_rigid_motion_is_reproduced_with_zero_strain(axis, degrees):
    X, T = distorted_box()
    axis = unit(axis)
    R = Rotation.from_rotvec(degrees * DEG * axis).as_matrix()
    x = X @ R.T + np.array([0.3, -1.2, 2.0])
    x_rec, y = reconstruct_free(X, T, x)
    error = np.abs(x_rec - x).max() / diagonal(X)
    print(f"rigid {degrees:.0f} deg about {np.round(axis, 3)}: max error / diagonal = {error:.2e}")
    assert error < 1e-8
    np.testing.assert_allclose(y[:, 3:], 0.0, atol=1e-12)
    np.testing.assert_allclose(y[:, :3], np.broadcast_to(degrees * DEG * axis, (len(T), 3)),
                               atol=1e-10)


def test_rotation_to_350_degrees_by_continuous_frames():
    """Frames 0 -> 350 deg in steps of < 30 deg, each referenced to the previous frame's omega."""
    X, T = distorted_box()
    axis = unit((0.2, -1.0, 0.4))
    recon = rs.PoissonReconstruction(X, T)
    y = None
    for degrees in np.linspace(0.0, 350.0, 13):
        R = Rotation.from_rotvec(degrees * DEG * axis).as_matrix()
        x = X @ R.T + np.array([1.0, 0.0, -0.5]) * degrees / 350.0
        y, _ = rs.pose_to_rs(X, T, x, reference=None if y is None else y[:, :3])
    magnitude = np.linalg.norm(y[:, :3], axis=1) / DEG
    u = recon.reconstruct(y, mean_displacement=recon.weighted_mean(x - X))
    error = np.abs(X + u - x).max() / diagonal(X)
    print(f"rigid 350 deg (continuous): |omega| in [{magnitude.min():.6f}, {magnitude.max():.6f}]"
          f" deg, max error / diagonal = {error:.2e}")
    np.testing.assert_allclose(y[:, :3], np.broadcast_to(350.0 * DEG * axis, (len(T), 3)),
                               atol=1e-9)
    assert error < 1e-8


def test_branch_propagation_follows_a_twist_past_pi():
    """Without a reference, omega of a 270 deg twist grows continuously along the bar."""
    X, T = meshgen.box_tet_mesh((4.0, 0.4, 0.4), (20, 2, 2), origin=(0.0, -0.2, -0.2))
    phi = 270.0 * DEG * X[:, 0] / 4.0
    c, s = np.cos(phi), np.sin(phi)
    x = np.stack([X[:, 0], c * X[:, 1] - s * X[:, 2], s * X[:, 1] + c * X[:, 2]], axis=1)
    y, inverted = rs.pose_to_rs(X, T, x)
    centroid_phi = 270.0 * DEG * X[T, 0].mean(axis=1) / 4.0
    assert not inverted.any()
    assert np.abs(y[:, 0] - centroid_phi).max() < 0.2       # shear tilts the axis only slightly
    assert y[:, 0].max() > 4.0                              # past pi, not wrapped to -pi..pi
    # Neighbours differ by the (coarse) shear rotation, < 0.6 rad here; a wrong branch jumps
    # by about 2 pi, as the principal values do where the twist passes pi.
    neighbours = rs.tet_neighbours(T)
    e, f = np.nonzero(neighbours >= 0)

    def largest_jump(omega):
        return np.linalg.norm(omega[e] - omega[neighbours[e, f]], axis=1).max()

    assert largest_jump(y[:, :3]) < 1.0
    R, _, _ = rs.polar_decomposition(rs.deformation_gradients(X, T, x))
    assert largest_jump(rs.log_rotation(R)) > 5.0


# 3. Smooth non-rigid deformation -------------------------------------------------------------

def test_smooth_compatible_deformation_is_reproduced():
    """Psi(y(x)) = x for any P1 pose x without inverted tets, up to round-off.

    x at the nodes defines a P1 field whose gradient on tet e is exactly F_e = G_e x. The polar
    decomposition and exp(log R) = R are exact up to round-off, so rs_target gives b_e = F_e - I
    = G_e u exactly: the least-squares residual is zero at u, and the minimiser is unique once
    the mean is fixed. Smoothness only keeps the tets uninverted and the strains moderate.
    """
    X, T = distorted_box(size=(3.0, 1.0, 1.0), cells=(9, 3, 3))
    X0, X1, X2 = (X - X.mean(axis=0)).T
    phi = 0.5 * X0                                           # twist about x, 0.5 rad/m
    Y1, Y2 = np.cos(phi) * X1 - np.sin(phi) * X2, np.sin(phi) * X1 + np.cos(phi) * X2
    radius = 2.5                                             # then bend in the x-y plane
    stretch = 1.0 + 0.1 * X2                                 # and a mild non-uniform stretch
    x = np.stack([(radius + Y1) * np.sin(stretch * X0 / radius),
                  (radius + Y1) * np.cos(stretch * X0 / radius) - radius, Y2 * stretch], axis=1)
    assert not (fem.tet_volumes(x, T) <= 0).any()
    x_rec, _ = reconstruct_free(X, T, x)
    error = np.abs(x_rec - x).max() / diagonal(X)
    print(f"smooth bend/twist: max error / diagonal = {error:.2e}")
    assert error < 1e-6


# 4.-6. Rotations -----------------------------------------------------------------------------

def test_exp_rotation_matches_scipy_and_is_a_rotation():
    rng = np.random.default_rng(2)
    directions = rng.normal(size=(200, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    angles = np.concatenate([rng.uniform(0.0, 12.0, 150), [0.0, 1e-9, 9.9e-5, 1.01e-4, np.pi],
                             rng.uniform(0.0, 1e-3, 45)])
    omega = directions * angles[:, None]
    R = rs.exp_rotation(omega)
    np.testing.assert_allclose(R, Rotation.from_rotvec(omega).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)
    # Across the Taylor switch at 1e-4 the map stays continuous (and exact).
    n = directions[:1]
    below, above = rs.exp_rotation(n * (1e-4 - 1e-12)), rs.exp_rotation(n * (1e-4 + 1e-12))
    assert np.abs(below - above).max() < 1e-15 + 3e-12


def random_y(rng, angles):
    directions = rng.normal(size=(len(angles), 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    return np.concatenate([directions * np.asarray(angles)[:, None],
                           0.2 * rng.normal(size=(len(angles), 6))], axis=1)


JACOBIAN_ANGLES = [0.0, 3e-6, 8e-6, 5e-4, 0.3, 1.0, 2.5, np.pi - 1e-3, np.pi, np.pi + 1e-3, 5.0]


def relative_error(a, b):
    return np.linalg.norm(a - b, axis=(-2, -1)) / np.linalg.norm(b, axis=(-2, -1))


def test_exp_rotation_derivative_matches_finite_differences():
    y = random_y(np.random.default_rng(3), JACOBIAN_ANGLES)
    dR = rs.exp_rotation_derivative(y[:, :3])                        # (E, 3, 3, 3), [:, i]
    fd = central_differences(lambda w: rs.exp_rotation(w).reshape(-1, 9), y[:, :3])
    error = relative_error(dR.reshape(-1, 3, 9), np.swapaxes(fd, 1, 2))
    print(f"dR/domega vs central differences: max relative error {error.max():.2e}")
    assert error.max() < 1e-6
    np.testing.assert_allclose(rs.exp_rotation_derivative(np.zeros((1, 3)))[0],
                               rs.skew(np.eye(3)), atol=1e-15)


def test_rs_target_jacobian_matches_finite_differences():
    y = random_y(np.random.default_rng(4), JACOBIAN_ANGLES)
    J = rs.rs_target_jacobian(y)
    fd = central_differences(lambda v: rs.rs_target(v).reshape(-1, 9), y)
    error = relative_error(J, fd)
    print(f"d vec(b)/dy vs central differences: max relative error {error.max():.2e}")
    assert error.max() < 1e-6


def test_log_rotation_round_trip_and_robust_at_zero_and_pi():
    rng = np.random.default_rng(5)
    directions = rng.normal(size=(40, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    angles = np.concatenate([rng.uniform(0.0, np.pi, 32),
                             [0.0, 1e-12, 1e-6, 1e-4, np.pi - 1e-9, np.pi - 1e-6, np.pi, 3.0]])
    omega = directions * angles[:, None]
    R = rs.exp_rotation(omega)
    log = rs.log_rotation(R)
    assert np.all(np.isfinite(log))
    assert np.linalg.norm(log, axis=1).max() <= np.pi + 1e-12
    np.testing.assert_allclose(rs.exp_rotation(log), R, atol=1e-13)
    not_pi = angles < np.pi - 1e-3
    np.testing.assert_allclose(log[not_pi], omega[not_pi], atol=1e-13)


def test_log_rotation_picks_the_branch_closest_to_the_reference():
    n = unit((1.0, -2.0, 0.5))
    theta = 0.4
    R = rs.exp_rotation((theta * n)[None].repeat(4, axis=0))
    # Same rotation, references near 2 pi - theta about -n, near theta + 2 pi about n,
    # near theta itself, and at zero.
    references = np.stack([-(2 * np.pi - theta - 0.3) * n, (theta + 2 * np.pi + 0.5) * n,
                           theta * n + 0.1, np.zeros(3)])
    log = rs.log_rotation(R, reference=references)
    np.testing.assert_allclose(log, np.stack([(theta - 2 * np.pi) * n, (theta + 2 * np.pi) * n,
                                              theta * n, theta * n]), atol=1e-12)
    # Near pi: a rotation by pi - d about n is pi + d about -n; a reference at -pi n picks it.
    d = 1e-3
    R_pi = rs.exp_rotation(((np.pi - d) * n)[None])
    np.testing.assert_allclose(rs.log_rotation(R_pi, reference=-np.pi * n[None]),
                               -(np.pi + d) * n[None], atol=1e-12)



def test_a_full_turn_keeps_the_reference_axis():
    """A rotation by exactly 2 pi k comes back from its matrix as a rotation vector of rounding
    size in an arbitrary direction; the branch closest to a reference near 2 pi n is 2 pi n."""
    n = unit((0.3, 1.0, -0.2))
    # The identity, up to rounding, as a pose's polar decomposition gives it.
    full_turn = rs.exp_rotation((2.5 * n)[None]) @ rs.exp_rotation(((2 * np.pi - 2.5) * n)[None])
    log = rs.log_rotation(full_turn, reference=(2 * np.pi - 0.6) * n[None])
    np.testing.assert_allclose(log, 2 * np.pi * n[None], atol=1e-9)


# 7. Pinned reconstruction and the Laplacian --------------------------------------------------

def test_pinned_reconstruction_holds_pins_and_solves_normal_equations():
    X, T = distorted_box()
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    recon = rs.PoissonReconstruction(X, T, pinned_nodes=pinned)
    b = np.random.default_rng(6).normal(size=(len(T), 3, 3))
    u = recon.solve(b)
    assert np.all(u[pinned] == 0.0)
    # Free rows of the normal equations: (L_s u)_k = sum_e V_e grad(phi_k) . b_e[i, :].
    free = np.setdiff1d(np.arange(len(X)), pinned)
    grads, volumes = fem.shape_gradients(X, T), fem.tet_volumes(X, T)
    rhs = np.zeros((len(X), 3))
    np.add.at(rhs, T, np.einsum("e,ekj,eij->eki", volumes, grads, b))
    L = -igl.cotmatrix(X, T)
    np.testing.assert_allclose(recon.laplacian.toarray(), L.toarray(), atol=1e-12)
    np.testing.assert_allclose((L @ u)[free], rhs[free], atol=1e-10 * np.abs(rhs).max())


def test_batched_solve_equals_one_solve_per_target():
    """solve_batch (one product and one SuperLU call for k targets) gives what solve gives
    target by target: pinned, and free with a prescribed mean displacement."""
    X, T = distorted_box()
    targets = np.random.default_rng(8).normal(size=(5, len(T), 3, 3))
    for pinned, mean in ((np.flatnonzero(X[:, 0] < 1e-9), None), (None, [0.1, -0.2, 0.3])):
        recon = rs.PoissonReconstruction(X, T, pinned_nodes=pinned)
        batch = recon.solve_batch(targets, mean_displacement=mean)
        single = np.stack([recon.solve(b, mean_displacement=mean) for b in targets])
        assert batch.shape == (5, len(X), 3)
        np.testing.assert_allclose(batch, single, rtol=0, atol=1e-12 * np.abs(single).max())
        as_list = recon.solve_batch(list(targets), mean_displacement=mean)
        np.testing.assert_array_equal(as_list, batch)
        generated = recon.solve_batch((b for b in targets), mean_displacement=mean)
        np.testing.assert_array_equal(generated, batch)
        if mean is not None:
            np.testing.assert_allclose([recon.weighted_mean(u) for u in batch],
                                       np.tile(mean, (5, 1)), atol=1e-12)


def test_entry_major_targets_give_the_same_right_hand_sides_and_solves():
    """rs_target_entries is rs_target laid out (3, 3, E); PoissonReconstruction takes either
    layout (entry_major) and gives the same right-hand sides and displacements."""
    X, T = distorted_box()
    recon = rs.PoissonReconstruction(X, T, pinned_nodes=np.flatnonzero(X[:, 0] < 1e-9))
    poses = np.random.default_rng(9).normal(scale=0.4, size=(3, len(T), 9))
    entries = [rs.rs_target_entries(y) for y in poses]
    targets = [rs.rs_target(y) for y in poses]
    for entry, target in zip(entries, targets):
        np.testing.assert_array_equal(entry.transpose(2, 0, 1), target)
        rhs = recon.right_hand_side(target)
        np.testing.assert_allclose(recon.right_hand_side(entry, entry_major=True), rhs,
                                   rtol=0, atol=1e-13 * np.abs(rhs).max())
    single = np.stack([recon.solve(target) for target in targets])
    np.testing.assert_allclose(recon.solve_batch(entries, entry_major=True), single,
                               rtol=0, atol=1e-12 * np.abs(single).max())


# 8. Volume of a large bending pose -----------------------------------------------------------

@pytest.fixture(scope="module")
def bent_bar():
    """Pinned 4:1:1 bar (16 x 4 x 4 cells, 2304 tets), its first mode and RS machinery."""
    X, T = meshgen.box_tet_mesh((4.0, 1.0, 1.0), (16, 4, 4))
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    K = fem.stiffness_matrix(X, T, 1.0e6, 0.45)
    result = modes.linear_modes(K, fem.lumped_masses(X, T, 1000.0), 1, pinned_nodes=pinned)
    W = result.vectors
    tip = X[:, 0] > 4.0 - 1e-9
    tip_motion = np.linalg.norm(W.reshape(-1, 3)[tip].mean(axis=0))
    QW = rs.linear_rs(rs.rs_operator(X, T), W)
    recon = rs.PoissonReconstruction(X, T, pinned_nodes=pinned)
    return X, T, W[:, 0].reshape(-1, 3), tip_motion, QW, recon


def test_rs_warp_keeps_volume_where_linear_modes_inflate(bent_bar):
    """Linear tip displacement 4 x the thickness. Measured: RS 0.987, linear 2.07."""
    X, T, w, tip_motion, QW, recon = bent_bar
    amplitude = 4.0 * 1.0 / tip_motion
    u = recon.reconstruct(rs.warp_modes(QW, [amplitude]))
    rest = rs.volume(X, T, X)
    rs_ratio = rs.volume(X, T, X + u) / rest
    linear_ratio = rs.volume(X, T, X + amplitude * w) / rest
    print(f"bar, tip 4x thickness: volume ratio RS {rs_ratio:.4f}, linear {linear_ratio:.4f}")
    assert abs(rs_ratio - 1.0) < 0.05
    assert linear_ratio > 2.0


# 9. Interpolation ----------------------------------------------------------------------------

def test_rs_interpolation_keeps_volume_where_linear_blend_collapses(bent_bar):
    """Pose A: the bar bent (tip 1.5 x thickness); pose B: A turned 120 deg about an oblique axis."""
    X, T, _, tip_motion, QW, pinned_recon = bent_bar
    x_a = X + pinned_recon.reconstruct(rs.warp_modes(QW, [1.5 / tip_motion]))
    R = Rotation.from_rotvec(120.0 * DEG * unit((0.3, 0.2, 1.0))).as_matrix()
    x_b = x_a @ R.T + np.array([0.5, -0.2, 0.1])
    y_a, _ = rs.pose_to_rs(X, T, x_a)
    y_b, _ = rs.pose_to_rs(X, T, x_b, reference=y_a[:, :3])
    recon = rs.PoissonReconstruction(X, T)                 # the blend is a free body
    mean_a, mean_b = recon.weighted_mean(x_a - X), recon.weighted_mean(x_b - X)
    rest = rs.volume(X, T, X)
    rs_ratios, linear_ratios = [], []
    for t in (0.25, 0.5, 0.75):
        u = recon.reconstruct(rs.interpolate(y_a, y_b, t), (1 - t) * mean_a + t * mean_b)
        rs_ratios.append(rs.volume(X, T, X + u) / rest)
        linear_ratios.append(rs.volume(X, T, (1 - t) * x_a + t * x_b) / rest)
    print("interpolation volume ratios at t = 0.25, 0.5, 0.75: RS "
          + ", ".join(f"{v:.4f}" for v in rs_ratios) + "; linear blend "
          + ", ".join(f"{v:.4f}" for v in linear_ratios))
    # The end points are reproduced, so the blend really runs from A to B.
    for t, x in ((0.0, x_a), (1.0, x_b)):
        u = recon.reconstruct(rs.interpolate(y_a, y_b, t), (1 - t) * mean_a + t * mean_b)
        assert np.abs(X + u - x).max() < 1e-8 * diagonal(X)
    assert np.all(np.abs(np.array(rs_ratios) - 1.0) < 0.02)
    assert linear_ratios[1] < 0.8


# 10. Inverted tets ---------------------------------------------------------------------------

def test_inverted_tets_are_flagged_and_stay_finite():
    X, T = meshgen.box_tet_mesh((1.0, 1.0, 1.0), (2, 2, 2))
    centre = np.flatnonzero(np.all(np.abs(X - 0.5) < 1e-9, axis=1))[0]
    x = X.copy()
    x[centre] = [0.55, 0.45, 1.4]                          # pushed out through the top face
    x[0] = x[1]                                            # and one collapsed edge (det F = 0)
    expected = fem.tet_volumes(x, T) <= 0.0
    assert 0 < expected.sum() < len(T)
    y, inverted = rs.pose_to_rs(X, T, x)
    assert np.all(np.isfinite(y))
    np.testing.assert_array_equal(inverted, expected)
    # Reflections live in S, so exp(omega)(I + eps) still equals F on every tet.
    F = rs.deformation_gradients(X, T, x)
    np.testing.assert_allclose(rs.rs_target(y), F - np.eye(3), atol=1e-12)


def test_polar_decomposition_of_degenerate_matrices():
    F = np.stack([np.zeros((3, 3)), np.outer([1.0, 2.0, 0.0], [0.0, 1.0, 1.0]),
                  np.diag([1.0, 1.0, -2.0]), -np.eye(3), np.diag([2.0, 0.5, 1.0])])
    R, S, inverted = rs.polar_decomposition(F)
    assert np.all(np.isfinite(R)) and np.all(np.isfinite(S))
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)
    np.testing.assert_allclose(R @ S, F, atol=1e-14)
    np.testing.assert_allclose(S, np.swapaxes(S, 1, 2), atol=0.0)
    np.testing.assert_array_equal(inverted, [True, True, True, True, False])
    assert np.all(np.isfinite(rs.log_rotation(R)))


# 11. Factor once -----------------------------------------------------------------------------

def test_reconstruction_factors_once(monkeypatch):
    calls = []
    splu = spla.splu

    def counting_splu(*args, **kwargs):
        calls.append(1)
        return splu(*args, **kwargs)

    monkeypatch.setattr(rs.spla, "splu", counting_splu)
    X, T = distorted_box()
    recon = rs.PoissonReconstruction(X, T)
    factor = recon.factor
    y = np.random.default_rng(7).normal(scale=0.3, size=(len(T), 9))
    first = recon.reconstruct(y)
    second = recon.reconstruct(y)
    assert len(calls) == 1 and recon.factor is factor
    np.testing.assert_array_equal(first, second)


# Neighbours ----------------------------------------------------------------------------------

def test_tet_neighbours_share_exactly_the_opposite_face():
    X, T = distorted_box()
    neighbours = rs.tet_neighbours(T)
    e, f = np.nonzero(neighbours >= 0)
    other = neighbours[e, f]
    assert np.all(np.any(neighbours[other] == e[:, None], axis=1))      # symmetric
    shared = (T[e][:, :, None] == T[other][:, None, :]).any(axis=2)     # (pairs, 4)
    assert np.all(shared.sum(axis=1) == 3)
    assert not shared[np.arange(len(e)), f].any()                       # the opposite vertex
    assert (neighbours < 0).sum() == len(igl.boundary_facets(T)[0])


def test_warp_pose_block_gives_warp_modes_of_every_pose_in_chunks():
    """Oracle: warp_modes pose by pose. Chunks of 4 over 10 poses (the last one short)."""
    rng = np.random.default_rng(11)
    QW = rng.normal(size=(7, 9, 3))
    Z = rng.normal(size=(10, 3))
    seen = []
    for start in range(0, 10, 4):
        Y = rs.warp_pose_block(QW, Z[start:start + 4])
        assert Y.shape == (7, 9, min(4, 10 - start))
        for k in range(Y.shape[2]):
            np.testing.assert_allclose(Y[:, :, k], rs.warp_modes(QW, Z[start + k]), atol=1e-14)
            seen.append(start + k)
    assert seen == list(range(10))
