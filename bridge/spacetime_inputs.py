"""Gather a space-time edit from the scene (main thread) into solver arrays."""
import dataclasses

import numpy as np

from ..solver import accuracy, rs, spacetime
from . import armature, bake, constraints, rs_tools, scene, staleness
from .scene import InputError


@dataclasses.dataclass
class SpaceTimeJob:
    object_name: str
    frames: list                 # scene frames, ascending
    problem: spacetime.SpaceTimeProblem
    optimise_material: bool
    iterations: int
    tools: rs_tools.RSTools
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

RIG_TIGHTNESS = 100.0   # handle weight factor on a rig (see gather)
MAX_FRAMES = 10000   # a bake is one shape key per frame: beyond this it is not usable


def frame_range(obj, blender_scene):
    settings = obj.rs_elastic
    if settings.use_scene_range:
        start, end = blender_scene.frame_start, blender_scene.frame_end
    else:
        start, end = settings.frame_start, settings.frame_end
    if end - start + 1 < 3:
        raise InputError(f"The frame range {start}–{end} has fewer than 3 frames")
    if end - start + 1 > MAX_FRAMES:
        raise InputError(f"The frame range {start}–{end} has more than {MAX_FRAMES} frames")
    return list(range(start, end + 1))


def optimised_modes(candidates):
    """How many modes material optimisation optimises out of ``candidates`` prepared ones.

    [L14]'s sampling matrix S (candidates x optimised) chooses which combinations of the
    candidate modes matter; with as many optimised modes as candidates it could only mix them.
    Two thirds keep most of the edit's freedom while leaving S a third of the modes to pick from.
    """
    return max(1, -(-2 * candidates // 3)) if candidates > 1 else candidates


def status_sentence(result):
    """(converged, one line) of a ``SpaceTimeResult`` for the panel and the command line."""
    if result.converged:
        return True, f"Solve converged ({result.reason})"
    return False, f"Solve did not converge: {result.reason}"


def prepared_tools(obj):
    staleness.require_current(obj)      # says what changed since Prepare Body
    tools = rs_tools.for_object(obj)
    if tools is None or tools.deformer is None:
        raise InputError(f"'{obj.name}' is not prepared for its current mesh: run Prepare Body")
    return tools


def poses_to_modal(tools, points_per_pose):
    """ẑ (k, m) of render-vertex poses (k, n, 3): carried to the nodes, turned into RS
    coordinates (each pose's rotation branch chained to the previous one) and fitted."""
    X, T = tools.nodes, tools.tets
    volumes = tools.volumes
    reference, fitted = None, []
    for points in points_per_pose:
        nodes = tools.pose_transfer.nodes_from_points(points)
        y, _ = rs.pose_to_rs(X, T, nodes, reference=reference, neighbours=tools.neighbours)
        fitted.append(spacetime.pose_to_modal(tools.modal_rs, volumes, y))
        reference = y[:, :3]
    return np.array(fitted).reshape(len(fitted), -1)


POSE_SAMPLES = 32   # vertices per pose key that must reach the sculpted positions


def spread_sample(points, count):
    """Indices of `count` points spread over the set (farthest-point sampling)."""
    count = min(count, len(points))
    chosen = [int(np.argmax(np.linalg.norm(points - points.mean(axis=0), axis=1)))]
    distance = np.linalg.norm(points - points[chosen[0]], axis=1)
    for _ in range(count - 1):
        chosen.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return np.array(chosen)


def _key_positions(obj, name):
    block = obj.data.shape_keys.key_blocks[name]
    co = np.empty(len(block.data) * 3)
    block.data.foreach_get("co", co)
    return co.reshape(-1, 3)


def gather(obj, blender_scene):
    """Validate and collect everything the solve needs. Raises InputError."""
    scene.require_body(obj)
    bake.require_target(obj)
    tools = prepared_tools(obj)
    settings = obj.rs_elastic
    frames = frame_range(obj, blender_scene)
    first = frames[0]
    rest = scene.base_vertices(obj)
    tracks, warnings = constraints.read_handles(obj, blender_scene, frames)
    rigged = armature.is_rigged(obj)
    if rigged:                 # the edit is a deviation from the rig, in the rest pose
        tracks = _rig_tracks(obj, blender_scene, tools, frames, tracks, warnings)

    handle_parts, track_slices, rest_centroids, count = [], [], [], 0
    handle_index = {h.empty.name: i for i, h in enumerate(settings.handles) if h.empty is not None}
    for track in tracks:
        rows, rest_centroid = spacetime.handle_geometry(rest, tools.surface_basis, track.vertices)
        rest_centroids.append(rest_centroid)
        c = len(track.frames)
        handle_parts.append((track.frames - first, np.repeat(rows[None], c, axis=0),
                             np.repeat(rest_centroid[None], c, axis=0), track.targets,
                             np.full(c, track.weight)))
        if track.rotations is not None:     # Orientation: spokes of the same vertices
            try:
                spoke_rows, spokes = spacetime.orientation_geometry(rest, tools.surface_basis,
                                                                    track.vertices)
            except ValueError:
                warnings.append(f"Handle '{track.name}': its vertices lie on a line, so they "
                                "have no orientation to follow; only its position is used")
            else:
                part = spacetime.orientation_constraints(track.rotation_frames - first,
                                                         track.rotations, spoke_rows, spokes,
                                                         track.weight)
                handle_parts.append(part)
                c += len(part[0])
        track_slices.append((handle_index[track.name], slice(count, count + c)))
        count += c

    # A pose key is met as positions of a spread sample of vertices: a sculpted pose need not be
    # one the modes' RS coordinates can fit, and what the animator sees is the positions.
    samples = spread_sample(rest, POSE_SAMPLES)
    sample_rows = tools.surface_basis.reshape(len(rest), 3, -1)[samples]         # (s, 3, rB)
    for frame, name in constraints.read_pose_keys(obj, frames):
        target = _key_positions(obj, name)[samples]
        handle_parts.append((np.full(len(samples), frame - first), sample_rows, rest[samples],
                             target, np.full(len(samples), 1.0 / len(samples))))
    key_frames, key_poses = [], []
    if settings.use_take:
        take_frames, take = bake.take_poses(obj)
        if not take_frames:
            raise InputError(f"'{obj.name}' has no take: bake, then Keep Bake as Take")
        inside = [i for i, f in enumerate(take_frames) if frames[0] <= f <= frames[-1]]
        key_frames += [take_frames[i] for i in inside]
        key_poses += [take[i] for i in inside]
    if not handle_parts and not key_frames:
        raise InputError(f"Nothing to solve for on '{obj.name}': key a handle's Empty, key a "
                         "shape key to 1 on a frame, or edit a take"
                         + (f" ({'; '.join(warnings)})" if warnings else ""))

    modes = tools.body.linear_modes
    candidates = tools.deformer.num_coords
    optimised = optimised_modes(candidates) if settings.optimize_material else candidates
    eigenvalues = modes.eigenvalues[:optimised]      # S = [I; 0] (candidates x optimised)
    damping = spacetime.rayleigh_damping(eigenvalues, settings.damping_mass,
                                         settings.damping_stiffness)
    h = blender_scene.render.fps_base / blender_scene.render.fps
    handles = None
    if handle_parts:
        handles = spacetime.HandleConstraints(*(np.concatenate(parts)
                                                for parts in zip(*handle_parts)))
    gamma, keyframe_weight = spacetime.suggest_weights(
        h, eigenvalues, damping, tools.deformer,
        None if handles is None else handles.rows, tightness=settings.tightness)
    keyframes = None
    if key_frames:      # the take's frames, fitted in RS coordinates (they are physical poses)
        keyframes = spacetime.Keyframes(np.array(key_frames) - first,
                                        poses_to_modal(tools, key_poses),
                                        np.full(len(key_frames), keyframe_weight * settings.take_weight))
    external = None
    if rigged:                 # what the bones' motion and gravity do to the flesh
        # The handles must also outweigh the rig's loads, which move the flesh far from rest:
        # at the default tightness a creature's ear missed its Empty by 1.4 cm, at 100 times
        # that by 2e-9 m (tests/blender/test_rig.py). Even so, on some tet meshes Gauss-Newton
        # crept along the stiff valley and stopped 1e-5 to 2e-3 of the diagonal short, so a rig
        # also meets its handles by the method of multipliers (spacetime.solve exact_handles):
        # on 9 creature meshes 7 misses fell to 1e-7 or less, one to 1e-5 and one stalled at 3e-3.
        gamma *= RIG_TIGHTNESS
        masses = tools.lumped_masses(settings.density)
        load = armature.rig_load(obj, blender_scene, tools, frames, h,
                                 scene.scene_gravity(blender_scene), masses)
        jacobian = tools.deformer.q_jacobian(np.zeros(tools.deformer.num_coords))
        external = load.modal_forces((np.array(frames) - first) * h, jacobian)[:, :optimised]
    problem = spacetime.SpaceTimeProblem(
        frames=len(frames), h=h, eigenvalues=eigenvalues, damping=damping,
        external_forces=external,
        deformer=tools.deformer, handles=handles, keyframes=keyframes, gamma=gamma,
        fix_start=not settings.use_take, material_freedom=settings.material_freedom)
    return SpaceTimeJob(obj.name, frames, problem, settings.optimize_material,
                        settings.iterations, tools, rest, track_slices,
                        [track.name for track in tracks],
                        handle_stretch_demands(tools, rest_centroids, tracks),
                        float(np.mean(obj.matrix_world.to_scale())), warnings,
                        exact_handles=rigged)


def _rig_tracks(obj, blender_scene, tools, frames, tracks, warnings):
    """Checks for an edit of a rigged body, and its handle targets in the rest pose."""
    armature.require_follow_group(obj, len(tools.pinned_nodes) > 0)
    if obj.rs_elastic.optimize_material:
        raise InputError(f"'{obj.name}' is rigged: material optimisation is not available on a "
                         "rig yet; untick Optimize Material")
    warnings += armature.warnings_for(obj)
    warnings += [f"Handle '{track.name}': orientation is not followed on a rigged body; only "
                 "its position is" for track in tracks if track.rotations is not None]
    return armature.rest_targets(obj, blender_scene, frames, tracks)


def solve(job_inputs, job):
    """Worker thread: run the solver and turn its result into render-vertex poses."""
    def progress(iteration, objective):
        job.step(min(0.95, iteration / max(job_inputs.iterations, 1)),
                 f"iteration {iteration}, objective {objective:.4g}")

    try:
        result = spacetime.solve(job_inputs.problem, optimise_material=job_inputs.optimise_material,
                                 iterations=job_inputs.iterations, callback=progress,
                                 should_cancel=job.is_cancelled,
                                 exact_handles=job_inputs.exact_handles)
    except spacetime.SolveCancelled:
        from .jobs import Cancelled
        raise Cancelled() from None
    LAST_STATUS[job_inputs.object_name] = status_sentence(result)
    if not result.converged:            # reported with the other warnings when the bake is applied
        job_inputs.warnings.append(status_sentence(result)[1])
    q = job_inputs.tools.deformer.q_batch(result.inputs)                 # (F, rB)
    displacement = q @ job_inputs.tools.surface_basis.T                    # (F, 3n)
    poses = job_inputs.rest[None] + displacement.reshape(len(q), -1, 3)
    bake.check_poses(job_inputs.object_name, job_inputs.rest, poses)
    job_inputs.warnings.extend(post_solve_checks(job_inputs, result))
    return result, poses


STRETCH_REPORTED = 0.05  # stretch (fraction) from which a handle's targets are reported


def handle_stretch_demands(tools, rest_centroids, tracks):
    """Per handle track: the stretch its keyed targets demand (``accuracy.target_stretch``, a
    fraction) and the scene frame where it is largest. Orientation spokes are left out."""
    if not tracks:
        return []
    demands, frames = accuracy.target_stretch(
        tools.nodes, tools.tets, tools.pinned_nodes, np.array(rest_centroids),
        [track.frames for track in tracks], [track.targets for track in tracks])
    return [(float(d), int(f)) for d, f in zip(demands, frames)]


def post_solve_checks(job_inputs, result, frames=4):
    """Sentences for the user after a solve (worker thread, no bpy).

    - Is the reduced model off? ``accuracy.reduced_error`` on ``frames`` telling frames, against
      full RS; warned above ``accuracy.REDUCED_ERROR_TOLERANCE`` = 1 % of the body's diagonal.
    - Which handles ask the body to stretch? Their targets' demand (``handle_stretch_demands``),
      reported from ``STRETCH_REPORTED`` = 5 % with the handle's residual. (The solved RS
      strain is no guide: on a cow bent at constant volume it reached 39 % in a few tets.)
    """
    tools, Z = job_inputs.tools, result.inputs
    modal_rs = tools.modal_rs[:, :, :Z.shape[1]]
    out = []
    picked = accuracy.telling_frames(modal_rs, Z, frames)
    if getattr(tools.deformer, "basis", None) is not None:
        errors = accuracy.reduced_error(tools.deformer, tools.reconstruction, modal_rs,
                                        Z[picked], tools.nodes)
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
