"""Accuracy of reduced RS where animators go (issue 12 item 2).

Oracle: full RS (``rs.PoissonReconstruction`` of the same RS coordinates). The 40-mode bar is
trained once per module with the default sizes (``reduced.default_basis_size`` and
``default_cubature_size``, training poses up to 180 deg).
Measured before this change (rB capped at 160, 150 tets, training up to 120 deg), same bar:
2.2 % of the diagonal at 180 deg. solver.accuracy: oracles are a complete basis (exact), a
direct numpy computation, a uniform 20 % stretch and a slender bar's bend.
"""

import numpy as np
import pytest

from solver import accuracy, fem, meshgen, modes, reduced, rs

NUM_MODES = 40


@pytest.fixture(scope="module")
def bar40():
    """Pinned 4:1:1 bar (12 x 3 x 3 cells, 648 tets), E = 1e7 Pa, 40 modes, default reduced RS."""
    X, T = meshgen.box_tet_mesh((4.0, 1.0, 1.0), (12, 3, 3))
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    K = fem.stiffness_matrix(X, T, 1.0e7, 0.45)
    masses = fem.lumped_masses(X, T, 1000.0)
    result = modes.linear_modes(K, masses, NUM_MODES, pinned_nodes=pinned)
    modal_rs = rs.linear_rs(rs.rs_operator(X, T), result.vectors)
    recon = rs.PoissonReconstruction(X, T, pinned_nodes=pinned)
    deformer, info = reduced.prepare_reduced_rs(X, T, masses, result.vectors,
                                                result.eigenvalues, recon, modal_rs=modal_rs,
                                                seed=0)
    print(f"rB = {deformer.basis_size}, |C| = {len(deformer.cubature_tets)}, {info['seconds']}")
    return dict(X=X, T=T, modal_rs=modal_rs, recon=recon, deformer=deformer)


def bend(modal_rs, degrees):
    """First bending mode's coordinates scaled so its largest tet rotation is ``degrees``."""
    z = np.zeros(modal_rs.shape[2])
    z[0] = np.radians(degrees) / rs.max_mode_rotations(modal_rs)[0]
    return z


def relative_error(bar, z):
    """max vertex |u_reduced - u_full| / bounding-box diagonal."""
    X = bar["X"]
    full = bar["recon"].reconstruct(bar["modal_rs"] @ z)
    u = bar["deformer"].displacement(z)
    return float(np.linalg.norm(u - full, axis=1).max() / np.linalg.norm(np.ptp(X, axis=0)))


def test_default_sizes_grow_with_the_mode_count():
    assert reduced.default_basis_size(10) == 120
    assert reduced.default_basis_size(14) == 160
    assert reduced.default_basis_size(20) == 20 + 20 * 21 // 2    # O(m^2): the pairs
    assert reduced.default_basis_size(40) == 40 + 40 * 41 // 2    # no fixed cap
    # Bounded by memory (24 N rB bytes <= budget), the DOFs and the tets.
    budget = reduced.MEMORY_BUDGET
    assert reduced.default_basis_size(40, num_nodes=10 ** 5) == budget // (24 * 10 ** 5)
    assert reduced.default_basis_size(40, num_nodes=10 ** 7) == 40      # the modes stay
    assert reduced.default_basis_size(40, num_nodes=208, num_tets=648) == 243
    assert reduced.default_cubature_size(243, num_tets=648) == 304
    assert reduced.default_cubature_size(40) == 150


def test_180_degree_bend_with_40_modes_within_1_percent(bar40):
    error = relative_error(bar40, bend(bar40["modal_rs"], 180.0))
    print(f"180 deg bend, 40 modes: {100 * error:.2f} % of the diagonal")
    assert error < 0.01


# Reduced error after a solve (solver.accuracy.reduced_error) ---------------------------------

def small_bar():
    X, T = meshgen.box_tet_mesh((1.5, 0.5, 0.5), (3, 1, 1))
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    free = np.repeat(~np.isin(np.arange(len(X)), pinned), 3)
    W = np.random.default_rng(0).normal(size=(3 * len(X), 2)) * free[:, None]
    modal_rs = rs.linear_rs(rs.rs_operator(X, T), W)
    recon = rs.PoissonReconstruction(X, T, pinned_nodes=pinned)
    return X, T, free, W, modal_rs, recon


def test_reduced_error_is_zero_when_the_basis_spans_the_full_pose():
    """Complete basis, every tet with unit weight: reduced RS is full RS, error ~ round-off."""
    X, T, free, W, modal_rs, recon = small_bar()
    B = np.eye(3 * len(X))[:, free]
    deformer = reduced.ReducedRS.build(X, T, modal_rs, B, recon, np.arange(len(T)),
                                       np.ones(len(T)))
    Z = np.array([[0.7, -1.3], [2.0, 0.5]])
    assert np.all(accuracy.reduced_error(deformer, recon, modal_rs, Z, X) < 1e-12)


