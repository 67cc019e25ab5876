"""Fill-reducing order of the modal factorisation (solver.ordering, issue 14).

Oracles: nested dissection is a permutation, repeatable, and a true dissection (the two halves
of the top split share no edge; only the separator touches both); on the 41k-tet bar it fills
SuperLU's factor less than SuperLU's own minimum degree; and the modes computed with it (by
SuperLU, or by the supernodal Cholesky on its blocks) are the modes of the minimum-degree solve
(eigenvalues within 1e-6 relative, subspaces within 1e-4 rad), free bodies included; its blocks
are its order cut into the leaves and separators.
"""
import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from solver import fem, meshgen, modes, ordering


def bar(n):
    X, T = meshgen.box_tet_mesh((4.0, 1.0, 1.0), (4 * n, n, n))
    return X, T, fem.stiffness_matrix(X, T, 1e6, 0.45), fem.lumped_masses(X, T, 1100.0)


def test_node_graph_links_nodes_that_share_a_tet():
    X, T = meshgen.box_tet_mesh((1.0, 1.0, 1.0), (2, 2, 2))
    graph = ordering.node_graph(fem.stiffness_matrix(X, T, 1e6, 0.3))
    expected = np.zeros((len(X), len(X)), dtype=bool)
    for tet in T:
        expected[np.ix_(tet, tet)] = True
    np.testing.assert_array_equal(graph.toarray() > 0, expected)


def test_nested_dissection_is_a_repeatable_permutation_with_a_true_separator():
    X, T, K, _ = bar(4)
    graph = ordering.node_graph(K)
    order = ordering.nested_dissection(X, graph, leaf_size=16)
    np.testing.assert_array_equal(np.sort(order), np.arange(len(X)))
    np.testing.assert_array_equal(order, ordering.nested_dissection(X, graph, leaf_size=16))
    # The top split along x (the bar's long side): left part, right part, separator last.
    left = X[:, 0] <= np.median(X[:, 0])
    separator = left & (graph @ (~left).astype(float) > 0)
    assert set(order[-separator.sum():]) == set(np.flatnonzero(separator))
    interior_left = left & ~separator
    assert (graph[interior_left][:, ~left]).nnz == 0            # halves share no edge
    dofs = ordering.dof_order(order)
    np.testing.assert_array_equal(dofs[:3], 3 * order[0] + np.arange(3))


def test_nested_dissection_fills_the_factor_less_than_minimum_degree():
    X, T, K, m = bar(12)                                      # 41k tets
    pinned = X[:, 0] < 1e-9
    free = np.repeat(~pinned, 3)
    A = (K[free][:, free] + sp.diags(np.repeat(m, 3)[free])).tocsc()
    mmd = spla.splu(A, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
    perm = ordering.dof_order(ordering.nested_dissection(X[~pinned], ordering.node_graph(A)))
    nd = spla.splu(A[perm][:, perm].tocsc(), permc_spec="NATURAL", diag_pivot_thresh=0.0,
                   options={"SymmetricMode": True})
    fill = {"mmd": mmd.L.nnz + mmd.U.nnz, "nd": nd.L.nnz + nd.U.nnz}
    print(f"41k-tet bar, nonzeros of L + U: {fill['mmd']:.3g} minimum degree, "
          f"{fill['nd']:.3g} nested dissection")
    assert fill["nd"] < 0.8 * fill["mmd"]
    b = np.cos(np.arange(A.shape[0]))
    x = np.empty_like(b)
    x[perm] = nd.solve(b[perm])
    assert np.linalg.norm(A @ x - b) < 1e-10 * np.linalg.norm(b)


def largest_principal_angle(U, V, m):
    """Largest principal angle [rad] between span U and span V in the M inner product."""
    w = np.sqrt(m)[:, None]
    s = scipy.linalg.svdvals(np.linalg.qr(w * U)[0].T @ np.linalg.qr(w * V)[0])
    return float(np.arccos(np.clip(s.min(), -1.0, 1.0)))


@pytest.mark.parametrize("factorisation", ["superlu_nd", "supernodal"])
@pytest.mark.parametrize("pinned_bar", [True, False], ids=["pinned", "free"])
def test_modes_with_nested_dissection_are_the_minimum_degree_modes(pinned_bar, factorisation):
    X, T, K, m = bar(8)                                       # 12k tets
    pins = np.flatnonzero(X[:, 0] < 1e-9) if pinned_bar else None
    old = modes.linear_modes(K, m, 20, pins, rest_positions=X, factorisation="superlu_mmd")
    new = modes.linear_modes(K, m, 20, pins, rest_positions=X, factorisation=factorisation)
    relative = np.abs(new.eigenvalues - old.eigenvalues) / old.eigenvalues
    angle = largest_principal_angle(new.vectors, old.vectors, np.repeat(m, 3))
    print(f"{factorisation} vs minimum degree: eigenvalues within {relative.max():.1e}, "
          f"largest principal angle {angle:.1e} rad")
    assert relative.max() < 1e-6
    assert angle < 1e-4


def test_nested_dissection_blocks_are_its_order_in_pieces():
    X, T, K, _ = bar(4)
    graph = ordering.node_graph(K)
    blocks = ordering.nested_dissection_blocks(X, graph, leaf_size=16)
    np.testing.assert_array_equal(np.concatenate(blocks),
                                  ordering.nested_dissection(X, graph, leaf_size=16))
    assert all(len(block) for block in blocks)
    left = X[:, 0] <= np.median(X[:, 0])                      # the last block: the top separator
    np.testing.assert_array_equal(np.sort(blocks[-1]),
                                  np.flatnonzero(left & (graph @ (~left).astype(float) > 0)))


@pytest.mark.parametrize("factorisation", ["superlu_nd", "supernodal"])
def test_nested_dissection_needs_the_rest_positions(factorisation):
    X, T, K, m = bar(2)
    with pytest.raises(ValueError, match="rest positions"):
        modes.linear_modes(K, m, 4, np.flatnonzero(X[:, 0] < 1e-9), factorisation=factorisation)
    with pytest.raises(ValueError, match="unknown factorisation"):
        modes.linear_modes(K, m, 4, None, rest_positions=X, factorisation="metis")
