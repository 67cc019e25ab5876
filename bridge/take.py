"""A take from any animation, the material fitted to it, and its motion continued (the scene
side of ``solver.take``).

Take from Animation reads the *evaluated* mesh of the take source (the body itself or
``take_source``) on every frame of the scene's range, so whatever animates it counts: shape-key
animation, Mesh Cache, MeshSequenceCache, Armature, Lattice, Hook, Soft Body and Cloth bakes.
The poses land where Keep Bake as Take puts a take (``bake.write_take``), so the space-time
editor reads them as it reads a kept bake. Reading the body itself, the extension's own bake
(its keys, its Mesh Cache modifier) and preview are muted: they are output, not input.

Take from Animation and Fit Material can take seconds: each reads the scene on the main thread
(``gather_take`` frame by frame, a generator that the UI runs on timer ticks with progress and
Esc; ``gather_fit``), works on a worker thread with progress and Esc (``jobs``:
``take_residuals``, ``fit_work``) and writes the result on the main thread (``store_take``,
``keep_fitted``); in background mode the same runs synchronously.

The fitted material lives in the .blend as an ID property on the object (``FITTED``, a plain
dict of ``solver.take.FittedMaterial``), so it survives save, reopen and undo.
"""
import contextlib
import dataclasses

import bpy
import numpy as np
import scipy.spatial

from ..solver import spacetime
from ..solver import take as solver_take
from . import bake, jobs, mesh_cache, prepared, scene
from .scene import InputError

FITTED = "rs_elastic_fitted_material"   # ID property on the object: the fitted material


def take_source(obj):
    """The object whose motion becomes the take: ``take_source``, or the body itself."""
    return obj.rs_elastic.take_source or obj


def scene_frames(blender_scene):
    """The scene's frame range as a list; InputError for fewer than 3 or too many frames."""
    start, end = blender_scene.frame_start, blender_scene.frame_end
    if not 3 <= end - start + 1 <= scene.MAX_FRAMES:
        raise InputError(f"The scene's frame range {start}–{end} must have 3 to "
                         f"{scene.MAX_FRAMES} frames to be a take")
    return list(range(start, end + 1))


@contextlib.contextmanager
def own_output_muted(obj):
    """While inside, the extension's bake and preview keys and its bake modifier do not act on
    ``obj``; their settings are put back on the way out."""
    blocks = bake.owned_keys(obj, "bake") + bake.owned_keys(obj, "preview")
    saved = [block.mute for block in blocks]
    for block in blocks:
        block.mute = True
    try:
        with mesh_cache.muted(obj):
            yield
    finally:
        for block, mute in zip(blocks, saved):
            block.mute = mute


def _edges(mesh):
    edges = np.empty(len(mesh.edges) * 2, dtype=np.int64)
    mesh.edges.foreach_get("vertices", edges)
    edges = np.sort(edges.reshape(-1, 2), axis=1)
    return edges[np.lexsort(edges.T[::-1])]


def require_same_vertices(obj, source, first_pose):
    """InputError (one line) unless the source's evaluated first pose (n', 3) has the body's
    vertices in the body's order: the same count, and either the same edges or every posed
    vertex nearest its own rest vertex."""
    n = len(obj.data.vertices)
    if len(first_pose) != n:
        raise InputError(f"'{source.name}' has {len(first_pose)} vertices, '{obj.name}' {n}: a "
                         "take source must have the same vertices in the same order")
    if source is obj or np.array_equal(_edges(source.data), _edges(obj.data)):
        return
    nearest = scipy.spatial.cKDTree(scene.base_vertices(obj)).query(first_pose)[1]
    if np.any(nearest != np.arange(n)):
        raise InputError(f"'{source.name}' has the vertex count of '{obj.name}' but not its "
                         "vertex order (its edges differ and its vertices are not nearest their "
                         "own): a take source must have the same vertices in the same order")


def _evaluated_positions(source, depsgraph):
    evaluated = source.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    try:
        co = np.empty(len(mesh.vertices) * 3, dtype=np.float64)
        mesh.vertices.foreach_get("co", co)
    finally:
        evaluated.to_mesh_clear()
    return co.reshape(-1, 3)


READ_SHARE = 0.5     # of Take from Animation's progress bar: reading the frames (then the fit)


