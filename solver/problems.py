"""The solver's problems, built from a prepared body (``body.PreparedBody``) and plain inputs.

``spacetime_problem`` turns handle tracks, pose keys and a take into a ``SpaceTimeProblem``;
``simulation`` turns a material's potential and the loads into a ``dynamics.Simulation``. The
Blender layer only reads the scene into these inputs, and the bench and the tests call the same
functions.
"""
import dataclasses

import numpy as np

from . import accuracy, cache, dynamics, inversion, materials, poses, rig, spacetime


class NothingToSolve(ValueError):
    """A space-time edit without a handle, pose key or take frame in its range."""


@dataclasses.dataclass
class HandleTrack:
    """One handle's targets, in the body's object space (its rest frame)."""
    name: str
    vertices: np.ndarray   # (k,) base-vertex indices
    weight: float
    frames: np.ndarray     # (c,) int scene frames
    targets: np.ndarray    # (c, 3) metres, object space
    rotation_frames: np.ndarray = None   # (o,) int scene frames of the orientation targets
    rotations: np.ndarray = None         # (o, 3, 3) handle rotation from rest, object space


@dataclasses.dataclass
class SpaceTimeSettings:
    """How an edit is solved (the body's space-time settings, as plain numbers)."""
    h: float                      # s per frame
    damping_mass: float = 0.0     # Rayleigh alpha [1/s]
    damping_stiffness: float = 0.0   # Rayleigh beta [s]
    tightness: float = spacetime.TIGHTNESS
    optimize_material: bool = False
    material_freedom: float = 1.5
    take_weight: float = 0.01     # a take frame's weight relative to a handle's
    handle_gamma_factor: float = 1.0   # handles weigh this much more (a rig's loads, see bridge)
    fitted: object = None         # a ``take.FittedMaterial`` used instead of the prepared one


@dataclasses.dataclass
class SpaceTimeSetup:
    """A space-time problem and what the caller needs to read its result back."""
    problem: spacetime.SpaceTimeProblem
    track_slices: list            # per track: slice of its rows among the handle constraints
    rest_centroids: np.ndarray    # (t, 3) each track's vertices' rest centroid [m]
    warnings: list


POSE_SAMPLES = 32   # vertices per pose key that must reach the sculpted positions


def spread_sample(points, count):
    """Indices (count,) of points (n, 3) spread over the set (farthest-point sampling)."""
    count = min(count, len(points))
    chosen = [int(np.argmax(np.linalg.norm(points - points.mean(axis=0), axis=1)))]
    distance = np.linalg.norm(points - points[chosen[0]], axis=1)
    for _ in range(count - 1):
        chosen.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return np.array(chosen)


