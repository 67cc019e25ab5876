"""The preparation stages' cache: their files on disk, an in-memory copy, and the records kept in
the .blend.

``STAGES`` names every stage once, with the class of its value (``to_arrays()`` /
``from_arrays(arrays)``), the schema of its file and the setting that holds its key; the file
names, the validation on load and `prune` all derive from it.

Each stage is cached in `//blendcache_<blend name>/<object>.<stage>.<key>.npz` (the temp folder
for an unsaved file); a new preparation writes new files beside the old ones, so a cancelled one
leaves the previous cache usable. Every loaded array is validated; on any doubt the file is
rebuilt with one warning.

The tet mesh itself travels with the .blend (`obj.rs_elastic["tet_mesh"]`, with the tets key it
was made for), because fTetWild is deterministic only where its worker can seed it (Linux,
``solver.tetwild_worker``) and may change between builds: re-preparing the same file, in any process
and without the cache folder, reuses it, and only a new surface or new mesher settings replace it.
`obj.rs_elastic["energy_cache"]` records the energy keys made for the current preparation, so
that `prune` keeps and `persist` copies their files.
"""
import collections
import dataclasses
import json
import os
import re
import shutil
import tempfile

import bpy
import numpy as np

from ..solver import cache, materials, modes, reduced
from ..solver.body import TetBody

# How often each stage really ran in this process (the tests read these to prove cache reuse).
stats = collections.Counter()

_MEMORY = collections.OrderedDict()   # cache key -> (value, parent digest)
_MEMORY_LIMIT = 16
_BEFORE_SAVE = []    # the cache folders of the file as it was before the save under way

TET_MESH = "tet_mesh"                 # obj.rs_elastic[TET_MESH]: {"key", "nodes", "tets"}
PREPARED_INPUTS = "prepared_inputs"   # obj.rs_elastic[PREPARED_INPUTS]: the fingerprint at Prepare
ENERGY_RECORD = "energy_cache"        # obj.rs_elastic[ENERGY_RECORD]: {"parent", "keys"} as JSON


def _check_tets(arrays, sizes):
    if (arrays["tets"].min(initial=0) < 0 or arrays["tets"].max(initial=0) >= sizes["N"]
            or tuple(arrays["phi_shape"])[1] != sizes["N"]):
        raise ValueError("tet indices out of range")


def _check_energy(arrays, sizes):
    if arrays["tets"].min(initial=0) < 0 or arrays["weights"].min(initial=0.0) < 0.0:
        raise ValueError("negative tet index or weight")


@dataclasses.dataclass(frozen=True)
class Stage:
    value_type: type        # to_arrays() and the classmethod from_arrays(arrays[, material])
    schema: dict            # what its file must hold; sizes with the same name must agree
    key_setting: str = None     # the settings property holding its key; None: the energy record
    check: object = None        # check(arrays, sizes): ValueError on what the schema cannot say
    takes_material: bool = False    # from_arrays(arrays, material)


STAGES = {
    "tets": Stage(TetBody, {"nodes": ("f", ("N", 3)), "tets": ("iu", ("E", 4)),
                            "phi_data": ("f", ("nnz",)), "phi_indices": ("iu", ("nnz",)),
                            "phi_indptr": ("iu", (None,)), "phi_shape": ("iu", (2,))},
                  "tets_key", _check_tets),
    "modes": Stage(modes.LinearModes, {"eigenvalues": ("f", ("r",)), "vectors": ("f", (None, "r")),
                                       "pinned_nodes": ("iu", (None,))}, "prepared_key"),
    "reduced": Stage(reduced.ReducedRS,
                     {"cubature_tets": ("iu", ("C",)), "cubature_weights": ("f", ("C",)),
                      "projections": ("f", (None, None, None)),
                      "modal_rs_cubature": ("f", (None, None, None)),
                      "linear_map": ("f", (None, None))}, "reduced_key"),
    "energy": Stage(materials.ReducedPotential,
                    {"tets": ("iu", ("C",)), "weights": ("f", ("C",)),
                     "strain_modes": ("f", ("C", 6, None))}, None, _check_energy,
                    takes_material=True),
}


def digest(stage, value):
    """Content hash of a stage's value: what the next stage's key is made of."""
    arrays = value.to_arrays()
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


def is_cached(folders, object_name, stage, key):
    """Whether the stage's value for `key` is in memory or has a file (no loading: for draw)."""
    return key in _MEMORY or any(os.path.exists(cache_file(folder, object_name, stage, key))
                                 for folder in folders)


def _stage_keys(settings):
    """(stage, key) of every stage file the object's preparation uses (keys may be "")."""
    pairs = []
    for stage, entry in STAGES.items():
        keys = ([getattr(settings, entry.key_setting)] if entry.key_setting
                else energy_record(settings)["keys"])
        pairs += [(stage, key) for key in keys]
    return tuple(pairs)


