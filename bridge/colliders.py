"""Read the scene's Collision-modifier objects and the body's contact samples for a simulation.

Main thread only. Everything is returned in the simulation's space (``gather`` in
``simulation_inputs``): the body's own object space for a still body, world space for a body on
keyed motion. Times are seconds from the first simulated frame.
"""
import math

import bpy
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from ..solver import contact
from . import scene, transforms
from .scene import InputError


class AffineMotion:
    """A collider's object-to-simulation matrix over time, sampled once per frame.

    times (F,) [s]; matrices (F, 4, 4). Between samples the rotation is slerped and the
    translation and stretch (the symmetric factor of the polar decomposition: scale and shear)
    are interpolated linearly; constant before the first and after the last sample, like
    Blender's constant extrapolation. Called with t [s], returns (4, 4).
    """

    def __init__(self, times, matrices):
        self.times = np.asarray(times, dtype=np.float64)
        matrices = np.asarray(matrices, dtype=np.float64)
        U, sigma, Vt = np.linalg.svd(matrices[:, :3, :3])
        flip = np.where(np.linalg.det(U @ Vt) < 0.0, -1.0, 1.0)      # mirrored: keep R proper
        U[:, :, 2] *= flip[:, None]
        sigma[:, 2] *= flip
        self.stretch = np.einsum("fij,fj,fkj->fik", np.swapaxes(Vt, 1, 2), sigma,
                                 np.swapaxes(Vt, 1, 2))                  # V diag(s) V^T
        self.translations = matrices[:, :3, 3]
        self._slerp = Slerp(self.times, Rotation.from_matrix(U @ Vt))

    def __call__(self, t):
        t = float(np.clip(t, self.times[0], self.times[-1]))
        i = int(np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, len(self.times) - 2))
        w = (t - self.times[i]) / (self.times[i + 1] - self.times[i])
        matrix = np.eye(4)
        stretch = (1.0 - w) * self.stretch[i] + w * self.stretch[i + 1]
        matrix[:3, :3] = self._slerp([t]).as_matrix()[0] @ stretch
        matrix[:3, 3] = (1.0 - w) * self.translations[i] + w * self.translations[i + 1]
        return matrix


def collider_objects(body, blender_scene):
    """Objects whose Collision modifier is on (viewport or render), in the body's Collider
    Collection when one is set, except the body itself; sorted by name so runs repeat."""
    settings = body.rs_elastic
    pool = (settings.collider_collection.all_objects if settings.collider_collection is not None
            else blender_scene.objects)
    found = []
    for obj in pool:
        if obj == body or obj.type != 'MESH':
            continue
        if any(m.type == 'COLLISION' and (m.show_viewport or m.show_render)
               for m in obj.modifiers) and obj.collision.use:
            found.append(obj)
    return sorted(found, key=lambda o: o.name)


def _sampled_matrices(objects, blender_scene, frames):
    """(objects, F, 4, 4) world matrices of each collider at each frame (one frame_set per
    frame); InputError naming a collider whose transform is not finite on a frame."""
    return transforms.world_matrices(objects, blender_scene, frames,
                                     [f"collider '{obj.name}'" for obj in objects])


def scene_colliders(body, blender_scene, frames, h, world_to_sim):
    """[contact.MeshCollider] for the body's colliders over `frames` (h [s] per frame).

    world_to_sim (4, 4): world space to the simulation's space. Each collider's evaluated mesh
    (its modifiers applied) is read once at the current frame; only its object transform moves it
    (keys, parents, constraints); a collider that deforms is seen in its current shape.
    InputError for a collider whose transform, mesh or settings are not finite numbers.
    """
    objects = collider_objects(body, blender_scene)
    if not objects:
        return []
    depsgraph = bpy.context.evaluated_depsgraph_get()
    matrices = _sampled_matrices(objects, blender_scene, frames)
    times = (np.asarray(frames, dtype=np.float64) - frames[0]) * h
    colliders = []
    for obj, per_frame in zip(objects, matrices):
        V, F = scene.evaluated_triangles(obj, depsgraph)
        options = _collision_options(obj)
        if not np.isfinite(V).all():
            raise InputError(f"Collider '{obj.name}': its mesh has positions that are not finite "
                             "numbers")
        to_sim = world_to_sim @ per_frame                                    # (F, 4, 4)
        if np.abs(to_sim - to_sim[0]).max() < 1e-9:                         # static
            V_sim = V @ to_sim[0, :3, :3].T + to_sim[0, :3, 3]
            if np.linalg.det(to_sim[0, :3, :3]) < 0.0:     # mirrored: keep the outside outside
                F = F[:, ::-1]
            colliders.append(contact.MeshCollider(V_sim, F, **options))
        else:
            colliders.append(contact.MeshCollider(V, F, motion=AffineMotion(times, to_sim),
                                                  **options))
    return colliders


def _collision_options(obj):
    """MeshCollider's keyword options from the object's Collision settings; InputError for one
    that is not a finite number."""
    settings = obj.collision
    for name in ("thickness_outer", "cloth_friction", "damping"):
        value = float(getattr(settings, name))
        if not math.isfinite(value):
            label = settings.bl_rna.properties[name].name
            raise InputError(f"Collider '{obj.name}': its {label} is {value:g}; it must be a "
                             "finite number")
    return dict(thickness=float(settings.thickness_outer),
                # Blender's cloth collisions read this field as Coulomb mu = value / 100.
                friction=float(settings.cloth_friction) / 100.0,
                damping=float(settings.damping), name=obj.name)


def contact_samples(rest, triangles, rows, total_mass, count):
    """(indices (k,) of the base vertices sampled, points (k, 3), rows (3k, rB), weights (k,)
    [m^2], masses (k,) [kg]) of the body's contact cubature: ``contact.surface_samples`` on its
    base mesh, each sample carrying the mass share of the surface it stands for. rest (n, 3),
    triangles (t, 3), rows (3n, rB)."""
    indices, weights = contact.surface_samples(rest, triangles, count)
    if not weights.sum() > 0.0:
        raise InputError("the body's surface has no area to collide with")
    rows = rows.reshape(len(rest), 3, -1)[indices].reshape(3 * len(indices), -1)
    masses = total_mass * weights / weights.sum()
    return indices, rest[indices], rows, weights, masses
