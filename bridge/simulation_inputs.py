"""Gather a simulation from the scene (main thread) and run it (worker thread)."""
import dataclasses

import numpy as np

from ..solver import contact, dynamics, fem, materials
from . import bake, colliders, scene, spacetime_inputs
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


def potential_for(tools, settings):
    """The reduced potential of the body's material (cached on the RSTools per model)."""
    cache = tools.__dict__.setdefault("_potentials", {})
    key = (settings.material_model, settings.fung_stiffening, settings.youngs_modulus,
           settings.poisson_ratio)
    if key not in cache:
        mu, lam = fem.lame_parameters(settings.youngs_modulus, settings.poisson_ratio)
        material = materials.make_material(settings.material_model, mu, lam,
                                           fung_stiffening=settings.fung_stiffening)
        volumes = np.abs(fem.tet_volumes(tools.nodes, tools.tets))
        cache[key], _ = materials.prepare_potential(
            material, tools.modal_rs, volumes, eigenvalues=tools.body.linear_modes.eigenvalues)
    return cache[key]


def contact_for(obj, blender_scene, tools, frames, h, world_to_sim, total_mass):
    """The body's ``contact.Contact`` against the scene's colliders, or None without any."""
    if not obj.rs_elastic.use_collisions:
        return None
    found = colliders.scene_colliders(obj, blender_scene, frames, h, world_to_sim)
    if not found:
        return None
    points, rows, weights, masses = colliders.contact_samples(
        scene.base_vertices(obj), scene.base_triangles(obj), tools.surface_basis, total_mass,
        obj.rs_elastic.contact_samples)
    return contact.Contact(found, points, rows, weights, masses,
                           integrator=obj.rs_elastic.integrator.lower())


def gather(obj, blender_scene):
    """Validate and set up the simulation. Raises InputError."""
    scene.require_body(obj)
    tools = spacetime_inputs.prepared_tools(obj)
    settings = obj.rs_elastic
    frames = spacetime_inputs.frame_range(obj, blender_scene)
    warnings = []
    free = len(tools.pinned_nodes) == 0
    fps = blender_scene.render.fps / blender_scene.render.fps_base
    h = 1.0 / fps
    gravity = scene.scene_gravity(blender_scene)
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
        frame_motion = dynamics.FrameMotion(times, rotations, translations)
    else:
        # A still object: simulate in its own space, with gravity turned into it.
        rotation = np.array(obj.matrix_world.to_quaternion().to_matrix())
        gravity = rotation.T @ gravity
    masses = fem.lumped_masses(tools.nodes, tools.tets, settings.density)
    # A keyed body simulates in world space, a still one in its own object space.
    world_to_sim = np.eye(4) if frame_motion is not None else np.linalg.inv(np.array(obj.matrix_world))
    body_contact = contact_for(obj, blender_scene, tools, frames, h, world_to_sim, masses.sum())
    try:
        simulation = dynamics.Simulation(
            tools.deformer, tools.nodes, masses, potential_for(tools, settings), h,
            gravity=gravity, mass_damping=settings.damping_mass,
            stiffness_damping=settings.damping_stiffness, free=free, frame_motion=frame_motion,
            integrator=settings.integrator.lower(), substeps=settings.substeps,
            contact=body_contact)
    except ValueError as exc:          # e.g. the body starts inside a collider
        raise InputError(f"'{obj.name}': {exc}") from None
    return SimulationJob(obj.name, frames, simulation, tools.surface_basis,
                         scene.base_vertices(obj), free, warnings)


def run(job_inputs, job):
    """Worker thread: simulate every frame and return the base-vertex poses (F, n, 3)."""
    steps = len(job_inputs.frames) - 1

    def progress(step, total):
        job.step(step / total, f"frame {job_inputs.frames[0] + step} of {job_inputs.frames[-1]}")

    try:
        trajectory = job_inputs.simulation.run(steps, callback=progress,
                                               should_cancel=job.is_cancelled)
    except dynamics.SimulationCancelled:
        raise Cancelled() from None
    if job_inputs.free:   # the floating frame's motion is part of the pose in object space
        poses = trajectory.world_positions(job_inputs.rest, job_inputs.rows)
    else:
        poses = job_inputs.rest[None] + trajectory.body_displacements(job_inputs.rows)
    bake.check_poses(job_inputs.object_name, job_inputs.rest, poses)
    return poses
