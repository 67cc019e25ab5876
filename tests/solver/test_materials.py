"""Tests for solver.materials: Cauchy-strain materials and the reduced potential V(s) (SPEC 6).

Oracles: central finite differences, the linear modal eigenvalues (V = 1/2 s^T Lambda s for the
linear material), closed-form uniaxial-stretch energies, and the exact all-tet sum for the
energy cubature.
"""

import numpy as np
import pytest

from solver import cubature, fem, materials, meshgen, modes, rs

MU, LAM = fem.lame_parameters(1e5, 0.3)
ALL = [materials.Linear(MU, LAM), materials.StVK(MU, LAM),
       materials.make_material("FUNG", MU, LAM, fung_stiffening=10.0)]
IDS = ["linear", "stvk", "fung"]


def central_gradient(f, x, h):
    """(n, k) central differences of f: (n, k) -> (n,) w.r.t. each of the k columns."""
    steps = np.eye(x.shape[1]) * h
    return np.stack([(f(x + d) - f(x - d)) / (2.0 * h) for d in steps], axis=-1)


def random_strains(rng, count, scale):
    return scale * rng.normal(size=(count, 6))


def uniaxial(a):
    """Strain components of a stretch a along x (dimensionless)."""
    return np.array([[a, 0.0, 0.0, 0.0, 0.0, 0.0]])


# Pointwise materials --------------------------------------------------------------------------

@pytest.mark.parametrize("material", ALL, ids=IDS)
@pytest.mark.parametrize("scale", [0.05, 0.4])
def test_material_derivatives_match_central_differences(material, scale):
    strain = random_strains(np.random.default_rng(1), 50, scale)
    psi, grad, hess = material.evaluate(strain)
    fd_grad = central_gradient(lambda e: material.evaluate(e, 0)[0], strain, 1e-6)
    fd_hess = central_gradient(lambda e: material.evaluate(e, 1)[1].T, strain, 1e-6)
    fd_hess = np.moveaxis(fd_hess, 0, 1)                  # (E, 6, 6): [e, i, k] = d g_i / d e_k
    g_err = np.abs(grad - fd_grad).max() / np.abs(grad).max()
    h_err = np.abs(hess - fd_hess).max() / np.abs(hess).max()
    print(f"{type(material).__name__} strain ~{scale}: gradient {g_err:.1e}, Hessian {h_err:.1e}")
    assert g_err < 1e-7 and h_err < 1e-7
    np.testing.assert_allclose(hess, np.swapaxes(hess, 1, 2), atol=1e-9 * np.abs(hess).max())


def test_linear_material_is_the_fem_energy_density():
    """psi(sym grad u) = 1/2 m^T C m with fem.elasticity_tensor (the same linear elasticity)."""
    rng = np.random.default_rng(2)
    grad_u = rng.normal(size=(20, 3, 3)) * 0.01
    C = fem.elasticity_tensor(MU, LAM)
    expected = 0.5 * np.einsum("ei,ij,ej->e", grad_u.reshape(-1, 9), C, grad_u.reshape(-1, 9))
    sym = 0.5 * (grad_u + np.swapaxes(grad_u, 1, 2))
    strain = sym[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]
    np.testing.assert_allclose(materials.Linear(MU, LAM).evaluate(strain)[0], expected, rtol=1e-12)


@pytest.mark.parametrize("material", ALL[1:], ids=IDS[1:])
def test_nonlinear_materials_equal_linear_to_first_order(material):
    linear = materials.Linear(*material.small_strain_lame)
    np.testing.assert_allclose(material.evaluate(np.zeros((1, 6)))[2],
                               linear.evaluate(np.zeros((1, 6)))[2], rtol=1e-12)
    strain = random_strains(np.random.default_rng(3), 30, 1.0)
    ratios = []
    for size in (1e-2, 1e-3):                     # psi_nl - psi_lin = O(|eps|^3)
        psi_nl = material.evaluate(size * strain, 0)[0]
        psi_lin = linear.evaluate(size * strain, 0)[0]
        ratios.append(np.abs(psi_nl / psi_lin - 1.0).max())
    print(f"{type(material).__name__}: |psi/psi_linear - 1| = {ratios[0]:.1e} at 1e-2, "
          f"{ratios[1]:.1e} at 1e-3")
    assert ratios[1] < 2e-2 and ratios[1] < 0.2 * ratios[0]


@pytest.mark.parametrize("material", ALL[1:], ids=IDS[1:])
def test_nonlinear_materials_are_stiffer_in_large_stretch(material):
    """Same small-strain stiffness; at 30 % stretch more energy and a larger restoring force."""
    linear = materials.Linear(*material.small_strain_lame)
    for a in (0.3, 0.5):
        psi_nl, g_nl, _ = material.evaluate(uniaxial(a), 1)
        psi_lin, g_lin, _ = linear.evaluate(uniaxial(a), 1)
        print(f"{type(material).__name__} stretch {a}: energy x{psi_nl[0] / psi_lin[0]:.3f}, "
              f"force x{g_nl[0, 0] / g_lin[0, 0]:.3f}")
        assert psi_nl[0] > 1.05 * psi_lin[0]
        assert g_nl[0, 0] > 1.1 * g_lin[0, 0]


