"""Gather a simulation from the scene (main thread) and run it (worker thread)."""
import dataclasses

import numpy as np

from ..solver import contact, dynamics, inversion, materials
from ..solver.frames import FrameMotion
from . import (armature, bake, bodies, colliders, jobs, prepared, scene,
               stage_cache)
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


def object_motion(obj, blender_scene, frames):
    """(rotations (F, 3, 3), translations (F, 3)) of the object's world transform per frame, or
    None if it does not move over the range (keys, parents and constraints all count)."""
    current = blender_scene.frame_current
    matrices = []
    try:
        for frame in frames:
            blender_scene.frame_set(frame)
            matrices.append(np.array(obj.matrix_world))
    finally:
        blender_scene.frame_set(current)
    matrices = np.array(matrices)
    if np.abs(matrices - matrices[0]).max() < 1e-9:
        return None
    linear = matrices[:, :3, :3]
    U, _, Vt = np.linalg.svd(linear)                  # the rotation part, scale removed
    return U @ Vt, matrices[:, :3, 3]


def energy_work(obj):
    """Main thread, before `gather`: None when the body's potential is at hand (Linear, or its
    energy cubature in memory), else work(job) for a worker thread that loads the cubature from
    the body's cache or trains it (progress, Esc), and leaves it in memory for `gather`."""
    scene.require_body(obj)
    energy = bodies.energy_inputs(obj)
    if energy is None:
        return None
    tools = prepared.require(obj)
    if bodies.cached_energy(energy, tools) is not None:
        return None
    return lambda job: bodies.energy_stage(energy, tools, job)


def record_energy(obj):
    """Main thread, after a simulation: note the cubature it used among the object's cache
    files (so a later Prepare keeps it and a save copies it next to the .blend)."""
    energy = bodies.energy_inputs(obj)
    tools = prepared.for_object(obj)
    if energy is not None and tools is not None:
        parent = bodies.energy_parent(tools)
        stage_cache.record_energy(obj, parent, energy.key(parent))


def potential_for(tools, settings):
    """The reduced potential of the body's material. StVK / Fung: the energy cubature, the
    body's fourth cache stage (`bodies.energy_stage`), from memory or its cache file, trained
    here only if nobody did before (the Simulate operator trains it first in its job, see
    `energy_work`). Linear: the exact quadratic form, kept on the RSTools."""
    energy = bodies.energy_inputs(settings.id_data)
    if energy is not None:
        job = jobs.Job(None)
        potential = bodies.energy_stage(energy, tools, job)
        for message in job.warnings:
            print(f"RS Elastic: {message}")
        return potential
    cache = tools.__dict__.setdefault("_potentials", {})
    key = (settings.youngs_modulus, settings.poisson_ratio)
    if key not in cache:
        mu, lam = bodies.material_lame(settings)
        cache[key], _ = materials.prepare_potential(materials.Linear(mu, lam), tools.modal_rs,
                                                    tools.volumes)
    return cache[key]


def contact_for(obj, blender_scene, tools, frames, h, world_to_sim, total_mass):
    """(the body's ``contact.Contact`` against the scene's colliders, the base vertices it
    samples (k,)), or (None, None) without any collider."""
    if not obj.rs_elastic.use_collisions:
        return None, None
    found = colliders.scene_colliders(obj, blender_scene, frames, h, world_to_sim)
    if not found:
        return None, None
    indices, points, rows, weights, masses = colliders.contact_samples(
        scene.base_vertices(obj), scene.base_triangles(obj), tools.surface_basis, total_mass,
        obj.rs_elastic.contact_samples)
    return contact.Contact(found, points, rows, weights, masses), indices


