"""A painted material: per-tet Young's modulus from a vertex group (issue 28, item 2).

Oracles: an independent, loop-free assembly of K = sum_e V_e B_e^T D_e B_e (Voigt strains,
shape functions from inverting [1 x y z], the textbook isotropic D_e) with each tet's own E;
the frequencies of that K and of lumped masses assembled alike, from scipy.sparse.linalg.eigsh
(shift-invert) on the free degrees of freedom (the issue's "full-space FEM of the same tets with
per-tet E, solved with scipy", within 1e-6 relative); the exact linearity of the carried weights
for a linear field; closed forms of StVK and Fung evaluated tet by tet, and central differences;
the full-space static solution K u = f for the simulation's equilibrium.
"""
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from solver import body as body_module
from solver import fem, inversion, materials, meshgen, preparation, problems

LENGTH, WIDTH = 1.0, 0.1
YOUNGS, NU, RHO, RATIO = 1.0e6, 0.45, 1000.0, 1.0 / 3.0


# --- an independent reference ------------------------------------------------------------------

def reference_stiffness(X, T, youngs, poisson):
    """Dense K (3N, 3N) = sum_e V_e B_e^T D_e B_e for per-tet youngs (E,), without fem."""
    n_tets = len(T)
    P = np.concatenate([np.ones((n_tets, 4, 1)), X[T]], axis=2)     # rows [1, x, y, z] per node
    coefficients = np.linalg.inv(P)                                   # phi_k = row . column k
    grads = np.transpose(coefficients[:, 1:, :], (0, 2, 1))           # (E, 4, 3)
    volumes = np.abs(np.linalg.det(P)) / 6.0
    gx, gy, gz = grads[..., 0], grads[..., 1], grads[..., 2]
    B = np.zeros((n_tets, 6, 12))                                     # [xx yy zz 2xy 2yz 2xz]
    B[:, 0, 0::3], B[:, 1, 1::3], B[:, 2, 2::3] = gx, gy, gz
    B[:, 3, 0::3], B[:, 3, 1::3] = gy, gx
    B[:, 4, 1::3], B[:, 4, 2::3] = gz, gy
    B[:, 5, 0::3], B[:, 5, 2::3] = gz, gx
    scale = np.asarray(youngs) / ((1.0 + poisson) * (1.0 - 2.0 * poisson))
    D = np.zeros((n_tets, 6, 6))
    D[:, :3, :3] = (scale * poisson)[:, None, None]
    D[:, [0, 1, 2], [0, 1, 2]] = (scale * (1.0 - poisson))[:, None]
    D[:, [3, 4, 5], [3, 4, 5]] = (scale * (1.0 - 2.0 * poisson) / 2.0)[:, None]
    K_e = volumes[:, None, None] * np.einsum("eki,ekl,elj->eij", B, D, B)
    dofs = (3 * T[:, :, None] + np.arange(3)).reshape(n_tets, 12)
    K = np.zeros((3 * len(X), 3 * len(X)))
    np.add.at(K, (dofs[:, :, None], dofs[:, None, :]), K_e)
    return K


def reference_masses(X, T, density):
    """(N,) lumped masses: a quarter of each tet's mass on each of its nodes."""
    volumes = np.abs(np.linalg.det(X[T[:, 1:]] - X[T[:, :1]])) / 6.0
    masses = np.zeros(len(X))
    np.add.at(masses, T, np.repeat(density * volumes[:, None] / 4.0, 4, axis=1))
    return masses


def reference_frequencies(X, T, tet_youngs, pinned, count):
    """(count,) lowest frequencies [Hz] of K u = lam M u on the free dofs, from scipy's sparse
    shift-invert eigensolver (eigsh about 0) on the independent assembly."""
    free = np.setdiff1d(np.arange(3 * len(X)), (3 * pinned[:, None] + np.arange(3)).ravel())
    K = sp.csc_matrix(reference_stiffness(X, T, tet_youngs, NU)[np.ix_(free, free)])
    M = sp.diags(np.repeat(reference_masses(X, T, RHO), 3)[free])
    eigenvalues = spla.eigsh(K, k=count, M=M, sigma=0.0, which="LM", tol=1e-14,
                             return_eigenvectors=False)
    return np.sqrt(np.sort(eigenvalues)) / (2.0 * np.pi)


def root_stiff_youngs(X, T):
    """(E,) Young's modulus of a bar painted 1 at its root, falling linearly to 0 at its tip:
    the tet's weight is the mean of its nodes' (linear in x, so 1 - x_centroid / L)."""
    weights = 1.0 - X[T, 0].mean(axis=1) / LENGTH
    return YOUNGS * RATIO ** (1.0 - weights)


