"""Tests for solver.modes: cantilever against beam theory, free-body and pinned modal analysis."""

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from solver import fem, meshgen, modes

E, NU, RHO = 1.0e6, 0.3, 1000.0


@pytest.fixture(scope="module")
def cantilever():
    """Clamped square beam L = 1 m, h = 0.1 m (L/h = 10), 80 x 8 x 8 cubes = 30 720 tets.

    Measured on this machine (assembly + 7 modes: about 1.5 s):
      first bending   omega / omega_EB = 1.020 (+2.0 %); its twin (other transverse direction) +4.1 %
      second bending  -2.5 %, axial +0.4 %.
    With 6 cells through the thickness the first bending error is +3.7 %, with 4 it is +8.2 %:
    linear tets are stiff in bending. The two transverse directions of the square section would
    be a double eigenvalue; the Freudenthal split is anisotropic and separates them by ~2 %.
    """
    L, h, n = 1.0, 0.1, 8
    X, T = meshgen.box_tet_mesh((L, h, h), (10 * n, n, n))
    K = fem.stiffness_matrix(X, T, E, NU)
    masses = fem.lumped_masses(X, T, RHO)
    clamped = np.flatnonzero(X[:, 0] < 1e-12)
    result = modes.linear_modes(K, masses, 7, pinned_nodes=clamped)
    return X, masses, result, L, h


def mode_fractions(X, masses, W):
    """Per mode: mass-weighted share of (section-mean transverse motion, axial motion).

    Bending moves whole cross-sections sideways; torsion leaves their mean in place; the axial
    mode moves along x.
    """
    section = np.unique(np.round(X[:, 0], 9), return_inverse=True)[1]
    U = W.reshape(len(X), 3, -1)
    total = np.einsum("n,nim->m", masses, U ** 2)
    section_mass = np.bincount(section, masses)
    bending = np.zeros(W.shape[1])
    for axis in (1, 2):
        mean = np.stack([np.bincount(section, masses * U[:, axis, m]) for m in range(W.shape[1])],
                        axis=1) / section_mass[:, None]
        bending += np.einsum("s,sm->m", section_mass, mean ** 2)
    axial = np.einsum("n,nm->m", masses, U[:, 0, :] ** 2)
    return bending / total, axial / total


def test_cantilever_bending_frequencies_match_euler_bernoulli(cantilever):
    X, masses, result, L, h = cantilever
    area, inertia = h * h, h ** 4 / 12.0
    base = np.sqrt(E * inertia / (RHO * area * L ** 4))
    omega = np.sqrt(result.eigenvalues)
    bending, _ = mode_fractions(X, masses, result.vectors)
    bending_omega = omega[bending > 0.9]
    assert len(bending_omega) >= 4  # two transverse directions x first and second bending
    first, second = 1.8751041 ** 2 * base, 4.6940911 ** 2 * base
    assert bending_omega[0] == pytest.approx(first, rel=0.03)
    assert bending_omega[1] == pytest.approx(first, rel=0.05)
    assert bending_omega[2] == pytest.approx(second, rel=0.05)
    assert result.mnf == pytest.approx(omega[0])
    np.testing.assert_allclose(result.frequencies_hz, omega / (2 * np.pi))


def test_cantilever_axial_frequency(cantilever):
    X, masses, result, L, _ = cantilever
    _, axial = mode_fractions(X, masses, result.vectors)
    assert np.sum(axial > 0.9) == 1
    omega_axial = np.sqrt(result.eigenvalues[axial > 0.9][0])
    assert omega_axial == pytest.approx(np.pi / (2 * L) * np.sqrt(E / RHO), rel=0.01)


def test_cantilever_modes_vanish_on_clamped_nodes(cantilever):
    X, _, result, _, _ = cantilever
    clamped = X[:, 0] < 1e-12
    np.testing.assert_array_equal(result.pinned_nodes, np.flatnonzero(clamped))
    assert np.all(result.vectors.reshape(len(X), 3, -1)[clamped] == 0.0)
    assert np.all(np.diff(result.eigenvalues) >= 0)


