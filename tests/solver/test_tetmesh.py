"""Tests for solver.tetmesh: fTetWild in a child process, input checks, crash isolation."""

import signal
import subprocess
import sys
import time

import igl
import numpy as np
import pytest

from solver import fem, tetmesh


def cube_surface(size=2.0):
    """Closed, outward-oriented triangle surface of [0, size]^3 (12 triangles)."""
    V = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) * size
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    F = np.array([[q[0], q[1], q[2]] for q in quads] + [[q[0], q[2], q[3]] for q in quads])
    return V, F


def icosphere(levels=3):
    """Unit icosphere: icosahedron, loop-subdivided ``levels`` times, projected to the sphere."""
    t = (1.0 + 5.0 ** 0.5) / 2.0
    V = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    F = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                  [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
                  [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    V, F = igl.upsample(V, F, levels)
    return V / np.linalg.norm(V, axis=1, keepdims=True), F


def enclosed_volume(V, F):
    a, b, c = (V[F[:, i]] for i in range(3))
    return np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0


def check_tet_mesh(X, T):
    assert X.dtype == np.float64 and T.dtype == np.int64 and T.shape[1] == 4
    assert np.all(fem.tet_volumes(X, T) > 0)
    np.testing.assert_array_equal(np.unique(T), np.arange(len(X)))  # no unreferenced nodes


def test_cube_tetrahedralises_to_its_volume():
    V, F = cube_surface(2.0)
    X, T = tetmesh.tetrahedralize(V, F, edge_length_fac=0.2)
    check_tet_mesh(X, T)
    assert fem.mesh_volume(X, T) == pytest.approx(8.0, rel=0.01)


def test_icosphere_tetrahedralises_to_its_volume():
    V, F = icosphere()
    X, T = tetmesh.tetrahedralize(V, F, edge_length_fac=0.1)
    check_tet_mesh(X, T)
    volume = fem.mesh_volume(X, T)
    assert volume == pytest.approx(enclosed_volume(V, F), rel=0.005)  # the polyhedron itself
    assert volume == pytest.approx(4.0 / 3.0 * np.pi, rel=0.02)       # the sphere it approximates


def test_min_dihedral_angles_of_known_tets():
    """Regular tet: arccos(1/3) = 70.53 deg at every edge; the corner of a cube: arccos(1/sqrt(3))
    = 54.74 deg at its slanted edges (90 at the others); a sliver: near 0; either orientation."""
    regular = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)
    corner = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    sliver = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 1e-3]], float)
    for X, expected in ((regular, np.degrees(np.arccos(1.0 / 3.0))),
                        (corner, np.degrees(np.arccos(1.0 / np.sqrt(3.0))))):
        angles = tetmesh.min_dihedral_angles(X, np.array([[0, 1, 2, 3], [1, 0, 2, 3]]))
        np.testing.assert_allclose(angles, expected, rtol=1e-12)
    assert tetmesh.min_dihedral_angles(sliver, np.array([[0, 1, 2, 3]]))[0] < 0.2


def test_empty_surface_raises():
    with pytest.raises(tetmesh.TetMeshError, match="no faces"):
        tetmesh.tetrahedralize(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    with pytest.raises(tetmesh.TetMeshError, match="no faces"):
        tetmesh.check_surface(np.zeros((4, 3)), np.zeros((0, 3), dtype=np.int64))


def test_flat_surfaces_raise():
    # A square in the plane z = 0 (both sides, so it is "closed" but has no thickness) ...
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    F = np.array([[0, 1, 2], [0, 2, 3], [0, 2, 1], [0, 3, 2]])
    with pytest.raises(tetmesh.TetMeshError, match="flat"):
        tetmesh.tetrahedralize(V, F)
    # ... and the same square tilted out of every coordinate plane.
    rotation = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))[0]
    with pytest.raises(tetmesh.TetMeshError, match="flat"):
        tetmesh.check_surface(V @ rotation.T + 5.0, F)


def test_surface_enclosing_no_volume_raises():
    V, F = cube_surface()
    doubled = np.vstack([F, F[:, ::-1]])  # every face twice, facing both ways
    with pytest.raises(tetmesh.TetMeshError, match="no volume"):
        tetmesh.check_surface(V, doubled)


def test_closed_surface_passes_check():
    tetmesh.check_surface(*cube_surface())
    V, F = cube_surface()
    tetmesh.check_surface(V, F[:, ::-1])  # inside-out orientation still encloses a volume


def write_script(tmp_path, body):
    path = tmp_path / "fake_worker.py"
    path.write_text(body)
    return path


def test_crashing_worker_is_reported_not_fatal(tmp_path, monkeypatch):
    monkeypatch.setattr(tetmesh, "WORKER", write_script(tmp_path, "import os\nos.abort()\n"))
    with pytest.raises(tetmesh.TetMeshError, match="crashed with signal SIGABRT"):
        tetmesh.tetrahedralize(*cube_surface())


