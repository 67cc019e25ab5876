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

``one_blas_thread`` makes that so inside Blender too, where numpy's OpenBLAS otherwise runs on
every core: while it is entered numpy's BLAS runs on one thread. The work of the reduced stage,
a simulation and a space-time solve is our own threads or many small products, and BLAS
threads taking turns with them or waking for each small product lost several-fold on a busy
machine (the 800-frame space-time bench edit with material: 1.5-2.0 s on two BLAS threads
against 0.7-1.0 s on one, in one process while another process kept one core busy). scipy's
own OpenBLAS (the modes' supernodal factorisation: large dense blocks) keeps its threads.
"""

import contextlib
import ctypes
import glob
import os
import threading
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


# numpy's bundled OpenBLAS: its thread-count functions, by the symbol names the wheels have used
# (numpy 2: scipy-openblas with a 64-bit suffix; numpy 1.26, Blender 4.2-4.5: openblas64_).
_BLAS_SYMBOLS = (("scipy_openblas_set_num_threads64_", "scipy_openblas_get_num_threads64_"),
                 ("openblas_set_num_threads64_", "openblas_get_num_threads64_"),
                 ("openblas_set_num_threads", "openblas_get_num_threads"))
_blas_lock = threading.Lock()
_blas_state = {"depth": 0, "restore": None}
_blas_controls = []                       # [(set, get)] once found; [None] where there is none


def numpy_blas_controls():
    """(set_num_threads, get_num_threads) of the OpenBLAS numpy was built with, found next to
    numpy (numpy.libs on Linux and Windows, numpy/.dylibs on macOS x86_64), or None (e.g.
    Accelerate on macOS arm64, which needs no limit). Loading the library again by its path
    gives the copy numpy already loaded."""
    if not _blas_controls:
        _blas_controls.append(_find_blas_controls())
    return _blas_controls[0]


def _find_blas_controls():
    import numpy
    package = os.path.dirname(numpy.__file__)
    for path in sorted(glob.glob(os.path.join(package + ".libs", "*openblas*"))
                       + glob.glob(os.path.join(package, ".dylibs", "*openblas*"))):
        try:
            library = ctypes.CDLL(path)
        except OSError:
            continue
        for set_name, get_name in _BLAS_SYMBOLS:
            if hasattr(library, set_name) and hasattr(library, get_name):
                set_threads, get_threads = getattr(library, set_name), getattr(library, get_name)
                set_threads.argtypes, set_threads.restype = [ctypes.c_int], None
                get_threads.argtypes, get_threads.restype = [], ctypes.c_int
                return set_threads, get_threads
    return None


@contextlib.contextmanager
def one_blas_thread():
    """Run numpy's BLAS on one thread inside the block (module docstring), then give it back
    the count it had. Nested and concurrent blocks share one limit: the first to enter sets
    it, the last to leave restores. Without a controllable OpenBLAS it does nothing."""
    controls = numpy_blas_controls()
    if controls is None:
        yield
        return
    set_threads, get_threads = controls
    with _blas_lock:
        if _blas_state["depth"] == 0:
            _blas_state["restore"] = get_threads()
            set_threads(1)
        _blas_state["depth"] += 1
    try:
        yield
    finally:
        with _blas_lock:
            _blas_state["depth"] -= 1
            if _blas_state["depth"] == 0:
                set_threads(_blas_state["restore"])
