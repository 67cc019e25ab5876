"""Prepared bodies: the input snapshot (main thread) and the preparation stages (worker thread).

Stage 1 (tets): fTetWild tet mesh of the evaluated mesh + embedding of the base mesh's vertices.
Stage 2 (modes): stiffness, lumped mass and linear modes for the material and pins, at Young's
modulus 1 Pa and density 1 kg/m³ (`preparation.unit_stiffness_modes`); the body's modes are these
moved to its Young's modulus and density (`preparation.modes_at`), so a change of either reuses
stages 2 and 3.
Stage 3 (reduced): the reduced RS basis and its cubature (the deformer every solve evaluates),
of the modes at 1 Pa and 1 kg/m³, moved to the body's density (`preparation.deformer_at`).
Stage 4 (energy, StVK and Fung only): the energy cubature of the material's reduced potential
(`solver.materials.prepare_potential`). Linear needs none (its potential is an exact quadratic
form), so it has no such stage and writes no file.

Keys are content addresses. The tets key hashes the surface and the mesher settings; the modes
key hashes the tet mesh *actually used* (its arrays) with the material but for Young's modulus
and density (Poisson's ratio, a painted one's stiffness group weights and ratio) and pins; the
reduced key hashes the modes' arrays with the reduced settings; the energy key hashes the tets'
and the modes' arrays and a painted body's per-tet stiffness (what the cubature is trained on)
with the material kind, every material parameter it is trained with but Young's modulus and
density (Poisson's ratio, and the stiffening for Fung only) and the training settings: it is
trained at 1 Pa in the coordinates of the modes at 1 kg/m³ and serves every modulus and density
(`preparation.unit_energy_potential`). So stages of
different runs can never mix. Each stage is looked up in memory, then in its cache file
(`stage_cache`), and computed only if neither has it.

A preparation may be told to only load (``cached_only``: the command line's `--only bake`, a
farm's Bake Only): a stage that is neither in memory nor in a cache file is then refused in one
line instead of computed. Embedding the tet mesh kept in the .blend is not refused (cheap, and the
same everywhere).

Whether a preparation still matches its object is `staleness`'s.
"""
import dataclasses
import functools

import bpy
import numpy as np

from ..solver import cache, embed, fem, preparation, proxy, tetmesh
from ..solver.body import PreparedBody
from . import armature, estimates, mesh_cache, scene, stage_cache, stage_rules, staleness
from .jobs import Cancelled, Job
from .scene import InputError

# How the energy cubature is trained; part of its key.
ENERGY_TRAINING = preparation.ENERGY_TRAINING


# --- inputs, read on the main thread --------------------------------------------------------------

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
    mesher_time_limit: float = tetmesh.DEFAULT_TIME_LIMIT   # [s] fTetWild may run (not in a key)
    base_triangles: np.ndarray = None   # (t, 3) triangles of the base mesh (the pin rule reads them)
    pin_weights: np.ndarray = None      # (n,) float32 in [0, 1], None for a free body
    pins_hold_volume: bool = False      # rigged: the Follow Rig group holds the flesh it paints
    stiffness_weights: np.ndarray = None   # (n,) float32 in [0, 1]; None: a uniform material
    stiffness_ratio: float = 1.0        # Young's modulus at weight 0 over that at weight 1
    stored_tets: tuple = None      # (nodes, tets) kept in the .blend for tets_key, or None
    fingerprint: dict = None       # what Prepare read (see `staleness.fingerprint`)
    youngs: float = 0.0
    poisson: float = 0.0
    density: float = 0.0
    num_modes: int = 0
    basis_size: int = 0            # reduced RS: largest basis B
    cubature_tets: int = 0         # reduced RS: largest cubature
    cubature_tolerance: float = 0.0
    training_poses: int = 0
    energy: "EnergyInputs" = None   # set to train the energy cubature too (StVK / Fung)
    cached_only: bool = False      # load what the .blend and its cache hold, compute nothing

    @property
    def meshing(self):
        return preparation.MeshingSettings(self.edge_length, self.envelope, self.proxy_triangles,
                                           self.mesher_time_limit)

    @property
    def reduced_settings(self):
        return preparation.ReducedSettings(self.basis_size, self.cubature_tets,
                                           self.cubature_tolerance, self.training_poses)

    @functools.cached_property
    def tets_key(self):
        return cache.content_key("tets", self.surface_vertices, self.surface_triangles,
                                 self.base_vertices, self.edge_length, self.envelope,
                                 ("proxy", self.proxy_triangles))

    def modes_key(self, tets_digest):
        """Key of the modes (at Young's modulus 1 Pa and density 1 kg/m³) of the tet mesh whose
        arrays hash to tets_digest: neither is in it (``preparation.unit_stiffness_modes``)."""
        pins = (stage_rules.PIN_RULES, self.pin_weights, self.base_triangles,
                self.pins_hold_volume) if self.pin_weights is not None else "free"
        painted = () if self.stiffness_weights is None else (
            (stage_rules.STIFFNESS_RULES, self.stiffness_weights, self.stiffness_ratio),)
        return cache.content_key("modes", stage_rules.MODES_RULES, tets_digest, pins,
                                 self.poisson, self.num_modes, *painted)

    def reduced_key(self, modes_digest):
        return cache.content_key("reduced", stage_rules.REDUCED_RULES, modes_digest,
                                 self.basis_size, self.cubature_tets, self.cubature_tolerance,
                                 self.training_poses)