def test_failing_worker_reports_exit_code_and_last_stderr_line(tmp_path, monkeypatch):
    script = "import sys\nprint('noise', file=sys.stderr)\nsys.exit('boom: bad surface')\n"
    monkeypatch.setattr(tetmesh, "WORKER", write_script(tmp_path, script))
    with pytest.raises(tetmesh.TetMeshError, match=r"exit code 1\): boom: bad surface"):
        tetmesh.tetrahedralize(*cube_surface())


def test_worker_without_output_or_tets_raises(tmp_path, monkeypatch):
    monkeypatch.setattr(tetmesh, "WORKER", write_script(tmp_path, "pass\n"))
    with pytest.raises(tetmesh.TetMeshError, match="no readable result"):
        tetmesh.tetrahedralize(*cube_surface())
    script = ("import sys, numpy as np\n"
              "np.savez(open(sys.argv[2], 'wb'), nodes=np.zeros((0, 3)),"
              " tets=np.zeros((0, 4), np.int32))\n")
    monkeypatch.setattr(tetmesh, "WORKER", write_script(tmp_path, script))
    with pytest.raises(tetmesh.TetMeshError, match="no tetrahedra"):
        tetmesh.tetrahedralize(*cube_surface())


def test_hanging_worker_times_out(tmp_path, monkeypatch):
    monkeypatch.setattr(tetmesh, "WORKER", write_script(tmp_path, "import time\ntime.sleep(30)\n"))
    with pytest.raises(tetmesh.TetMeshError, match="did not finish"):
        tetmesh.tetrahedralize(*cube_surface(), timeout=1.0)


def test_a_tiny_time_limit_stops_a_real_ftetwild_run(monkeypatch):
    """A fine icosphere (about 20 s of fTetWild on two cores) with a 1 s limit: TetMeshTimeout
    carrying the limit, raised within the limit plus the worker's start and one poll, and the
    worker is gone (killed, not left meshing)."""
    started = []
    popen = tetmesh.subprocess.Popen

    def remember(*args, **kwargs):
        started.append(popen(*args, **kwargs))
        return started[-1]

    monkeypatch.setattr(tetmesh.subprocess, "Popen", remember)
    start = time.monotonic()
    with pytest.raises(tetmesh.TetMeshTimeout, match="did not finish within 1 s") as info:
        tetmesh.tetrahedralize(*icosphere(5), edge_length_fac=0.01, timeout=1.0)
    elapsed = time.monotonic() - start
    assert info.value.limit == 1.0 and isinstance(info.value, tetmesh.TetMeshError)
    assert elapsed < 1.0 + 3.0, elapsed
    assert len(started) == 1 and started[0].poll() is not None     # killed and reaped


def test_the_worker_bounds_its_own_time(tmp_path):
    """A worker whose parent no longer watches it ends by itself a few seconds after its limit
    (SIGALRM), inside fTetWild's native code too; unbounded, this run takes minutes."""
    V, F = icosphere(5)
    in_path, out_path = tmp_path / "in.npz", tmp_path / "out.npz"
    with open(in_path, "wb") as f:
        np.savez(f, vertices=V, faces=F.astype(np.int32), edge_length_fac=0.01, epsilon=1e-3,
                 num_threads=0, time_limit=0.5)
    start = time.monotonic()
    result = subprocess.run([sys.executable, str(tetmesh.WORKER), str(in_path), str(out_path)],
                            env=tetmesh._worker_env(), cwd=tmp_path, capture_output=True,
                            timeout=120)
    elapsed = time.monotonic() - start
    assert result.returncode == -signal.SIGALRM
    assert elapsed < 30.0, elapsed
    assert not out_path.exists()


def test_cancel_kills_the_worker_promptly(tmp_path, monkeypatch):
    monkeypatch.setattr(tetmesh, "WORKER", write_script(tmp_path, "import time\ntime.sleep(30)\n"))
    polls = []
    start = time.monotonic()
    with pytest.raises(tetmesh.TetMeshError, match="cancelled"):
        tetmesh.tetrahedralize(*cube_surface(), should_cancel=lambda: polls.append(1) or len(polls) > 3)
    assert time.monotonic() - start < 5.0


def test_worker_interpreter_is_configurable(tmp_path):
    """``python=`` selects the interpreter; a broken one is a TetMeshError, not an exception leak."""
    fake_python = tmp_path / "python_that_dies"
    fake_python.write_text("#!/bin/sh\nkill -SEGV $$\n")
    fake_python.chmod(0o755)
    with pytest.raises(tetmesh.TetMeshError, match="SIGSEGV"):
        tetmesh.tetrahedralize(*cube_surface(), python=str(fake_python))
    with pytest.raises(tetmesh.TetMeshError, match="could not start"):
        tetmesh.tetrahedralize(*cube_surface(), python=str(tmp_path / "missing"))
    X, T = tetmesh.tetrahedralize(*cube_surface(), edge_length_fac=0.3, python=sys.executable)
    check_tet_mesh(X, T)


# Input hygiene: loose vertices and far-away or huge bodies ------------------------------------

