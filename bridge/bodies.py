"""Prepared bodies: the solver's preparation stages, their disk cache and an in-memory copy.

Stage 1 (tets): fTetWild tet mesh of the evaluated mesh + embedding of the base mesh's vertices.
Stage 2 (modes): stiffness, lumped mass and linear modes for the material and pins.
Stage 3 (reduced): the reduced RS basis and its cubature (the deformer every solve evaluates).
Stage 4 (energy, StVK and Fung only): the energy cubature of the material's reduced potential
(`solver.materials.prepare_potential`). Linear needs none (its potential is an exact quadratic
form), so it has no such stage and writes no file.

Keys are content addresses. The tets key hashes the surface and the mesher settings; the modes
key hashes the tet mesh *actually used* (its arrays) with the material and pins; the reduced key
hashes the modes' arrays with the reduced settings; the energy key hashes the tets' and the
modes' arrays (what the cubature is trained on) with the material kind, every material parameter
it is trained with (Young's modulus and Poisson's ratio, and the stiffening for Fung only) and the
training settings. So stages of different runs can never mix.
Each stage is cached in `//blendcache_<blend name>/<object>.<stage>.<key>.npz` (the temp folder for
an unsaved file); a new preparation writes new files beside the old ones, so a cancelled one
leaves the previous cache usable. Every loaded array is validated; on any doubt the file is
rebuilt with one warning.

The tet mesh itself travels with the .blend (`obj.rs_elastic["tet_mesh"]`, with the tets key it
was made for), because fTetWild is not deterministic: re-preparing the same file, in any process
and without the cache folder, reuses it, and only a new surface or new mesher settings replace it.

Staleness: Prepare records a fingerprint of what it read (mesh, modifiers, pins, settings) in
`obj.rs_elastic["prepared_inputs"]`; `stale_reason` compares it with the object now. The
material model is not part of it: Simulate trains (or loads) the energy cubature of whichever
model is set, and `obj.rs_elastic["energy_cache"]` records the energy keys made for the current
preparation, so that `prune` keeps and `persist` copies their files.
"""
import collections
import dataclasses
import functools
import json
import os
import re
import shutil
import tempfile

import bpy
import numpy as np
import scipy.sparse as sp

from ..solver import cache, embed, fem, materials, modes, proxy, reduced, rig, rs, tetmesh
from . import armature, mesh_cache, scene
from .jobs import Cancelled, Job
from .scene import InputError

# How often each stage really ran in this process (the tests read these to prove cache reuse).
stats = collections.Counter()

_MEMORY = collections.OrderedDict()   # cache key -> (value, parent digest)
_MEMORY_LIMIT = 16

TET_MESH = "tet_mesh"                 # obj.rs_elastic[TET_MESH]: {"key", "nodes", "tets"}
PREPARED_INPUTS = "prepared_inputs"   # obj.rs_elastic[PREPARED_INPUTS]: the fingerprint at Prepare
ENERGY_RECORD = "energy_cache"        # obj.rs_elastic[ENERGY_RECORD]: {"parent", "keys"} as JSON

# How the energy cubature is trained (`materials.prepare_potential`); part of its key.
ENERGY_TRAINING = dict(num_poses=200, max_tets=200, tol=1e-4, max_rotation=np.pi / 2, seed=0)


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
                            shape=tuple(int(n) for n in a["phi_shape"]))
        return cls(a["nodes"], a["tets"].astype(np.int64), Phi)


@dataclasses.dataclass
class PreparedBody:
    tet_body: TetBody
    linear_modes: modes.LinearModes
    deformer: reduced.ReducedRS = None      # None for a body prepared before reduced RS existed
    keys: tuple = ("", "", "")               # (tets, modes, reduced) keys it was made under
    digests: tuple = ("", "")                # content digests of (tet_body, linear_modes)
    energy: materials.ReducedPotential = None   # the energy cubature, if Prepare made one
    energy_key: str = ""
    # (n, N) csr: the embedding for displacements, with the pinned vertices held by pinned
    # nodes (embed.SurfacePins.embedding); None: the tet body's own (a free body)
    pinned_embedding: sp.csr_matrix = None

    @property
    def displacement_embedding(self):
        """(n, N) csr mapping node displacements to base-vertex displacements (pins hold)."""
        return self.tet_body.embedding if self.pinned_embedding is None else self.pinned_embedding

    def surface_mode(self, index):
        """(n, 3) displacement of the base vertices for mode `index` (0-based), mass-normalised."""
        w = self.linear_modes.vectors[:, index].reshape(-1, 3)
        return self.displacement_embedding @ w


def _modes_to_arrays(m):
    return dict(eigenvalues=m.eigenvalues, vectors=m.vectors, pinned_nodes=m.pinned_nodes)


def _modes_from_arrays(a):
    return modes.LinearModes(eigenvalues=a["eigenvalues"], vectors=a["vectors"],
                             pinned_nodes=a["pinned_nodes"].astype(np.int64))


