"""Prepared bodies: the solver's preparation stages, their disk cache and an in-memory copy.

Stage 1 (tets): fTetWild tet mesh of the evaluated mesh + embedding of the base mesh's vertices.
Stage 2 (modes): stiffness, lumped mass and linear modes for the material and pins.
Stage 3 (reduced): the reduced RS basis and its cubature (the deformer every solve evaluates).
Each stage is cached in `//blendcache_<blend name>/<object>.<stage>.<key>.npz` (the temp folder for
an unsaved file). The key hashes everything the stage depends on, so a stale file is never used,
and a new preparation writes new files beside the old ones: an unfinished or cancelled one leaves
the previous cache usable. Files of keys the object no longer uses are pruned once a preparation
is applied. An unreadable file is reported and rebuilt.
"""
import collections
import dataclasses
import functools
import os
import re
import tempfile

import bpy
import numpy as np
import scipy.sparse as sp

from ..solver import cache, embed, fem, modes, reduced, rs, tetmesh
from . import scene
from .jobs import Cancelled
from .scene import InputError

# How often each stage really ran in this process (the tests read these to prove cache reuse).
stats = collections.Counter()

_MEMORY = collections.OrderedDict()   # cache key -> TetBody, LinearModes or ReducedRS
_MEMORY_LIMIT = 16


@dataclasses.dataclass
class TetBody:
    nodes: np.ndarray        # (N, 3) float64, object space, metres
    tets: np.ndarray         # (E, 4) int64, positively oriented
    embedding: sp.csr_matrix  # (n, N) barycentric weights: base vertices = embedding @ nodes

    def to_arrays(self):
        Phi = self.embedding
        return dict(nodes=self.nodes, tets=self.tets, phi_data=Phi.data, phi_indices=Phi.indices,
                    phi_indptr=Phi.indptr, phi_shape=np.asarray(Phi.shape))

    @classmethod
    def from_arrays(cls, a):
        Phi = sp.csr_matrix((a["phi_data"], a["phi_indices"], a["phi_indptr"]),
                            shape=tuple(a["phi_shape"]))
        return cls(a["nodes"], a["tets"], Phi)


@dataclasses.dataclass
class PreparedBody:
    tet_body: TetBody
    linear_modes: modes.LinearModes
    deformer: reduced.ReducedRS = None      # None for a body prepared before reduced RS existed

    def surface_mode(self, index):
        """(n, 3) displacement of the base vertices for mode `index` (0-based), mass-normalised."""
        w = self.linear_modes.vectors[:, index].reshape(-1, 3)
        return self.tet_body.embedding @ w


def _modes_to_arrays(m):
    return dict(eigenvalues=m.eigenvalues, vectors=m.vectors, pinned_nodes=m.pinned_nodes)


def _modes_from_arrays(a):
    return modes.LinearModes(eigenvalues=a["eigenvalues"], vectors=a["vectors"],
                             pinned_nodes=a["pinned_nodes"])


# --- where the cache lives ------------------------------------------------------------------------

def cache_dirs():
    """Folders searched for cache files, the first being where new files are written."""
    temp = os.path.join(tempfile.gettempdir(), "rs_elastic_cache")
    if not bpy.data.filepath:
        return [temp]
    folder, name = os.path.split(bpy.data.filepath)
    return [os.path.join(folder, f"blendcache_{os.path.splitext(name)[0]}"), temp]


def _safe_name(object_name):
    return re.sub(r"[^A-Za-z0-9_-]", "_", object_name)


def cache_file(folder, object_name, stage, key):
    return os.path.join(folder, f"{_safe_name(object_name)}.{stage}.{key[:16]}.npz")


def prune(obj):
    """Delete the object's cache files whose key it no longer uses (in its primary folder)."""
    settings = obj.rs_elastic
    keep = {cache_file(cache_dirs()[0], obj.name, stage, key)
            for stage, key in _stage_keys(settings) if key}
    folder = cache_dirs()[0]
    pattern = re.compile(re.escape(_safe_name(obj.name)) + r"\.(tets|modes|reduced)\.[0-9a-f]+\.npz$")
    try:
        names = os.listdir(folder)
    except OSError:
        return
    for name in names:
        path = os.path.join(folder, name)
        if pattern.match(name) and path not in keep:
            try:
                os.remove(path)
            except OSError:
                pass


def _stage_keys(settings):
    return (("tets", settings.tets_key), ("modes", settings.prepared_key),
            ("reduced", settings.reduced_key))


def _to_arrays(stage, value):
    if stage == "tets":
        return value.to_arrays()
    if stage == "modes":
        return _modes_to_arrays(value)
    return value.save_arrays()


def _from_arrays(stage, arrays):
    if stage == "tets":
        return TetBody.from_arrays(arrays)
    if stage == "modes":
        return _modes_from_arrays(arrays)
    return reduced.ReducedRS.from_arrays(arrays)


# --- inputs, read on the main thread ----------------------------------------------------------------