@dataclasses.dataclass
class EnergyInputs:
    """What the energy stage reads besides the prepared body (a main-thread snapshot)."""
    object_name: str
    cache_dirs: list
    kind: str                  # "STVK" or "FUNG"
    youngs: float              # [Pa] (at weight 1 of a stiffness group)
    poisson: float
    fung_stiffening: float     # dimensionless; only Fung reads it
    material: object = None    # the prepared body's (``for_body``): a cubature is trained for it

    @functools.cached_property
    def parameters(self):
        """The material parameters the cubature depends on (not Young's modulus nor density: it
        is trained at 1 Pa in the modes at 1 kg/m³, ``preparation.unit_energy_potential``;
        Fung's stiffening for Fung only: StVK's cubature does not read it, so changing it
        reuses StVK's file)."""
        stiffening = (self.fung_stiffening,) if self.kind == "FUNG" else ()
        return (stage_rules.ENERGY_RULES, self.poisson) + stiffening

    def for_body(self, body):
        """These inputs with the material of the PreparedBody (its painted stiffness, if any)."""
        return dataclasses.replace(self, material=body.material(
            self.kind, self.youngs, self.poisson, fung_stiffening=self.fung_stiffening))

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
    return EnergyInputs(obj.name, stage_cache.cache_dirs(), settings.material_model,
                        settings.youngs_modulus, settings.poisson_ratio, settings.fung_stiffening)


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
    scene.require_no_copies(obj, depsgraph)
    settings = obj.rs_elastic
    V, F = rest_surface(obj, depsgraph)
    try:
        tetmesh.check_surface(V, F)
    except tetmesh.TetMeshError as exc:
        raise InputError(f"'{obj.name}': {exc}") from None
    inputs = BodyInputs(obj.name, V, F, scene.base_vertices(obj), settings.edge_length,
                        settings.envelope, stage_cache.cache_dirs(),
                        proxy_triangles=settings.proxy_triangles,
                        mesher_time_limit=settings.mesher_time_limit)
    inputs.stored_tets = stage_cache.stored_tet_mesh(obj, inputs.tets_key)
    if not with_material:
        return inputs
    try:
        fem.lame_parameters(settings.youngs_modulus, settings.poisson_ratio)   # a stable material
        if not settings.density > 0.0:
            raise ValueError(f"Density must be positive, got {settings.density:g} kg/m³")
    except ValueError as exc:
        raise InputError(str(exc)) from None
    if settings.stiffness_group:
        inputs.stiffness_weights = _stiffness_weights(obj, settings.stiffness_group)
        inputs.stiffness_ratio = _stiffness_ratio(settings)
    if settings.pin_group:
        weights = _pin_weights(obj, settings.pin_group)
        if weights.all():
            raise InputError(f"Every vertex of '{obj.name}' is in pin group "
                             f"'{settings.pin_group}': nothing is left free to move")
        inputs.pin_weights = weights
        inputs.base_triangles = scene.base_triangles(obj)
        inputs.pins_hold_volume = armature.is_rigged(obj)
    inputs.fingerprint = staleness.fingerprint(obj)
    inputs.youngs = settings.youngs_modulus
    inputs.poisson = settings.poisson_ratio
    inputs.density = settings.density
    inputs.num_modes = settings.num_modes
    inputs.basis_size = settings.basis_size
    inputs.cubature_tets = settings.cubature_tets
    inputs.cubature_tolerance = settings.cubature_tolerance
    inputs.training_poses = settings.training_poses
    return inputs