# Version of the automatic basis and cubature sizing and training range (solver.reduced): a
# reduced cache built under other rules is rebuilt, not reused. Bump it when they change.
REDUCED_RULES = "reduced-2: O(m^2) basis, cubature 1.25 rB, training to 180 deg"

# Version of the pin rule (solver.embed.pin_surface); part of the modes key, so modes pinned
# under another rule are rebuilt, not reused. Bump it when the rule changes.
PIN_RULES = "surface pins 2: faces clamp by their tet-surface facets"

# What a stage's file must hold; sizes with the same name must agree (see cache.validate).
_SCHEMAS = {
    "tets": {"nodes": ("f", ("N", 3)), "tets": ("iu", ("E", 4)), "phi_data": ("f", ("nnz",)),
             "phi_indices": ("iu", ("nnz",)), "phi_indptr": ("iu", (None,)),
             "phi_shape": ("iu", (2,))},
    "modes": {"eigenvalues": ("f", ("r",)), "vectors": ("f", (None, "r")),
              "pinned_nodes": ("iu", (None,))},
    "reduced": {"cubature_tets": ("iu", ("C",)), "cubature_weights": ("f", ("C",)),
                "projections": ("f", (None, None, None)), "modal_rs_cubature": ("f", (None, None, None)),
                "linear_map": ("f", (None, None))},
    "energy": {"tets": ("iu", ("C",)), "weights": ("f", ("C",)),
               "strain_modes": ("f", ("C", 6, None))},
}


def digest(stage, value):
    """Content hash of a stage's value: what the next stage's key is made of."""
    arrays = _to_arrays(stage, value)
    return cache.content_key(stage, *(np.asarray(arrays[name]) for name in sorted(arrays)))


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
    """Delete the object's cache files whose key it no longer uses (in its primary folder).

    An undo can bring back a key whose files are gone: `load_prepared` then recomputes them
    (the tet mesh is kept in the .blend, so the recomputed stages have the same keys).
    """
    settings = obj.rs_elastic
    keep = {cache_file(cache_dirs()[0], obj.name, stage, key)
            for stage, key in _stage_keys(settings) if key}
    folder = cache_dirs()[0]
    pattern = re.compile(re.escape(_safe_name(obj.name))
                         + r"\.(tets|modes|reduced|energy)\.[0-9a-f]+\.npz$")
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
            ("reduced", settings.reduced_key),
            *(("energy", key) for key in _energy_record(settings)["keys"]))


def _to_arrays(stage, value):
    if stage in ("tets", "energy"):
        return value.to_arrays()
    if stage == "modes":
        return _modes_to_arrays(value)
    return value.save_arrays()


def _from_arrays(stage, arrays, path, material=None):
    """The stage's value from validated arrays (the energy stage's for `material`); CacheCorrupt
    on any doubt."""
    sizes = cache.validate(arrays, _SCHEMAS[stage], path)
    try:
        if stage == "energy":
            if arrays["tets"].min(initial=0) < 0 or arrays["weights"].min(initial=0.0) < 0.0:
                raise ValueError("negative tet index or weight")
            return materials.ReducedPotential.from_arrays(material, arrays)
        if stage == "tets":
            if (arrays["tets"].min(initial=0) < 0 or arrays["tets"].max(initial=0) >= sizes["N"]
                    or tuple(arrays["phi_shape"])[1] != sizes["N"]):
                raise ValueError("tet indices out of range")
            return TetBody.from_arrays(arrays)
        if stage == "modes":
            return _modes_from_arrays(arrays)
        return reduced.ReducedRS.from_arrays(arrays)
    except (KeyError, ValueError, IndexError, TypeError) as exc:
        raise cache.CacheCorrupt(f"cache file {path} is inconsistent ({exc})") from None


# --- the tet mesh kept in the .blend (main thread) --------------------------------------------------

def stored_tet_mesh(obj, key):
    """(nodes (N, 3) float64, tets (E, 4) int64) kept in the object for this tets key, or None."""
    group = obj.rs_elastic.get(TET_MESH)
    if group is None or group.get("key") != key:
        return None
    try:
        nodes = np.array(group["nodes"], dtype=np.float64).reshape(-1, 3)
        tets = np.array(group["tets"], dtype=np.int64).reshape(-1, 4)
    except (KeyError, ValueError, TypeError):
        return None
    if (len(tets) == 0 or not np.all(np.isfinite(nodes)) or tets.min() < 0
            or tets.max() >= len(nodes)):
        return None
    return nodes, tets


def store_tet_mesh(obj, key, tet_body):
    """Keep the tet mesh in the object (undoable, per object: linked duplicates may differ)."""
    kept = stored_tet_mesh(obj, key)
    if (kept is not None and np.array_equal(kept[0], tet_body.nodes)
            and np.array_equal(kept[1], tet_body.tets)):
        return
    # float64 and int32 arrays go into ID properties through the buffer protocol (milliseconds).
    obj.rs_elastic[TET_MESH] = {
        "key": key, "nodes": np.ascontiguousarray(tet_body.nodes, dtype=np.float64).ravel(),
        "tets": np.ascontiguousarray(tet_body.tets, dtype=np.int32).ravel()}