def test_stvk_uniaxial_stretch_closed_form():
    """eps = diag(a, 0, 0): E_G = a + a^2/2 on xx only, psi = (mu + lam/2) E_G^2."""
    a = 0.37
    green = a + 0.5 * a * a
    psi, grad, _ = materials.StVK(MU, LAM).evaluate(uniaxial(a), 1)
    assert psi[0] == pytest.approx((MU + 0.5 * LAM) * green ** 2, rel=1e-12)
    assert grad[0, 0] == pytest.approx((2.0 * MU + LAM) * green * (1.0 + a), rel=1e-12)


def test_fung_is_stvk_plus_exponential():
    f = materials.Fung(2.0, 3.0, 5.0, 1.0, 0.7)
    strain = random_strains(np.random.default_rng(4), 10, 0.2)
    psi1 = materials.StVK(2.0, 3.0).evaluate(strain, 0)[0]
    psi2 = materials.StVK(5.0, 1.0).evaluate(strain, 0)[0]
    np.testing.assert_allclose(f.evaluate(strain, 0)[0], psi1 + 0.7 * (np.exp(psi2) - 1.0),
                               rtol=1e-12)
    assert materials.make_material("fung", MU, LAM).small_strain_lame == pytest.approx((MU, LAM))


def test_make_material_rejects_unknown_kinds():
    with pytest.raises(ValueError, match="unknown material"):
        materials.make_material("rubber", MU, LAM)
    with pytest.raises(ValueError, match="stiffening"):
        materials.make_material("FUNG", MU, LAM, fung_stiffening=0.0)


# Reduced potential ----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def bar():
    """Pinned 4:1:1 bar, 12 x 3 x 3 cells (648 tets), E = 1e5 Pa, 8 modes."""
    X, T = meshgen.box_tet_mesh((0.6, 0.15, 0.15), (12, 3, 3))
    masses = fem.lumped_masses(X, T, 1000.0)
    K = fem.stiffness_matrix(X, T, 1e5, 0.3)
    result = modes.linear_modes(K, masses, 8, np.flatnonzero(X[:, 0] < 1e-9))
    modal_rs = rs.linear_rs(rs.rs_operator(X, T), result.vectors)
    return dict(X=X, T=T, modal_rs=modal_rs, volumes=fem.tet_volumes(X, T),
                eigenvalues=result.eigenvalues)


def test_linear_potential_is_half_s_lambda_s(bar):
    potential = materials.ReducedPotential.exact(materials.Linear(MU, LAM), bar["modal_rs"],
                                                 bar["volumes"])
    Lam = np.diag(bar["eigenvalues"])
    error = np.abs(potential.rest_hessian - Lam).max() / Lam.max()
    print(f"sum V_e U^T C U vs diag(lambda): max relative error {error:.1e}")
    assert error < 1e-10
    s = np.random.default_rng(5).normal(size=8)
    assert potential.energy(s) == pytest.approx(0.5 * s @ Lam @ s, rel=1e-10)
    np.testing.assert_allclose(potential.gradient(s), Lam @ s, rtol=1e-9,
                               atol=1e-12 * np.abs(Lam @ s).max())


def rotation_scaled_poses(bar, count, degrees, seed):
    return cubature.training_poses(8, bar["eigenvalues"], count, np.random.default_rng(seed),
                                   max_rotation=np.radians(degrees), modal_rs=bar["modal_rs"])


@pytest.mark.parametrize("material", ALL[1:], ids=IDS[1:])
def test_reduced_potential_derivatives_match_central_differences(bar, material):
    potential = materials.ReducedPotential.exact(material, bar["modal_rs"], bar["volumes"])
    errors = []
    for s in rotation_scaled_poses(bar, 4, 60.0, 6):
        _, grad, hess = potential.evaluate(s)
        h = 1e-6 * np.abs(s).max()
        fd_grad = central_gradient(lambda z: np.array([potential.energy(v) for v in z]),
                                   s[None], h)[0]
        fd_hess = central_gradient(lambda z: np.array([potential.gradient(v) for v in z]).T,
                                   s[None], h)[:, 0, :]
        errors.append((np.abs(grad - fd_grad).max() / np.abs(grad).max(),
                       np.abs(hess - fd_hess).max() / np.abs(hess).max()))
    g_err, h_err = np.max(errors, axis=0)
    print(f"{type(material).__name__} V(s): gradient {g_err:.1e}, Hessian {h_err:.1e}")
    assert g_err < 1e-6 and h_err < 1e-6