@pytest.fixture(scope="module")
def free_block():
    """11 x 5 x 5 nodes (825 DOFs): above DENSE_LIMIT, so linear_modes takes the eigsh path."""
    X, T = meshgen.box_tet_mesh((2.0, 0.8, 0.6), (10, 4, 4))
    X = X + 0.02 * np.sin(3.0 * X[:, [1, 2, 0]])  # break the box's symmetries a little
    T = fem.orient_tets(X, T)
    K = fem.stiffness_matrix(X, T, E, NU)
    masses = fem.lumped_masses(X, T, RHO)
    M = sp.diags(np.repeat(masses, 3), format="csr")
    reference = scipy.linalg.eigh(K.toarray(), M.toarray(), eigvals_only=True)
    return X, K, masses, M, reference


def test_free_body_has_exactly_six_zero_modes(free_block):
    X, K, masses, M, _ = free_block
    sigma = -1e-6 * np.mean(K.diagonal() / M.diagonal())
    values = np.sort(spla.eigsh(K, k=12, M=M, sigma=sigma, return_eigenvectors=False))
    assert modes.count_near_zero(values, rel_tol=1e-8) == 6
    R = modes.rigid_motions(X)
    assert np.linalg.matrix_rank(R) == 6
    assert np.linalg.norm(K @ R) <= 1e-8 * spla.norm(K) * np.linalg.norm(R)


@pytest.mark.parametrize("dense_limit", [0, 10 ** 6], ids=["eigsh", "dense"])
def test_free_modes_skip_rigid_motions(free_block, monkeypatch, dense_limit):
    monkeypatch.setattr(modes, "DENSE_LIMIT", dense_limit)
    X, K, masses, M, reference = free_block
    r = 10
    result = modes.linear_modes(K, masses, r)
    W, lam = result.vectors, result.eigenvalues
    assert W.shape == (3 * len(X), r) and lam.shape == (r,)
    assert len(result.pinned_nodes) == 0
    np.testing.assert_allclose(lam, reference[6:6 + r], rtol=1e-8)
    assert np.all(lam > 0)
    np.testing.assert_allclose(W.T @ (M @ W), np.eye(r), atol=1e-8)
    np.testing.assert_allclose(W.T @ (K @ W), np.diag(lam), atol=1e-8 * lam.max())
    # Deformation modes are mass-orthogonal to the rigid motions.
    R = modes.rigid_motions(X)
    assert np.abs(R.T @ (M @ W)).max() <= 1e-8 * np.linalg.norm(R, axis=0).max()


def test_pinned_modes_match_reduced_problem_and_vanish_on_pins(free_block):
    X, K, masses, M, _ = free_block
    pinned = np.flatnonzero(X[:, 0] > X[:, 0].max() - 0.1)
    result = modes.linear_modes(K, masses, 5, pinned_nodes=pinned)
    free = np.repeat(~np.isin(np.arange(len(X)), pinned), 3)
    reference = scipy.linalg.eigh(K[free][:, free].toarray(), M[free][:, free].toarray(),
                                  eigvals_only=True, subset_by_index=(0, 4))
    np.testing.assert_allclose(result.eigenvalues, reference, rtol=1e-8)
    assert np.all(result.vectors.reshape(len(X), 3, -1)[pinned] == 0.0)
    W = result.vectors
    np.testing.assert_allclose(W.T @ (M @ W), np.eye(5), atol=1e-8)


def small_problem():
    X, T = meshgen.box_tet_mesh((1.0, 1.0, 1.0), (1, 1, 1))
    return X, fem.stiffness_matrix(X, T, E, NU), fem.lumped_masses(X, T, RHO)


def test_all_pinned_raises():
    X, K, m = small_problem()
    with pytest.raises(ValueError, match="all nodes are pinned"):
        modes.linear_modes(K, m, 1, pinned_nodes=np.arange(len(X)))


