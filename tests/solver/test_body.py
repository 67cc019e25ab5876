"""Tests for solver.body: a prepared body's arrays through a cache file, and what the tet body keeps."""

import numpy as np
import pytest

from solver import body, cache, embed, fem, meshgen, modes

SIZE = (0.4, 0.1, 0.1)


@pytest.fixture(scope="module")
def tet_body():
    X, T = meshgen.box_tet_mesh(SIZE, (4, 1, 1))
    points = np.random.default_rng(3).uniform(0.0, 1.0, (20, 3)) * SIZE
    return body.TetBody(X, T, embed.embed_points(X, T, points))


def test_a_tet_body_comes_back_from_its_cache_file_bit_for_bit(tet_body, tmp_path):
    path = str(tmp_path / "tets.npz")
    cache.save(path, "key", tet_body.to_arrays())
    loaded = body.TetBody.from_arrays(cache.load(path, "key"))
    np.testing.assert_array_equal(loaded.nodes, tet_body.nodes)
    np.testing.assert_array_equal(loaded.tets, tet_body.tets)
    assert loaded.tets.dtype == np.int64
    assert loaded.embedding.shape == tet_body.embedding.shape
    assert (loaded.embedding != tet_body.embedding).nnz == 0


def test_linear_modes_come_back_from_their_cache_file_bit_for_bit(tet_body, tmp_path):
    X, T = tet_body.nodes, tet_body.tets
    pinned = np.flatnonzero(X[:, 0] < 1e-9)
    result = modes.linear_modes(fem.stiffness_matrix(X, T, 1e6, 0.3), fem.lumped_masses(X, T, 1e3),
                                3, pinned, rest_positions=X)
    path = str(tmp_path / "modes.npz")
    cache.save(path, "key", result.to_arrays())
    loaded = modes.LinearModes.from_arrays(cache.load(path, "key"))
    np.testing.assert_array_equal(loaded.eigenvalues, result.eigenvalues)
    np.testing.assert_array_equal(loaded.vectors, result.vectors)
    np.testing.assert_array_equal(loaded.pinned_nodes, pinned)


def test_the_tet_body_keeps_its_volumes_and_masses_once_per_density(tet_body):
    volumes = tet_body.volumes
    assert volumes.sum() == pytest.approx(np.prod(SIZE), rel=1e-12)       # the box's volume
    np.testing.assert_array_equal(volumes, np.abs(fem.tet_volumes(tet_body.nodes, tet_body.tets)))
    masses = tet_body.lumped_masses(1000.0)
    assert masses.sum() == pytest.approx(1000.0 * np.prod(SIZE), rel=1e-12)
    np.testing.assert_array_equal(masses, fem.lumped_masses(tet_body.nodes, tet_body.tets, 1000.0))
    assert tet_body.lumped_masses(1000.0) is masses and tet_body.volumes is volumes
    assert tet_body.lumped_masses(500.0).sum() == pytest.approx(0.5 * masses.sum(), rel=1e-12)
    with pytest.raises(ValueError):                 # shared by every caller: nobody writes to them
        masses[0] = 0.0
    with pytest.raises(ValueError):
        volumes[0] = 0.0