def read_motion(blender_scene, obj, source, frames):
    """A generator reading (F, n, 3) the source's evaluated vertex positions [its object space]
    on ``frames``, one frame per step: it yields (fraction, message) after each and returns the
    positions, checked against the body's vertices. The scene's current frame is put back when
    it ends, fails or is closed (``jobs``: Esc). Main thread."""
    current = blender_scene.frame_current
    muting = own_output_muted(obj) if source is obj else contextlib.nullcontext()
    poses = []
    try:
        with muting:
            for index, frame in enumerate(frames):
                blender_scene.frame_set(frame)
                pose = _evaluated_positions(source, bpy.context.evaluated_depsgraph_get())
                if not poses:
                    require_same_vertices(obj, source, pose)
                elif len(pose) != len(poses[0]):
                    raise InputError(f"'{source.name}' changes its vertex count on frame "
                                     f"{frame}: a take needs the same vertices on every frame")
                poses.append(pose)
                yield (READ_SHARE * (index + 1) / len(frames),
                       f"reading frame {index + 1} of {len(frames)}")
    finally:
        blender_scene.frame_set(current)
    poses = np.array(poses)
    if not np.isfinite(poses).all():
        raise InputError(f"'{source.name}' has positions that are not finite numbers")
    return poses


@dataclasses.dataclass
class TakeInputs:
    """What Take from Animation read on the main thread: the source's motion, checked."""
    object_name: str
    source_name: str
    frames: list
    poses: np.ndarray           # (F, n, 3) [object space]
    body: object                # PreparedBody
    rest: np.ndarray            # (n, 3) base vertices at rest


def gather_take(context, obj):
    """Main thread: validate the body (InputError), then return a generator that reads its take
    source's motion over the scene's range frame by frame (``read_motion``) and returns the
    ``TakeInputs``."""
    scene.require_body(obj)
    bake.require_writable(obj, "store a take")
    body = prepared.require(obj)
    frames = scene_frames(context.scene)
    return _read_take(context.scene, obj, take_source(obj), frames, body)


def _read_take(blender_scene, obj, source, frames, body):
    poses = yield from read_motion(blender_scene, obj, source, frames)
    return TakeInputs(obj.name, source.name, frames, poses, body, scene.base_vertices(obj))


def _frame_progress(job, count, start, end, what):
    """step(i) for ``solver.take.take_to_modal``: the job's fraction from start to end."""
    def step(index):
        job.step(start + (end - start) * (index + 1) / count,
                 f"{what} frame {index + 1} of {count}")
    return step


def take_residuals(inputs, job):
    """Worker thread: (F,) [m] how far the modes' fit misses each of the take's frames."""
    step = _frame_progress(job, len(inputs.frames), READ_SHARE, 0.95, "fitting the modes to")
    _, residuals = solver_take.take_to_modal(inputs.body, inputs.rest, inputs.poses, step=step)
    return residuals


def store_take(obj, inputs):
    """Main thread: the read motion becomes the body's take, which the editor then uses."""
    bake.write_take(obj, inputs.frames, inputs.poses)
    obj.rs_elastic.use_take = True


# --- the fitted material ----------------------------------------------------------------------

def fitted_material(obj):
    """The object's ``FittedMaterial``, or None if it has none."""
    data = obj.get(FITTED)
    return None if data is None else solver_take.FittedMaterial.from_dict(data.to_dict())


def _fit_range(obj, take_frames):
    """The take frames (consecutive) Fit Material fits."""
    settings = obj.rs_elastic
    start, end = settings.fit_frame_start, settings.fit_frame_end
    if end <= 0 or end < start:
        start, end = take_frames[0], take_frames[-1]
    chosen = [f for f in take_frames if start <= f <= end]
    if len(chosen) < 3 or chosen[-1] - chosen[0] + 1 != len(chosen):
        raise InputError(f"'{obj.name}': the fit range {start}–{end} holds "
                         f"{len(chosen)} take frames; it needs at least 3, with none missing")
    return chosen


@dataclasses.dataclass
class FitInputs:
    """What Fit Material read on the main thread: the take's frames in the fit range."""
    object_name: str
    body: object                # PreparedBody
    rest: np.ndarray            # (n, 3) base vertices at rest
    frames: list                # consecutive scene frames
    poses: np.ndarray           # (k, n, 3) the take's poses on them [object space]
    h: float                    # [s] per frame
    damping_mass: float
    damping_stiffness: float
    material_freedom: float