def forget_prepared(obj):
    """Drop the record of a preparation (its keys stay in settings until the caller clears them)."""
    for name in (PREPARED_INPUTS, ENERGY_RECORD):
        if obj.rs_elastic.get(name) is not None:
            del obj.rs_elastic[name]


# --- what Prepare read, and whether it still holds (main thread) ------------------------------------

_SKIPPED_MODIFIER_PROPS = {"rna_type", "name", "show_expanded", "is_active", "show_in_editmode",
                           "show_on_cage", "show_render", "use_pin_to_last", "persistent_uid",
                           "is_override_data_editable", "execution_time", "use_apply_on_spline"}


def _modifier_stack(obj):
    """A text describing the modifier stack: every modifier's type and settings."""
    parts = []
    for m in obj.modifiers:
        if mesh_cache.is_bake_modifier(obj, m):     # the bake's own player is not an input
            continue
        values = []
        for prop in m.bl_rna.properties:
            if prop.identifier in _SKIPPED_MODIFIER_PROPS or prop.is_readonly \
                    or prop.type == 'COLLECTION':
                continue
            value = getattr(m, prop.identifier, None)
            if prop.type == 'POINTER':
                value = getattr(value, "name", None)
            elif getattr(prop, "is_array", False):
                value = tuple(value)
            values.append((prop.identifier, value))
        if m.type == 'NODES':
            values += [(k, repr(m[k])) for k in m.keys()]     # the node group's inputs
        parts.append((m.type, m.name, values))
    return repr(parts)


def pin_weights(obj, group_name):
    """(n,) float32 weights of the named vertex group over the base vertices (0 outside it).

    Blender has no bulk accessor for group weights, so this walks the memberships once.
    """
    group = obj.vertex_groups.get(group_name)
    if group is None:
        raise InputError(f"Pin group '{group_name}' does not exist on '{obj.name}'")
    index = group.index
    weights = np.zeros(len(obj.data.vertices), dtype=np.float32)
    for v in obj.data.vertices:
        for g in v.groups:
            if g.group == index:
                weights[v.index] = g.weight
    return weights


def _geometry_fingerprint(obj):
    """The costly part of the fingerprint: vertices, faces, modifiers, pin weights (hashes)."""
    mesh = obj.data
    co = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", co)
    corners = np.empty(len(mesh.loops), dtype=np.int32)
    corner_vert = mesh.attributes.get(".corner_vert")     # 100× faster than mesh.loops
    if corner_vert is not None:
        corner_vert.data.foreach_get("value", corners)
    else:
        mesh.loops.foreach_get("vertex_index", corners)
    sizes = np.empty(len(mesh.polygons), dtype=np.int32)
    mesh.polygons.foreach_get("loop_start", sizes)
    group = obj.rs_elastic.pin_group
    if not group:
        pins = "free"
    elif obj.vertex_groups.get(group) is None:
        pins = "missing"
    else:
        pins = cache.content_key(pin_weights(obj, group))
    return {"vertex count": str(len(mesh.vertices)), "faces": cache.content_key(corners, sizes),
            "vertices": cache.content_key(co), "modifiers": cache.content_key(_modifier_stack(obj)),
            "pin group": pins}


def _settings_fingerprint(settings):
    return {"tet mesh settings": repr((settings.edge_length, settings.envelope,
                                       settings.proxy_triangles)),
            "material": repr((settings.youngs_modulus, settings.poisson_ratio, settings.density)),
            "number of modes": repr(settings.num_modes),
            "reduced RS settings": repr((settings.basis_size, settings.cubature_tets,
                                         settings.cubature_tolerance, settings.training_poses))}


_GEOMETRY = {}   # object pointer -> (pin group name, its index, geometry fingerprint), for draw


def fingerprint(obj, cached=False):
    """dict component -> text/hash of everything Prepare reads. `cached` reuses the geometry
    part until a depsgraph update of the object or its mesh (for the panel, which runs in draw)."""
    settings = obj.rs_elastic
    group = obj.vertex_groups.get(settings.pin_group) if settings.pin_group else None
    mesh = obj.data
    tag = (settings.pin_group, None if group is None else group.index, len(mesh.vertices),
           len(mesh.polygons), len(obj.modifiers))
    entry = _GEOMETRY.get(obj.as_pointer()) if cached else None
    if entry is None or entry[0] != tag:
        entry = _GEOMETRY[obj.as_pointer()] = (tag, _geometry_fingerprint(obj))
    return {**entry[1], **_settings_fingerprint(settings)}