def test_too_many_modes_raises():
    X, K, m = small_problem()  # 8 nodes, 24 DOFs, 18 deformation modes
    assert len(modes.linear_modes(K, m, 17).eigenvalues) == 17
    with pytest.raises(ValueError, match="at most 17"):
        modes.linear_modes(K, m, 18)
    with pytest.raises(ValueError, match="at most"):
        modes.linear_modes(K, m, 3, pinned_nodes=np.arange(7))  # one free node, 3 DOFs
    with pytest.raises(ValueError, match="at least one mode"):
        modes.linear_modes(K, m, 0)


def test_a_stiffness_that_is_not_positive_semi_definite_raises():
    X, T = meshgen.box_tet_mesh((3.0, 1.0, 1.0), (12, 4, 4))   # 975 DOFs: the sparse path
    K, m = fem.stiffness_matrix(X, T, E, NU), fem.lumped_masses(X, T, RHO)
    pins = np.flatnonzero(X[:, 0] < 1e-9)
    assert len(modes.linear_modes(K, m, 4, pins, rest_positions=X).eigenvalues) == 4
    with pytest.raises(ValueError, match="not positive semi-definite"):
        modes.linear_modes(-K, m, 4, pins, rest_positions=X)


def test_disconnected_free_body_raises():
    X1, T1 = meshgen.box_tet_mesh(cells=(2, 1, 1))
    X2, T2 = meshgen.box_tet_mesh(cells=(2, 1, 1), origin=(5.0, 0.0, 0.0))
    X, T = np.vstack([X1, X2]), np.vstack([T1, T2 + len(X1)])
    K, m = fem.stiffness_matrix(X, T, E, NU), fem.lumped_masses(X, T, RHO)
    with pytest.raises(ValueError, match="2 disconnected parts"):
        modes.linear_modes(K, m, 3)
    with pytest.raises(ValueError, match="no pinned"):
        modes.linear_modes(K, m, 3, pinned_nodes=[0, 1, 2])
    both_pinned = [0, 1, 2, len(X1), len(X1) + 1, len(X1) + 2]  # three corners of each part
    assert np.all(modes.linear_modes(K, m, 3, pinned_nodes=both_pinned).eigenvalues > 0)


# Determinism: signs and repeated-eigenvalue bases ---------------------------------------------

def block_problem(cells=(10, 4, 4), size=(2.0, 0.8, 0.6), warp=0.02):
    X, T = meshgen.box_tet_mesh(size, cells)
    X = X + warp * np.sin(3.0 * X[:, [1, 2, 0]])
    T = fem.orient_tets(X, T)
    return X, T, fem.stiffness_matrix(X, T, E, NU), fem.lumped_masses(X, T, RHO)


def permuted(X, T, order):
    """The same mesh with node i renamed to position order^-1[i]: X_new = X[order]."""
    inverse = np.empty_like(order)
    inverse[order] = np.arange(len(order))
    return X[order], inverse[T]


@pytest.mark.parametrize("with_positions", [True, False], ids=["positions", "index"])
def test_same_call_twice_gives_identical_modes(with_positions):
    """ARPACK's start vector is fixed: two calls in one process agree bit for bit."""
    X, T, K, m = block_problem()
    pins = np.flatnonzero(X[:, 0] < 0.25)
    rest = X if with_positions else None
    first = modes.linear_modes(K, m, 20, pins, rest_positions=rest)
    spla.eigsh(K, k=3, sigma=-1.0)  # advance any global random state between the calls
    second = modes.linear_modes(K, m, 20, pins, rest_positions=rest)
    np.testing.assert_array_equal(first.vectors, second.vectors)
    np.testing.assert_array_equal(first.eigenvalues, second.eigenvalues)