def _stiffness_weights(obj, group):
    """(n,) float32 weights of the stiffness group in [0, 1] (0 outside it); InputError for a
    group that does not exist or holds a weight that is not a number."""
    weights = scene.stiffness_weights(obj, group)
    if not np.isfinite(weights).all():
        vertex = int(np.flatnonzero(~np.isfinite(weights))[0])
        raise InputError(f"Stiffness group '{group}' has a weight that is not a number (vertex "
                         f"{vertex}): paint it again")
    return np.clip(weights, 0.0, 1.0)


def _stiffness_ratio(settings):
    """The Stiffness Ratio; InputError unless it is above 0 and keeps the softest or stiffest
    part within Young's modulus's limit (not a number is refused with every setting, by
    ``scene.check_settings``)."""
    ratio = settings.stiffness_ratio
    if not ratio > 0.0:
        raise InputError(f"Stiffness ratio must be above 0, got {ratio:g}")
    label, largest, unit = scene.MATERIAL_LIMITS["youngs_modulus"]
    if settings.youngs_modulus * ratio > largest:
        raise InputError(f"Stiffness ratio × {label} must be at most {largest:g} {unit}, got "
                         f"{settings.youngs_modulus * ratio:g} {unit}")
    return float(ratio)


def _pin_weights(obj, group):
    """(n,) float32 weights of the pin group in [0, 1]; InputError for a group that pins nothing
    (no vertex at ``embed.PIN_THRESHOLD`` or more) or holds a weight that is not a number."""
    weights = scene.pin_weights(obj, group)
    if not np.isfinite(weights).all():
        vertex = int(np.flatnonzero(~np.isfinite(weights))[0])
        raise InputError(f"Pin group '{group}' has a weight that is not a number (vertex "
                         f"{vertex}): paint it again")
    weights = np.clip(weights, 0.0, 1.0)
    if not weights.any():
        raise InputError(f"Pin group '{group}' has no vertices; clear Pin Group for a free body")
    threshold = embed.PIN_THRESHOLD
    if not (weights >= threshold).any():
        raise InputError(f"Pin group '{group}' pins nothing: only vertices weighted "
                         f"{threshold:g} or more are pinned, and its largest weight is "
                         f"{weights.max():.2g}; paint the pinned part {threshold:g} or more, or "
                         "clear Pin Group for a free body")
    return weights


# --- the stages (worker-thread safe: no bpy) ------------------------------------------------------

def _refuse_unless_computing(object_name, cached_only, missing):
    """A preparation that may only load stops here, before computing what is `missing` ("its
    linear modes are"), with one line."""
    if cached_only:
        raise InputError(f"'{object_name}' is not prepared: {missing} not in the cache next to "
                         "the .blend, and bake only prepares nothing (prepare it first)")


def proxy_for(inputs, job):
    """(V, F, closed) of the surface fTetWild meshes (``preparation.mesher_surface``); says which
    and how long it should take in the progress. InputError at once, before fTetWild starts, when
    the estimate is over the time limit."""
    V, F, closed = preparation.mesher_surface(inputs.surface_vertices, inputs.surface_triangles,
                                              inputs.meshing, say=job.step)
    limit = inputs.mesher_time_limit
    thinness = proxy.surface_thinness(V, F, inputs.meshing.edge_length)
    seconds = estimates.mesher_seconds(len(F), thinness)
    if seconds > limit:
        raise InputError(estimates.over_limit(inputs.object_name, len(F), closed, limit,
                                              thinness))
    if not closed:
        job.warn(f"'{inputs.object_name}' is not a closed manifold, so fTetWild meshes all "
                 f"{len(F):,} of its triangles (slower)")
    job.step(0.05, f"Tetrahedralising {len(F):,} triangles with fTetWild: roughly "
                   f"{seconds:.0f} s (limit {limit:g} s)")
    return V, F, closed


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
            _refuse_unless_computing(inputs.object_name, inputs.cached_only, "its tet mesh is")
            V, F, closed = proxy_for(inputs, job)
            stage_cache.stats["tetrahedralize"] += 1
            try:
                X, T = preparation.tet_mesh(V, F, inputs.meshing, should_cancel=job.is_cancelled)
            except tetmesh.TetMeshTimeout as exc:
                closed = closed and proxy.is_closed_manifold(F)     # a small surface is not tried
                thinness = proxy.surface_thinness(V, F, inputs.meshing.edge_length)
                raise InputError(estimates.out_of_time(inputs.object_name, len(F), closed,
                                                       exc.limit, thinness)) from None
            except tetmesh.TetMeshError as exc:
                if job.is_cancelled():
                    raise Cancelled() from None
                raise InputError(f"Tetrahedralisation of '{inputs.object_name}' failed: {exc}") from None
        job.step(0.45, "Embedding the mesh in the tets")
        return preparation.embedded(X, T, inputs.base_vertices)

    return stage_cache.get_or_compute(inputs, "tets", inputs.tets_key, "", compute, job,
                                      same_as_stored)