def gather(obj, blender_scene):
    """Validate and set up the simulation. Raises InputError."""
    scene.require_body(obj)
    bake.require_target(obj)
    tools = prepared.require(obj)
    settings = obj.rs_elastic
    frames = scene.frame_range(obj, blender_scene)
    warnings = []
    free = len(tools.pinned_nodes) == 0
    fps = blender_scene.render.fps / blender_scene.render.fps_base
    h = 1.0 / fps
    gravity = scene.scene_gravity(blender_scene)
    if armature.is_rigged(obj):
        return _gather_rigged(obj, blender_scene, tools, frames, h, gravity, warnings)
    motion = object_motion(obj, blender_scene, frames)
    scale = np.array(obj.matrix_world.to_scale())
    if np.abs(scale - 1.0).max() > 1e-6:
        warnings.append(f"'{obj.name}' is scaled by {tuple(np.round(scale, 3))}: the simulation "
                        "treats its object space as metres")
    frame_motion = None
    if motion is not None:
        if free:
            raise InputError(f"'{obj.name}' is animated but has no pins: give it a Pin Group so "
                             "its keyed motion has something to carry")
        rotations, translations = motion
        times = (np.array(frames) - frames[0]) * h
        frame_motion = FrameMotion(times, rotations, translations)
    else:
        # A still object: simulate in its own space, with gravity turned into it.
        rotation = np.array(obj.matrix_world.to_quaternion().to_matrix())
        gravity = rotation.T @ gravity
    masses = tools.lumped_masses(settings.density)
    # The volume barrier over all tets keeps the body from inverting; tets let every step check.
    potential = inversion.with_barrier(potential_for(tools, settings), tools.modal_rs,
                                       tools.volumes)
    # ... and one on the reconstruction keeps the positions the user sees from inverting.
    potential = inversion.with_reconstruction_barrier(potential, tools.deformer, tools.nodes,
                                                      tools.tets)
    # A keyed body simulates in world space, a still one in its own object space.
    world_to_sim = (np.eye(4) if frame_motion is not None
                    else np.linalg.inv(np.array(obj.matrix_world)))
    body_contact, _ = contact_for(obj, blender_scene, tools, frames, h, world_to_sim,
                                  masses.sum())
    try:
        simulation = dynamics.Simulation(
            tools.deformer, tools.nodes, masses, potential, h, gravity=gravity,
            mass_damping=settings.damping_mass, stiffness_damping=settings.damping_stiffness,
            free=free, frame_motion=frame_motion, integrator=settings.integrator.lower(),
            substeps=settings.substeps, tets=tools.tets, contact=body_contact)
    except ValueError as exc:          # e.g. contact samples that do not fit the basis
        raise InputError(f"'{obj.name}': {exc}") from None
    if settings.start_settled and free:
        warnings.append(f"'{obj.name}' has no pins: it falls freely, so it starts from its rest "
                        "shape (Start Settled needs pins)")
    return SimulationJob(obj.name, frames, simulation, tools.surface_basis,
                         scene.base_vertices(obj), free, warnings,
                         settle=settings.start_settled and not free)


def _gather_rigged(obj, blender_scene, tools, frames, h, gravity, warnings):
    """A rigged body: its flesh simulated in rest space under the rig's loads (no frame motion,
    gravity through the rig), baked as shape keys the Armature modifier carries. Its contact
    samples are skinned to the world, where the colliders are."""
    settings = obj.rs_elastic
    armature.require_follow_group(obj, len(tools.pinned_nodes) > 0)
    warnings += armature.warnings_for(obj)
    masses = tools.lumped_masses(settings.density)
    potential = inversion.with_barrier(potential_for(tools, settings), tools.modal_rs,
                                       tools.volumes)
    load = armature.rig_load(obj, blender_scene, tools, frames, h, gravity, masses)
    potential = armature.held_by_follow_weights(obj, tools, masses, potential)
    potential = inversion.with_reconstruction_barrier(potential, tools.deformer, tools.nodes,
                                                      tools.tets)
    body_contact, sampled = contact_for(obj, blender_scene, tools, frames, h, np.eye(4),
                                        masses.sum())
    placement = (None if body_contact is None
                 else armature.skinned_placement(obj, load.motion, sampled))
    try:
        simulation = dynamics.Simulation(
            tools.deformer, tools.nodes, masses, potential, h, gravity=np.zeros(3),
            mass_damping=settings.damping_mass, stiffness_damping=settings.damping_stiffness,
            integrator=settings.integrator.lower(), substeps=settings.substeps, tets=tools.tets,
            external_force=load.force, contact=body_contact, sample_placement=placement)
    except ValueError as exc:          # e.g. contact samples that do not fit the basis
        raise InputError(f"'{obj.name}': {exc}") from None
    return SimulationJob(obj.name, frames, simulation, tools.surface_basis,
                         scene.base_vertices(obj), False, warnings, settle=settings.start_settled)


def run(job_inputs, job):
    """Worker thread: simulate every frame and return the base-vertex poses (F, n, 3)."""
    steps = len(job_inputs.frames) - 1

    def progress(step, total):
        job.step(step / total, f"frame {job_inputs.frames[0] + step} of {job_inputs.frames[-1]}")

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
    if job_inputs.free:   # the floating frame's motion is part of the pose in object space
        poses = trajectory.world_positions(job_inputs.rest, job_inputs.rows)
    else:
        poses = job_inputs.rest[None] + trajectory.body_displacements(job_inputs.rows)
    bake.check_poses(job_inputs.object_name, job_inputs.rest, poses)
    return poses