def distorted_box(seed=3):
    X, T = meshgen.box_tet_mesh((0.6, 0.3, 0.2), (3, 2, 2))
    rng = np.random.default_rng(seed)
    inner = np.all((X > 1e-9) & (X < np.array([0.6, 0.3, 0.2]) - 1e-9), axis=1)
    X = X.copy()
    X[inner] += rng.uniform(-0.03, 0.03, (inner.sum(), 3))
    return X, fem.orient_tets(X, T)


@pytest.fixture(scope="module")
def painted_bar():
    """A 1 x 0.1 x 0.1 m bar (16 x 2 x 2 cells) pinned at x = 0, its render vertices the tet
    nodes, painted 1 - x / L with ratio 1/3 (stiff root, soft tip); 8 modes."""
    X, T = meshgen.box_tet_mesh((LENGTH, WIDTH, WIDTH), (16, 2, 2))
    tet_body = preparation.embedded(X, T, X)
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    scale = preparation.stiffness_scale(tet_body, 1.0 - X[:, 0] / LENGTH, RATIO)
    linear = preparation.linear_modes(tet_body, YOUNGS, NU, RHO, 8, pinned, stiffness_scale=scale)
    body = body_module.PreparedBody(tet_body, linear, None, stiffness_scale=scale)
    return body, pinned


# --- the stiffness matrix -----------------------------------------------------------------------

def test_per_tet_stiffness_matches_an_independent_assembly():
    X, T = distorted_box()
    tet_youngs = 10.0 ** np.random.default_rng(4).uniform(4.0, 7.0, len(T))
    K = fem.stiffness_matrix(X, T, tet_youngs, 0.3).toarray()
    reference = reference_stiffness(X, T, tet_youngs, 0.3)
    error = np.abs(K - reference).max() / np.abs(reference).max()
    print(f"per-tet K against the reference assembly: max relative error {error:.1e}")
    assert error < 1e-12
    uniform = reference_stiffness(X, T, np.full(len(T), tet_youngs.mean()), 0.3)
    assert np.abs(uniform - reference).max() > 1e3 * error * np.abs(reference).max()


def test_a_uniform_array_gives_the_scalar_stiffness_bit_for_bit():
    X, T = distorted_box()
    scalar = fem.stiffness_matrix(X, T, 2.5e6, 0.3)
    array = fem.stiffness_matrix(X, T, np.full(len(T), 2.5e6), 0.3)
    np.testing.assert_array_equal(array.indptr, scalar.indptr)
    np.testing.assert_array_equal(array.indices, scalar.indices)
    np.testing.assert_array_equal(array.data, scalar.data)


def test_a_young_modulus_that_is_not_positive_anywhere_is_refused():
    X, T = distorted_box()
    tet_youngs = np.full(len(T), 1e6)
    tet_youngs[5] = 0.0
    with pytest.raises(ValueError, match="Young's modulus must be positive"):
        fem.stiffness_matrix(X, T, tet_youngs, 0.3)
    tet_youngs[5] = np.nan
    with pytest.raises(ValueError, match="Young's modulus must be positive"):
        fem.lame_parameters(tet_youngs, 0.3)


# --- from paint to tets -------------------------------------------------------------------------

def test_the_interpolation_is_geometric_between_ratio_and_one():
    youngs = fem.painted_youngs(2e6, 0.01, np.array([1.0, 0.5, 0.0, -0.2, 1.3]))
    np.testing.assert_allclose(youngs, [2e6, 2e5, 2e4, 2e4, 2e6], rtol=1e-14)
    for ratio in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="stiffness ratio"):
            fem.painted_youngs(2e6, ratio, np.zeros(3))


def test_a_linear_paint_on_the_surface_reaches_the_inner_tets_exactly():
    """Render vertices on the surface only: the inner nodes get the harmonic extension, which
    is exact for a linear field, so each tet's weight is the field at its centroid."""
    X, T = meshgen.box_tet_mesh((LENGTH, 0.3, 0.3), (8, 3, 3))
    surface = np.flatnonzero(np.any((X < 1e-9) | (X > np.array([LENGTH, 0.3, 0.3]) - 1e-9),
                                    axis=1))
    assert len(surface) < len(X)                               # some nodes are inside
    tet_body = preparation.embedded(X, T, X[surface])
    field = 0.2 + 0.6 * X[surface, 0] / LENGTH - 0.5 * X[surface, 2]
    weights = preparation.tet_weights(tet_body, field)
    centroids = X[T].mean(axis=1)
    expected = 0.2 + 0.6 * centroids[:, 0] / LENGTH - 0.5 * centroids[:, 2]
    np.testing.assert_allclose(weights, expected, atol=1e-12)
    scale = preparation.stiffness_scale(tet_body, field, 0.25)
    np.testing.assert_allclose(scale, 0.25 ** (1.0 - expected), rtol=1e-12)