def surface_pins(inputs, tet_body):
    """embed.SurfacePins of the pin group's weights (``preparation.surface_pins``), or None for
    a free body. Cheap next to the modes, and a function of the modes' key: computed again
    rather than cached."""
    if inputs.pin_weights is None:
        return None
    return preparation.surface_pins(tet_body, inputs.base_vertices, inputs.base_triangles,
                                    inputs.pin_weights, inputs.envelope,
                                    holds_volume=inputs.pins_hold_volume)


def stiffness_scale(inputs, tet_body):
    """(E,) the painted stiffness of the tets (``preparation.stiffness_scale``), or None for a
    uniform material. Cheap next to the modes (one sparse solve for the inner nodes), and a
    function of the modes' key: computed again rather than cached."""
    if inputs.stiffness_weights is None:
        return None
    return preparation.stiffness_scale(tet_body, inputs.stiffness_weights, inputs.stiffness_ratio)


def modes_stage(inputs, tet_body, job, tets_digest, pins, scale=None):
    """Linear modes at Young's modulus 1 Pa and density 1 kg/m³ for the pins (``surface_pins``;
    None for a free body) and the rest of the material, a painted body's per-tet stiffness
    ``scale`` (E,) included:
    from memory, the disk cache, or eigsh (``preparation.unit_stiffness_modes``)."""

    def compute():
        _refuse_unless_computing(inputs.object_name, inputs.cached_only, "its linear modes are")
        title = f"Computing {inputs.num_modes} linear modes"
        job.step(0.55, title)
        stage_cache.stats["modes"] += 1
        try:
            return preparation.unit_stiffness_modes(
                tet_body, inputs.poisson, inputs.num_modes,
                None if pins is None else pins.nodes, stiffness_scale=scale,
                progress=lambda f, message: job.step(0.55 + 0.15 * f, f"{title}: {message}"))
        except ValueError as exc:
            raise InputError(f"'{inputs.object_name}': {exc}") from None

    def fits(m):
        return m.vectors.shape[0] == 3 * len(tet_body.nodes)

    return stage_cache.get_or_compute(inputs, "modes", inputs.modes_key(tets_digest), tets_digest,
                                      compute, job, fits)


def reduced_stage(inputs, tet_body, unit_modes, job, modes_digest=None, end=0.99):
    """The reduced RS deformer of the modes at 1 Pa and 1 kg/m³ (``modes_stage``): from memory,
    the disk cache, or basis + cubature training (its progress runs from 0.72 to `end`)."""
    modes_digest = modes_digest or stage_cache.digest("modes", unit_modes)

    def compute():
        _refuse_unless_computing(inputs.object_name, inputs.cached_only,
                                 "its reduced RS deformer is")
        job.step(0.72, "Reduced RS: training poses")
        stage_cache.stats["reduced"] += 1
        return preparation.reduced_deformer(
            tet_body, unit_modes, inputs.reduced_settings,
            progress=lambda f, message: job.step(0.72 + (end - 0.72) * f, f"Reduced RS: {message}"))

    def fits(d):
        return d.basis is None or d.basis.shape[0] == 3 * len(tet_body.nodes)

    return stage_cache.get_or_compute(inputs, "reduced", inputs.reduced_key(modes_digest),
                                      modes_digest, compute, job, fits)