def test_reduced_error_matches_a_direct_computation():
    """Linear modes (u = W z) against full RS, recomputed by hand."""
    X, T, free, W, modal_rs, recon = small_bar()
    deformer = reduced.LinearDeformer(2, W)
    Z = np.array([[0.3, -0.2], [1.0, 0.4], [0.0, 0.0]])
    got = accuracy.reduced_error(deformer, recon, modal_rs, Z, X)
    diagonal = np.sqrt(1.5 ** 2 + 0.5 ** 2 + 0.5 ** 2)
    for z, value in zip(Z, got):
        full = recon.reconstruct(modal_rs @ z)
        expected = np.abs(np.linalg.norm((W @ z).reshape(-1, 3) - full, axis=1)).max() / diagonal
        assert value == pytest.approx(expected, rel=1e-12, abs=1e-15)
    assert got[1] > 1e-3 and got[2] == 0.0          # large poses leave the linear model


def test_telling_frames_pick_the_largest_rotations():
    modal_rs = small_bar()[4]
    Z = np.outer([0.1, 3.0, 0.5, 2.0, 1.0], [1.0, 0.5])
    np.testing.assert_array_equal(accuracy.telling_frames(modal_rs, Z, count=3), [1, 3])


# Stretch the targets demand (solver.accuracy.target_stretch) --------------------------------

def straight_bar():
    """4 x 1 x 1 bar, 8 x 2 x 2 cells: node rows run straight along x through (y, z) = (.5, .5)."""
    X, T = meshgen.box_tet_mesh((4.0, 1.0, 1.0), (8, 2, 2))
    return X, T, np.flatnonzero(X[:, 0] < 1e-9)


def test_edge_graph_holds_each_tet_edge_once_with_its_length():
    X, T = meshgen.box_tet_mesh((1.0, 1.0, 1.0), (1, 1, 1))
    graph = accuracy.edge_graph(X, T)
    edges = {tuple(sorted((int(t[a]), int(t[b])))) for t in T for a in range(4)
             for b in range(a + 1, 4)}
    assert graph.nnz == 2 * len(edges)
    for i, j in edges:
        assert graph[i, j] == pytest.approx(np.linalg.norm(X[i] - X[j]), rel=1e-15)


def test_a_tip_target_20_percent_beyond_the_length_demands_20_percent():
    """Pinned bar: the straight edge path from (0, .5, .5) to the tip centroid is 4 m long, so a
    target at x = 4.8 is 1.2 times as far as any bending reaches: demand 0.2 (exact)."""
    X, T, pinned = straight_bar()
    demand, frame = accuracy.target_stretch(X, T, pinned, [[4.0, 0.5, 0.5]], [[3, 7]],
                                            [[[4.0, 0.5, 0.5], [4.8, 0.5, 0.5]]])
    assert demand[0] == pytest.approx(0.2, abs=1e-12) and frame[0] == 7


def test_a_bent_tip_target_demands_no_stretch():
    """The tip of the bar turned up 90 deg about the pinned end (an arc of length 4 ends 2.55 m
    from it): reachable by bending, so the demand is negative."""
    X, T, pinned = straight_bar()
    radius = 4.0 / (np.pi / 2)
    target = [radius, 0.5, 0.5 + radius]
    demand, _ = accuracy.target_stretch(X, T, pinned, [[4.0, 0.5, 0.5]], [[5]], [[target]])
    assert demand[0] < 0.0


def test_two_handles_of_a_free_body_keyed_apart_demand_stretch_on_their_common_frames():
    """No pins: the two end handles are 4 m apart by the straight path; keyed 4.4 m apart on
    frame 2, each 0.2 m out, they both demand 10 %; frame 5 keys only one of them and is not
    compared. Keyed apart with one of them at rest, only the one that moved is named."""
    X, T, _ = straight_bar()
    ends = [[0.0, 0.5, 0.5], [4.0, 0.5, 0.5]]
    frames = [[2, 5], [2]]
    targets = [[[-0.2, 0.5, 0.5], [-9.0, 0.5, 0.5]], [[4.2, 0.5, 0.5]]]
    demand, frame = accuracy.target_stretch(X, T, [], ends, frames, targets)
    np.testing.assert_allclose(demand, [0.1, 0.1], atol=1e-12)
    assert frame.tolist() == [2, 2]
    targets = [[[0.0, 0.5, 0.5], [-9.0, 0.5, 0.5]], [[4.4, 0.5, 0.5]]]
    demand, frame = accuracy.target_stretch(X, T, [], ends, frames, targets)
    assert demand[1] == pytest.approx(0.1, abs=1e-12) and frame[1] == 2
    assert demand[0] < 0.0