@pytest.mark.parametrize("dense_limit", [0, 10 ** 6], ids=["eigsh", "dense"])
def test_renumbered_nodes_give_the_same_modes(monkeypatch, dense_limit):
    """Modes are a property of the body, not of its node numbering (signs included)."""
    monkeypatch.setattr(modes, "DENSE_LIMIT", dense_limit)
    X, T, K, m = block_problem()
    order = np.random.default_rng(7).permutation(len(X))
    Xp, Tp = permuted(X, T, order)
    a = modes.linear_modes(K, m, 12, rest_positions=X)
    b = modes.linear_modes(fem.stiffness_matrix(Xp, Tp, E, NU), fem.lumped_masses(Xp, Tp, RHO),
                           12, rest_positions=Xp)
    np.testing.assert_allclose(b.eigenvalues, a.eigenvalues, rtol=1e-10)
    Wa = a.vectors.reshape(len(X), 3, -1)[order]
    Wb = b.vectors.reshape(len(X), 3, -1)
    np.testing.assert_allclose(Wb, Wa, atol=1e-8 * np.abs(Wa).max())


def test_fresh_interpreter_gives_the_same_modes(tmp_path):
    """A new process (new ARPACK state, new address space) reproduces the modes to 1e-10."""
    import subprocess
    import sys
    from pathlib import Path

    script = (
        "import sys, numpy as np\n"
        "sys.path[:0] = sys.argv[2:]\n"
        "from tests.solver.test_modes import block_problem\n"
        "from solver import modes\n"
        "X, T, K, m = block_problem()\n"
        "r = modes.linear_modes(K, m, 20, np.flatnonzero(X[:, 0] < 0.25), rest_positions=X)\n"
        "np.save(sys.argv[1], r.vectors)\n")
    root = Path(__file__).resolve().parents[2]
    out = tmp_path / "w.npy"
    subprocess.run([sys.executable, "-c", script, str(out), str(root), *sys.path], check=True,
                   cwd=root)
    X, T, K, m = block_problem()
    here = modes.linear_modes(K, m, 20, np.flatnonzero(X[:, 0] < 0.25), rest_positions=X)
    np.testing.assert_allclose(np.load(out), here.vectors, rtol=0, atol=1e-10)


def test_symmetric_cube_gets_one_basis_for_its_repeated_eigenvalues(monkeypatch):
    """A cube meshed symmetrically under axis permutations has repeated eigenvalues; the basis
    inside each cluster is fixed by the test fields, so two different eigensolvers (ARPACK and
    LAPACK, which return different arbitrary bases) and a renumbering all give the same modes."""
    X, T = meshgen.box_tet_mesh((1.0, 1.0, 1.0), (5, 5, 5))
    K, m = fem.stiffness_matrix(X, T, E, NU), fem.lumped_masses(X, T, RHO)
    r = 14
    lanczos = modes.linear_modes(K, m, r, rest_positions=X)
    lam = lanczos.eigenvalues
    assert np.sum(np.diff(lam) <= 1e-8 * lam[1:]) >= 3  # the test needs repeated eigenvalues
    monkeypatch.setattr(modes, "DENSE_LIMIT", 10 ** 6)
    dense = modes.linear_modes(K, m, r, rest_positions=X)
    scale = np.abs(lanczos.vectors).max()
    np.testing.assert_allclose(dense.vectors, lanczos.vectors, atol=1e-6 * scale)
    order = np.random.default_rng(8).permutation(len(X))
    Xp, Tp = permuted(X, T, order)
    renumbered = modes.linear_modes(fem.stiffness_matrix(Xp, Tp, E, NU),
                                    fem.lumped_masses(Xp, Tp, RHO), r, rest_positions=Xp)
    np.testing.assert_allclose(renumbered.vectors.reshape(len(X), 3, r),
                               dense.vectors.reshape(len(X), 3, r)[order], atol=1e-6 * scale)


class _Stop(Exception):
    pass