def forget_fingerprints(depsgraph_updates):
    """Drop the cached geometry fingerprints once a mesh or an object's geometry changed (all of
    them for None: after a load or an undo)."""
    if depsgraph_updates is None:
        _GEOMETRY.clear()
        return
    for update in depsgraph_updates:
        if isinstance(update.id, (bpy.types.Mesh, bpy.types.Object)) and (
                update.is_updated_geometry or isinstance(update.id, bpy.types.Mesh)):
            _GEOMETRY.clear()     # cheap to rebuild for the few objects a panel shows
            return


def _what_changed(obj, before, now):
    """What to tell the user about the first component that differs, or None."""
    for name, value in now.items():
        if before.get(name) == value:
            continue
        if name == "pin group" and value == "missing":
            return (f"pin group '{obj.rs_elastic.pin_group}' no longer exists (renamed or deleted "
                    "since Prepare Body): set Pin Group and prepare again")
        if name == "vertex count":
            what = f"the vertex count changed since Prepare Body ({before.get(name)} → {value})"
        elif name == "vertices":
            what = "the mesh's vertices moved since Prepare Body"
        else:
            what = f"the {name} changed since Prepare Body"
        return what + ": prepare again"
    return None


def stale_reason(obj, cached=False):
    """Why the prepared body no longer matches the object, in words, or None if it does."""
    settings = obj.rs_elastic
    if not settings.is_prepared:
        return None
    record = settings.get(PREPARED_INPUTS)
    if record is None:
        return "it was prepared by an older version of RS Elastic: prepare again"
    return _what_changed(obj, json.loads(record), fingerprint(obj, cached=cached))


def require_current(obj):
    """Raise InputError saying what changed if the object's preparation is stale."""
    reason = stale_reason(obj)
    if reason:
        raise InputError(f"'{obj.name}': {reason}")


def record_prepared(obj, prepared_fingerprint):
    obj.rs_elastic[PREPARED_INPUTS] = json.dumps(prepared_fingerprint, sort_keys=True)


# --- inputs, read on the main thread ----------------------------------------------------------------

@dataclasses.dataclass
class BodyInputs:
    object_name: str
    surface_vertices: np.ndarray   # evaluated mesh without shape keys, object space
    surface_triangles: np.ndarray
    base_vertices: np.ndarray      # the mesh's own vertices
    edge_length: float
    envelope: float
    cache_dirs: list
    proxy_triangles: int = 0       # proxy budget (0: automatic, solver.proxy.triangle_budget)
    base_triangles: np.ndarray = None   # (t, 3) triangles of the base mesh (the pin rule reads them)
    pin_weights: np.ndarray = None      # (n,) float32 in [0, 1], None for a free body
    pins_hold_volume: bool = False      # rigged: the Follow Rig group holds the flesh it paints
    stored_tets: tuple = None      # (nodes, tets) kept in the .blend for tets_key, or None
    fingerprint: dict = None       # what Prepare read (see `fingerprint`)
    youngs: float = 0.0
    poisson: float = 0.0
    density: float = 0.0
    num_modes: int = 0
    basis_size: int = 0            # reduced RS: largest basis B
    cubature_tets: int = 0         # reduced RS: largest cubature
    cubature_tolerance: float = 0.0
    training_poses: int = 0
    energy: "EnergyInputs" = None   # set to train the energy cubature too (StVK / Fung)

    @functools.cached_property
    def tets_key(self):
        return cache.content_key("tets", self.surface_vertices, self.surface_triangles,
                                 self.base_vertices, self.edge_length, self.envelope,
                                 ("proxy", self.proxy_triangles))

    def modes_key(self, tets_digest):
        """Key of the modes of the tet mesh whose arrays hash to tets_digest."""
        pins = (PIN_RULES, self.pin_weights, self.base_triangles, self.pins_hold_volume) \
            if self.pin_weights is not None else "free"
        return cache.content_key("modes", tets_digest, pins, self.youngs, self.poisson,
                                 self.density, self.num_modes)

    def reduced_key(self, modes_digest):
        return cache.content_key("reduced", REDUCED_RULES, modes_digest, self.basis_size,
                                 self.cubature_tets, self.cubature_tolerance, self.training_poses)


@dataclasses.dataclass
class EnergyInputs:
    """What the energy stage reads besides the prepared body (a main-thread snapshot)."""
    object_name: str
    cache_dirs: list
    kind: str                  # "STVK" or "FUNG"
    youngs: float              # [Pa]
    poisson: float
    fung_stiffening: float     # dimensionless; only Fung reads it

    @functools.cached_property
    def parameters(self):
        """The material parameters the cubature is trained with (Fung's stiffening for Fung only:
        StVK's cubature does not depend on it, so changing it reuses StVK's file)."""
        stiffening = (self.fung_stiffening,) if self.kind == "FUNG" else ()
        return (self.youngs, self.poisson) + stiffening

    @functools.cached_property
    def material(self):
        mu, lam = fem.lame_parameters(self.youngs, self.poisson)
        return materials.make_material(self.kind, mu, lam, fung_stiffening=self.fung_stiffening)

    def key(self, parent):
        """Key of the cubature for the prepared body whose `energy_parent` is parent."""
        return cache.content_key("energy", parent, self.kind, self.parameters,
                                 sorted(ENERGY_TRAINING.items()))

    @property
    def label(self):
        return {"STVK": "StVK", "FUNG": "Fung"}[self.kind]


