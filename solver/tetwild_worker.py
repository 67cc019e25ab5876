"""Standalone fTetWild worker, run by ``solver.tetmesh`` in a separate process.

Usage: python tetwild_worker.py IN.npz OUT.npz

IN.npz holds ``vertices`` (n, 3) float64, ``faces`` (m, 3) int32, scalars ``edge_length_fac``,
``epsilon`` and ``num_threads`` (0 = all cores). OUT.npz receives ``nodes`` (N, 3) float64 and
``tets`` (E, 4) int32. A crash of fTetWild kills only this process. Imports nothing but numpy
and pytetwild (no package-relative imports: it is run as a script).
"""

import sys

import numpy as np


def main(in_path, out_path):
    import pytetwild

    with np.load(in_path, allow_pickle=False) as data:
        vertices = np.ascontiguousarray(data["vertices"], dtype=np.float64)
        faces = np.ascontiguousarray(data["faces"], dtype=np.int32)
        edge_length_fac = float(data["edge_length_fac"])
        epsilon = float(data["epsilon"])
        num_threads = int(data["num_threads"]) if "num_threads" in data.files else 0
    nodes, tets = pytetwild.tetrahedralize(vertices, faces, edge_length_fac=edge_length_fac,
                                           epsilon=epsilon, num_threads=num_threads, quiet=True)
    with open(out_path, "wb") as f:
        np.savez(f, nodes=np.asarray(nodes, dtype=np.float64), tets=np.asarray(tets, dtype=np.int32))


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: tetwild_worker.py IN.npz OUT.npz")
    main(sys.argv[1], sys.argv[2])