@pytest.mark.parametrize("material", ALL[1:], ids=IDS[1:])
def test_reduced_nonlinear_potential_is_stiffer_at_large_deformation(bar, material):
    """Along a bending mode: equal curvature at rest, more energy and force when bent far."""
    linear = materials.ReducedPotential.exact(materials.Linear(*material.small_strain_lame),
                                              bar["modal_rs"], bar["volumes"])
    nonlinear = materials.ReducedPotential.exact(material, bar["modal_rs"], bar["volumes"])
    np.testing.assert_allclose(nonlinear.rest_hessian, linear.rest_hessian,
                               rtol=1e-10, atol=1e-10 * linear.rest_hessian.max())
    s = np.zeros(8)
    s[0] = np.radians(90.0) / np.linalg.norm(bar["modal_rs"][:, :3, 0], axis=1).max()
    e_nl, g_nl, _ = nonlinear.evaluate(s, 1)
    e_lin, g_lin, _ = linear.evaluate(s, 1)
    print(f"{type(material).__name__}, mode 1 at 90 deg: energy x{e_nl / e_lin:.3f}, "
          f"force x{g_nl[0] / g_lin[0]:.3f}")
    assert e_nl > e_lin and g_nl[0] > g_lin[0]


@pytest.mark.parametrize("stored", [True, False], ids=["stored", "random-blocks"])
@pytest.mark.parametrize("material, degrees, max_tets", [(ALL[1], 90.0, 60), (ALL[2], 60.0, 150)],
                         ids=IDS[1:])
def test_energy_cubature_reproduces_held_out_forces(bar, material, degrees, max_tets, stored,
                                                    monkeypatch):
    """Trained on 100 poses, checked on 30 others of the same kind (bending up to ``degrees``),
    with every column stored and every tet scored, and (a body too large to store them) with
    random blocks of candidates.

    Fung's exponential concentrates the energy of a strongly bent pose in its few most
    strained tets, so its cubature needs more tets and its worst pose is off by more.
    """
    if not stored:
        monkeypatch.setattr(materials, "STORED_COLUMNS", 0)
    tets, weights, info = materials.train_energy_cubature(
        material, bar["modal_rs"], bar["volumes"], rotation_scaled_poses(bar, 100, degrees, 7),
        tol=1e-3, max_tets=max_tets, rng=np.random.default_rng(8))
    exact = materials.ReducedPotential.exact(material, bar["modal_rs"], bar["volumes"])
    approx = materials.ReducedPotential.cubature(material, bar["modal_rs"], bar["volumes"],
                                                 tets, weights)
    errors = []
    for s in rotation_scaled_poses(bar, 30, degrees, 9):            # poses not trained on
        e0, g0, _ = exact.evaluate(s, 1)
        e1, g1, _ = approx.evaluate(s, 1)
        errors.append((abs(e1 / e0 - 1.0), np.linalg.norm(g1 - g0) / np.linalg.norm(g0)))
    median, worst = np.median(errors, axis=0), np.max(errors, axis=0)
    print(f"{type(material).__name__} cubature: {len(tets)} of {len(bar['T'])} tets, training "
          f"residual {info['relative_residual']:.1e}; held out energy / force error: median "
          f"{median[0]:.1e} / {median[1]:.1e}, worst {worst[0]:.1e} / {worst[1]:.1e}")
    assert np.all(weights > 0)
    assert len(tets) <= max_tets < len(bar["T"])
    assert np.all(median < 0.01) and np.all(worst < 0.15)


def tet_column(material, bar, tet, poses, scale):
    """Tet ``tet``'s column [grad V_e, V_e] / scale over ``poses``, from a one-tet potential
    (an independent path to ``materials._tet_columns``)."""
    one = materials.ReducedPotential.cubature(material, bar["modal_rs"], bar["volumes"], [tet],
                                              [1.0])
    return np.concatenate([materials._pose_row(one, s) for s in poses] / scale).reshape(-1)


@pytest.mark.parametrize("material", ALL[1:], ids=IDS[1:])
def test_energy_cubature_first_pick_is_the_best_of_every_tet(bar, material):
    """With the columns stored, the first pick is the tet whose column has the largest cosine
    with the target among all tets (the greedy's choice; a random block of 50 candidates
    would see a few of the 648): cosines computed tet by tet from one-tet potentials, the
    target from the exact sum."""
    poses = rotation_scaled_poses(bar, 12, 60.0, 3)
    exact = materials.ReducedPotential.exact(material, bar["modal_rs"], bar["volumes"])
    rows = np.array([materials._pose_row(exact, s) for s in poses])
    scale = np.concatenate([np.repeat(np.linalg.norm(rows[:, :-1], axis=1)[:, None], 8, axis=1),
                            np.abs(rows[:, -1:])], axis=1)
    target = (rows / scale).reshape(-1)
    cosines = []
    for tet in range(len(bar["T"])):
        column = tet_column(material, bar, tet, poses, scale)
        cosines.append(target @ column / np.linalg.norm(column))
    tets, _, _ = materials.train_energy_cubature(material, bar["modal_rs"], bar["volumes"],
                                                 poses, tol=1e-6, max_tets=1, candidates=50,
                                                 rng=np.random.default_rng(0))
    print(f"picked {tets}, best {np.argmax(cosines)} (score {max(cosines):.4f}); "
          f"the picked one's {cosines[tets[0]]:.4f}")
    assert tets[0] == np.argmax(cosines)


