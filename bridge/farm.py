"""A shot's bodies baked on a Flamenco farm, one task per body (the job type farm/rs_elastic_bake.js).

Submission, in the artist's Blender through the Flamenco add-on: the job type's `eval` reads
`scene.rs_elastic_farm.plan`, which is `plan_json` below: every body of the shot, how it is baked
(space-time edit or simulation, over which frames), the bodies whose bakes it needs, listed so
that those come first, and the file its bake goes to. The job type turns that list into tasks.

Each body's file is a new bake file of the extension's (`mesh_cache.new_bake_name`:
`<body>.<identity>.pc2` in `blendcache_<shot>/bakes/` next to the shot), its identity new at each
submission: tasks running side by side never write the same file, and a job never writes over
the files the shot plays. On a worker, each task runs the command line (bridge/cli.py) on the
shot without saving it: its body is baked to the file the job named for it, after the files of
the bodies it needs were set playing on them (`play_bakes`: their bake modifiers play them and
their records name them, as a bake in this Blender would). The last task (`collect`) checks that
every body's file is there, fits its body and plays in the body's Bake To form, and saves the
shot with them; the files the shot played before go once it is saved.

A body needs another body's bake when that bake moves or shapes what it reads (`needed_bakes`):
a collider that is itself a body (a simulation reads its colliders' evaluated meshes), or a vertex
parent or a surface-reading constraint (vertex-group subtarget, Shrinkwrap) on a body, anywhere up
the chains of the body itself, of its handles' Empties or of its colliders. A take is not one: it
is kept in the body's own shape keys, in the .blend.
"""
import contextlib
import json
import os
import shutil

import bpy
import numpy as np

from . import bake, colliders, constraints, mesh_cache, scene
from .scene import InputError

JOB_TYPE_FILE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "farm",
                             "rs_elastic_bake.js")
MANAGER_PROGRAMS = ("flamenco-manager", "flamenco-manager.exe")

# Parent types that place the child on the parent's deformed vertices (so on its bake).
DEFORMED_PARENTS = {'VERTEX', 'VERTEX_3'}

PLAYBACK_TOLERANCE = 1e-6   # of the body's size: float32 shape keys blend within ~1e-7


# --- the plan, read at submission ---------------------------------------------------------------

def farm_bodies(view_layer):
    """The shot's bodies: the view layer's mesh objects with a tet mesh (tetrahedralized or
    prepared), by name."""
    return sorted((obj for obj in view_layer.objects
                   if obj.type == 'MESH' and obj.rs_elastic.tets_key), key=lambda obj: obj.name)


def bake_mode(obj, frames):
    """'spacetime' for a body with something to solve for (a handle's Empty, a pose key in
    `frames`, or Edit the Take on), 'simulate' for any other."""
    settings = obj.rs_elastic
    if (settings.use_take or any(handle.empty is not None for handle in settings.handles)
            or constraints.read_pose_keys(obj, frames)):
        return "spacetime"
    return "simulate"


def _moved_by(obj, body_names, seen):
    """Names of the bodies whose deformation moves `obj`: a vertex parent up its parent chain,
    or a constraint reading a body's surface, through the chains of constraint targets too."""
    found = set()
    while obj is not None and obj.name not in seen:
        seen.add(obj.name)
        for constraint in getattr(obj, "constraints", ()):
            target = getattr(constraint, "target", None)
            if target is None:
                continue
            reads_surface = constraint.type == 'SHRINKWRAP' or getattr(constraint, "subtarget", "")
            if target.name in body_names and target.type == 'MESH' and reads_surface:
                found.add(target.name)
            found |= _moved_by(target, body_names, seen)
        if obj.parent is not None and obj.parent_type in DEFORMED_PARENTS \
                and obj.parent.name in body_names:
            found.add(obj.parent.name)
        obj = obj.parent
    return found


def needed_bakes(obj, mode, blender_scene, body_names):
    """Sorted names of the bodies whose bakes this body's bake reads (see the module's notes)."""
    sources = [obj]
    if mode == "spacetime":
        sources += [handle.empty for handle in obj.rs_elastic.handles if handle.empty is not None]
    elif obj.rs_elastic.use_collisions:
        sources += colliders.collider_objects(obj, blender_scene)
    needed, seen = set(), set()
    for source in sources:
        if source is not obj and source.name in body_names:      # a collider that is a body
            needed.add(source.name)
        needed |= _moved_by(source, body_names, seen)
    needed.discard(obj.name)
    return sorted(needed)


