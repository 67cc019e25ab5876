"""Gather a simulation from the scene (main thread) and run it (worker thread)."""
import dataclasses

import numpy as np

from ..solver import contact, dynamics, problems
from ..solver.frames import FrameMotion
from . import (armature, bake, bodies, colliders, jobs, prepared, scene,
               stage_cache, take, transforms)
from .jobs import Cancelled
from .scene import InputError


@dataclasses.dataclass
class SimulationJob:
    object_name: str
    frames: list
    simulation: dynamics.Simulation
    rows: np.ndarray        # (3n, rB) Φ B
    rest: np.ndarray        # (n, 3) base vertices, object space
    free: bool
    warnings: list
    settle: bool = False    # start at rest in static equilibrium (Start Settled)


MIRROR = np.diag([1.0, 1.0, -1.0])   # the world reflection a keyed mirrored body moves in


def body_placement(obj, blender_scene, frames, h, gravity, free):
    """Where the simulation of a non-rigged body runs over `frames` (h [s] apart): (frame
    motion, gravity (3,) there, world to simulation (4, 4)).

    Q: the orthogonal polar factors of the body's transforms (scale and shear dropped: the
    simulation treats object space as metres). A still body runs in its own object space under
    gravity Q^T g (for a mirrored body Q is a reflection, and Q^T g is still where the world's
    down is in its space). A keyed (parented, constrained) body runs in world space on a
    ``FrameMotion`` of the rotations Q and the translations c. A mirrored body's Q is a
    reflection, which no motion of the body can be; physics does not change in a mirror, so it
    runs in the world mirrored by W = MIRROR, where it is carried by the rotations W Q,
    translations W c, under gravity W g, among its colliders mirrored by W: in its own space it
    moves exactly as it does in the real world.
    InputError for a transform that is not finite or scaled to zero on a frame, or a keyed
    `free` body (one without pins)."""
    name = f"'{obj.name}'"
    matrices = transforms.world_matrices([obj], blender_scene, frames, [name])[0]
    transforms.require_invertible(name, matrices, frames)
    Q, mirrored = transforms.orthogonal_parts(name, matrices, frames)
    if np.abs(matrices - matrices[0]).max() < 1e-9:
        return None, Q[0].T @ gravity, np.linalg.inv(matrices[0])
    if free:
        raise InputError(f"'{obj.name}' is animated but has no pins: give it a Pin Group so "
                         "its keyed motion has something to carry")
    world = MIRROR if mirrored else np.eye(3)
    motion = FrameMotion((np.array(frames) - frames[0]) * h, world @ Q,
                         matrices[:, :3, 3] @ world.T)
    world_to_sim = np.eye(4)
    world_to_sim[:3, :3] = world
    return motion, world @ gravity, world_to_sim


def energy_work(obj):
    """Main thread, before `gather`: None when the body's potential is at hand (Linear, or its
    energy cubature in memory), else work(job) for a worker thread that loads the cubature from
    the body's cache or trains it (progress, Esc), and leaves it in memory for `gather`."""
    scene.require_body(obj)
    energy = bodies.energy_inputs(obj)
    if energy is None:
        return None
    body = prepared.require(obj)
    if bodies.cached_energy(energy, body) is not None:
        return None
    return lambda job: bodies.energy_stage(energy, body, job)


def record_energy(obj):
    """Main thread, after a simulation: note the cubature it used among the object's cache
    files (so a later Prepare keeps it and a save copies it next to the .blend)."""
    energy = bodies.energy_inputs(obj)
    body = prepared.for_object(obj)
    if energy is not None and body is not None:
        parent = bodies.energy_parent(body)
        stage_cache.record_energy(obj, parent, energy.key(parent))


