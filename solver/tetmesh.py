"""Tetrahedralisation of closed triangle surfaces with fTetWild, isolated in a child process.

fTetWild (through pytetwild) is native code that can crash or hang on bad input. Running it
inside Blender would take Blender down with it, so ``tetrahedralize`` runs
``tetwild_worker.py`` with a separate Python interpreter and turns any failure (signal, non-zero
exit, timeout, missing output) into a ``TetMeshError`` the caller can show to the user.
The worker runs in a temporary directory because fTetWild drops a ``__tracked_surface.stl``
into its working directory.

Input hygiene: vertices no face uses are dropped before fTetWild (a loose vertex far away would
set the bounding box that the edge length and envelope are fractions of; very far away it crashed
fTetWild), and the surface is moved to its bounding-box centre and scaled to a unit diagonal
(fTetWild works in absolute coordinates: a body 1e7 m from the origin took minutes), then the
nodes are mapped back. The relative settings are unchanged by this, as both are fractions of
the diagonal.
"""

import importlib.util
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from . import fem

WORKER = Path(__file__).with_name("tetwild_worker.py")

DEFAULT_TIME_LIMIT = 120.0  # [s] before the worker is killed (the Blender setting's default)
# fTetWild's optimisation stops at this conformal AMIPS energy or after this many passes. Its own
# defaults (10, 80) spent most of its time polishing: STOP_ENERGY_NOTE below.
STOP_ENERGY = 10.0
MAX_ITERATIONS = 20
FLAT_TOLERANCE = 1e-6      # thinnest principal extent / largest, below which a surface is flat
VOLUME_TOLERANCE = 1e-9    # |enclosed volume| / diagonal^3, below which nothing is enclosed


class TetMeshError(RuntimeError):
    """The surface cannot be tetrahedralised; the message is meant for the user."""


class TetMeshTimeout(TetMeshError):
    """fTetWild did not finish within ``limit`` seconds (the worker was killed)."""

    def __init__(self, limit):
        super().__init__(f"fTetWild did not finish within {limit:g} s")
        self.limit = limit


def check_surface(V, F):
    """Raise TetMeshError with a readable message if (V, F) cannot enclose a volume.

    V: (n, 3) float vertices, F: (m, 3) int triangles. Rejects empty input, out-of-range indices,
    non-finite coordinates, flat surfaces (thinnest principal extent < 1e-6 x the largest, which
    also catches tilted planes) and surfaces enclosing no volume (e.g. open or cancelling sheets
    with |signed volume| < 1e-9 x bbox diagonal^3).
    """
    V = np.asarray(V, dtype=np.float64).reshape(-1, 3)
    F = np.asarray(F).reshape(-1, 3)
    if len(F) == 0 or len(V) == 0:
        raise TetMeshError("the surface has no faces; a closed mesh with volume is needed")
    if F.min() < 0 or F.max() >= len(V):
        raise TetMeshError(f"face indices must lie in [0, {len(V)})")
    if not np.all(np.isfinite(V)):
        raise TetMeshError("the surface has non-finite vertex coordinates")
    used = V[np.unique(F)]
    if len(used) < 4:
        raise TetMeshError("the surface has fewer than four distinct vertices, so it encloses "
                           "no volume; a closed mesh is needed")
    centred = used - used.mean(axis=0)
    extents = np.linalg.svd(centred, compute_uv=False)
    if extents[0] == 0.0 or extents[-1] < FLAT_TOLERANCE * extents[0]:
        raise TetMeshError("the surface is flat (it has no thickness), so it encloses no volume; "
                           "give it thickness (e.g. a Solidify modifier) first")
    diagonal = np.linalg.norm(used.max(axis=0) - used.min(axis=0))
    # Divergence theorem about the centroid: sum of signed volumes of the cones over the faces.
    a, b, c = (V[F[:, i]] - used.mean(axis=0) for i in range(3))
    volume = np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0
    if abs(volume) < VOLUME_TOLERANCE * diagonal ** 3:
        raise TetMeshError("the surface encloses no volume (is it open, or made of "
                           "sheets facing each other?); a closed mesh is needed")


def tetrahedralize(V, F, edge_length_fac=0.05, epsilon=1e-3, timeout=DEFAULT_TIME_LIMIT,
                   python=None, num_threads=0, should_cancel=None, stop_energy=STOP_ENERGY,
                   max_iterations=MAX_ITERATIONS):
    """Tet mesh of the closed triangle surface (V, F) by fTetWild in a separate process.

    V: (n, 3) float vertices [m]; F: (m, 3) int triangles (triangulate polygons first).
    edge_length_fac: target edge length / bbox diagonal; epsilon: envelope / bbox diagonal.
    timeout: seconds before the worker is killed (then TetMeshTimeout); python: interpreter to run
    the worker (default ``sys.executable``, which inside Blender is Blender's bundled Python);
    num_threads: fTetWild threads, 0 = all cores; should_cancel: optional callable polled a few
    times a second, and when it returns True the worker is killed and TetMeshError raised;
    stop_energy, max_iterations: fTetWild's optimisation stops at that AMIPS energy or after that
    many passes (``STOP_ENERGY``, ``MAX_ITERATIONS``). Vertices no face uses are ignored, and
    fTetWild sees the surface centred and scaled to a unit bounding-box diagonal (module
    docstring).
    Returns X (N, 3) float64 and T (E, 4) int64, positively oriented, every node used.
    Raises TetMeshError for unusable input or when fTetWild fails or crashes, and its subclass
    TetMeshTimeout when it runs out of time.
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F)
    assert F.ndim == 2 and F.shape[1] == 3, f"F must be (M, 3) triangles, got shape {F.shape}"
    check_surface(V, F)
    V, F = _used_vertices(V, F)
    centre, diagonal = _normalisation(V)
    options = dict(edge_length_fac=float(edge_length_fac), epsilon=float(epsilon),
                   num_threads=int(num_threads), time_limit=float(timeout),
                   stop_energy=float(stop_energy), max_iterations=int(max_iterations))
    X, T = _run_tetwild((V - centre) / diagonal, F, options, timeout, python, should_cancel)
    T = fem.orient_tets(X, T)  # in unit coordinates, where volumes are best resolved
    return X * diagonal + centre, T


def _used_vertices(V, F):
    """(V', F') keeping only the vertices some face uses, F renumbered."""
    used, F_new = np.unique(F, return_inverse=True)
    return V[used], F_new.reshape(F.shape)


def _normalisation(V):
    """(centre (3,), diagonal) of V's bounding box: fTetWild gets (V - centre) / diagonal."""
    lo, hi = V.min(axis=0), V.max(axis=0)
    return 0.5 * (lo + hi), float(np.linalg.norm(hi - lo))


