"""Tests for solver.fem against analytic oracles (SPEC.md sections 1 and 8)."""

import numpy as np
import pytest
import scipy.sparse.linalg as spla

from solver import fem, meshgen, modes

E, NU, RHO = 2.0e6, 0.3, 1100.0


def distorted_box(seed=0):
    """Box tet mesh with randomly moved interior nodes (no axis-aligned special cases)."""
    X, T = meshgen.box_tet_mesh((2.0, 1.0, 1.5), (4, 3, 3))
    rng = np.random.default_rng(seed)
    interior = np.all((X > 1e-9) & (X < np.array([2.0, 1.0, 1.5]) - 1e-9), axis=1)
    X = X.copy()
    X[interior] += rng.uniform(-0.08, 0.08, (interior.sum(), 3))
    return X, fem.orient_tets(X, T)


def test_orient_tets_makes_volumes_positive():
    X, T = distorted_box()
    flipped = T.copy()
    flipped[::2, [0, 1]] = flipped[::2, [1, 0]]
    assert np.all(fem.tet_volumes(X, flipped)[::2] < 0)
    fixed = fem.orient_tets(X, flipped)
    assert np.all(fem.tet_volumes(X, fixed) > 0)
    np.testing.assert_array_equal(np.sort(fixed, axis=1), np.sort(T, axis=1))


def test_shape_gradients_sum_to_zero_and_reproduce_linear_functions():
    X, T = distorted_box()
    grads = fem.shape_gradients(X, T)
    assert np.abs(grads.sum(axis=1)).max() < 1e-12
    # sum_k X_k grad(phi_k)^T = I on each tet
    np.testing.assert_allclose(np.einsum("eki,ekj->eij", X[T], grads),
                               np.broadcast_to(np.eye(3), (len(T), 3, 3)), atol=1e-12)


def test_mesh_volume_of_box():
    X, T = meshgen.box_tet_mesh((2.0, 1.0, 1.5), (4, 3, 3))
    assert fem.mesh_volume(X, T) == pytest.approx(3.0, rel=1e-12)
    assert np.all(fem.tet_volumes(X, T) > 0)


def test_gradient_operator_maps_rest_to_identity_and_affine_field_to_A():
    X, T = distorted_box()
    G = fem.gradient_operator(X, T)
    assert G.shape == (9 * len(T), 3 * len(X))
    np.testing.assert_allclose(G @ X.reshape(-1), np.tile(fem.VEC_I, len(T)), atol=1e-12)
    rng = np.random.default_rng(1)
    A, b = rng.normal(size=(3, 3)), rng.normal(size=3)
    u = X @ A.T + b
    np.testing.assert_allclose((G @ u.reshape(-1)).reshape(-1, 9),
                               np.broadcast_to(A.reshape(-1), (len(T), 9)), atol=1e-11)


def test_lame_parameters():
    mu, lam = fem.lame_parameters(1.0e6, 0.25)
    assert mu == pytest.approx(4.0e5)
    assert lam == pytest.approx(4.0e5)


def test_elasticity_tensor_energy_matches_psi():
    mu, lam = fem.lame_parameters(E, NU)
    C = fem.elasticity_tensor(mu, lam)
    np.testing.assert_allclose(C, C.T)
    grad_u = np.random.default_rng(2).normal(size=(3, 3))
    eps = 0.5 * (grad_u + grad_u.T)
    psi = mu * np.sum(eps * eps) + 0.5 * lam * np.trace(grad_u) ** 2
    m = grad_u.reshape(-1)
    assert 0.5 * m @ C @ m == pytest.approx(psi, rel=1e-12)


def test_rigid_motions_in_null_space_of_K():
    X, T = distorted_box()
    K = fem.stiffness_matrix(X, T, E, NU)
    R = modes.rigid_motions(X)
    k_norm = spla.norm(K)
    for r in R.T:
        assert np.linalg.norm(K @ r) <= 1e-8 * k_norm * np.linalg.norm(r)


def test_K_symmetric_positive_semidefinite():
    X, T = distorted_box()
    K = fem.stiffness_matrix(X, T, E, NU)
    assert spla.norm(K - K.T) <= 1e-14 * spla.norm(K)
    eigenvalues = np.linalg.eigvalsh(K.toarray())
    assert eigenvalues.min() >= -1e-10 * eigenvalues.max()
    # Exactly six zero eigenvalues: the three translations and three rotations.
    assert modes.count_near_zero(eigenvalues, rel_tol=1e-10) == 6


def test_single_tet_uniform_strain_energy():
    """u = A X on one tet: 1/2 u^T K u must equal V * psi(A) = 1/2 V eps:C:eps."""
    X = np.array([[0.1, 0.0, 0.2], [1.3, 0.1, 0.0], [0.2, 0.9, 0.1], [0.3, 0.2, 1.1]])
    T = np.array([[0, 1, 2, 3]])
    K = fem.stiffness_matrix(X, T, E, NU)
    A = np.array([[1e-3, 2e-3, -1e-3], [0.0, -2e-3, 3e-3], [1e-3, 1e-3, 4e-3]])
    u = (X @ A.T).reshape(-1)
    mu, lam = fem.lame_parameters(E, NU)
    eps = 0.5 * (A + A.T)
    volume = abs(np.linalg.det((X[1:] - X[0]).T)) / 6.0
    expected = volume * (mu * np.sum(eps * eps) + 0.5 * lam * np.trace(eps) ** 2)
    assert 0.5 * u @ (K @ u) == pytest.approx(expected, rel=1e-12)


def test_total_mass_is_density_times_volume():
    X, T = distorted_box()
    masses = fem.lumped_masses(X, T, RHO)
    assert masses.shape == (len(X),)
    assert np.all(masses > 0)
    assert masses.sum() == pytest.approx(RHO * fem.mesh_volume(X, T), rel=1e-10)
    # Lumped mass is a quarter of every adjacent tet's mass.
    expected = np.bincount(T.ravel(), np.repeat(RHO * fem.tet_volumes(X, T) / 4.0, 4), len(X))
    np.testing.assert_allclose(masses, expected, rtol=1e-12)


@pytest.mark.parametrize("youngs, poisson", [(0.0, 0.3), (-1.0, 0.3), (1e6, 0.5), (1e6, 0.7),
                                             (1e6, -1.0), (np.nan, 0.3)])
def test_bad_material_raises(youngs, poisson):
    X, T = meshgen.box_tet_mesh()
    with pytest.raises(ValueError):
        fem.stiffness_matrix(X, T, youngs, poisson)


@pytest.mark.parametrize("density", [0.0, -5.0])
def test_bad_density_raises(density):
    X, T = meshgen.box_tet_mesh()
    with pytest.raises(ValueError, match="density"):
        fem.lumped_masses(X, T, density)


def test_box_tet_mesh_is_conforming():
    """Every interior face is shared by two tets: only the box's own faces are boundary faces."""
    import igl

    cells = (3, 2, 4)
    X, T = meshgen.box_tet_mesh((3.0, 2.0, 4.0), cells, origin=(1.0, -1.0, 0.5))
    assert T.shape == (6 * 24, 4)
    np.testing.assert_allclose(X.min(axis=0), [1.0, -1.0, 0.5])
    np.testing.assert_allclose(X.max(axis=0), [4.0, 1.0, 4.5])
    faces, _, _ = igl.boundary_facets(T)
    nx, ny, nz = cells
    assert len(faces) == 2 * 2 * (nx * ny + ny * nz + nx * nz)  # two triangles per cube face