def test_energy_cubature_columns_sum_to_the_exact_forces_on_any_number_of_threads(
        bar, monkeypatch):
    """The stored columns (computed in chunks on threads) sum to the exact all-tet force and
    energy of every pose, each matches its one-tet potential to float32 rounding, and one
    thread gives the same training bit for bit."""
    material = ALL[2]
    poses = rotation_scaled_poses(bar, 10, 60.0, 4)
    monkeypatch.setattr(materials, "COLUMN_CHUNK", 100)          # several chunks, some parallel
    stored, rows = materials._all_columns(material, bar["modal_rs"][:, 3:, :],
                                          np.abs(bar["volumes"]), poses, None)
    exact = materials.ReducedPotential.exact(material, bar["modal_rs"], bar["volumes"])
    want = np.array([materials._pose_row(exact, s) for s in poses])
    np.testing.assert_allclose(rows, want, rtol=1e-10, atol=1e-12 * np.abs(want).max())
    unit = np.ones_like(want)
    for tet in (0, 101, len(bar["T"]) - 1):
        column = tet_column(material, bar, tet, poses, unit)
        np.testing.assert_allclose(stored[:, tet], column, rtol=1e-6,
                                   atol=1e-6 * np.abs(column).max())

    def train():
        return materials.train_energy_cubature(material, bar["modal_rs"], bar["volumes"], poses,
                                               tol=1e-4, max_tets=40,
                                               rng=np.random.default_rng(0))
    many = train()
    monkeypatch.setattr(cubature.threads, "worker_count", lambda: 1)
    one = train()
    np.testing.assert_array_equal(one[0], many[0])
    np.testing.assert_array_equal(one[1], many[1])


def test_energy_cubature_training_stops_when_its_progress_raises(bar):
    """A cancel (an exception from ``progress``) during the stored columns stops the training
    there: no pick is made."""
    calls = []

    def progress(fraction, message):
        calls.append(message)
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        materials.train_energy_cubature(ALL[1], bar["modal_rs"], bar["volumes"],
                                        rotation_scaled_poses(bar, 10, 60.0, 4),
                                        progress=progress)
    assert len(calls) == 1 and calls[0].startswith("training columns")


def test_prepare_potential_is_exact_for_linear_and_a_cubature_otherwise(bar):
    linear, info = materials.prepare_potential(materials.Linear(MU, LAM), bar["modal_rs"],
                                               bar["volumes"], bar["eigenvalues"])
    assert info == {} and linear.is_quadratic and linear.tets is None
    stvk, info = materials.prepare_potential(materials.StVK(MU, LAM), bar["modal_rs"],
                                             bar["volumes"], bar["eigenvalues"], num_poses=60,
                                             max_tets=40)
    assert not stvk.is_quadratic and 0 < len(stvk.tets) <= 40
    np.testing.assert_array_equal(stvk.tets, info["tets"])
    np.testing.assert_allclose(stvk.rest_hessian, linear.rest_hessian, rtol=0.05,
                               atol=0.05 * linear.rest_hessian.max())


@pytest.mark.parametrize("material", ALL, ids=IDS)
def test_a_saved_and_loaded_potential_evaluates_bit_for_bit_alike(bar, material, tmp_path):
    """to_arrays / from_arrays through an .npz file: the same energy, force and Hessian."""
    potential, _ = materials.prepare_potential(material, bar["modal_rs"], bar["volumes"],
                                               bar["eigenvalues"], num_poses=30, max_tets=30)
    path = tmp_path / "potential.npz"
    np.savez(path, **potential.to_arrays())
    with np.load(path, allow_pickle=False) as data:
        loaded = materials.ReducedPotential.from_arrays(dict(data), material)
    if potential.tets is None:
        assert loaded.tets is None
    else:
        np.testing.assert_array_equal(loaded.tets, potential.tets)
    assert loaded.is_quadratic == potential.is_quadratic
    for s in rotation_scaled_poses(bar, 3, 60.0, 11):
        for got, want in zip(loaded.evaluate(s), potential.evaluate(s)):
            np.testing.assert_array_equal(got, want)