def _run_tetwild(V, F, options, timeout, python, should_cancel):
    """fTetWild on (V, F) in the worker process with the worker's scalar ``options`` (its
    docstring): (X (N, 3) float64, T (E, 4) int64), every node used."""
    with tempfile.TemporaryDirectory(prefix="rs_elastic_tetwild_") as tmp:
        in_path, out_path = os.path.join(tmp, "in.npz"), os.path.join(tmp, "out.npz")
        with open(in_path, "wb") as f:
            np.savez(f, vertices=V, faces=F.astype(np.int32), **options)
        _run_worker(python or sys.executable, in_path, out_path, tmp, timeout, should_cancel)
        try:
            with np.load(out_path, allow_pickle=False) as out:
                X = np.asarray(out["nodes"], dtype=np.float64)
                T = np.asarray(out["tets"], dtype=np.int64)
        except (OSError, ValueError, KeyError) as exc:
            raise TetMeshError(f"fTetWild produced no readable result ({exc})") from exc
    if T.ndim != 2 or T.shape[1] != 4 or len(T) == 0:
        raise TetMeshError("fTetWild produced no tetrahedra; is the surface closed and not tiny?")
    return _remove_unreferenced(X, T)


def _worker_env():
    """Environment for the worker: PYTHONPATH = the directories numpy and pytetwild import from."""
    paths = []
    for name in ("numpy", "pytetwild"):
        spec = importlib.util.find_spec(name)
        if spec is None or spec.origin is None:
            raise TetMeshError(f"the Python package '{name}' is not installed")
        root = str(Path(spec.origin).resolve().parent.parent)  # .../site-packages
        if root not in paths:
            paths.append(root)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(paths + [p for p in [env.get("PYTHONPATH")] if p])
    return env


def _run_worker(python, in_path, out_path, cwd, timeout, should_cancel=None):
    """Run the worker; raise TetMeshError on cancel, crash or non-zero exit, TetMeshTimeout when
    it runs past ``timeout`` seconds (it is killed either way)."""
    try:
        process = subprocess.Popen([python, str(WORKER), in_path, out_path], cwd=cwd,
                                   env=_worker_env(), stdout=subprocess.DEVNULL,
                                   stderr=subprocess.PIPE, text=True, errors="replace")
    except OSError as exc:
        raise TetMeshError(f"could not start the tetrahedralisation process ({exc})") from exc
    deadline = time.monotonic() + timeout
    while True:
        try:
            _, stderr = process.communicate(timeout=0.2)
            break
        except subprocess.TimeoutExpired:
            if should_cancel is not None and should_cancel():
                process.kill()
                process.communicate()
                raise TetMeshError("tetrahedralisation cancelled") from None
            if time.monotonic() > deadline:
                process.kill()
                process.communicate()
                raise TetMeshTimeout(timeout) from None
    if process.returncode != 0:
        lines = [line for line in stderr.splitlines() if line.strip()]
        detail = f": {lines[-1].strip()}" if lines else ""
        raise TetMeshError(f"fTetWild failed ({_describe_exit(process.returncode)}){detail}")


def _describe_exit(code):
    """'exit code 3' or 'crashed with signal SIGSEGV' for a subprocess return code."""
    if code < 0:
        try:
            return f"crashed with signal {signal.Signals(-code).name}"
        except ValueError:
            return f"crashed with signal {-code}"
    return f"exit code {code}"


def _remove_unreferenced(X, T):
    """Drop nodes no tet uses (fTetWild can leave some) and renumber T accordingly."""
    used, T_new = np.unique(T, return_inverse=True)
    return X[used], T_new.reshape(T.shape).astype(np.int64)


def min_dihedral_angles(X, T):
    """(E,) smallest interior dihedral angle [deg] of each tet of (X (N, 3), T (E, 4)): 70.53 for
    a regular tet, near 0 for a sliver (which stiffens the FEM and slows its solves)."""
    P = np.asarray(X, dtype=np.float64)[np.asarray(T)]
    faces = ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))
    normals = []
    for k, (a, b, c) in enumerate(faces):       # face k is opposite vertex k: point away from it
        n = np.cross(P[:, b] - P[:, a], P[:, c] - P[:, a])
        n *= -np.sign(np.einsum("ij,ij->i", n, P[:, k] - P[:, a]))[:, None]
        normals.append(n / np.linalg.norm(n, axis=1, keepdims=True))
    cosines = [np.einsum("ij,ij->i", normals[i], normals[j])
               for i in range(4) for j in range(i + 1, 4)]
    # faces i and j meet at an edge; the interior angle there is pi minus their outward normals'
    return np.degrees(np.pi - np.arccos(np.clip(np.min(cosines, axis=0), -1.0, 1.0)))
