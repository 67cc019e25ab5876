"""Gather a space-time edit from the scene (main thread) into the solver's problem, and run it
(worker thread)."""
import dataclasses

import numpy as np

from ..solver import accuracy, problems, spacetime
from ..solver.body import PreparedBody
from . import armature, bake, constraints, prepared, scene, take
from .jobs import Cancelled
from .scene import InputError


@dataclasses.dataclass
class SpaceTimeJob:
    object_name: str
    frames: list                 # scene frames, ascending
    problem: spacetime.SpaceTimeProblem
    optimise_material: bool
    iterations: int              # most solver steps (None: the solver's own limits)
    body: PreparedBody
    rest: np.ndarray             # (n, 3) base vertices
    track_slices: list           # per handle track: (handle index in settings, slice of constraints)
    track_names: list            # per handle track: its Empty's name (for messages)
    stretch_demands: list        # per handle track: (stretch its targets demand, scene frame)
    world_scale: float           # the object's mean world scale (residuals in world metres)
    warnings: list
    exact_handles: bool = False  # meet the handles by the method of multipliers (a rig: gather)


# Last solve's (converged, sentence) per object name, for the panel and the command line; set by
# the worker (plain Python, no bpy), lost with the session like the job itself.
LAST_STATUS = {}

# Handle weight factor on a rig. The handles must also outweigh the rig's loads, which move the
# flesh far from rest: at the default tightness a creature's ear missed its Empty by 1.4 cm, at
# 100 times that by 2e-9 m (tests/blender/test_rig.py). Even so, on some tet meshes Gauss-Newton
# crept along the stiff valley and stopped 1e-5 to 2e-3 of the diagonal short, so a rig also
# meets its handles by the method of multipliers (spacetime.solve exact_handles): on 9 creature
# meshes 7 misses fell to 1e-7 or less, one to 1e-5 and one stalled at 3e-3.
RIG_TIGHTNESS = 100.0


def status_sentence(result):
    """(converged, one line) of a ``SpaceTimeResult`` for the panel and the command line."""
    if result.converged:
        said = "" if result.reason in ("", "converged") else f" ({result.reason})"
        return True, f"Solve converged{said}"
    return False, f"Solve did not converge: {result.reason}"


def settings_of(obj, blender_scene):
    """The body's space-time settings as a ``problems.SpaceTimeSettings``."""
    settings = obj.rs_elastic
    fitted = None
    if settings.use_fitted_material:
        fitted = take.fitted_material(obj)
        if fitted is None:
            raise InputError(f"'{obj.name}' has no fitted material: run Fit Material, or untick "
                             "Use Fitted Material")
    return problems.SpaceTimeSettings(
        h=scene.frame_interval(blender_scene), damping_mass=settings.damping_mass,
        damping_stiffness=settings.damping_stiffness, tightness=settings.tightness,
        optimize_material=settings.optimize_material,
        material_freedom=settings.material_freedom, take_weight=settings.take_weight,
        fitted=fitted)


def _take(obj, warnings):
    """(frames, poses) of the kept take when the edit follows it, else None. A Take Weight of 0
    means the take is not followed (said in `warnings`)."""
    if not obj.rs_elastic.use_take:
        return None
    if obj.rs_elastic.take_weight == 0.0:
        warnings.append("Take Weight is 0, so the take is not followed")
        return None
    take_frames, take = bake.take_poses(obj)
    if not take_frames:
        raise InputError(f"'{obj.name}' has no take: bake, then Keep Bake as Take")
    return take_frames, take


def gather(obj, blender_scene):
    """Validate and collect everything the solve needs. Raises InputError."""
    scene.require_body(obj)
    bake.require_target(obj)
    body = prepared.require(obj)
    settings = settings_of(obj, blender_scene)
    frames = scene.frame_range(obj, blender_scene)
    rest = scene.base_vertices(obj)
    tracks, warnings = constraints.read_handles(obj, blender_scene, frames)
    tracks = _movable(body, tracks, warnings)
    pose_keys = [(frame, scene.shape_key_positions(obj, name))
                 for frame, name in constraints.read_pose_keys(obj, frames)]
    take = _take(obj, warnings)
    external = None
    if armature.is_rigged(obj):   # the edit is a deviation from the rig, in the rest pose
        tracks = _rig_tracks(obj, blender_scene, body, frames, tracks, warnings)
        load = armature.rig_load(obj, blender_scene, body, frames, settings.h,
                                 scene.scene_gravity(blender_scene),
                                 body.lumped_masses(obj.rs_elastic.density))
        external = load.modal_forces       # what the bones' motion and gravity do to the flesh
        settings.handle_gamma_factor = RIG_TIGHTNESS
    try:
        setup = problems.spacetime_problem(body, rest, frames, tracks, pose_keys, take,
                                           settings, external_forces=external)
    except problems.NothingToSolve:
        raise InputError(f"Nothing to solve for on '{obj.name}': key a handle's Empty, key a "
                         "shape key to 1 on a frame, or edit a take"
                         + (f" ({'; '.join(warnings)})" if warnings else "")) from None
    except ValueError as exc:
        raise InputError(f"'{obj.name}': {exc}") from None
    handle_index = {h.empty.name: i for i, h in enumerate(obj.rs_elastic.handles)
                    if h.empty is not None}
    return SpaceTimeJob(obj.name, frames, setup.problem, settings.optimize_material,
                        obj.rs_elastic.iterations or None, body, rest,
                        [(handle_index[t.name], rows) for t, rows in zip(tracks, setup.track_slices)],
                        [track.name for track in tracks],
                        problems.handle_stretch_demands(body, setup.rest_centroids, tracks),
                        world_scale(obj), warnings + setup.warnings,
                        exact_handles=external is not None)