# --- modes: the oracle ------------------------------------------------------------------

def test_painted_frequencies_match_a_full_space_reference(painted_bar):
    body, pinned = painted_bar
    X, T = body.nodes, body.tets
    reference = reference_frequencies(X, T, root_stiff_youngs(X, T), pinned, 8)
    frequencies = body.linear_modes.frequencies_hz
    error = np.abs(frequencies / reference - 1.0).max()
    print("painted frequencies [Hz]:", np.array2string(frequencies, precision=5))
    print(f"against the full-space reference: max relative error {error:.1e}")
    assert error < 1e-6
    # The painting matters: between the uniform soft and the uniform stiff bar, far from both.
    stiff = reference_frequencies(X, T, np.full(len(T), YOUNGS), pinned, 8)
    assert np.all(frequencies < 0.97 * stiff) and np.all(frequencies > 1.03 * np.sqrt(RATIO) * stiff)


# --- the reduced potentials ---------------------------------------------------------------------

def test_the_linear_potential_is_the_painted_quadratic_form(painted_bar):
    body, _ = painted_bar
    W = body.linear_modes.vectors
    reduced_K = W.T @ reference_stiffness(body.nodes, body.tets,
                                          root_stiff_youngs(body.nodes, body.tets), NU) @ W
    potential = problems.linear_potential(body, YOUNGS, NU)
    assert potential.is_quadratic
    error = np.abs(potential.rest_hessian - reduced_K).max() / np.abs(reduced_K).max()
    print(f"painted Linear potential's Hessian against W^T K(E_e) W: {error:.1e}")
    assert error < 1e-9
    s = np.random.default_rng(2).normal(size=W.shape[1]) * 1e-3
    assert potential.energy(s) == pytest.approx(0.5 * s @ reduced_K @ s, rel=1e-9)
    np.testing.assert_allclose(potential.gradient(s), reduced_K @ s, rtol=1e-8,
                               atol=1e-10 * np.abs(reduced_K @ s).max())
    # Kept per material, keyed by the per-tet values: the same body and Young's modulus reuse
    # it; the same tets and modes without the paint are another (stiffer) form.
    assert problems.linear_potential(body, YOUNGS, NU) is potential
    uniform = body_module.PreparedBody(body.tet_body, body.linear_modes, None)
    stiffer = problems.linear_potential(uniform, YOUNGS, NU)
    assert np.all(np.diag(stiffer.rest_hessian) > 1.05 * np.diag(potential.rest_hessian))


def random_tet_lame(rng, count):
    mu, lam = fem.lame_parameters(10.0 ** rng.uniform(4.0, 6.0, count), 0.35)
    return mu, lam


def stvk_density(strain, mu, lam):
    """mu tr(E_G^2) + lam/2 tr(E_G)^2 of E_G = ((I + eps)^2 - I) / 2, tet by tet."""
    S = materials.strain_matrices(strain) + np.eye(3)
    green = 0.5 * (S @ S - np.eye(3))
    trace = np.trace(green, axis1=1, axis2=2)
    return mu * np.einsum("eij,eij->e", green, green) + 0.5 * lam * trace ** 2