def dependency_order(needs):
    """Names of `needs` ({name: names it needs}) ordered so that each comes after what it needs,
    ties by name. Raises InputError naming the bodies of a cycle."""
    order, done, waiting = [], set(), dict(needs)
    while waiting:
        ready = sorted(name for name, after in waiting.items() if set(after) <= done)
        if not ready:
            links = "; ".join(f"'{a}' needs '{b}'" for a, b in _a_cycle(waiting, done))
            raise InputError(f"Bodies need each other's bakes in a circle ({links}): break one "
                             "link (a collider, a vertex parent or a constraint)")
        order.append(ready[0])
        done.add(ready[0])
        del waiting[ready[0]]
    return order


def _a_cycle(waiting, done):
    """[(name, name it needs)] around one cycle among `waiting` bodies, none of which is ready:
    follow unmet needs (the first by name) from the first body until one repeats."""
    path = [min(waiting)]
    while True:
        following = min(set(waiting[path[-1]]) - done)
        if following in path:
            loop = path[path.index(following):] + [following]
            return list(zip(loop, loop[1:]))
        path.append(following)


def plan(blender_scene, view_layer):
    """[{name, mode, frames "A-B", after [names], bake_file}] of the shot's bodies, each after
    the bodies it needs, `bake_file` a new bake file name of the body's. Raises InputError for a
    body without a valid frame range, or a cycle."""
    bodies = farm_bodies(view_layer)
    names = {obj.name for obj in bodies}
    entries = {}
    for obj in bodies:
        try:
            frames = scene.frame_range(obj, blender_scene)
        except InputError as exc:
            raise InputError(f"'{obj.name}': {exc}") from None
        mode = bake_mode(obj, frames)
        entries[obj.name] = dict(name=obj.name, mode=mode, frames=f"{frames[0]}-{frames[-1]}",
                                 after=needed_bakes(obj, mode, blender_scene, names),
                                 bake_file=mesh_cache.new_bake_name(obj))
    order = dependency_order({name: entry["after"] for name, entry in entries.items()})
    return [entries[name] for name in order]


def plan_json(blender_scene):
    """`plan` as the JSON string the job type reads: {"bodies": [...]}, or {"error": "..."} for
    the job type to refuse the submission with."""
    context = bpy.context
    view_layer = (context.view_layer if context.scene == blender_scene
                  else blender_scene.view_layers[0])
    try:
        return json.dumps({"bodies": plan(blender_scene, view_layer)})
    except InputError as exc:
        return json.dumps({"error": str(exc)})


class RSElasticFarm(bpy.types.PropertyGroup):
    """Read by the job type's `eval` at submission (scene.rs_elastic_farm.plan)."""
    plan: bpy.props.StringProperty(
        name="Farm Plan", get=lambda self: plan_json(self.id_data),
        description="The shot's bodies, how each is baked, whose bakes it needs and the file "
                    "its bake goes to (JSON, for the Flamenco job type rs-elastic-bake)")


# --- on the farm ----------------------------------------------------------------------------------

def bake_path(obj, file_name):
    """The path of the farm bake `file_name` of `obj` in the shot's bakes folder; InputError
    unless it is a bake file name of that body (``mesh_cache.bake_name``: no folder, the body's
    name, an identity)."""
    if mesh_cache.identity_of(obj, file_name) is None:
        raise InputError(f"'{file_name}' is not a bake file name of '{obj.name}' (expected "
                         f"{mesh_cache.bake_name(obj, '<16 hex digits>')})")
    return os.path.join(mesh_cache.bakes_folder(), file_name)


def farm_bake(obj, path, blender_scene, read=True):
    """(frames, poses (F, n, 3) float32 or None unless `read`) of the body's farm bake at
    `path`, checked against the body: InputError if it is missing, unreadable, or its vertex or
    frame count is not the body's."""
    frames = scene.frame_range(obj, blender_scene)
    try:
        samples, points = mesh_cache.read_pc2_header(path)
        poses = mesh_cache.read_pc2(path)[0] if read else None
    except FileNotFoundError:
        raise InputError(f"'{obj.name}' has no farm bake: {path} is missing") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"'{obj.name}': its farm bake cannot be read: {exc}") from None
    if points != len(obj.data.vertices):
        raise InputError(f"'{obj.name}': its farm bake {path} has {points} vertices, its mesh "
                         f"{len(obj.data.vertices)}")
    if samples != len(frames):
        raise InputError(f"'{obj.name}': its farm bake {path} has {samples} frames, its frame "
                         f"range {frames[0]}-{frames[-1]} has {len(frames)}")
    return frames, poses