def prune(obj):
    """Delete the object's cache files whose key it no longer uses (in its primary folder).

    An undo can bring back a key whose files are gone: `bodies.load_prepared` then recomputes
    them (the tet mesh is kept in the .blend, so the recomputed stages have the same keys).
    """
    settings = obj.rs_elastic
    keep = {cache_file(cache_dirs()[0], obj.name, stage, key)
            for stage, key in _stage_keys(settings) if key}
    folder = cache_dirs()[0]
    pattern = re.compile(re.escape(_safe_name(obj.name))
                         + r"\.(" + "|".join(STAGES) + r")\.[0-9a-f]+\.npz$")
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


def note_folders_before_save():
    """save_pre: remember where the file's stages are now, for `persist` after the save."""
    _BEFORE_SAVE[:] = cache_dirs()


def persist(obj):
    """Make sure the object's prepared stages are in its primary cache folder (after a file is
    saved under a new name its cache moves next to it: copied from where the file kept it before
    the save, or from the temporary folder)."""
    folders = cache_dirs()
    for stage, key in _stage_keys(obj.rs_elastic):
        if not key:
            continue
        target = cache_file(folders[0], obj.name, stage, key)
        if cache.stored_key(target) == key:
            continue
        sources = [cache_file(folder, obj.name, stage, key)
                   for folder in folders[1:] + _BEFORE_SAVE]
        source = next((path for path in sources if cache.stored_key(path) == key), None)
        if source is None:
            continue     # not on disk: rebuilt when next used
        try:
            os.makedirs(folders[0], exist_ok=True)
            shutil.copyfile(source, target)
        except OSError as exc:
            print(f"RS Elastic: could not write the cache {target}: {exc}")


# --- reading and writing a stage (worker-thread safe: no bpy) -------------------------------------

def _from_arrays(stage, arrays, path, material=None):
    """The stage's value from validated arrays (the energy stage's for `material`); CacheCorrupt
    on any doubt."""
    entry = STAGES[stage]
    sizes = cache.validate(arrays, entry.schema, path)
    try:
        if entry.check is not None:
            entry.check(arrays, sizes)
        return entry.value_type.from_arrays(arrays, *((material,) if entry.takes_material else ()))
    except (KeyError, ValueError, IndexError, TypeError) as exc:
        raise cache.CacheCorrupt(f"cache file {path} is inconsistent ({exc})") from None


def _remember(key, value, parent):
    _MEMORY[key] = (value, parent)
    _MEMORY.move_to_end(key)
    while len(_MEMORY) > _MEMORY_LIMIT:
        _MEMORY.popitem(last=False)


def from_memory(key, parent):
    """The value kept in memory for this key, if it was made from `parent`, else None."""
    entry = _MEMORY.get(key)
    return entry[0] if entry is not None and entry[1] == parent else None


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


def _save(inputs, stage, key, value, parent, job):
    path = cache_file(inputs.cache_dirs[0], inputs.object_name, stage, key)
    try:
        cache.save(path, key, dict(value.to_arrays(), parent_digest=np.array(parent)))
    except OSError as exc:
        job.warn(f"Could not write the cache {path}: {exc}")


def get_or_compute(inputs, stage, key, parent, compute, job, accept=lambda value: True):
    """A stage's value: from memory, else its valid cache file, else compute() (then saved).
    `inputs` names the object and its cache folders (and the material, for the energy stage);
    `parent` is the digest of what it is computed from; `accept` rejects a value on doubt."""
    value = from_memory(key, parent)
    if value is None or not accept(value):
        value = _read_file(inputs.cache_dirs, inputs.object_name, stage, key, parent, job.warn,
                           getattr(inputs, "material", None))
    if value is None or not accept(value):
        value = compute()
        _save(inputs, stage, key, value, parent, job)
    _remember(key, value, parent)
    return value


# --- for the overlay (safe in draw: no recomputing) -----------------------------------------------

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


# --- the records kept in the .blend (main thread) -------------------------------------------------

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


def energy_record(settings):
    """{"parent": energy parent digest of the recorded preparation, "keys": its energy keys}."""
    try:
        record = json.loads(settings.get(ENERGY_RECORD) or "{}")
        return {"parent": str(record.get("parent", "")), "keys": [str(k) for k in record["keys"]]}
    except (ValueError, TypeError, KeyError, AttributeError):
        return {"parent": "", "keys": []}


def record_energy(obj, parent, key=""):
    """Note that the energy cubature `key` was made for the preparation whose energy parent is
    `parent` (main thread). Keys of another preparation are forgotten (and `prune` removes
    their files); `key` "" only starts the record of a new preparation."""
    old = energy_record(obj.rs_elastic)
    keys = list(old["keys"]) if old["parent"] == parent else []
    if key and key not in keys:
        keys.append(key)
    new = {"parent": parent, "keys": keys}
    if new != old:
        obj.rs_elastic[ENERGY_RECORD] = json.dumps(new)