@pytest.mark.parametrize("kind", ["STVK", "FUNG"])
def test_per_tet_nonlinear_materials_match_a_direct_evaluation(kind):
    rng = np.random.default_rng(11)
    count, stiffening = 9, 7.0
    mu, lam = random_tet_lame(rng, count)
    material = materials.make_material(kind, mu, lam, fung_stiffening=stiffening)
    assert material.per_tet
    strain = rng.normal(scale=0.15, size=(count, 6))
    if kind == "STVK":
        direct = stvk_density(strain, mu, lam)
    else:
        uniaxial = mu + 0.5 * lam
        direct = (stvk_density(strain, 0.5 * mu, 0.5 * lam) + 0.5 * uniaxial / stiffening
                  * (np.exp(stvk_density(strain, stiffening * mu / uniaxial,
                                         stiffening * lam / uniaxial)) - 1.0))
    psi, grad, hess = material.evaluate(strain)
    np.testing.assert_allclose(psi, direct, rtol=1e-12)
    h = 1e-6
    steps = h * np.eye(6)
    psi_plus = np.stack([material.evaluate(strain + d, 0)[0] for d in steps], axis=1)
    psi_minus = np.stack([material.evaluate(strain - d, 0)[0] for d in steps], axis=1)
    np.testing.assert_allclose(grad, (psi_plus - psi_minus) / (2 * h), rtol=1e-6,
                               atol=1e-6 * np.abs(grad).max())
    grad_plus = np.stack([material.evaluate(strain + d, 1)[1] for d in steps], axis=1)
    grad_minus = np.stack([material.evaluate(strain - d, 1)[1] for d in steps], axis=1)
    np.testing.assert_allclose(hess, (grad_plus - grad_minus) / (2 * h), rtol=1e-5,
                               atol=1e-6 * np.abs(hess).max())
    # Each tet's row is what the uniform material of its own parameters gives.
    for e in (0, count - 1):
        alone = materials.make_material(kind, mu[e], lam[e], fung_stiffening=stiffening)
        np.testing.assert_allclose(alone.evaluate(strain[e:e + 1])[2], hess[e:e + 1], rtol=1e-12)


@pytest.mark.parametrize("kind", ["LINEAR", "STVK", "FUNG"])
def test_a_per_tet_cubature_sums_its_own_tets_parameters(painted_bar, kind):
    """A cubature over some tets of a painted body: its energy is sum_c w_c V_c psi(U_c s) with
    each tet's own parameters; the training columns of all tets sum to the exact target; the
    volume barrier scales each tet by its own bulk modulus."""
    body, _ = painted_bar
    material = body.material(kind, YOUNGS, NU)
    modal_rs, volumes = body.modal_rs, body.volumes
    rng = np.random.default_rng(8)
    tets = np.sort(rng.choice(len(volumes), 40, replace=False))
    weights = rng.uniform(0.5, 2.0, len(tets))
    potential = materials.ReducedPotential.cubature(material, modal_rs, volumes, tets, weights)
    s = rng.normal(size=modal_rs.shape[2]) * 0.02
    strain = modal_rs[tets, 3:, :] @ s
    mu, lam = fem.lame_parameters(body.tet_youngs(YOUNGS)[tets], NU)
    direct = materials.make_material(kind, mu, lam).evaluate(strain, 0)[0]
    assert potential.energy(s) == pytest.approx(float(weights * volumes[tets] @ direct),
                                                rel=1e-12)
    loaded = materials.ReducedPotential.from_arrays(potential.to_arrays(), material)
    assert loaded.evaluate(s)[0] == potential.evaluate(s)[0]
    np.testing.assert_array_equal(loaded.evaluate(s)[2], potential.evaluate(s)[2])

    exact = materials.ReducedPotential.exact(material, modal_rs, volumes)
    poses = rng.normal(size=(3, modal_rs.shape[2])) * 0.02
    every = np.arange(len(volumes))
    columns = materials._tet_columns(material, every, modal_rs[:, 3:, :], volumes, poses,
                                     np.ones((3, modal_rs.shape[2] + 1)))
    target = np.concatenate([np.append(exact.gradient(z), exact.energy(z)) for z in poses])
    np.testing.assert_allclose(columns.sum(axis=1), target, rtol=1e-10,
                               atol=1e-12 * np.abs(target).max())

    barrier = inversion.with_barrier(potential, modal_rs, volumes).barrier
    mu, lam = fem.lame_parameters(body.tet_youngs(YOUNGS), NU)
    small_mu, small_lam = material.small_strain_lame
    np.testing.assert_allclose(small_mu, mu, rtol=1e-12)
    np.testing.assert_allclose(barrier.weights,
                               inversion.BARRIER_SCALE * (lam + 2.0 * mu / 3.0) * volumes,
                               rtol=1e-12)