def test_loose_vertices_do_not_change_the_mesh():
    """A vertex no face uses, far from a unit cube, is ignored: the edge length stays a fraction
    of the cube's diagonal (before: 6 tets with it at (10, 10, 10), SIGSEGV farther away)."""
    V, F = cube_surface(1.0)
    alone = tetmesh.tetrahedralize(V, F, edge_length_fac=0.1)
    counts = [len(alone[1])]
    for loose in ([10.0, 10.0, 10.0], [1e6, -3e5, 2e6]):
        X, T = tetmesh.tetrahedralize(np.vstack([V[:3], [loose], V[3:]]),
                                      np.where(F >= 3, F + 1, F), edge_length_fac=0.1)
        check_tet_mesh(X, T)
        assert np.abs(X).max() <= 1.0 + 1e-9  # the loose vertex is not a node
        assert fem.mesh_volume(X, T) == pytest.approx(1.0, rel=0.01)
        counts.append(len(T))
    print("tets: cube alone, with a loose vertex at 10 m, at 2e6 m:", counts)
    assert max(counts) <= 1.5 * min(counts)


def test_far_and_scaled_cubes_mesh_like_the_cube_at_the_origin():
    """fTetWild sees unit coordinates: a cube 1e7 m away (before: blocked for 600 s) or a
    1 km cube meshes as fast and as finely as the unit cube at the origin."""
    V, F = cube_surface(1.0)
    X0, T0 = tetmesh.tetrahedralize(V, F, edge_length_fac=0.1)
    offset = np.array([1e7, -2e7, 3e6])
    start = time.monotonic()
    X1, T1 = tetmesh.tetrahedralize(V + offset, F, edge_length_fac=0.1, timeout=60.0)
    far_time = time.monotonic() - start
    X2, T2 = tetmesh.tetrahedralize(V * 1000.0, F, edge_length_fac=0.1, timeout=60.0)
    print(f"tets at the origin {len(T0)}, at 1e7 m {len(T1)} ({far_time:.1f} s), "
          f"1 km cube {len(T2)}")
    check_tet_mesh(X1, T1)
    check_tet_mesh(X2, T2)
    assert far_time < 30.0
    assert X1.min(axis=0) == pytest.approx(offset, abs=1e-6)
    assert X1.max(axis=0) == pytest.approx(offset + 1.0, abs=1e-6)
    assert fem.mesh_volume(X1 - offset, T1) == pytest.approx(1.0, rel=0.01)
    assert fem.mesh_volume(X2, T2) == pytest.approx(1e9, rel=0.01)
    assert max(len(T0), len(T1), len(T2)) <= 1.5 * min(len(T0), len(T1), len(T2))


# Reproducibility: fTetWild's shuffle seeded ----------------------------------------------------

@pytest.mark.skipif(not sys.platform.startswith("linux"),
                    reason="the worker fixes fTetWild's random_device seed on Linux only")
def test_the_same_surface_meshes_to_the_same_tets_every_time(tmp_path):
    """fTetWild shuffles its triangle insertion order from std::random_device; the worker seeds
    it, so three runs (in three worker processes, on all cores) give bit-identical meshes.
    Unseeded, icosphere runs differ in node count from run to run."""
    V, F = icosphere(2)
    meshes = [tetmesh.tetrahedralize(V, F, edge_length_fac=0.1) for _ in range(3)]
    print("nodes, tets per run:", [(len(X), len(T)) for X, T in meshes])
    for X, T in meshes[1:]:
        np.testing.assert_array_equal(X, meshes[0][0])
        np.testing.assert_array_equal(T, meshes[0][1])
    in_path, out_path = tmp_path / "in.npz", tmp_path / "out.npz"
    with open(in_path, "wb") as f:
        np.savez(f, vertices=V, faces=F.astype(np.int32), edge_length_fac=0.1, epsilon=1e-3)
    subprocess.run([sys.executable, str(tetmesh.WORKER), str(in_path), str(out_path)],
                   env=tetmesh._worker_env(), cwd=tmp_path, check=True, timeout=120)
    with np.load(out_path) as out:
        assert bool(out["seeded"])


def test_the_worker_finds_the_random_device_call_slot_only_where_it_is():
    """The seed goes through the call slot named by the library's JUMP_SLOT relocation: found in
    pytetwild's library, absent for a symbol it does not call and in a file that is no ELF; a
    library this process has not loaded is left alone."""
    from pytetwild import PyfTetWildWrapper
    from solver import tetwild_worker
    library = PyfTetWildWrapper.__file__
    slot = tetwild_worker._plt_slot_offset(library, tetwild_worker.RANDOM_DEVICE_GETVAL)
    assert slot is not None and slot % 8 == 0
    assert tetwild_worker._plt_slot_offset(library, b"_ZN12not_a_symbolEv") is None
    assert tetwild_worker._plt_slot_offset(str(tetmesh.WORKER), b"anything") is None
    assert not tetwild_worker.seed_random_device("/nonexistent/library.so")