def energy_inputs(obj):
    """EnergyInputs of the object's material model, or None for Linear (which needs no cubature)."""
    settings = obj.rs_elastic
    if settings.material_model == 'LINEAR':
        return None
    return EnergyInputs(obj.name, cache_dirs(), settings.material_model, settings.youngs_modulus,
                        settings.poisson_ratio, settings.fung_stiffening)


def rest_surface(obj, depsgraph):
    """The evaluated surface (modifiers applied) without shape keys: bakes and previews are
    shape keys, and the tet mesh must not depend on the frame they play."""
    # A rigged body is prepared in its rest pose; a Mesh Cache bake is output, not the shape.
    with armature.rest_pose(obj, depsgraph), mesh_cache.muted(obj, depsgraph):
        return _surface_without_keys(obj, depsgraph)


def _surface_without_keys(obj, depsgraph):
    if obj.data.shape_keys is None:
        return scene.evaluated_triangles(obj, depsgraph)
    saved = obj.show_only_shape_key, obj.active_shape_key_index
    obj.show_only_shape_key, obj.active_shape_key_index = True, 0   # the reference key alone
    try:
        depsgraph.update()
        return scene.evaluated_triangles(obj, depsgraph)
    finally:
        obj.show_only_shape_key, obj.active_shape_key_index = saved
        depsgraph.update()


def read_inputs(obj, depsgraph, with_material=True):
    """Validate the object and snapshot everything the stages need. Raises InputError."""
    scene.require_body(obj)
    settings = obj.rs_elastic
    V, F = rest_surface(obj, depsgraph)
    try:
        tetmesh.check_surface(V, F)
    except tetmesh.TetMeshError as exc:
        raise InputError(f"'{obj.name}': {exc}") from None
    inputs = BodyInputs(obj.name, V, F, scene.base_vertices(obj), settings.edge_length,
                        settings.envelope, cache_dirs(), proxy_triangles=settings.proxy_triangles)
    inputs.stored_tets = stored_tet_mesh(obj, inputs.tets_key)
    if not with_material:
        return inputs
    try:
        fem.lame_parameters(settings.youngs_modulus, settings.poisson_ratio)
        if not settings.density > 0.0:
            raise ValueError(f"Density must be positive, got {settings.density:g} kg/m³")
    except ValueError as exc:
        raise InputError(str(exc)) from None
    if settings.pin_group:
        weights = np.clip(pin_weights(obj, settings.pin_group), 0.0, 1.0)
        if not weights.any():
            raise InputError(f"Pin group '{settings.pin_group}' has no vertices; "
                             "clear Pin Group for a free body")
        if weights.all():
            raise InputError(f"Every vertex of '{obj.name}' is in pin group "
                             f"'{settings.pin_group}': nothing is left free to move")
        inputs.pin_weights = weights
        inputs.base_triangles = scene.base_triangles(obj)
        inputs.pins_hold_volume = armature.is_rigged(obj)
    inputs.fingerprint = fingerprint(obj)
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

def _remember(key, value, parent):
    _MEMORY[key] = (value, parent)
    _MEMORY.move_to_end(key)
    while len(_MEMORY) > _MEMORY_LIMIT:
        _MEMORY.popitem(last=False)


def _read_file(folders, object_name, stage, key, parent, warn, material=None):
    """A valid cached value for this key (and parent digest), or None. A damaged file is
    reported once through warn() and removed, so it is rebuilt."""
    for folder in folders:
        path = cache_file(folder, object_name, stage, key)
        try:
            arrays = cache.load(path, key)
            if arrays is None:
                continue
            if str(arrays.pop("parent_digest", "")) != parent:
                continue     # made from other contents: not ours (cannot happen by key alone)
            value = _from_arrays(stage, arrays, path, material)
        except cache.CacheCorrupt as exc:
            warn(f"{exc}; rebuilding it")
            try:
                os.remove(path)
            except OSError:
                pass
            continue
        stats[f"{stage}_cache_hits"] += 1
        return value
    return None


def _save_cached(inputs, stage, key, value, parent, job):
    path = cache_file(inputs.cache_dirs[0], inputs.object_name, stage, key)
    try:
        cache.save(path, key, dict(_to_arrays(stage, value), parent_digest=np.array(parent)))
    except OSError as exc:
        job.warn(f"Could not write the cache {path}: {exc}")


def _cubature_size(inputs, X, T, linear_modes):
    """Cubature tets: the user's setting, raised to ``reduced.default_cubature_size`` of the
    automatic basis when Basis Size is 0 (automatic), since that basis grows as O(modes^2)."""
    if inputs.basis_size:
        return inputs.cubature_tets
    automatic = reduced.default_basis_size(linear_modes.vectors.shape[1], num_nodes=len(X),
                                           num_tets=len(T))
    return max(inputs.cubature_tets, reduced.default_cubature_size(automatic, num_tets=len(T)))


