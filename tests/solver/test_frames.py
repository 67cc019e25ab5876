"""Tests for solver.frames.polar_decomposition: the split of a transform's linear part into an
orthogonal factor and a stretch, mirrors included (oracles: the defining identities, and
transforms built from a known rotation and scale)."""
import numpy as np
from scipy.spatial.transform import Rotation

from solver import frames


def test_polar_factors_are_orthogonal_and_a_symmetric_stretch_whatever_the_sign():
    rng = np.random.default_rng(11)
    linear = rng.normal(size=(40, 3, 3))
    Q, P = frames.polar_decomposition(linear)
    np.testing.assert_allclose(Q @ P, linear, atol=1e-12)
    np.testing.assert_allclose(np.swapaxes(Q, 1, 2) @ Q, np.broadcast_to(np.eye(3), Q.shape),
                               atol=1e-12)
    np.testing.assert_allclose(P, np.swapaxes(P, 1, 2), atol=1e-12)
    assert np.linalg.eigvalsh(P).min() >= -1e-12
    signs = np.sign(np.linalg.det(linear))
    assert (signs < 0).any() and (signs > 0).any()
    np.testing.assert_allclose(np.linalg.det(Q), signs, atol=1e-12)


def test_a_mirrored_or_scaled_rotation_keeps_its_rotation_in_the_orthogonal_factor():
    R = Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix()
    Q, P = frames.polar_decomposition(R @ np.diag([1.0, 1.0, -1.0]))   # Blender scale z = -1
    np.testing.assert_allclose(Q, R @ np.diag([1.0, 1.0, -1.0]), atol=1e-12)
    np.testing.assert_allclose(P, np.eye(3), atol=1e-12)
    Q, P = frames.polar_decomposition(R @ np.diag([2.0, 3.0, 0.5]))   # scale (2, 3, 0.5)
    np.testing.assert_allclose(Q, R, atol=1e-12)
    np.testing.assert_allclose(P, np.diag([2.0, 3.0, 0.5]), atol=1e-12)