@dataclasses.dataclass
class BodyInputs:
    object_name: str
    surface_vertices: np.ndarray   # evaluated mesh, object space
    surface_triangles: np.ndarray
    base_vertices: np.ndarray      # the mesh's own vertices
    edge_length: float
    envelope: float
    cache_dirs: list
    pin_mask: np.ndarray = None    # (n,) bool over base vertices, None for a free body
    youngs: float = 0.0
    poisson: float = 0.0
    density: float = 0.0
    num_modes: int = 0
    basis_size: int = 0            # reduced RS: largest basis B
    cubature_tets: int = 0         # reduced RS: largest cubature
    cubature_tolerance: float = 0.0
    training_poses: int = 0

    @functools.cached_property
    def tets_key(self):
        return cache.content_key("tets", self.surface_vertices, self.surface_triangles,
                                 self.base_vertices, self.edge_length, self.envelope)

    @functools.cached_property
    def modes_key(self):
        pins = self.pin_mask if self.pin_mask is not None else "free"
        return cache.content_key("modes", self.tets_key, pins, self.youngs, self.poisson,
                                 self.density, self.num_modes)

    @functools.cached_property
    def reduced_key(self):
        return cache.content_key("reduced", self.modes_key, self.basis_size, self.cubature_tets,
                                 self.cubature_tolerance, self.training_poses)


def read_inputs(obj, depsgraph, with_material=True):
    """Validate the object and snapshot everything the stages need. Raises InputError."""
    scene.require_body(obj)
    settings = obj.rs_elastic
    V, F = scene.evaluated_triangles(obj, depsgraph)
    try:
        tetmesh.check_surface(V, F)
    except tetmesh.TetMeshError as exc:
        raise InputError(f"'{obj.name}': {exc}") from None
    inputs = BodyInputs(obj.name, V, F, scene.base_vertices(obj), settings.edge_length,
                        settings.envelope, cache_dirs())
    if not with_material:
        return inputs
    try:
        fem.lame_parameters(settings.youngs_modulus, settings.poisson_ratio)
        if not settings.density > 0.0:
            raise ValueError(f"Density must be positive, got {settings.density:g} kg/m³")
    except ValueError as exc:
        raise InputError(str(exc)) from None
    if settings.pin_group:
        mask = scene.vertex_group_mask(obj, settings.pin_group)
        if not mask.any():
            raise InputError(f"Pin group '{settings.pin_group}' has no vertices; "
                             "clear Pin Group for a free body")
        if mask.all():
            raise InputError(f"Every vertex of '{obj.name}' is in pin group "
                             f"'{settings.pin_group}': nothing is left free to move")
        inputs.pin_mask = mask
    inputs.youngs = settings.youngs_modulus
    inputs.poisson = settings.poisson_ratio
    inputs.density = settings.density
    inputs.num_modes = settings.num_modes
    inputs.basis_size = settings.basis_size
    inputs.cubature_tets = settings.cubature_tets
    inputs.cubature_tolerance = settings.cubature_tolerance
    inputs.training_poses = settings.training_poses
    return inputs


# --- the stages (worker-thread safe: no bpy) --------------------------------------------------------

def _remember(key, value):
    _MEMORY[key] = value
    _MEMORY.move_to_end(key)
    while len(_MEMORY) > _MEMORY_LIMIT:
        _MEMORY.popitem(last=False)


def _load_cached(inputs, stage, key, job):
    """Arrays of a valid cache file for this key, or None. Corrupt files are reported and removed."""
    for folder in inputs.cache_dirs:
        path = cache_file(folder, inputs.object_name, stage, key)
        try:
            arrays = cache.load(path, key)
        except cache.CacheCorrupt as exc:
            job.warn(f"{exc}; rebuilding it")
            try:
                os.remove(path)
            except OSError:
                pass
            continue
        if arrays is not None:
            stats[f"{stage}_cache_hits"] += 1
            return arrays
    return None


def _save_cached(inputs, stage, key, arrays, job):
    path = cache_file(inputs.cache_dirs[0], inputs.object_name, stage, key)
    try:
        cache.save(path, key, arrays)
    except OSError as exc:
        job.warn(f"Could not write the cache {path}: {exc}")


def _cached_stage(inputs, stage, key, compute, job):
    """A stage's value: from memory, else its valid cache file, else compute() (then saved)."""
    if key in _MEMORY:
        return _MEMORY[key]
    arrays = _load_cached(inputs, stage, key, job)
    if arrays is not None:
        value = _from_arrays(stage, arrays)
    else:
        value = compute()
        _save_cached(inputs, stage, key, _to_arrays(stage, value), job)
    _remember(key, value)
    return value