def optimised_modes(candidates):
    """How many modes material optimisation optimises out of ``candidates`` prepared ones.

    [L14]'s sampling matrix S (candidates x optimised) chooses which combinations of the
    candidate modes matter; with as many optimised modes as candidates it could only mix them.
    Two thirds keep most of the edit's freedom while leaving S a third of the modes to pick from.
    """
    return max(1, -(-2 * candidates // 3)) if candidates > 1 else candidates


def handle_parts(body, rest, tracks, first):
    """Constraint rows of the handle tracks, frames counted from scene frame ``first``.

    Returns (parts: per track one or two HandleConstraints argument tuples, track_slices,
    rest_centroids (t, 3), warnings).
    """
    parts, slices, centroids, warnings, count = [], [], [], [], 0
    for track in tracks:
        rows, centroid = spacetime.handle_geometry(rest, body.surface_basis, track.vertices)
        centroids.append(centroid)
        c = len(track.frames)
        parts.append((track.frames - first, np.repeat(rows[None], c, axis=0),
                      np.repeat(centroid[None], c, axis=0), track.targets,
                      np.full(c, track.weight)))
        if track.rotations is not None:     # Orientation: spokes of the same vertices
            try:
                spoke_rows, spokes = spacetime.orientation_geometry(rest, body.surface_basis,
                                                                    track.vertices)
            except ValueError:
                warnings.append(f"Handle '{track.name}': its vertices lie on a line, so they "
                                "have no orientation to follow; only its position is used")
            else:
                part = spacetime.orientation_constraints(track.rotation_frames - first,
                                                         track.rotations, spoke_rows, spokes,
                                                         track.weight)
                parts.append(part)
                c += len(part[0])
        slices.append(slice(count, count + c))
        count += c
    return parts, slices, np.array(centroids).reshape(-1, 3), warnings


def pose_key_parts(body, rest, pose_keys, first):
    """Constraint rows of pose keys [(scene frame, positions (n, 3))].

    A pose key is met as positions of a spread sample of vertices: a sculpted pose need not be
    one the modes' RS coordinates can fit, and what the animator sees is the positions.
    """
    if not pose_keys:
        return []
    samples = spread_sample(rest, POSE_SAMPLES)
    sample_rows = body.surface_basis.reshape(len(rest), 3, -1)[samples]          # (s, 3, rB)
    weights = np.full(len(samples), 1.0 / len(samples))
    return [(np.full(len(samples), frame - first), sample_rows, rest[samples],
             positions[samples], weights) for frame, positions in pose_keys]


def spacetime_problem(body, rest, frames, tracks=(), pose_keys=(), take=None, settings=None,
                      external_forces=None):
    """The ``SpaceTimeProblem`` of an edit of a prepared body.

    rest (n, 3) [m] base vertices; frames: the scene frames solved, ascending; tracks:
    ``HandleTrack``s; pose_keys: [(scene frame, positions (n, 3))]; take: (scene frames (k,),
    poses (k, n, 3)) followed softly where nothing else constrains, or None;
    settings: ``SpaceTimeSettings``; external_forces: None, or a function (times (F,) [s],
    dq/dz at rest (rB, m)) -> (F, m) modal forces (a rig's loads). Returns a ``SpaceTimeSetup``;
    ``NothingToSolve`` (a ValueError) when there is nothing to solve for.
    """
    first, count = frames[0], len(frames)
    parts, slices, centroids, warnings = handle_parts(body, rest, tracks, first)
    parts += pose_key_parts(body, rest, list(pose_keys), first)
    take_frames, take_poses = [], []
    if take is not None:
        inside = [i for i, f in enumerate(take[0]) if first <= f <= frames[-1]]
        take_frames = [take[0][i] for i in inside]
        take_poses = [take[1][i] for i in inside]
    if not parts and not take_frames:
        raise NothingToSolve("nothing to solve for")

    candidates = body.deformer.num_coords
    eigenvalues, damping, sampling = material_of(body, settings)
    handles = None
    if parts:
        handles = spacetime.HandleConstraints(*(np.concatenate(p) for p in zip(*parts)))
    gamma, keyframe_weight = spacetime.suggest_weights(
        settings.h, eigenvalues, damping, body.deformer,
        None if handles is None else handles.rows, tightness=settings.tightness)
    keyframes = None
    if take_frames:     # the take's frames, fitted in RS coordinates (they are physical poses)
        keyframes = spacetime.Keyframes(np.array(take_frames) - first,
                                        poses.poses_to_modal(body, take_poses),
                                        np.full(len(take_frames),
                                                keyframe_weight * settings.take_weight))
    external = None
    if external_forces is not None:
        jacobian = body.deformer.q_jacobian(np.zeros(candidates))
        external = external_forces(np.arange(count) * settings.h, jacobian) @ sampling
    problem = spacetime.SpaceTimeProblem(
        frames=count, h=settings.h, eigenvalues=eigenvalues, damping=damping,
        external_forces=external, deformer=body.deformer, handles=handles, keyframes=keyframes,
        sampling=sampling, gamma=gamma * settings.handle_gamma_factor, fix_start=take is None,
        material_freedom=settings.material_freedom)
    return SpaceTimeSetup(problem, slices, centroids, warnings)


def material_of(body, settings):
    """(eigenvalues (r,) [rad^2/s^2], damping (r,) [1/s], sampling S (m, r)) an edit starts
    from: the fitted material when ``settings.fitted`` is set, else the prepared modes (all m, or
    ``optimised_modes`` of them under material optimisation, S = [I; 0]) with Rayleigh damping.
    ValueError for a fitted material of another preparation (another number of modes)."""
    candidates = body.deformer.num_coords
    fitted = settings.fitted
    if fitted is not None:
        if fitted.sampling.shape[0] != candidates:
            raise ValueError(f"the fitted material has {fitted.sampling.shape[0]} modes, the "
                             f"body {candidates}: it was prepared again since, so fit again")
        return fitted.eigenvalues, fitted.damping, fitted.sampling
    optimised = optimised_modes(candidates) if settings.optimize_material else candidates
    eigenvalues = body.linear_modes.eigenvalues[:optimised]
    damping = spacetime.rayleigh_damping(eigenvalues, settings.damping_mass,
                                         settings.damping_stiffness)
    return eigenvalues, damping, np.eye(candidates, optimised)


def handle_stretch_demands(body, rest_centroids, tracks):
    """Per handle track: (the stretch its keyed targets demand, a fraction; the scene frame where
    it is largest) (``accuracy.target_stretch``). Orientation spokes are left out."""
    if not tracks:
        return []
    demands, frames = accuracy.target_stretch(
        body.nodes, body.tets, body.pinned_nodes, np.asarray(rest_centroids),
        [track.frames for track in tracks], [track.targets for track in tracks])
    return [(float(d), int(f)) for d, f in zip(demands, frames)]


# --- simulation ---------------------------------------------------------------------------------

@dataclasses.dataclass
class SimulationSettings:
    """How a body is simulated (its simulation settings, as plain numbers)."""
    h: float                          # s per frame
    density: float                    # kg/m^3
    gravity: tuple = (0.0, 0.0, 0.0)  # m/s^2, in the simulation's space
    damping_mass: float = 0.0         # Rayleigh alpha [1/s]
    damping_stiffness: float = 0.0    # Rayleigh beta [s]
    integrator: str = "newmark"       # or "implicit_euler"
    substeps: int = 0                 # steps per frame; 0: from the highest mode frequency


def linear_potential(body, youngs, poisson):
    """The Linear material's reduced potential on the body (an exact quadratic form) for its
    Young's modulus [Pa] and Poisson's ratio, with the body's painted stiffness if it has one
    (``PreparedBody.material``). Made once per material and kept on the body, keyed by the
    per-tet Young's modulus it is made of (a number for a uniform body)."""
    tet_youngs = body.tet_youngs(youngs)
    key = (cache.content_key(tet_youngs) if np.ndim(tet_youngs) else tet_youngs, poisson)
    kept = body.__dict__.setdefault("_linear_potentials", {})
    if key not in kept:
        kept[key], _ = materials.prepare_potential(body.material("LINEAR", youngs, poisson),
                                                   body.modal_rs, body.volumes)
    return kept[key]


def simulation(body, potential, settings, frame_motion=None, contact=None, external_force=None,
               sample_placement=None, follow_stiffness=None):
    """The ``dynamics.Simulation`` of a prepared body with its material's reduced ``potential``.

    Every simulation carries two volume barriers: one on each tet's RS stretch, which keeps the
    body from inverting, and one on the reconstruction, which keeps the positions the user sees
    from inverting; and every step checks every tet. A body without pins is free (it falls and
    spins). frame_motion: a keyed body's ``frames.FrameMotion``; contact: a ``contact.Contact``;
    external_force, sample_placement: a rig's loads and contact placement (``dynamics``);
    follow_stiffness: (N,) a rig's springs holding the flesh to the bones (``rig``).
    """
    deformer = dynamics.step_deformer(body.deformer)      # one object for the steps and terms
    potential = inversion.with_barrier(potential, body.modal_rs, body.volumes)
    if follow_stiffness is not None:
        potential = rig.HeldPotential(potential, deformer, follow_stiffness)
    potential = inversion.with_reconstruction_barrier(potential, deformer, body.nodes,
                                                      body.tets)
    return dynamics.Simulation(
        deformer, body.nodes, body.lumped_masses(settings.density), potential, settings.h,
        gravity=settings.gravity, mass_damping=settings.damping_mass,
        stiffness_damping=settings.damping_stiffness, free=len(body.pinned_nodes) == 0,
        frame_motion=frame_motion, integrator=settings.integrator, substeps=settings.substeps,
        tets=body.tets, contact=contact, external_force=external_force,
        sample_placement=sample_placement)
