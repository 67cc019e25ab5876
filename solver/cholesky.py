"""Sparse Cholesky factorisation A = L L^T of a symmetric positive definite matrix, by blocks.

The unknowns are eliminated block by block in a given order (``solver.ordering`` gives the
blocks of a nested dissection: leaves, then the separators that split them). Each block is a
supernode: its columns of L are stored as one dense lower-triangular diagonal block L11 (s, s)
and one dense block L21 (u, s) on the later unknowns its subtree touches. The numeric work is
multifrontal: a block's front gathers its rows of A and the Schur-complement updates of its
children, then one dense Cholesky (LAPACK potrf), one triangular solve (BLAS trsm) and one
rank-s update (BLAS syrk) eliminate it. Almost every flop is dense level-3 BLAS, which is why
this beats SuperLU's LU of the same matrix in the same order several times over on tet meshes
(``make bench``, modes rows), and why a solve with many right-hand sides at once costs little
more than one.

Works for any partition of the unknowns into blocks that are eliminated in the given order
(a block's front rows are its own unknowns and every later unknown that A or a child's update
couples to it; its parent is the block holding the first of those). Nested dissection makes the
fronts small: a block's later unknowns lie in the separators around its subtree.

Shapes: A (n, n) sparse SPD; blocks: list of int arrays partitioning range(n), in elimination
order; right-hand sides (n,) or (n, k).
"""
import numpy as np
import scipy.sparse as sp
from scipy.linalg import blas, lapack


class SupernodalCholesky:
    """A = L L^T for SPD A (n, n), eliminated in ``blocks`` order (module docstring).

    Raises numpy.linalg.LinAlgError if A is not positive definite.
    Attributes: ``permutation`` (n,) the unknowns in elimination order; ``nnz`` stored entries
    of L (dense blocks, so a little more than the exact fill).
    """

    def __init__(self, A, blocks):
        A = sp.csr_matrix(A, dtype=np.float64)
        n = A.shape[0]
        self.permutation = np.concatenate([np.asarray(b, dtype=np.int64) for b in blocks])
        if A.shape != (n, n) or len(self.permutation) != n or not np.array_equal(
                np.sort(self.permutation), np.arange(n)):
            raise ValueError(f"blocks must partition the {A.shape[0]} unknowns of a square matrix")
        sizes = np.array([len(b) for b in blocks], dtype=np.int64)
        self._starts = np.r_[0, np.cumsum(sizes)]
        P = A[self.permutation][:, self.permutation].tocsr()
        P.sum_duplicates()
        self._later, children = _symbolic(P, self._starts)
        self._diagonal, self._off_diagonal = _numeric(P, self._starts, self._later, children)
        self.nnz = int(sum(s * (s + 1) // 2 + s * len(u)
                           for s, u in zip(sizes, self._later)))

    def solve(self, b):
        """x = A^-1 b for b (n,) or (n, k); returns the same shape."""
        b = np.asarray(b, dtype=np.float64)
        y = np.asfortranarray(b.reshape(len(b), -1)[self.permutation])
        starts, later = self._starts, self._later
        # Every product goes through scipy's BLAS, as the factorisation does: numpy brings its
        # own OpenBLAS, and two BLAS thread pools taking turns on small products stall each
        # other (a 32-column solve took 10 times as long on two threads).
        product = _matrix_vector if y.shape[1] == 1 else _matrix_matrix
        for t, (L11, L21) in enumerate(zip(self._diagonal, self._off_diagonal)):
            a, e = starts[t], starts[t + 1]
            y[a:e] = blas.dtrsm(1.0, L11, y[a:e], lower=1)
            if len(later[t]):
                y[later[t]] = product(L21, y[a:e], y[later[t]], 0)
        for t in range(len(self._diagonal) - 1, -1, -1):
            a, e = starts[t], starts[t + 1]
            if len(later[t]):
                y[a:e] = product(self._off_diagonal[t], y[later[t]], y[a:e], 1)
            y[a:e] = blas.dtrsm(1.0, self._diagonal[t], y[a:e], lower=1, trans_a=1)
        x = np.empty_like(y)
        x[self.permutation] = y
        return x.reshape(b.shape)


