"""Pose transfer from embedded points to tet nodes."""
import numpy as np
from scipy.spatial.transform import Rotation

from solver import embed, meshgen, transfer


def box_with_surface_points(seed=0):
    X, T = meshgen.box_tet_mesh((2.0, 1.0, 1.0), (6, 3, 3))
    rng = np.random.default_rng(seed)
    # Points on and near the surface, as a render mesh would be, fewer than the nodes.
    P = rng.uniform((0, 0, 0), (2, 1, 1), size=(60, 3))
    axis = rng.integers(0, 3, size=60)
    P[np.arange(60), axis] = np.where(rng.random(60) < 0.5, 0.0, (2.0, 1.0, 1.0)[0])
    P = np.clip(P, 0, (2, 1, 1))
    return X, T, P, embed.embed_points(X, T, P)


def test_face_adjacent_pairs_counts_interior_faces():
    X, T = meshgen.box_tet_mesh((1.0, 1.0, 1.0), (2, 2, 2))
    pairs = transfer.face_adjacent_pairs(T)
    faces = np.sort(T[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), axis=1)
    _, counts = np.unique(faces, axis=0, return_counts=True)
    assert len(pairs) == np.sum(counts == 2)
    shared = [len(set(T[a]) & set(T[b])) for a, b in pairs]
    assert set(shared) == {3}


def test_rest_rigid_and_affine_poses_carry_over_exactly():
    X, T, P, Phi = box_with_surface_points()
    move = transfer.PoseTransfer(X, T, Phi)
    R = Rotation.from_rotvec([0.3, -1.9, 0.7]).as_matrix()
    A = R @ np.diag([1.3, 0.8, 1.1])
    for M, c in ((np.eye(3), 0.0), (R, np.array([1.0, -2.0, 0.5])), (A, np.array([0.1, 0.2, 0.3]))):
        x = move.nodes_from_points(P @ M.T + c)
        np.testing.assert_allclose(x, X @ M.T + c, atol=1e-7)


def test_smooth_pose_is_matched_at_the_points():
    X, T, P, Phi = box_with_surface_points(1)
    bend = lambda Y: Y + 0.1 * np.column_stack([np.zeros(len(Y)), np.zeros(len(Y)), Y[:, 0] ** 2])
    x = transfer.PoseTransfer(X, T, Phi).nodes_from_points(bend(P))
    assert np.abs(Phi @ x - bend(P)).max() < 1e-3
    # Inside, the smoothest fit is not the quadratic itself but stays within 10 % of its size.
    assert np.abs(x - bend(X)).max() < 0.1 * np.abs(bend(X) - X).max()
