"""Structured tetrahedral meshes of boxes (tests, benchmarks, demos)."""

import itertools

import numpy as np

from . import fem


def box_tet_mesh(size=(1.0, 1.0, 1.0), cells=(1, 1, 1), origin=(0.0, 0.0, 0.0)):
    """Tet mesh of the box ``origin + [0, Lx] x [0, Ly] x [0, Lz]``.

    size: (Lx, Ly, Lz) in metres; cells: (nx, ny, nz) cubes per axis, each split into the six
    tets of the Freudenthal (Kuhn) subdivision along its main diagonal. Every cube uses the same
    split, so neighbouring cubes share their face diagonals and the mesh is conforming.

    Returns X ((nx+1)(ny+1)(nz+1), 3) float64 and T (6 nx ny nz, 4) int64, positively oriented.
    Node (i, j, k) has index (i * (ny+1) + j) * (nz+1) + k.
    """
    nx, ny, nz = (int(c) for c in cells)
    if min(nx, ny, nz) < 1:
        raise ValueError(f"box_tet_mesh needs at least one cell per axis (got {cells})")
    axes = [np.linspace(0.0, float(L), n + 1) + float(o) for L, n, o in zip(size, (nx, ny, nz), origin)]
    X = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)

    def node(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    i, j, k = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz),
                                              indexing="ij"))
    tets = []
    # One tet per axis order: walk from corner 000 to 111 one unit step at a time.
    for order in itertools.permutations(range(3)):
        corner = np.zeros(3, dtype=np.int64)
        path = [node(i, j, k)]
        for axis in order:
            corner[axis] += 1
            path.append(node(i + corner[0], j + corner[1], k + corner[2]))
        tets.append(np.stack(path, axis=1))
    T = np.concatenate(tets).astype(np.int64)
    return X, fem.orient_tets(X, T)