def test_the_energy_cubature_is_trained_on_the_painted_parameters(painted_bar):
    """StVK's cubature trained on a painted body (preparation.energy_potential) reproduces the
    exact all-tet painted energy at poses it was not trained on; tets and weights trained on
    the uniform material instead, evaluated with the paint, do an order of magnitude worse."""
    body, _ = painted_bar
    material = body.material("STVK", YOUNGS, NU)
    uniform = materials.make_material("STVK", *fem.lame_parameters(YOUNGS, NU))
    trained = preparation.energy_potential(body, "STVK", YOUNGS, NU)
    elsewhere, _ = materials.prepare_potential(uniform, body.modal_rs, body.volumes,
                                               eigenvalues=body.linear_modes.eigenvalues,
                                               **preparation.ENERGY_TRAINING)
    elsewhere = elsewhere.with_material(material)
    exact = materials.ReducedPotential.exact(material, body.modal_rs, body.volumes)
    scale = 1.0 / np.sqrt(body.linear_modes.eigenvalues)          # a mode's natural amplitude
    poses = np.random.default_rng(5).normal(size=(6, len(scale))) * scale * 0.05

    def error(potential):
        return max(abs(potential.energy(z) / exact.energy(z) - 1.0) for z in poses)

    print(f"painted StVK cubature against the exact painted energy: {error(trained):.1e} "
          f"(trained on the uniform material: {error(elsewhere):.1e})")
    assert error(trained) < 1.5e-4 < error(elsewhere)


@pytest.mark.parametrize("kind", ["STVK", "FUNG"])
def test_one_energy_cubature_serves_every_youngs_modulus(painted_bar, kind):
    """The energy cubature is trained at 1 Pa (preparation.energy_potential): asked for two
    moduli it picks the same tets and weights bit for bit, and its energy, force and Hessian at
    E are E times those at 1 Pa and those of the exact painted material at E within its fit."""
    body, _ = painted_bar
    low = preparation.energy_potential(body, kind, YOUNGS, NU, fung_stiffening=8.0)
    high = preparation.energy_potential(body, kind, 7.0 * YOUNGS, NU, fung_stiffening=8.0)
    np.testing.assert_array_equal(low.tets, high.tets)
    np.testing.assert_array_equal(low.weights, high.weights)
    scale = 1.0 / np.sqrt(body.linear_modes.eigenvalues)
    poses = np.random.default_rng(8).normal(size=(4, len(scale))) * scale * 0.05
    exact = materials.ReducedPotential.exact(body.material(kind, 7.0 * YOUNGS, NU, 8.0),
                                             body.modal_rs, body.volumes)
    for z in poses:
        for at_low, at_high in zip(low.evaluate(z), high.evaluate(z)):
            np.testing.assert_allclose(at_high, 7.0 * at_low, rtol=1e-10)
        assert abs(high.energy(z) / exact.energy(z) - 1.0) < 1e-3
    with pytest.raises(ValueError, match="Young's modulus"):
        preparation.energy_at(low, body, kind, 0.0, NU)


# --- the simulation -----------------------------------------------------------------------------

def test_a_painted_bar_settles_where_the_full_static_solution_of_its_tets_puts_it():
    """Static equilibrium under gravity of the simulation of a painted body (its Linear
    potential, reduced RS) against the full-space K(E_e) u = f: within 3 %, where the uniform
    stiff bar sags by 30 % less."""
    X, T = meshgen.box_tet_mesh((4.0, 1.0, 1.0), (8, 2, 2))
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    youngs = 2e7
    body = preparation.prepare_body(X, T, X, youngs, NU, RHO, 6, pinned=pinned,
                                    stiffness=(1.0 - X[:, 0] / 4.0, RATIO))
    settings = problems.SimulationSettings(h=1.0 / 24.0, density=RHO, gravity=(0.0, 0.0, -9.81))
    sim = problems.simulation(body, problems.linear_potential(body, youngs, NU), settings)
    sim.static_equilibrium()
    sag = (body.deformer.basis @ sim.q).reshape(-1, 3)
    free = np.setdiff1d(np.arange(3 * len(X)), (3 * pinned[:, None] + np.arange(3)).ravel())
    force = np.zeros((len(X), 3))
    force[:, 2] = -9.81 * reference_masses(X, T, RHO)
    tip = np.flatnonzero(X[:, 0] > 4.0 - 1e-9)

    def full_sag(tet_youngs):
        K = reference_stiffness(X, T, tet_youngs, NU)[np.ix_(free, free)]
        u = np.zeros(3 * len(X))
        u[free] = spla.splu(sp.csc_matrix(K)).solve(force.ravel()[free])
        return u.reshape(-1, 3)[tip, 2].mean()

    weights = 1.0 - X[T, 0].mean(axis=1) / 4.0
    painted = full_sag(youngs * RATIO ** (1.0 - weights))
    stiff = full_sag(np.full(len(T), youngs))
    reduced_ = sag[tip, 2].mean()
    print(f"tip sag: reduced {reduced_:.5f} m, full painted {painted:.5f} m, "
          f"full uniform stiff {stiff:.5f} m")
    assert painted < 1.3 * stiff < 0.0
    assert abs(reduced_ / painted - 1.0) < 0.03