def tet_stage(inputs, job):
    """The tet mesh and embedding for these inputs: from memory, the disk cache, or fTetWild."""
    def compute():
        job.step(0.05, "Tetrahedralising with fTetWild")
        stats["tetrahedralize"] += 1
        try:
            X, T = tetmesh.tetrahedralize(inputs.surface_vertices, inputs.surface_triangles,
                                          edge_length_fac=inputs.edge_length,
                                          epsilon=inputs.envelope,
                                          should_cancel=job.is_cancelled)
        except tetmesh.TetMeshError as exc:
            if job.is_cancelled():
                raise Cancelled() from None
            raise InputError(f"Tetrahedralisation of '{inputs.object_name}' failed: {exc}") from None
        job.step(0.45, "Embedding the mesh in the tets")
        return TetBody(X, T, embed.embed_points(X, T, inputs.base_vertices))

    return _cached_stage(inputs, "tets", inputs.tets_key, compute, job)


def modes_stage(inputs, tet_body, job):
    """Linear modes for the material and pins: from memory, the disk cache, or eigsh."""
    def compute():
        pinned = None
        if inputs.pin_mask is not None:
            pinned = embed.pinned_nodes_from_vertices(tet_body.embedding, inputs.pin_mask)
            if len(pinned) >= len(tet_body.nodes):
                raise InputError(f"The pins of '{inputs.object_name}' hold every tet node: "
                                 "nothing is left free to move")
        job.step(0.55, "Assembling stiffness and mass")
        K = fem.stiffness_matrix(tet_body.nodes, tet_body.tets, inputs.youngs, inputs.poisson)
        masses = fem.lumped_masses(tet_body.nodes, tet_body.tets, inputs.density)
        job.step(0.65, f"Computing {inputs.num_modes} linear modes")
        stats["modes"] += 1
        try:
            return modes.linear_modes(K, masses, inputs.num_modes, pinned)
        except ValueError as exc:
            raise InputError(f"'{inputs.object_name}': {exc}") from None

    return _cached_stage(inputs, "modes", inputs.modes_key, compute, job)


def reduced_stage(inputs, tet_body, linear_modes, job):
    """The reduced RS deformer: from memory, the disk cache, or basis + cubature training."""
    def compute():
        X, T = tet_body.nodes, tet_body.tets
        pinned = linear_modes.pinned_nodes
        job.step(0.72, "Reduced RS: training poses")
        stats["reduced"] += 1
        recon = rs.PoissonReconstruction(X, T, pinned_nodes=pinned if len(pinned) else None)
        masses = fem.lumped_masses(X, T, inputs.density)
        deformer, _ = reduced.prepare_reduced_rs(
            X, T, masses, linear_modes.vectors, linear_modes.eigenvalues, recon,
            max_size=inputs.basis_size or None, max_tets=inputs.cubature_tets,
            tol=inputs.cubature_tolerance, num_poses=inputs.training_poses,
            progress=lambda f, message: job.step(0.72 + 0.27 * f, f"Reduced RS: {message}"))
        return deformer

    return _cached_stage(inputs, "reduced", inputs.reduced_key, compute, job)


def prepare(inputs, job):
    """All three stages; returns a PreparedBody."""
    tet_body = tet_stage(inputs, job)
    linear_modes = modes_stage(inputs, tet_body, job)
    deformer = reduced_stage(inputs, tet_body, linear_modes, job)
    job.step(1.0, "Done")
    return PreparedBody(tet_body, linear_modes, deformer)


# --- for the preview and later operators -------------------------------------------------------------

def load_prepared(obj):
    """The PreparedBody the object was last prepared with, or None if it cannot be found."""
    settings = obj.rs_elastic
    if not settings.prepared_key:
        return None
    tet_body = _load_stage(obj, "tets", settings.tets_key)
    linear_modes = _load_stage(obj, "modes", settings.prepared_key)
    if tet_body is None or linear_modes is None:
        return None
    return PreparedBody(tet_body, linear_modes, _load_stage(obj, "reduced", settings.reduced_key))


def persist(obj):
    """Make sure the object's prepared stages are in its primary cache folder (after a file is
    saved under a new name its cache moves next to it)."""
    folder = cache_dirs()[0]
    for stage, key in _stage_keys(obj.rs_elastic):
        if not key:
            continue
        path = cache_file(folder, obj.name, stage, key)
        if cache.stored_key(path) == key:
            continue
        value = _load_stage(obj, stage, key)
        if value is None:
            continue
        arrays = _to_arrays(stage, value)
        try:
            cache.save(path, key, arrays)
        except OSError as exc:
            print(f"RS Elastic: could not write the cache {path}: {exc}")


def load_tet_body(obj):
    return _load_stage(obj, "tets", obj.rs_elastic.tets_key)


def _load_stage(obj, stage, key):
    if not key:
        return None
    if key in _MEMORY:
        return _MEMORY[key]
    for folder in cache_dirs():
        try:
            arrays = cache.load(cache_file(folder, obj.name, stage, key), key)
        except cache.CacheCorrupt:
            continue
        if arrays is not None:
            value = _from_arrays(stage, arrays)
            _remember(key, value)
            return value
    return None
