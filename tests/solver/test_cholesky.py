"""Supernodal Cholesky (solver.cholesky, issue 14).

Oracles: solves agree with SuperLU's on a tet-mesh stiffness (one and many right-hand sides),
for the nested-dissection blocks and for an arbitrary partition into consecutive blocks; the
stored factor reproduces A (L L^T = A entry by entry, from unit right-hand sides); an
indefinite matrix and blocks that are not a partition are refused.
"""
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from solver import fem, meshgen, ordering
from solver.cholesky import SupernodalCholesky


def shifted_bar(n, shift=1.0):
    """SPD K + shift M of a free 4:1:1 bar ((3N, 3N) csr) and its node positions."""
    X, T = meshgen.box_tet_mesh((4.0, 1.0, 1.0), (4 * n, n, n))
    K = fem.stiffness_matrix(X, T, 1e6, 0.45)
    masses = np.repeat(fem.lumped_masses(X, T, 1100.0), 3)
    return (K + shift * sp.diags(masses)).tocsr(), X


def nd_blocks(A, X, leaf_size=16):
    return [ordering.dof_order(block) for block in
            ordering.nested_dissection_blocks(X, ordering.node_graph(A), leaf_size)]


def test_solves_agree_with_superlu_for_one_and_many_right_hand_sides():
    A, X = shifted_bar(4)
    factor = SupernodalCholesky(A, nd_blocks(A, X))
    reference = spla.splu(A.tocsc())
    B = np.cos(np.arange(A.shape[0])[:, None] * (1.0 + np.arange(5))[None, :])
    X_many = factor.solve(B)
    assert X_many.shape == B.shape
    np.testing.assert_allclose(X_many, reference.solve(B), rtol=0, atol=1e-10 * abs(X_many).max())
    x_one = factor.solve(B[:, 2])
    assert x_one.shape == (A.shape[0],)
    np.testing.assert_allclose(x_one, X_many[:, 2], rtol=0, atol=1e-12 * abs(x_one).max())
    assert np.linalg.norm(A @ X_many - B) < 1e-10 * np.linalg.norm(B)


def test_any_partition_into_consecutive_blocks_gives_the_same_solution():
    A, X = shifted_bar(3)
    n = A.shape[0]
    cuts = np.unique(np.random.default_rng(7).integers(1, n, size=40))
    blocks = np.split(np.arange(n)[::-1], cuts)          # reversed order, uneven blocks
    b = np.sin(np.arange(n) * 0.37)
    x = SupernodalCholesky(A, blocks).solve(b)
    np.testing.assert_allclose(x, spla.spsolve(A.tocsc(), b), rtol=0, atol=1e-10 * abs(x).max())


def test_the_stored_factor_reproduces_the_matrix():
    A, X = shifted_bar(2)
    factor = SupernodalCholesky(A, nd_blocks(A, X, leaf_size=4))
    n = A.shape[0]
    L = np.zeros((n, n))                                  # assembled in elimination order
    for t, (L11, L21) in enumerate(zip(factor._diagonal, factor._off_diagonal)):
        a, e = factor._starts[t], factor._starts[t + 1]
        L[a:e, a:e] = np.tril(L11)
        L[factor._later[t], a:e] = L21
    p = factor.permutation
    dense = A.toarray()[np.ix_(p, p)]
    np.testing.assert_allclose(L @ L.T, dense, rtol=0, atol=1e-10 * abs(dense).max())
    assert factor.nnz >= np.count_nonzero(np.tril(L))


def test_an_indefinite_matrix_is_refused():
    A, X = shifted_bar(2, shift=-1e5)                      # K - sigma M with sigma above modes
    with pytest.raises(np.linalg.LinAlgError, match="not positive definite"):
        SupernodalCholesky(A, nd_blocks(A, X))


def test_blocks_must_partition_the_unknowns():
    A, X = shifted_bar(2)
    n = A.shape[0]
    with pytest.raises(ValueError, match="partition"):
        SupernodalCholesky(A, [np.arange(n - 1)])
    with pytest.raises(ValueError, match="partition"):
        SupernodalCholesky(A, [np.arange(n), np.array([0])])
