"""After a solve: how far the reduced model is from full RS, and which targets demand stretch.

Two questions the tool must answer when a big edit looks wrong (issue 12). Was the reduced RS
model off its training range? ``reduced_error`` compares reduced positions with the full RS
reconstruction (``rs.PoissonReconstruction``) of the same RS coordinates, on a few frames
(``telling_frames``), since each costs a Poisson solve. Or did the targets ask the body to
stretch? ``target_stretch``: bending keeps the length of every path through the body, so a
handle keyed farther from the pins, or from another handle, than the shortest path at rest can
only be met by stretching. (The solved RS strain is no answer: a cow bent at constant volume
carried 39 % strain in a few tets.)

Shapes and units: modal_rs (E, 9, m) linear RS coordinates per unit deformer input (rows
omega (3) [rad], then strain eps (6: xx, xy, xz, yy, yz, zz)); Z (F, m) deformer inputs per frame;
X (N, 3) tet nodes [m]; T (E, 4).
"""

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph

from . import cubature, rs

REDUCED_ERROR_TOLERANCE = 0.01   # fraction of the bounding-box diagonal worth a warning


def telling_frames(modal_rs, Z, count=4):
    """Indices (<= count,) ascending of the frames of Z (F, m) with the largest rotation.

    Reduced RS errors grow with rotation (off the training range first), so these frames bound
    the error of the rest; the largest-strain frame is added when it is not among them.
    """
    Z = np.atleast_2d(np.asarray(Z, dtype=np.float64))
    rotation, strain = cubature.pose_extremes(modal_rs, Z)
    picks = list(np.argsort(rotation)[::-1][:max(int(count) - 1, 1)])
    picks.append(int(np.argmax(strain)))
    return np.unique(np.asarray(picks, dtype=np.int64))[:max(int(count), 1)]


def reduced_error(deformer, recon, modal_rs, Z, X):
    """(F,) largest vertex |u_reduced - u_full| per frame, as a fraction of the diagonal.

    deformer: a ``reduced.ReducedRS`` (with its basis) or anything with ``displacement(z)``
    (N, 3) [m]; recon: the body's ``rs.PoissonReconstruction`` (same pins as the deformer);
    u_full = recon.reconstruct(modal_rs z), one Poisson solve per frame (few frames only).
    """
    Z = np.atleast_2d(np.asarray(Z, dtype=np.float64))
    diagonal = float(np.linalg.norm(np.ptp(np.asarray(X), axis=0)))
    out = np.empty(len(Z))
    for k, z in enumerate(Z):                       # one Poisson solve per frame
        full = recon.reconstruct(np.asarray(modal_rs) @ z)
        reduced = np.reshape(deformer.displacement(z), (-1, 3))
        out[k] = np.linalg.norm(reduced - full, axis=1).max() / diagonal
    return out


def edge_graph(X, T):
    """Sparse (N, N) symmetric graph of the tet mesh's edges weighted by their rest lengths [m]."""
    T = np.asarray(T, dtype=np.int64)
    pairs = np.concatenate([T[:, [a, b]] for a in range(4) for b in range(a + 1, 4)])
    pairs = np.unique(np.sort(pairs, axis=1), axis=0)
    lengths = np.linalg.norm(X[pairs[:, 0]] - X[pairs[:, 1]], axis=1)
    graph = scipy.sparse.coo_matrix((lengths, (pairs[:, 0], pairs[:, 1])), shape=(len(X),) * 2)
    return (graph + graph.T).tocsr()


def target_stretch(X, T, pinned, rest_points, frames, targets):
    """The stretch each handle's targets demand: (H,) fractions (0.2 = 20 %) and (H,) frames.

    X (N, 3), T (E, 4): the rest tet mesh [m]; pinned (P,) pinned node indices (may be empty);
    rest_points (H, 3): the handles' rest centroids; frames, targets: per handle, its keyed
    frame indices (c_h,) and target centroids (c_h, 3) [m], in the body's frame.

    Bending and twisting keep the length of every path through the body, so a target farther
    from a pinned node than the shortest path from that node to the handle at rest, or two
    handles keyed on one frame farther apart than the path between them, can only be met by
    stretching the body by at least that ratio; a pair's ratio counts for the handle keyed
    farther from its rest place (for both on a tie). Paths run along tet edges (Dijkstra) from the
    node nearest each handle, plus the gap to its centroid; they zigzag, so they are longer than
    the true in-body distance and the demand is an underestimate (a lower bound on the stretch
    needed). Returns max(ratio) - 1 per handle (negative when nothing is demanded) and the frame
    where it is largest (-1 for a handle with no frames).
    """
    X = np.asarray(X, dtype=np.float64)
    rest_points = np.atleast_2d(np.asarray(rest_points, dtype=np.float64))
    pinned = np.asarray(pinned, dtype=np.int64)
    nearest = np.array([int(np.argmin(np.linalg.norm(X - c, axis=1))) for c in rest_points])
    gap = np.linalg.norm(X[nearest] - rest_points, axis=1)                      # (H,)
    paths = scipy.sparse.csgraph.dijkstra(edge_graph(X, T), indices=nearest) + gap[:, None]
    demand = np.full(len(rest_points), -np.inf)
    worst = np.full(len(rest_points), -1, dtype=np.int64)

    def consider(h, ratios, at):
        if len(ratios) and ratios.max() - 1.0 > demand[h]:
            k = int(np.argmax(ratios))
            demand[h], worst[h] = float(ratios[k]) - 1.0, int(at[k])

    for h, (f, t) in enumerate(zip(frames, targets)):
        f, t = np.asarray(f, dtype=np.int64), np.asarray(t, dtype=np.float64).reshape(-1, 3)
        if len(pinned):
            reach = np.maximum(paths[h, pinned], 1e-300)                             # (P,)
            ratios = np.linalg.norm(t[:, None, :] - X[pinned][None], axis=2) / reach
            consider(h, ratios.max(axis=1), f)
        for g in range(len(rest_points)):
            if g == h:
                continue
            common, i, j = np.intersect1d(f, np.asarray(frames[g], dtype=np.int64),
                                          return_indices=True)
            reach = max(paths[h, nearest[g]] + gap[g], 1e-300)
            other = np.asarray(targets[g], dtype=np.float64).reshape(-1, 3)
            # A pair's demand goes to the handle keyed farther from its rest place (both on a
            # tie): a handle keyed where it rests asks nothing of the body.
            mine = np.linalg.norm(t[i] - rest_points[h], axis=1)
            theirs = np.linalg.norm(other[j] - rest_points[g], axis=1)
            moved = mine >= theirs * (1.0 - 1e-9) - 1e-12           # a tie within round-off
            consider(h, (np.linalg.norm(t[i] - other[j], axis=1) / reach)[moved], common[moved])
    return demand, worst
