"""Poses of the render mesh read through a prepared body's RS coordinates.

A pose is the render mesh's vertex positions p (n, 3) [m], object space (a shape key, a frame
of a take). It is carried to the tet nodes (``transfer.PoseTransfer``), turned into RS
coordinates (``rs.pose_to_rs``) and from there either fitted by the modes (``poses_to_modal``) or
blended with another pose (``interpolate_poses``).
"""
import numpy as np

from . import rs, spacetime


# Poses per least-squares solve in ``poses_to_modal``: one solve of a chunk costs about what one
# pose's does (the matrix is the same), and the chunk's RS coordinates (K, E, 9) are in memory.
POSES_PER_SOLVE = 32


def poses_to_modal(body, poses, step=None):
    """Modal coordinates ẑ (k, m) of render-vertex poses (k, n, 3).

    Each pose's rotation branch is chained to the previous pose's, so a sequence that turns
    on (a twist past 180°, a spin) stays continuous from pose to pose. step(i), if given, is
    called after pose i (progress; it may raise to stop).
    """
    X, T = body.nodes, body.tets
    reference, fitted, chunk = None, [], []
    for index, points in enumerate(poses):
        nodes = body.pose_transfer.nodes_from_points(points)
        y, _ = rs.pose_to_rs(X, T, nodes, reference=reference, neighbours=body.neighbours)
        chunk.append(y)
        reference = y[:, :3]
        if len(chunk) == POSES_PER_SOLVE or index == len(poses) - 1:
            fitted.append(spacetime.pose_to_modal(body.modal_rs, body.volumes, np.array(chunk)))
            chunk = []
        if step is not None:
            step(index)
    return np.concatenate(fitted) if fitted else np.zeros((0, body.modal_rs.shape[2]))


def keeps_pins(body, rest, *poses):
    """True when every pose (n, 3) holds the body's pinned vertices (those tied to a pinned
    node) at their rest positions rest (n, 3); False for a free body."""
    pinned = body.pinned_nodes
    if not len(pinned):
        return False
    rows = body.displacement_embedding[:, pinned].getnnz(axis=1) > 0
    return all(np.abs(p[rows] - rest[rows]).max(initial=0.0) < 1e-9 for p in poses)


def interpolate_poses(body, rest, points_a, points_b, ts):
    """Render-vertex poses (len(ts), n, 3) at the blend weights ``ts`` between poses a and b
    (n, 3) of the base vertices at rest ``rest`` (n, 3), and how many tets the two poses invert.

    Both poses are carried to the tet nodes, turned into RS coordinates (b's rotation branch
    chosen nearest to a's, so each tet turns the short way), blended linearly and reconstructed.
    What the tets cannot express (sub-tet surface detail, the transfer's fit error) is carried
    along as a residual blended linearly, so t = 0 and t = 1 give back the poses exactly.
    When both poses keep the pinned vertices at rest the reconstruction holds the pins, else
    only the mean position is carried.
    """
    X, T = body.nodes, body.tets
    pins_fixed = keeps_pins(body, rest, points_a, points_b)
    nodes_a = body.pose_transfer.nodes_from_points(points_a)
    nodes_b = body.pose_transfer.nodes_from_points(points_b)
    y_a, inverted_a = rs.pose_to_rs(X, T, nodes_a, neighbours=body.neighbours)
    y_b, inverted_b = rs.pose_to_rs(X, T, nodes_b, reference=y_a[:, :3])
    recon = body.reconstruction if pins_fixed else body.free_reconstruction
    weights = recon.weights
    mean_a = weights @ (nodes_a - X) / weights.sum()
    mean_b = weights @ (nodes_b - X) / weights.sum()
    embedded = body.embedding @ X

    def surface(y, mean):
        # Displacements through the pinned embedding, so pinned vertices stay exactly at rest.
        return embedded + body.surface(recon.reconstruct(y, mean_displacement=mean))

    residual_a = points_a - surface(y_a, mean_a)
    residual_b = points_b - surface(y_b, mean_b)
    poses = [surface(rs.interpolate(y_a, y_b, t), (1 - t) * mean_a + t * mean_b)
             + (1 - t) * residual_a + t * residual_b for t in ts]
    return np.array(poses), int(np.count_nonzero(inverted_a | inverted_b))