def _movable(body, tracks, warnings):
    """The tracks whose vertices the body can move; a handle on pinned vertices alone is left
    out (said in `warnings`): nothing can move it, and its constraint rows are zero."""
    rows = body.surface_basis.reshape(-1, 3, body.surface_basis.shape[1])
    movable = [bool(np.any(rows[track.vertices])) for track in tracks]
    warnings += [f"Handle '{track.name}': all its vertices are pinned, so nothing can move it; "
                 "ignored" for track, moves in zip(tracks, movable) if not moves]
    return [track for track, moves in zip(tracks, movable) if moves]


def world_scale(obj):
    """The object's mean world scale, positive (a mirrored object's too): handle residuals are
    reported in world metres, and a mirror changes no length."""
    return float(np.mean(np.abs(obj.matrix_world.to_scale())))


def _rig_tracks(obj, blender_scene, body, frames, tracks, warnings):
    """Checks for an edit of a rigged body, and its handle targets in the rest pose."""
    armature.require_follow_group(obj, len(body.pinned_nodes) > 0)
    if obj.rs_elastic.optimize_material:
        raise InputError(f"'{obj.name}' is rigged: material optimisation is not available on a "
                         "rig yet; untick Optimize Material")
    warnings += armature.warnings_for(obj)
    warnings += [f"Handle '{track.name}': orientation is not followed on a rigged body; only "
                 "its position is" for track in tracks if track.rotations is not None]
    return armature.rest_targets(obj, blender_scene, frames, tracks)


def solve(job_inputs, job):
    """Worker thread: run the solver and turn its result into render-vertex poses."""
    try:
        result = spacetime.solve(job_inputs.problem, optimise_material=job_inputs.optimise_material,
                                 iterations=job_inputs.iterations, progress=job.step,
                                 should_cancel=job.is_cancelled,
                                 exact_handles=job_inputs.exact_handles)
    except spacetime.SolveCancelled:
        raise Cancelled() from None
    LAST_STATUS[job_inputs.object_name] = status_sentence(result)
    if not result.converged:            # reported with the other warnings when the bake is applied
        job_inputs.warnings.append(status_sentence(result)[1])
    poses = job_inputs.body.surface_positions(job_inputs.rest, result.inputs)
    bake.check_poses(job_inputs.object_name, job_inputs.rest, poses)
    job_inputs.warnings.extend(post_solve_checks(job_inputs, result))
    return result, poses


STRETCH_REPORTED = 0.05  # stretch (fraction) from which a handle's targets are reported


def post_solve_checks(job_inputs, result, frames=4):
    """Sentences for the user after a solve (worker thread, no bpy).

    - Is the reduced model off? ``accuracy.reduced_error`` on ``frames`` telling frames, against
      full RS; warned above ``accuracy.REDUCED_ERROR_TOLERANCE`` = 1 % of the body's diagonal.
    - Which handles ask the body to stretch? Their targets' demand (``problems.handle_stretch_demands``),
      reported from ``STRETCH_REPORTED`` = 5 % with the handle's residual. (The solved RS
      strain is no guide: on a cow bent at constant volume it reached 39 % in a few tets.)
    """
    body, Z = job_inputs.body, result.inputs
    modal_rs = body.modal_rs[:, :, :Z.shape[1]]
    out = []
    picked = accuracy.telling_frames(modal_rs, Z, frames)
    if getattr(body.deformer, "basis", None) is not None:
        errors = accuracy.reduced_error(body.deformer, body.reconstruction, modal_rs,
                                        Z[picked], body.nodes)
        worst = int(np.argmax(errors))
        if errors[worst] > accuracy.REDUCED_ERROR_TOLERANCE:
            out.append(f"The reduced model is off full RS by {100 * errors[worst]:.1f} % of the "
                       f"body's size on frame {job_inputs.frames[picked[worst]]}: the edit "
                       "left its training range; more modes or a larger Basis Size / Cubature "
                       "Tets would follow it better")
    for (_, rows), name, (demand, frame) in zip(job_inputs.track_slices, job_inputs.track_names,
                                                job_inputs.stretch_demands):
        if demand > STRETCH_REPORTED:
            residual = job_inputs.world_scale * float(result.handle_residuals[rows].max())
            out.append(f"Handle '{name}' asks the body to stretch by at least "
                       f"{100 * demand:.0f} % on frame {frame} (residual {residual:.3g} m): its "
                       "target is farther than bending can reach")
    return out
