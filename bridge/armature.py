"""A mesh deformed by an Armature modifier, read as a rig the flesh rides on (main thread).

The elastic motion of a rigged body is a deviation u in the mesh's rest space (the mesh as it is
without the Armature modifier), carried by the skinning: world x = sum_b w_b T_b(t) (X + u).
Blender computes exactly that when u is baked into shape keys, since shape keys come before
every modifier: the Armature modifier then carries the bake along with the rig. The solver
(``solver.rig``) needs the bones' world-from-rest transforms per frame and the vertices'
normalised bone weights; the body's pins are its *Follow Rig* part (they move exactly with the
bones).

Only what Blender's Armature modifier does with vertex groups is modelled: linear blend
skinning. Bone envelopes, dual-quaternion skinning (Preserve Volume) and multi-modifier
blending are reported and left out.
"""
import contextlib
import dataclasses

import numpy as np

from ..solver import rig
from . import scene, transforms
from .scene import InputError


def armature_modifier(obj):
    """The object's first enabled Armature modifier that names an armature, or None."""
    for modifier in obj.modifiers:
        if modifier.type == 'ARMATURE' and modifier.object is not None \
                and (modifier.show_viewport or modifier.show_render):
            return modifier
    return None


def is_rigged(obj):
    return obj is not None and obj.type == 'MESH' and armature_modifier(obj) is not None


@contextlib.contextmanager
def rest_pose(obj, depsgraph=None):
    """While inside, the object's Armature modifiers are off, so its evaluated mesh is the rest
    shape the flesh is prepared on (the settings are put back on the way out)."""
    saved = [(m, m.show_viewport, m.show_render) for m in obj.modifiers if m.type == 'ARMATURE']
    try:
        for modifier, _, _ in saved:
            modifier.show_viewport = modifier.show_render = False
        if depsgraph is not None and saved:
            depsgraph.update()
        yield
    finally:
        for modifier, viewport, render in saved:
            modifier.show_viewport, modifier.show_render = viewport, render
        if depsgraph is not None and saved:
            depsgraph.update()


def warnings_for(obj):
    """Sentences for the parts of the Armature modifier the simulation does not model."""
    modifier = armature_modifier(obj)
    out = []
    if modifier.use_bone_envelopes:
        out.append(f"'{modifier.name}' also deforms by bone envelopes: the simulation follows "
                   "its vertex groups only")
    if modifier.use_deform_preserve_volume:
        out.append(f"'{modifier.name}' preserves volume (dual quaternions): the simulation "
                   "follows the bones by linear blending, so joints may differ slightly")
    if modifier.vertex_group:
        out.append(f"'{modifier.name}' is masked by vertex group '{modifier.vertex_group}': "
                   "the simulation ignores the mask")
    if sum(m.type == 'ARMATURE' for m in obj.modifiers) > 1:
        out.append(f"'{obj.name}' has more than one Armature modifier: only '{modifier.name}' "
                   "drives the simulation")
    return out


def deform_bones(obj):
    """Names of the armature's deform bones that have a vertex group on the mesh."""
    rig = armature_modifier(obj).object
    return [bone.name for bone in rig.data.bones
            if bone.use_deform and obj.vertex_groups.get(bone.name) is not None]


def vertex_weights(obj, bones):
    """(n, b + 1) float64 skinning weights of the base vertices: one column per bone of
    ``bones``, normalised per vertex as the Armature modifier does, and a last column 1 for
    vertices no bone moves (they stay with the object)."""
    groups = [obj.vertex_groups[name].index for name in bones]
    weights = np.zeros((len(obj.data.vertices), len(bones) + 1))
    weights[:, :-1] = scene.group_weight_matrix(obj, groups)
    total = weights.sum(axis=1)
    moved = total > 1e-4                  # the modifier's own threshold for "no bone"
    weights[moved] /= total[moved, None]
    weights[~moved] = 0.0
    weights[~moved, -1] = 1.0
    return weights


def selected_bones(rig):
    """Names of the armature object's selected bones (the selection lives on the pose bones
    from Blender 5.0, on the bones before)."""
    pose = rig.pose.bones
    return [bone.name for bone in rig.data.bones
            if (pose[bone.name].select if hasattr(pose[bone.name], "select") else bone.select)]


def select_bones(rig, names):
    """Select exactly ``names`` among the armature's bones (either Blender's way)."""
    for bone in rig.data.bones:
        target = rig.pose.bones[bone.name] if hasattr(rig.pose.bones[bone.name], "select") \
            else bone
        target.select = bone.name in names


def bone_group_weights(obj, bones):
    """(n,) sum over ``bones`` of the vertices' weights in their vertex groups, at most 1."""
    groups = [obj.vertex_groups[name].index for name in bones]
    return np.minimum(scene.group_weight_matrix(obj, groups).sum(axis=1), 1.0)


