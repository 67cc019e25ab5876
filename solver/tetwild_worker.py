"""Standalone fTetWild worker, run by ``solver.tetmesh`` in a separate process.

Usage: python tetwild_worker.py IN.npz OUT.npz

IN.npz holds ``vertices`` (n, 3) float64, ``faces`` (m, 3) int32, scalars ``edge_length_fac``,
``epsilon``, ``num_threads`` (0 = all cores), ``time_limit`` (seconds, 0 = none) and, optionally,
``stop_energy`` and ``max_iterations`` (fTetWild's optimisation stops at that AMIPS energy or
after that many passes; pytetwild's defaults when absent). OUT.npz
receives ``nodes`` (N, 3) float64 and ``tets`` (E, 4) int32. A crash of fTetWild kills only this
process. Imports nothing but numpy and pytetwild (no package-relative imports: it is run as a
script).

The parent kills this process at the time limit. It also bounds itself, a few seconds later, with
an alarm whose default action ends the process even inside fTetWild's native code: so a worker
whose parent died (Blender was killed) does not mesh on for minutes. POSIX only.
"""

import math
import signal
import sys

import numpy as np

# (name in IN.npz, pytetwild keyword, type) of the optional optimisation settings
OPTIMISATION = (("stop_energy", "stop_energy", float), ("max_iterations", "num_opt_iter", int))
SELF_LIMIT_MARGIN = 5   # [s] after the parent's limit, so the parent's kill and message come first


def bound_own_time(time_limit):
    """Let SIGALRM (default action: terminate) end this process after the limit and a margin."""
    if time_limit > 0.0 and hasattr(signal, "alarm"):
        signal.signal(signal.SIGALRM, signal.SIG_DFL)
        signal.alarm(int(math.ceil(time_limit)) + SELF_LIMIT_MARGIN)


def main(in_path, out_path):
    with np.load(in_path, allow_pickle=False) as data:
        vertices = np.ascontiguousarray(data["vertices"], dtype=np.float64)
        faces = np.ascontiguousarray(data["faces"], dtype=np.int32)
        edge_length_fac = float(data["edge_length_fac"])
        epsilon = float(data["epsilon"])
        num_threads = int(data["num_threads"]) if "num_threads" in data.files else 0
        time_limit = float(data["time_limit"]) if "time_limit" in data.files else 0.0
        optimisation = {key: cast(data[name]) for name, key, cast in OPTIMISATION
                        if name in data.files}
    bound_own_time(time_limit)
    import pytetwild

    nodes, tets = pytetwild.tetrahedralize(vertices, faces, edge_length_fac=edge_length_fac,
                                           epsilon=epsilon, num_threads=num_threads, quiet=True,
                                           **optimisation)
    with open(out_path, "wb") as f:
        np.savez(f, nodes=np.asarray(nodes, dtype=np.float64), tets=np.asarray(tets, dtype=np.int32))


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: tetwild_worker.py IN.npz OUT.npz")
    main(sys.argv[1], sys.argv[2])