def test_progress_is_reported_between_solves_and_can_stop_them():
    """The eigen solve reports before each shift-invert solve, fractions rising in [0, 1), and
    an exception raised there (how Esc cancels a Prepare) ends it; reporting changes nothing."""
    X, T, K, m = block_problem()
    assert 3 * len(X) > modes.DENSE_LIMIT                  # the shift-invert path
    pins = np.flatnonzero(X[:, 0] < 0.25)
    fractions = []
    reported = modes.linear_modes(K, m, 20, pins, rest_positions=X,
                                  progress=lambda f, message: fractions.append(f))
    plain = modes.linear_modes(K, m, 20, pins, rest_positions=X)
    np.testing.assert_array_equal(reported.vectors, plain.vectors)
    assert len(fractions) > 20                             # tens of solves, each reported
    assert fractions == sorted(fractions) and 0.0 <= fractions[0] and fractions[-1] < 1.0

    calls = []

    def stop_at_the_fifth(fraction, message):
        calls.append(message)
        if len(calls) == 5:
            raise _Stop()
    with pytest.raises(_Stop):
        modes.linear_modes(K, m, 20, pins, rest_positions=X, progress=stop_at_the_fifth)
    assert len(calls) == 5


# --- modes at Young's modulus 1 Pa, scaled (what Prepare caches) ------------------------------

@pytest.mark.parametrize("painted", [False, True], ids=["uniform", "painted"])
def test_modes_at_a_material_are_the_unit_modes_moved(painted):
    """K is linear in Young's modulus and M in a uniform density: the modes Prepare caches at
    1 Pa and 1 kg/m^3, moved to (E, rho), equal an independent modal analysis of the stiffness
    at E and the masses at rho (eigenvalues to eigsh's accuracy, vectors with the same signs),
    and two moduli at one density share the very same vectors."""
    from solver import preparation
    X, T = meshgen.box_tet_mesh((1.0, 0.2, 0.2), (10, 2, 2))
    tet_body = preparation.embedded(X, T, X)
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    scale = (preparation.stiffness_scale(tet_body, 1.0 - X[:, 0], 0.25) if painted else None)
    unit = preparation.unit_stiffness_modes(tet_body, NU, 6, pinned, scale)
    for density in (RHO, 7.5):
        shared = None
        for youngs in (E, 3.7e8):
            moved = preparation.linear_modes(tet_body, youngs, NU, density, 6, pinned, scale)
            np.testing.assert_allclose(moved.vectors, unit.vectors / np.sqrt(density),
                                       rtol=1e-15, atol=0.0)
            if shared is not None:
                np.testing.assert_array_equal(moved.vectors, shared)
            shared = moved.vectors
            np.testing.assert_array_equal(moved.eigenvalues,
                                          unit.eigenvalues * (youngs / density))
            K = fem.stiffness_matrix(X, T, youngs if scale is None else youngs * scale, NU)
            reference = modes.linear_modes(K, fem.lumped_masses(X, T, density), 6, pinned,
                                           rest_positions=X)
            np.testing.assert_allclose(moved.eigenvalues, reference.eigenvalues, rtol=1e-9)
            np.testing.assert_allclose(moved.vectors, reference.vectors,
                                       atol=1e-7 * np.abs(reference.vectors).max())


@pytest.mark.parametrize("youngs", [0.0, -1e6, float("nan"), float("inf")])
def test_a_youngs_modulus_that_is_not_positive_is_refused(youngs):
    from solver import preparation
    X, T = meshgen.box_tet_mesh((1.0, 0.2, 0.2), (4, 1, 1))
    unit = preparation.unit_stiffness_modes(preparation.embedded(X, T, X), NU, 3,
                                            np.flatnonzero(X[:, 0] < 1e-9))
    with pytest.raises(ValueError, match="Young's modulus"):
        preparation.modes_at(unit, youngs, RHO)


@pytest.mark.parametrize("density", [0.0, -1000.0, float("nan"), float("inf")])
def test_a_density_that_is_not_positive_is_refused(density):
    from solver import preparation
    X, T = meshgen.box_tet_mesh((1.0, 0.2, 0.2), (4, 1, 1))
    tet_body = preparation.embedded(X, T, X)
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    unit = preparation.unit_stiffness_modes(tet_body, NU, 3, pinned)
    with pytest.raises(ValueError, match="Density"):
        preparation.modes_at(unit, E, density)
    with pytest.raises(ValueError, match="Density"):
        preparation.linear_modes(tet_body, E, NU, density, 3, pinned)