def gather_fit(obj, blender_scene):
    """Main thread: validate the body and read the take's frames in the fit range. Raises
    InputError."""
    scene.require_body(obj)
    body = prepared.require(obj)
    take_frames, take_poses = bake.take_poses(obj)
    if not take_frames:
        raise InputError(f"'{obj.name}' has no take: Take from Animation, or bake and Keep Bake "
                         "as Take")
    frames = _fit_range(obj, take_frames)
    poses = take_poses[[take_frames.index(f) for f in frames]]
    settings = obj.rs_elastic
    return FitInputs(obj.name, body, scene.base_vertices(obj), frames, poses,
                     scene.frame_interval(blender_scene), settings.damping_mass,
                     settings.damping_stiffness, settings.material_freedom)


# Share of a fit's progress bar taken by the take's modal coordinates (the rest: the solve).
FIT_READING = 0.3
FIT_ROUNDS = 20         # material rounds of a fit (``solver.take.fit_material``'s default)


def fit_work(inputs, job):
    """Worker thread: the ``FittedMaterial`` of the take's frames; ``jobs.Cancelled`` on Esc."""
    step = _frame_progress(job, len(inputs.frames), 0.0, FIT_READING, "reading the take's")

    def progress(iteration, objective):
        job.step(min(0.95, FIT_READING + (1.0 - FIT_READING) * iteration / FIT_ROUNDS),
                 f"round {iteration}, objective {objective:.4g}")

    modal, _ = solver_take.take_to_modal(inputs.body, inputs.rest, inputs.poses, step=step)
    try:
        return solver_take.fit_material(
            inputs.body, inputs.rest, inputs.frames, inputs.poses, modal, inputs.h,
            inputs.damping_mass, inputs.damping_stiffness,
            material_freedom=inputs.material_freedom, iterations=FIT_ROUNDS, callback=progress,
            should_cancel=job.is_cancelled)
    except spacetime.SolveCancelled:
        raise jobs.Cancelled() from None


def keep_fitted(obj, fitted):
    """Main thread: keep the ``FittedMaterial`` on the object (in the .blend, undone with it)."""
    obj[FITTED] = fitted.to_dict()


def require_fitted(obj, body):
    """The object's ``FittedMaterial`` for its prepared ``body``; InputError if it has none, or
    one of an earlier preparation."""
    fitted = fitted_material(obj)
    if fitted is None:
        raise InputError(f"'{obj.name}' has no fitted material: run Fit Material first")
    if fitted.sampling.shape[0] != body.deformer.num_coords:
        raise InputError(f"'{obj.name}' was prepared again since Fit Material: fit again")
    return fitted


def simulated_material(obj, body, potential, settings):
    """(potential, ``problems.SimulationSettings``) of a simulation: as given, or with Use
    Fitted Material the fitted stiffness on the potential and the Rayleigh damping nearest the
    fitted damping (``solver.take``)."""
    if not obj.rs_elastic.use_fitted_material:
        return potential, settings
    fitted = require_fitted(obj, body)
    alpha, beta = solver_take.fitted_rayleigh(fitted)
    return (solver_take.FittedPotential(potential, fitted),
            dataclasses.replace(settings, damping_mass=alpha, damping_stiffness=beta))


def continue_motion(obj, frame_end):
    """Bake the fitted material's free motion from the fit's last frame to ``frame_end``
    (the frames after the fit; the take's keys are untouched). Returns the baked frames."""
    scene.require_body(obj)
    bake.require_target(obj)
    fitted = fitted_material(obj)
    if fitted is None:
        raise InputError(f"'{obj.name}' has no fitted material: run Fit Material first")
    if frame_end <= fitted.last_frame:
        raise InputError(f"Continue to frame {frame_end}: it must come after the fit's last "
                         f"frame {fitted.last_frame}")
    if frame_end - fitted.last_frame > scene.MAX_FRAMES:
        raise InputError(f"Continue to frame {frame_end}: more than {scene.MAX_FRAMES} frames "
                         "after the fit")
    body = prepared.require(obj)
    fitted = require_fitted(obj, body)
    frames = list(range(fitted.last_frame + 1, frame_end + 1))
    rest = scene.base_vertices(obj)
    positions = body.surface_positions(rest, solver_take.continue_motion(fitted, len(frames)))
    bake.check_poses(obj.name, rest, positions)
    bake.write_bake(obj, frames, positions)
    return frames