def _cached_stage(inputs, stage, key, parent, compute, job, accept=lambda value: True):
    """A stage's value: from memory, else its valid cache file, else compute() (then saved).
    `parent` is the digest of what it is computed from; `accept` rejects a value on doubt."""
    entry = _MEMORY.get(key)
    value = entry[0] if entry is not None and entry[1] == parent else None
    if value is None or not accept(value):
        value = _read_file(inputs.cache_dirs, inputs.object_name, stage, key, parent, job.warn,
                           getattr(inputs, "material", None))
    if value is None or not accept(value):
        value = compute()
        _save_cached(inputs, stage, key, value, parent, job)
    _remember(key, value, parent)
    return value


def proxy_for(inputs, job):
    """The surface fTetWild meshes: the evaluated surface, or its simplified closed proxy when it
    has more triangles than the budget (the Proxy Triangles setting, 0: ``proxy.triangle_budget``
    of the edge length). Says which in the progress."""
    V, F = inputs.surface_vertices, inputs.surface_triangles
    budget = inputs.proxy_triangles or proxy.triangle_budget(V, F, inputs.edge_length)
    if len(F) > budget:
        job.step(0.02, f"Simplifying {len(F):,} triangles to a {budget:,}-triangle proxy")
        V, F, simplified = proxy.proxy_surface(V, F, budget)
        if not simplified:
            job.warn(f"'{inputs.object_name}' is not a closed manifold, so fTetWild meshes all "
                     f"{len(F):,} of its triangles (slower)")
    job.step(0.05, f"Tetrahedralising {len(F):,} triangles with fTetWild")
    return V, F


def tet_stage(inputs, job):
    """The tet mesh and embedding: the one kept in the .blend if any (embedded again when no
    cache file has it), else from memory, the disk cache, or fTetWild."""
    stored = inputs.stored_tets

    def same_as_stored(tet_body):
        return stored is None or (np.array_equal(tet_body.nodes, stored[0])
                                  and np.array_equal(tet_body.tets, stored[1]))

    def compute():
        if stored is not None:
            X, T = stored
        else:
            V, F = proxy_for(inputs, job)
            stats["tetrahedralize"] += 1
            try:
                X, T = tetmesh.tetrahedralize(V, F, edge_length_fac=inputs.edge_length,
                                              epsilon=inputs.envelope,
                                              should_cancel=job.is_cancelled)
            except tetmesh.TetMeshError as exc:
                if job.is_cancelled():
                    raise Cancelled() from None
                raise InputError(f"Tetrahedralisation of '{inputs.object_name}' failed: {exc}") from None
        job.step(0.45, "Embedding the mesh in the tets")
        return TetBody(X, T, embed.embed_points(X, T, inputs.base_vertices))

    return _cached_stage(inputs, "tets", inputs.tets_key, "", compute, job, same_as_stored)


def surface_pins(inputs, tet_body):
    """embed.SurfacePins of the pin group's weights (the rule is embed.pin_surface), or None for
    a free body. Cheap next to the modes, and a function of the modes' key: computed again
    rather than cached."""
    if inputs.pin_weights is None:
        return None
    X, T, Phi = tet_body.nodes, tet_body.tets, tet_body.embedding
    # A rig's Follow Rig weights are volumetric, as its springs below 0.5 are (rig.node_values).
    carried = rig.node_values(Phi, inputs.pin_weights, X, T)[:, 0] if inputs.pins_hold_volume \
        else None
    # fTetWild's surface strays up to the envelope from the mesh: twice that still finds the
    # tet-surface nodes of a painted face (embed.PIN_TOLERANCE is this for the default envelope).
    return embed.pin_surface(X, T, Phi, inputs.base_vertices, inputs.base_triangles,
                             inputs.pin_weights, threshold=0.5, tolerance=2.0 * inputs.envelope,
                             node_weights=carried)


def modes_stage(inputs, tet_body, job, tets_digest, pins):
    """Linear modes for the material and the pins (``surface_pins``; None for a free body):
    from memory, the disk cache, or eigsh."""
    def compute():
        pinned = None
        if pins is not None:
            pinned = pins.nodes
            if len(pinned) >= len(tet_body.nodes):
                raise InputError(f"The pins of '{inputs.object_name}' hold every tet node: "
                                 "nothing is left free to move")
        job.step(0.55, "Assembling stiffness and mass")
        K = fem.stiffness_matrix(tet_body.nodes, tet_body.tets, inputs.youngs, inputs.poisson)
        masses = fem.lumped_masses(tet_body.nodes, tet_body.tets, inputs.density)
        job.step(0.65, f"Computing {inputs.num_modes} linear modes")
        stats["modes"] += 1
        try:
            return modes.linear_modes(K, masses, inputs.num_modes, pinned,
                                      rest_positions=tet_body.nodes)
        except ValueError as exc:
            raise InputError(f"'{inputs.object_name}': {exc}") from None

    def fits(m):
        return m.vectors.shape[0] == 3 * len(tet_body.nodes)

    return _cached_stage(inputs, "modes", inputs.modes_key(tets_digest), tets_digest, compute,
                         job, fits)