def play_bakes(bakes, blender_scene):
    """Set the farm bakes `bakes` ([(body, path)]: the bodies a task's body needs) playing on
    their bodies, each from the first frame of its range, as their bakes. InputError if one is
    missing or does not fit."""
    for obj, path in bakes:
        frames, _ = farm_bake(obj, path, blender_scene, read=False)
        bake.play_cache_bake(obj, frames[0], path)


@contextlib.contextmanager
def _only_the_bake(obj):
    """While inside, the object's other modifiers and its own shape keys are off, so its
    evaluated mesh is what the bake plays."""
    keys = obj.data.shape_keys
    blocks = [] if keys is None else [b for b in keys.key_blocks[1:] if bake.role(keys, b) is None]
    modifiers = [m for m in obj.modifiers if not mesh_cache.is_bake_modifier(obj, m)]
    saved = [(m, m.show_viewport) for m in modifiers], [(b, b.mute) for b in blocks]
    for modifier in modifiers:
        modifier.show_viewport = False
    for block in blocks:
        block.mute = True
    try:
        yield
    finally:
        for modifier, shown in saved[0]:
            modifier.show_viewport = shown
        for block, mute in saved[1]:
            block.mute = mute


def playback_error(obj, blender_scene, frames, poses):
    """Largest distance between what plays and the bake on the first, middle and last frames, as
    a fraction of the body's size (its first pose's bounding-box diagonal)."""
    size = float(np.linalg.norm(poses[0].max(axis=0) - poses[0].min(axis=0)))
    current, worst = blender_scene.frame_current, 0.0
    with _only_the_bake(obj):
        try:
            for frame in sorted({frames[0], frames[len(frames) // 2], frames[-1]}):
                blender_scene.frame_set(frame)
                mesh = obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).data
                played = np.empty(len(mesh.vertices) * 3)
                mesh.vertices.foreach_get("co", played)
                if played.size != poses[0].size:
                    return np.inf
                worst = max(worst, float(np.abs(played.reshape(-1, 3)
                                                - poses[frame - frames[0]]).max()))
        finally:
            blender_scene.frame_set(current)
    return worst / size


def collect(bakes, blender_scene):
    """The farm's last step: every farm bake of `bakes` ([(body, path)]), checked, made its
    body's bake in its Bake To form (its bake modifier playing the .pc2, or shape keys written
    from it), then checked to play. Raises InputError naming the first body whose bake is
    missing or does not play. No file is deleted: returns the bake files the shot no longer
    plays (its earlier bakes, the farm's files of shape-key bodies), for
    ``mesh_cache.discard`` once the shot is saved."""
    checked = [(obj, path, *farm_bake(obj, path, blender_scene)) for obj, path in bakes]
    unplayed = {path for obj, path, _, _ in checked if obj.rs_elastic.bake_to != 'CACHE'}
    for obj, path, frames, poses in checked:
        unplayed.add(mesh_cache.bake_file(obj))
        if obj.rs_elastic.bake_to == 'CACHE':
            bake.play_cache_bake(obj, frames[0], path)
        else:
            bake.write_bake(obj, frames, poses)
    for obj, path, frames, poses in checked:
        error = playback_error(obj, blender_scene, frames, poses)
        if not error <= PLAYBACK_TOLERANCE:
            raise InputError(f"'{obj.name}': its farm bake does not play as baked (off by "
                             f"{error:.3g} of its size)")
    return sorted(p for p in unplayed if p is not None)


def write_job_type(folder):
    """Copy the job type into a Flamenco Manager's `scripts` folder: `folder` itself, or the
    `scripts` folder beside the manager's program when `folder` holds it. Returns the path."""
    folder = os.path.abspath(bpy.path.abspath(folder))
    if not os.path.isdir(folder):
        raise InputError(f"{folder} is not a folder")
    if any(os.path.isfile(os.path.join(folder, name)) for name in MANAGER_PROGRAMS):
        folder = os.path.join(folder, "scripts")
    target = os.path.join(folder, os.path.basename(JOB_TYPE_FILE))
    try:
        os.makedirs(folder, exist_ok=True)
        shutil.copyfile(JOB_TYPE_FILE, target + ".part")
        os.replace(target + ".part", target)
    except OSError as exc:
        raise InputError(f"Could not write {target}: {exc}") from None
    return target


def register():
    bpy.utils.register_class(RSElasticFarm)
    bpy.types.Scene.rs_elastic_farm = bpy.props.PointerProperty(type=RSElasticFarm)


def unregister():
    del bpy.types.Scene.rs_elastic_farm
    bpy.utils.unregister_class(RSElasticFarm)