def potential_for(body, settings):
    """The reduced potential of the body's material. StVK / Fung: the energy cubature, the
    body's fourth cache stage (`bodies.energy_stage`), from memory or its cache file, trained
    here only if nobody did before (the Simulate operator trains it first in its job, see
    `energy_work`). Linear: the exact quadratic form (``problems.linear_potential``)."""
    energy = bodies.energy_inputs(settings.id_data)
    if energy is None:
        return problems.linear_potential(body, settings.youngs_modulus, settings.poisson_ratio)
    job = jobs.Job(None)
    potential = bodies.energy_stage(energy, body, job)
    for message in job.warnings:
        print(f"RS Elastic: {message}")
    return potential


def settings_of(obj, blender_scene, gravity):
    """The body's simulation settings as a ``problems.SimulationSettings``."""
    settings = obj.rs_elastic
    return problems.SimulationSettings(
        h=scene.frame_interval(blender_scene), density=settings.density, gravity=gravity,
        damping_mass=settings.damping_mass, damping_stiffness=settings.damping_stiffness,
        integrator=settings.integrator.lower(), substeps=settings.substeps)


def contact_for(obj, blender_scene, body, frames, h, world_to_sim, total_mass):
    """(the body's ``contact.Contact`` against the scene's colliders, the base vertices it
    samples (k,)), or (None, None) without any collider."""
    if not obj.rs_elastic.use_collisions:
        return None, None
    found = colliders.scene_colliders(obj, blender_scene, frames, h, world_to_sim)
    if not found:
        return None, None
    indices, points, rows, weights, masses = colliders.contact_samples(
        scene.base_vertices(obj), scene.base_triangles(obj), body.surface_basis, total_mass,
        obj.rs_elastic.contact_samples)
    return contact.Contact(found, points, rows, weights, masses), indices


def gather(obj, blender_scene):
    """Validate and set up the simulation. Raises InputError."""
    scene.require_body(obj)
    bake.require_target(obj)
    body = prepared.require(obj)
    frames = scene.frame_range(obj, blender_scene)
    gravity = scene.scene_gravity(blender_scene)
    if armature.is_rigged(obj):
        return _gather_rigged(obj, blender_scene, body, frames, gravity)
    warnings, free = [], len(body.pinned_nodes) == 0
    scale = np.abs(np.array(obj.matrix_world.to_scale()))      # a mirror is not a scale
    if np.abs(scale - 1.0).max() > 1e-6:
        shown = ", ".join(f"{value:g}" for value in np.round(scale, 3))
        warnings.append(f"'{obj.name}' is scaled by ({shown}): the simulation treats its object "
                        "space as metres")
    h = scene.frame_interval(blender_scene)
    frame_motion, gravity, world_to_sim = body_placement(obj, blender_scene, frames, h,
                                                           gravity, free)
    settings = settings_of(obj, blender_scene, gravity)
    body_contact, _ = contact_for(obj, blender_scene, body, frames, h, world_to_sim,
                                  body.lumped_masses(settings.density).sum())
    simulation = _simulation(obj, body, settings, frame_motion=frame_motion, contact=body_contact)
    start_settled = obj.rs_elastic.start_settled
    if start_settled and free:
        warnings.append(f"'{obj.name}' has no pins: it falls freely, so it starts from its rest "
                        "shape (Start Settled needs pins)")
    return SimulationJob(obj.name, frames, simulation, body.surface_basis,
                         scene.base_vertices(obj), free, warnings,
                         settle=start_settled and not free)


def _simulation(obj, body, settings, **loads):
    try:
        potential, settings = take.simulated_material(obj, body,
                                                      potential_for(body, obj.rs_elastic),
                                                      settings)
        return problems.simulation(body, potential, settings, **loads)
    except ValueError as exc:          # e.g. contact samples that do not fit the basis
        raise InputError(f"'{obj.name}': {exc}") from None