def reduced_stage(inputs, tet_body, linear_modes, job, modes_digest=None, end=0.99):
    """The reduced RS deformer: from memory, the disk cache, or basis + cubature training
    (its progress runs from 0.72 to `end`)."""
    modes_digest = modes_digest or digest("modes", linear_modes)

    def compute():
        X, T = tet_body.nodes, tet_body.tets
        pinned = linear_modes.pinned_nodes
        job.step(0.72, "Reduced RS: training poses")
        stats["reduced"] += 1
        recon = rs.PoissonReconstruction(X, T, pinned_nodes=pinned if len(pinned) else None)
        masses = fem.lumped_masses(X, T, inputs.density)
        deformer, _ = reduced.prepare_reduced_rs(
            X, T, masses, linear_modes.vectors, linear_modes.eigenvalues, recon,
            max_size=inputs.basis_size or None, max_tets=_cubature_size(inputs, X, T,
                                                                         linear_modes),
            tol=inputs.cubature_tolerance, num_poses=inputs.training_poses,
            progress=lambda f, message: job.step(0.72 + (end - 0.72) * f, f"Reduced RS: {message}"))
        return deformer

    def fits(d):
        return d.basis is None or d.basis.shape[0] == 3 * len(tet_body.nodes)

    return _cached_stage(inputs, "reduced", inputs.reduced_key(modes_digest), modes_digest,
                         compute, job, fits)


def energy_parent(body):
    """Digest of what a body's energy cubature is trained on: its tets' and its modes' arrays."""
    tets_digest, modes_digest = body.digests
    if not (tets_digest and modes_digest):
        tets_digest = digest("tets", body.tet_body)
        modes_digest = digest("modes", body.linear_modes)
    return cache.content_key("energy parent", tets_digest, modes_digest)


def _fits_body(body):
    """accept() for an energy cubature: its tets and modal coordinates are the body's."""
    def fits(potential):
        return (potential.tets is not None and len(potential.tets) > 0
                and int(potential.tets.max()) < len(body.tet_body.tets)
                and potential.num_coords == len(body.linear_modes.eigenvalues))
    return fits


def cached_energy(energy, body):
    """The body's energy cubature for EnergyInputs `energy` if it is in memory, else None."""
    parent = energy_parent(body)
    entry = _MEMORY.get(energy.key(parent))
    if entry is None or entry[1] != parent or not _fits_body(body)(entry[0]):
        return None
    return entry[0]


def energy_stage(energy, body, job, modal_rs=None, start=0.0, end=1.0):
    """The reduced potential (`materials.ReducedPotential`) of EnergyInputs `energy` on the
    PreparedBody: from memory, the disk cache, or trained (worker-thread safe; its progress runs
    from `start` to `end`, and a cancel stops the training). modal_rs: optional callable giving
    the body's (E, 9, m) modal RS coordinates, if the caller keeps them; computed otherwise."""
    parent = energy_parent(body)
    X, T = body.tet_body.nodes, body.tet_body.tets
    title = f"{energy.label} energy cubature"

    def compute():
        job.step(start, f"{title}: RS coordinates of the modes")
        stats["energy"] += 1
        Y = modal_rs() if modal_rs is not None else rs.linear_rs(rs.rs_operator(X, T),
                                                                 body.linear_modes.vectors)
        potential, _ = materials.prepare_potential(
            energy.material, Y, np.abs(fem.tet_volumes(X, T)),
            eigenvalues=body.linear_modes.eigenvalues, **ENERGY_TRAINING,
            progress=lambda f, message: job.step(start + (end - start) * f, f"{title}: {message}"))
        return potential

    return _cached_stage(energy, "energy", energy.key(parent), parent, compute, job,
                         _fits_body(body))


def prepare(inputs, job):
    """The three stages, each keyed by the contents of the one before, and the energy stage if
    inputs.energy is set; returns a PreparedBody."""
    tet_body = tet_stage(inputs, job)
    tets_digest = digest("tets", tet_body)
    pins = surface_pins(inputs, tet_body)
    linear_modes = modes_stage(inputs, tet_body, job, tets_digest, pins)
    modes_digest = digest("modes", linear_modes)
    deformer = reduced_stage(inputs, tet_body, linear_modes, job, modes_digest,
                             end=0.99 if inputs.energy is None else 0.9)
    keys = (inputs.tets_key, inputs.modes_key(tets_digest), inputs.reduced_key(modes_digest))
    body = PreparedBody(tet_body, linear_modes, deformer, keys, (tets_digest, modes_digest),
                        pinned_embedding=None if pins is None else pins.embedding)
    if inputs.energy is not None:
        body.energy = energy_stage(inputs.energy, body, job, start=0.9, end=0.99)
        body.energy_key = inputs.energy.key(energy_parent(body))
    job.step(1.0, "Done")
    return body


