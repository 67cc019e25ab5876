"""Tests for solver.embed: Phi reproduces embedded points at rest and follows the tets."""

from pathlib import Path

import igl
import numpy as np
import pytest

from solver import embed, fem, meshgen, tetmesh

MESHES = Path("/work/shared/data/meshes")
SIZE = np.array([2.0, 1.0, 1.5])


@pytest.fixture(scope="module")
def box():
    X, T = meshgen.box_tet_mesh(tuple(SIZE), (4, 3, 3))
    rng = np.random.default_rng(0)
    interior = np.all((X > 1e-9) & (X < SIZE - 1e-9), axis=1)
    X = X.copy()
    X[interior] += rng.uniform(-0.08, 0.08, (interior.sum(), 3))
    return X, fem.orient_tets(X, T)


def test_interior_points_get_barycentric_coordinates(box):
    X, T = box
    P = np.random.default_rng(1).uniform(0.01, 1.0, (500, 3)) * (SIZE - 0.02)
    Phi = embed.embed_points(X, T, P)
    assert Phi.shape == (len(P), len(X))
    np.testing.assert_allclose(Phi @ X, P, rtol=0, atol=1e-12 * np.linalg.norm(SIZE))
    np.testing.assert_allclose(np.asarray(Phi.sum(axis=1)).ravel(), 1.0, atol=1e-12)
    assert Phi.data.min() >= -1e-12  # inside: true barycentric coordinates
    assert np.all(np.diff(Phi.indptr) <= 4)
    # Every row's nodes form one tet of the mesh.
    tets = {tuple(t) for t in np.sort(T, axis=1)}
    rows = [tuple(np.sort(Phi.indices[a:b])) for a, b in zip(Phi.indptr[:-1], Phi.indptr[1:])]
    assert all(any(set(r) <= set(t) for t in tets) for r in rows[:50])


def test_points_outside_are_reproduced_by_affine_extension(box):
    X, T = box
    rng = np.random.default_rng(2)
    P = rng.uniform(0.0, 1.0, (300, 3)) * SIZE
    axis = rng.integers(0, 3, len(P))
    side = rng.integers(0, 2, len(P))
    # Push each point just outside one face of the box.
    P[np.arange(len(P)), axis] = np.where(side == 1, SIZE[axis] + 0.03, -0.03)
    Phi = embed.embed_points(X, T, P)
    np.testing.assert_allclose(Phi @ X, P, rtol=0, atol=1e-9 * np.linalg.norm(SIZE))
    np.testing.assert_allclose(np.asarray(Phi.sum(axis=1)).ravel(), 1.0, atol=1e-12)
    assert Phi.data.min() < 0  # outside: at least some weights extrapolate


def test_embedding_follows_affine_deformation(box):
    """Phi is linear in node positions: an affine map of the nodes moves the points the same way."""
    X, T = box
    P = np.random.default_rng(3).uniform(-0.05, 1.05, (200, 3)) * SIZE
    Phi = embed.embed_points(X, T, P)
    A, b = np.array([[1.1, 0.2, 0.0], [0.0, 0.9, 0.3], [0.1, 0.0, 1.2]]), np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(Phi @ (X @ A.T + b), P @ A.T + b, atol=1e-10)


def test_pinned_nodes_hold_pinned_vertices(box):
    X, T = box
    P = np.random.default_rng(4).uniform(0.0, 1.0, (200, 3)) * SIZE
    Phi = embed.embed_points(X, T, P)
    mask = P[:, 0] < 0.5
    pinned = embed.pinned_nodes_from_vertices(Phi, mask)
    assert pinned.dtype.kind == "i" and np.all(np.diff(pinned) > 0)
    # Pinned rows only touch pinned nodes, and every pinned node is used by a pinned row ...
    touched = np.unique(Phi[mask].indices)
    np.testing.assert_array_equal(touched, pinned)
    # ... so moving every other node leaves the pinned render vertices exactly in place.
    moved = X + 1.0
    moved[pinned] = X[pinned]
    np.testing.assert_array_equal(Phi[mask] @ moved, Phi[mask] @ X)
    assert not np.allclose(Phi[~mask] @ moved, Phi[~mask] @ X)


def test_surface_of_real_mesh_embeds_in_its_tetwild_mesh():
    """spot.obj through fTetWild (coarse, ~12k tets): every surface vertex is reproduced."""
    V, F = igl.read_triangle_mesh(str(MESHES / "spot.obj"))
    X, T = tetmesh.tetrahedralize(V, F, edge_length_fac=0.1)
    Phi = embed.embed_points(X, T, V)
    diagonal = np.linalg.norm(V.max(axis=0) - V.min(axis=0))
    assert np.abs(Phi @ X - V).max() <= 1e-6 * diagonal
    np.testing.assert_allclose(np.asarray(Phi.sum(axis=1)).ravel(), 1.0, atol=1e-10)
    # Points are at most an envelope's width outside, so weights stay bounded.
    assert np.abs(Phi.data).max() < 10.0