def bone_transforms(obj, bones, blender_scene, frames):
    """(F, b + 1, 3, 4) world-from-rest affine transforms per frame: each bone's, then the
    object's own (for vertices no bone moves). The Armature modifier maps rest point X of the
    mesh to A P_b B_b^-1 A^-1 M X in world space, with A the armature's and M the mesh's world
    matrix, P_b the posed and B_b the rest bone matrix (armature space)."""
    if transforms.transforming():       # frame_set would undo the artist's move
        raise transforms.ArtistMoving()
    rig = armature_modifier(obj).object
    current = blender_scene.frame_current
    out = np.empty((len(frames), len(bones) + 1, 3, 4))
    rest_inverse = np.array([np.linalg.inv(np.array(rig.data.bones[name].matrix_local))
                             for name in bones]).reshape(-1, 4, 4)
    try:
        for f, frame in enumerate(frames):
            blender_scene.frame_set(frame)
            A, M = np.array(rig.matrix_world), np.array(obj.matrix_world)
            posed = np.array([np.array(rig.pose.bones[name].matrix)
                              for name in bones]).reshape(-1, 4, 4)
            to_armature = np.linalg.inv(A) @ M
            out[f, :-1] = (A @ posed @ rest_inverse @ to_armature)[:, :3, :]
            out[f, -1] = M[:3, :]
    finally:
        blender_scene.frame_set(current)
    return out


def require_follow_group(obj, has_pins):
    if not has_pins:
        raise InputError(f"'{obj.name}' is rigged but has no Follow Rig group: set the Pin "
                         "Group to the vertices that move exactly with the bones (the rest is "
                         "free flesh), then Prepare")


def rig_load(obj, blender_scene, body, frames, h, gravity, masses):
    """The ``solver.rig.RigLoad`` of a rigged body over ``frames`` (h [s] apart): the bones'
    motion and gravity (3,) [m/s^2, world] as its flesh feels them; masses (N,) [kg]."""
    bones = deform_bones(obj)
    transforms = bone_transforms(obj, bones, blender_scene, frames)
    weights = rig.node_weights(body.embedding, vertex_weights(obj, bones), body.nodes,
                               body.tets)
    motion = rig.RigMotion((np.array(frames) - frames[0]) * h, transforms)
    return rig.RigLoad(motion, weights, masses, body.deformer.basis, body.nodes,
                       gravity=gravity)


def skinned_placement(obj, motion, vertices):
    """Callable t [s] -> (A (k, 3, 3), b (k, 3)): the skinning that carries base ``vertices``
    (k,) from the rest space to the world along ``motion`` (a ``solver.rig.RigMotion`` of this
    body's deform bones), for ``dynamics.Simulation``'s ``sample_placement``."""
    weights = vertex_weights(obj, deform_bones(obj))[np.asarray(vertices, dtype=np.int64)]
    return lambda t: motion.placement(t, weights)


def rest_targets(obj, blender_scene, frames, tracks):
    """Handle tracks with their targets moved from the body's object space at each frame into
    its rest pose: through the inverse skinning of the handle (its vertices' mean bone weights),
    so a handle met in the rest pose lands on its Empty once the Armature modifier runs."""
    bones = deform_bones(obj)
    transforms = bone_transforms(obj, bones, blender_scene, frames)       # (F, b + 1, 3, 4)
    weights = vertex_weights(obj, bones)
    first = frames[0]
    out = []
    for track in tracks:
        rows = np.asarray(track.frames) - first
        skin = np.einsum("b,fbij->fij", weights[track.vertices].mean(axis=0), transforms[rows])
        world = transforms[rows, -1]                                       # the object's own
        points = np.einsum("fij,fj->fi", world[:, :, :3], track.targets) + world[:, :, 3]
        rest = np.linalg.solve(skin[:, :, :3], (points - skin[:, :, 3])[:, :, None])[:, :, 0]
        out.append(dataclasses.replace(track, targets=rest, rotation_frames=None,
                                       rotations=None))
    return out


def follow_stiffness(obj, body, masses):
    """The springs of the Follow Rig weights between 0 and the pin threshold
    (``solver.rig.follow_stiffness``, stiffest at the body's fastest mode; masses (N,) [kg]),
    or None when the group paints only 0 and pins."""
    weights = scene.group_weights(obj, obj.rs_elastic.pin_group)
    if not np.any((weights > 0.0) & (weights < rig.PIN_THRESHOLD)):
        return None
    follow = rig.node_values(body.embedding, weights, body.nodes, body.tets)[:, 0]
    omega = float(np.sqrt(np.max(body.linear_modes.eigenvalues)))
    return rig.follow_stiffness(follow, masses, body.deformer.basis, omega)