def _gather_rigged(obj, blender_scene, body, frames, gravity):
    """A rigged body: its flesh simulated in rest space under the rig's loads (no frame motion,
    gravity through the rig), baked as shape keys the Armature modifier carries. Its contact
    samples are skinned to the world, where the colliders are."""
    armature.require_follow_group(obj, len(body.pinned_nodes) > 0)
    warnings = armature.warnings_for(obj)
    settings = settings_of(obj, blender_scene, np.zeros(3))
    masses = body.lumped_masses(settings.density)
    load = armature.rig_load(obj, blender_scene, body, frames, settings.h, gravity, masses)
    body_contact, sampled = contact_for(obj, blender_scene, body, frames, settings.h, np.eye(4),
                                        masses.sum())
    placement = (None if body_contact is None
                 else armature.skinned_placement(obj, load.motion, sampled))
    simulation = _simulation(obj, body, settings, contact=body_contact, external_force=load.force,
                             sample_placement=placement,
                             follow_stiffness=armature.follow_stiffness(obj, body, masses))
    return SimulationJob(obj.name, frames, simulation, body.surface_basis,
                         scene.base_vertices(obj), False, warnings,
                         settle=obj.rs_elastic.start_settled)


# A frame is slow when it took at least this many internal steps at the shortest retake length
# (dt / 2^MAX_STEP_SPLITS): as much work as 2^MAX_STEP_SPLITS substeps, for one substep's time.
SLOW_FRAME_STEPS = 2 ** dynamics.MAX_STEP_SPLITS


def slow_frames(simulation, first_frame):
    """Scene frames (ascending) the simulation took slowly (``SLOW_FRAME_STEPS``); first_frame:
    the frame it starts at (its step k ends on first_frame + k, as ``InversionError`` counts)."""
    return [first_frame + frame for frame, count in sorted(simulation.shortest_steps.items())
            if count >= SLOW_FRAME_STEPS]


def slow_warning(object_name, frames, total):
    """One line on frames whose steps were cut to the shortest length to keep every tet from
    inverting, and what usually avoids that; None when there were none."""
    if not frames:
        return None
    cut = 2 ** dynamics.MAX_STEP_SPLITS
    return (f"'{object_name}': {len(frames)} of {total} frames (from frame {frames[0]}) were slow: "
            f"their steps were cut to 1/{cut} to keep every tet from inverting. A larger Basis "
            "Size (0 is automatic), more Substeps or a stiffer material usually avoid it")


def run(job_inputs, job):
    """Worker thread: simulate every frame and return the base-vertex poses (F, n, 3)."""
    steps = len(job_inputs.frames) - 1
    simulation, first = job_inputs.simulation, job_inputs.frames[0]

    def progress(step, total):
        slow = slow_frames(simulation, first)
        note = (f"Slow since frame {slow[0]}: steps are cut to keep tets from inverting"
                if slow else None)       # why it is slow, while it still runs
        job.step(step / total, f"frame {first + step} of {job_inputs.frames[-1]}", note)

    if job_inputs.settle:
        job.step(0.0, "settling into static equilibrium")
        job_inputs.simulation.static_equilibrium()
    try:
        trajectory = job_inputs.simulation.run(steps, callback=progress,
                                               should_cancel=job.is_cancelled)
    except dynamics.SimulationCancelled:
        raise Cancelled() from None
    except dynamics.ContactError as exc:       # starts inside a collider, or run into by one
        raise InputError(f"The simulation of '{job_inputs.object_name}' stopped: {exc}. "
                         "Nothing was baked") from None
    except dynamics.InversionError as exc:
        raise InputError(f"The simulation of '{job_inputs.object_name}' stopped at frame "
                         f"{job_inputs.frames[0] + exc.frame}: {exc.detail}. Nothing was "
                         "baked") from None
    warning = slow_warning(job_inputs.object_name, slow_frames(simulation, first), steps)
    if warning is not None:
        job.warn(warning)
    if job_inputs.free:   # the floating frame's motion is part of the pose in object space
        poses = trajectory.world_positions(job_inputs.rest, job_inputs.rows)
    else:
        poses = job_inputs.rest[None] + trajectory.body_displacements(job_inputs.rows)
    bake.check_poses(job_inputs.object_name, job_inputs.rest, poses)
    return poses