def _matrix_matrix(L, x, y, transpose):
    """y - op(L) x for x, y (., k), op = transpose or not (BLAS gemm)."""
    return blas.dgemm(-1.0, L, x, beta=1.0, c=y, trans_a=transpose)


def _matrix_vector(L, x, y, transpose):
    """y - op(L) x for x, y (., 1) (BLAS gemv)."""
    return blas.dgemv(-1.0, L, x[:, 0], beta=1.0, y=y[:, 0], trans=transpose)[:, None]


def _symbolic(P, starts):
    """Later unknowns of each block's front (list of sorted int arrays, positions in the
    elimination order) and each block's children (list of lists). P is A permuted (csr)."""
    count = len(starts) - 1
    owner = np.repeat(np.arange(count), np.diff(starts))
    later, children = [], [[] for _ in range(count)]
    for t in range(count):
        a, e = starts[t], starts[t + 1]
        cols = P.indices[P.indptr[a]:P.indptr[e]]
        rows = np.unique(np.concatenate([cols[cols >= e]] + [later[c] for c in children[t]]))
        rows = rows[rows >= e]
        later.append(rows)
        if len(rows):
            children[owner[rows[0]]].append(t)
    return later, children


def _extend_add(front, update, at):
    """front[at][:, at] += update on the lower triangle, by runs of consecutive ``at``.

    A child's later unknowns fall into few consecutive runs of its parent's front (a handful of
    separator pieces), so a few slice additions replace one scatter of every entry."""
    cut = np.flatnonzero(np.diff(at) != 1) + 1
    first, last = np.r_[0, cut], np.r_[cut, len(at)]
    for i in range(len(first)):
        rows = slice(at[first[i]], at[first[i]] + last[i] - first[i])
        for j in range(i + 1):
            cols = slice(at[first[j]], at[first[j]] + last[j] - first[j])
            front[rows, cols] += update[first[i]:last[i], first[j]:last[j]]


def _numeric(P, starts, later, children):
    """Dense blocks (L11 list, L21 list) by multifrontal elimination (module docstring).

    Only the lower triangle of a front is meaningful: child updates map into the parent by an
    increasing index map, so their lower triangles land in the parent's lower triangle."""
    n = P.shape[0]
    local = np.full(n, -1, dtype=np.int64)
    diagonal, off_diagonal, updates = [], [], {}
    for t in range(len(starts) - 1):
        a, e = starts[t], starts[t + 1]
        s = e - a
        rows = np.r_[np.arange(a, e), later[t]]
        local[rows] = np.arange(len(rows))
        front = np.zeros((len(rows), len(rows)), order="F")
        lo, hi = P.indptr[a], P.indptr[e]
        column = np.repeat(np.arange(s), np.diff(P.indptr[a:e + 1]))
        row = local[P.indices[lo:hi]]
        inside = row >= 0            # entries to earlier unknowns were eliminated already
        front[row[inside], column[inside]] = P.data[lo:hi][inside]
        for c in children[t]:
            _extend_add(front, updates.pop(c), local[later[c]])
        local[rows] = -1
        L11, info = lapack.dpotrf(front[:s, :s], lower=1, clean=1)
        if info != 0:
            raise np.linalg.LinAlgError("the matrix is not positive definite "
                                        f"(pivot {a + info - 1} of {n})")
        diagonal.append(L11)
        if len(rows) == s:
            off_diagonal.append(np.zeros((0, s)))
            continue
        L21 = blas.dtrsm(1.0, L11, front[s:, :s], side=1, lower=1, trans_a=1)
        off_diagonal.append(L21)
        updates[t] = blas.dsyrk(-1.0, L21, beta=1.0, c=front[s:, s:], lower=1)
    return diagonal, off_diagonal