# --- for the preview and later operators -------------------------------------------------------------

def load_prepared(obj):
    """The PreparedBody the object was last prepared with, or None if it is stale or cannot be
    rebuilt under the same keys.

    The stages are looked up again from the object's current inputs (memory, then files), so
    files that were pruned (an undo brought back an older preparation) are quietly recomputed;
    the result is used only if it lands on exactly the keys the object records.
    """
    settings = obj.rs_elastic
    if not settings.prepared_key or stale_reason(obj, cached=True):
        return None
    try:
        inputs = read_inputs(obj, bpy.context.evaluated_depsgraph_get())
    except InputError:
        return None
    if inputs.tets_key != settings.tets_key:
        return None
    job = Job(None)
    try:
        body = prepare(inputs, job)
    except (InputError, ValueError, RuntimeError) as exc:
        print(f"RS Elastic: could not rebuild '{obj.name}': {exc}")
        return None
    for message in job.warnings:
        print(f"RS Elastic: {message}")
    if body.keys[:2] != (settings.tets_key, settings.prepared_key):
        return None
    if body.keys[2] != settings.reduced_key:
        # Same inputs, but recomputed modes need not be bit-identical (eigensolver signs), so
        # the deformer built on them gets another content key: it is the one to use now.
        settings.reduced_key = body.keys[2]
        settings.reduced_basis_count = body.deformer.basis_size
        settings.cubature_count = len(body.deformer.cubature_tets)
    return body


def _energy_record(settings):
    try:
        record = json.loads(settings.get(ENERGY_RECORD) or "{}")
        return {"parent": str(record.get("parent", "")), "keys": [str(k) for k in record["keys"]]}
    except (ValueError, TypeError, KeyError, AttributeError):
        return {"parent": "", "keys": []}


def record_energy(obj, parent, key=""):
    """Note that the energy cubature `key` was made for the preparation whose energy parent is
    `parent` (main thread). Keys of another preparation are forgotten (and `prune` removes
    their files); `key` "" only starts the record of a new preparation."""
    old = _energy_record(obj.rs_elastic)
    keys = list(old["keys"]) if old["parent"] == parent else []
    if key and key not in keys:
        keys.append(key)
    new = {"parent": parent, "keys": keys}
    if new != old:
        obj.rs_elastic[ENERGY_RECORD] = json.dumps(new)


def energy_ready(obj):
    """Whether Simulate finds the energy cubature of the object's material model without training
    it (in memory or in a cache file of the preparation it records); None for Linear, which
    needs none. Safe in draw: it only hashes the key and looks for the file."""
    energy = energy_inputs(obj)
    if energy is None:
        return None
    parent = _energy_record(obj.rs_elastic)["parent"]
    if not parent:
        return False
    key = energy.key(parent)
    return key in _MEMORY or any(os.path.exists(cache_file(folder, obj.name, "energy", key))
                                 for folder in energy.cache_dirs)


def persist(obj):
    """Make sure the object's prepared stages are in its primary cache folder (after a file is
    saved under a new name its cache moves next to it)."""
    folders = cache_dirs()
    for stage, key in _stage_keys(obj.rs_elastic):
        if not key:
            continue
        target = cache_file(folders[0], obj.name, stage, key)
        if cache.stored_key(target) == key:
            continue
        sources = [cache_file(folder, obj.name, stage, key) for folder in folders[1:]]
        source = next((path for path in sources if cache.stored_key(path) == key), None)
        if source is None:
            continue     # not on disk: rebuilt when next used
        try:
            os.makedirs(folders[0], exist_ok=True)
            shutil.copyfile(source, target)
        except OSError as exc:
            print(f"RS Elastic: could not write the cache {target}: {exc}")


def load_tet_body(obj):
    """The object's tet mesh (nodes and tets only matter to the overlay), or None. Safe in draw."""
    key = obj.rs_elastic.tets_key
    entry = _MEMORY.get(key)
    if entry is not None:
        return entry[0]
    stored = stored_tet_mesh(obj, key)
    if stored is not None:
        return TetBody(stored[0], stored[1], None)
    return _read_file(cache_dirs(), obj.name, "tets", key, "", lambda message: None)


def load_pinned_nodes(obj):
    """(p,) tet nodes the prepared modes hold fixed, or None. Safe in draw (no recomputing)."""
    key = obj.rs_elastic.prepared_key
    entry = _MEMORY.get(key)
    if entry is not None:
        return entry[0].pinned_nodes
    for folder in cache_dirs():
        try:
            arrays = cache.load(cache_file(folder, obj.name, "modes", key), key)
        except cache.CacheCorrupt:
            continue
        pins = None if arrays is None else arrays.get("pinned_nodes")
        if pins is not None and pins.dtype.kind in "iu" and pins.ndim == 1:
            return pins
    return None