def energy_parent(body):
    """Digest of what a body's energy cubature is trained on: its tets' and its modes' arrays,
    and a painted body's per-tet stiffness."""
    tets_digest, modes_digest = body.digests
    if not (tets_digest and modes_digest):
        tets_digest = stage_cache.digest("tets", body.tet_body)
        modes_digest = stage_cache.digest("modes", body.linear_modes)
    painted = () if body.stiffness_scale is None else (("painted", body.stiffness_scale),)
    return cache.content_key("energy parent", tets_digest, modes_digest, *painted)


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
    potential = stage_cache.from_memory(energy.key(parent), parent)
    if potential is None or not _fits_body(body)(potential):
        return None
    return _at_modulus(potential, energy, body)


def _at_modulus(potential, energy, body):
    """The cached cubature `potential` (at 1 Pa and 1 kg/m³) with the body's material at the
    inputs' Young's modulus, in the body's modal coordinates."""
    return preparation.energy_at(potential, body, energy.kind, energy.youngs, energy.poisson,
                                 energy.fung_stiffening)


def energy_stage(energy, body, job, start=0.0, end=1.0, cached_only=False):
    """The reduced potential (`materials.ReducedPotential`) of EnergyInputs `energy` on the
    PreparedBody: from memory, the disk cache, or trained unless `cached_only` (worker-thread
    safe; its progress runs from `start` to `end`, and a cancel stops the training)."""
    parent = energy_parent(body)
    title = f"{energy.label} energy cubature"
    energy = energy.for_body(body)

    def compute():
        _refuse_unless_computing(energy.object_name, cached_only, f"its {title} is")
        job.step(start, f"{title}: RS coordinates of the modes")
        stage_cache.stats["energy"] += 1
        return preparation.unit_energy_potential(
            body, energy.kind, energy.poisson, energy.fung_stiffening,
            progress=lambda f, message: job.step(start + (end - start) * f, f"{title}: {message}"))

    potential = stage_cache.get_or_compute(energy, "energy", energy.key(parent), parent, compute,
                                           job, _fits_body(body))
    return _at_modulus(potential, energy, body)


def prepare(inputs, job):
    """The three stages, each keyed by the contents of the one before, and the energy stage if
    inputs.energy is set; returns a PreparedBody."""
    tet_body = tet_stage(inputs, job)
    tets_digest = stage_cache.digest("tets", tet_body)
    pins = surface_pins(inputs, tet_body)
    scale = stiffness_scale(inputs, tet_body)
    unit_modes = modes_stage(inputs, tet_body, job, tets_digest, pins, scale)
    modes_digest = stage_cache.digest("modes", unit_modes)
    unit_deformer = reduced_stage(inputs, tet_body, unit_modes, job, modes_digest,
                                  end=0.99 if inputs.energy is None else 0.9)
    keys = (inputs.tets_key, inputs.modes_key(tets_digest), inputs.reduced_key(modes_digest))
    try:
        linear_modes = preparation.modes_at(unit_modes, inputs.youngs, inputs.density)
        deformer = preparation.deformer_at(unit_deformer, inputs.density)
    except ValueError as exc:
        raise InputError(f"'{inputs.object_name}': {exc}") from None
    body = PreparedBody(tet_body, linear_modes, deformer, keys, (tets_digest, modes_digest),
                        pinned_embedding=None if pins is None else pins.embedding,
                        stiffness_scale=scale, unit_modes=unit_modes, density=inputs.density)
    if inputs.energy is not None:
        body.energy = energy_stage(inputs.energy, body, job, start=0.9, end=0.99,
                                   cached_only=inputs.cached_only)
        body.energy_key = inputs.energy.key(energy_parent(body))
    job.step(1.0, "Done")
    return body


# --- for the preview and later operators ----------------------------------------------------------

def load_prepared(obj):
    """The PreparedBody the object was last prepared with, or None if it is stale or cannot be
    rebuilt under the same keys.

    The stages are looked up again from the object's current inputs (memory, then files), so
    files that were pruned (an undo brought back an older preparation) are quietly recomputed;
    the result is used only if it lands on exactly the keys the object records.
    """
    settings = obj.rs_elastic
    if not settings.prepared_key or staleness.stale_reason(obj, cached=True):
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


def energy_ready(obj):
    """Whether Simulate finds the energy cubature of the object's material model without training
    it (in memory or in a cache file of the preparation it records); None for Linear, which
    needs none. Safe in draw: it only hashes the key and looks for the file."""
    energy = energy_inputs(obj)
    if energy is None:
        return None
    parent = stage_cache.energy_record(obj.rs_elastic)["parent"]
    if not parent:
        return False
    return stage_cache.is_cached(energy.cache_dirs, obj.name, "energy", energy.key(parent))

