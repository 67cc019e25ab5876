"""Ordered parallel map for per-pose work that releases the GIL, and tall products by row blocks.

The reduced stage repeats the same large, independent computations pose by pose or term by
term: RS targets (numpy over all tets), sparse products and SuperLU solves of the prefactored
Poisson system. All of these release the GIL, so threads share one copy of the operators and
still run on several cores (on this 2-core machine a SuperLU solve of the 98k-tet bar's
Laplacian runs 1.9x faster on two threads than one after the other, results bit-identical).
Results come back in input order, so the outcome does not depend on scheduling.

``matmul`` and ``inner`` do the same for tall dense products (basis x coefficients, Gram
matrices of bases): BLAS runs on one thread while the stage's own threads use the cores, so
they split the rows into fixed blocks of ROW_BLOCK and run one product per block. Blocks are
fixed, not one per thread, so the result is the same whatever the number of threads.
"""

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

MAX_WORKERS = 4     # each worker holds its own E-sized temporaries: bound the memory
ROW_BLOCK = 4096    # rows per block of ``matmul`` and ``inner``: fixed, so results are too


def worker_count():
    """Threads to use: the cores this process may run on, at most ``MAX_WORKERS``."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:                     # macOS and Windows have no affinity query
        cores = os.cpu_count() or 1
    return max(1, min(MAX_WORKERS, cores))


def ordered_map(function, items, workers=None):
    """[function(item) for item in items], computed on ``workers`` threads (default
    ``worker_count()``), in input order. An exception in any call propagates."""
    items = list(items)
    workers = worker_count() if workers is None else int(workers)
    if workers <= 1 or len(items) <= 1:
        return [function(item) for item in items]
    with ThreadPoolExecutor(max_workers=min(workers, len(items))) as pool:
        return list(pool.map(function, items))


def even_parts(count, workers=None):
    """range(count) as at most ``workers`` (default ``worker_count()``) consecutive slices of
    near-equal length, none empty: one share of a batch per thread."""
    if count <= 0:
        return []
    workers = worker_count() if workers is None else int(workers)
    bounds = np.linspace(0, count, max(1, min(workers, count)) + 1).astype(int)
    return [slice(lo, hi) for lo, hi in zip(bounds[:-1], bounds[1:])]


def fixed_parts(count, size):
    """range(count) as consecutive slices of ``size`` (the last one shorter). For batches whose
    rounding can depend on their size (a batched SuperLU solve of several right-hand sides,
    whose BLAS kernels differ with the column count): parts that do not depend on the number
    of threads give the same result on any."""
    return [slice(start, min(start + size, count)) for start in range(0, count, size)]


def row_blocks(count):
    """range(count) as consecutive slices of ROW_BLOCK (the last one shorter)."""
    return fixed_parts(count, ROW_BLOCK)


def matmul(A, B, out=None):
    """A (n, k) @ B (k, p) -> (n, p), one product per block of ROW_BLOCK rows of A, the blocks
    on several threads. For tall products with BLAS on one thread (the reduced stage's own
    threads use the cores): about 2x on two cores. out: optional (n, p) array to fill."""
    if out is None:
        out = np.empty((A.shape[0], B.shape[1]), dtype=np.result_type(A, B))
    ordered_map(lambda rows: np.matmul(A[rows], B, out=out[rows]), row_blocks(A.shape[0]))
    return out


def inner(A, B, weights=None):
    """A^T diag(weights) B (k, p) for tall A (n, k), B (n, p) and optional weights (n,): one
    product per block of ROW_BLOCK rows, on several threads, the partial products added in
    block order (the same sum whatever the number of threads)."""
    def part(rows):
        right = B[rows] if weights is None else weights[rows, None] * B[rows]
        return A[rows].T @ right

    parts = ordered_map(part, row_blocks(A.shape[0]))
    if not parts:
        return np.zeros((A.shape[1], B.shape[1]), dtype=np.result_type(A, B))
    total = parts[0]
    for partial in parts[1:]:
        total += partial
    return total
