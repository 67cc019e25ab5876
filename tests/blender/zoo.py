"""The scene zoo (issue 26): cases generated from independent scene features, each run through
every operator and the command line, with invariants checked after every step.

A case is one value of each axis:

    modifier   none, every type of `bpy.types.Modifier`'s enum that a mesh takes (with a minimal
               valid setup: targets, groups, binds), Geometry Nodes as pass-through, deforming,
               instancing and generating node groups
    added      the modifier is in the file from the start, or added after Prepare Body
    transform  identity, non-uniform scale, negative scale, an animated parent
    mode       Object, Edit, Sculpt, Weight Paint (each operator runs in it)
    linkage    single, linked duplicate (a shared mesh), library-linked, library override
    target     shape keys, Mesh Cache
    frames     3, 4, 24
    baker      Simulate and Bake, Solve and Bake, the command line simulating or solving

`cases()` draws them (pairwise coverage, seeded); `run(spec)` runs one case inside a Blender
child process (see tests/blender/test_zoo.py) and writes what it saw, step by step, to a report.
The invariants (each a `Violation`'s `invariant`):

    traceback  no Python traceback reaches the user: an operator returns FINISHED or CANCELLED
               or raises a RuntimeError of exactly one line, nothing prints a traceback (handlers,
               draw code), the command line ends with 0, 1 or 2 and one line
    refusal    an operator that refuses (CANCELLED or an error) or fails changes nothing: the
               objects, the user's data, the extension's results and keys, the files on disk;
               the command line saves nothing when it fails
    playback   a bake plays back what the operator baked (the evaluated mesh, depsgraph, within
               1e-6 of the diagonal), and still does after undo and redo, save and reopen,
               save-as to another folder and reopen
    undo       undo brings back the state before the operator, redo the state after it
    reopen     save and reopen change nothing
    clear      Clear Bake removes the bake, its modifier and file, and leaves the user's data as
               it was before the bake
    preview    the mode preview, ticked and unticked, leaves the file as it was
    panel      every panel draws for the body in each state
    time       a case ends within its time bound (RS_ELASTIC_ZOO_TIMEOUT, 120 s)
    crash      Blender does not die
    harness    the scene could not be built (a zoo bug, or Blender refused the combination)
"""
import ctypes
import dataclasses
import hashlib
import itertools
import json
import os
import pathlib
import random
import re
import struct
import subprocess
import sys
import time
import traceback

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[2]
HERE = pathlib.Path(__file__).resolve().parent

# --- the matrix -------------------------------------------------------------------------------

NODE_VARIANTS = ("passthrough", "deform", "instance", "generate")
ADDED = ("first", "afterprep")
TRANSFORMS = ("identity", "nonuniform", "negscale", "animparent")
MODES = ("object", "edit", "sculpt", "weightpaint")
LINKAGES = ("single", "linked_dup", "library", "override")
TARGETS = ("keys", "cache")
FRAMES = (3, 4, 24)
BAKERS = ("simulate", "spacetime", "cli_simulate", "cli_spacetime")
AXES = ("modifier", "added", "transform", "mode", "linkage", "target", "frames", "baker")

BLENDER_MODE = {"object": 'OBJECT', "edit": 'EDIT', "sculpt": 'SCULPT',
                "weightpaint": 'WEIGHT_PAINT'}
SEED = 26
SAMPLE_SIZE = 40          # cases in `make test`; `make test-zoo` runs the whole pairwise set
TOLERANCE = 1e-6          # of the body's diagonal


@dataclasses.dataclass(frozen=True)
class Case:
    modifier: str
    added: str
    transform: str
    mode: str
    linkage: str
    target: str
    frames: int
    baker: str

    @property
    def id(self):
        return (f"{self.modifier}-{self.added}-{self.transform}-{self.mode}-{self.linkage}-"
                f"{self.target}-{self.frames}f-{self.baker}")


def mesh_modifier_types():
    """The types of `bpy.types.Modifier`'s enum that Blender adds to a mesh object (the others
    belong to Grease Pencil or volumes: `modifiers.new` returns None for them)."""
    import bpy
    mesh = bpy.data.meshes.new("zoo probe")
    probe = bpy.data.objects.new("zoo probe", mesh)
    try:
        kinds = []
        for item in bpy.types.Modifier.bl_rna.properties["type"].enum_items:
            modifier = probe.modifiers.new(item.identifier, item.identifier)
            if modifier is not None:
                kinds.append(item.identifier)
                probe.modifiers.remove(modifier)
        return kinds
    finally:
        bpy.data.objects.remove(probe)
        bpy.data.meshes.remove(mesh)


def axis_values(modifier_types):
    """{axis: values}; Geometry Nodes stands for one value per node-group variant."""
    modifiers = ["none"]
    for kind in modifier_types:
        modifiers += [f"NODES_{v}" for v in NODE_VARIANTS] if kind == 'NODES' else [kind]
    return {"modifier": modifiers, "added": ADDED, "transform": TRANSFORMS, "mode": MODES,
            "linkage": LINKAGES, "target": TARGETS, "frames": FRAMES, "baker": BAKERS}


def is_valid(values):
    """Whether a (partial) case {axis: value} can be built: Blender refuses Edit, Sculpt and
    Weight Paint on linked data (a library-linked object, or an override's linked mesh), and
    a modifier on a library-linked object; no modifier is added only once."""
    mode, linkage, added = values.get("mode"), values.get("linkage"), values.get("added")
    if mode not in (None, "object") and linkage not in (None, "single", "linked_dup"):
        return False
    if added == "afterprep" and (linkage == "library" or values.get("modifier") == "none"):
        return False
    return True


def product_size(values):
    """Cases in the full product of the axes (invalid combinations left out)."""
    return sum(1 for combo in itertools.product(*(values[a] for a in AXES))
               if is_valid(dict(zip(AXES, combo))))


def pair(a, b):
    """Two (axis, value) items as one pair, in the order of AXES."""
    return (a, b) if AXES.index(a[0]) < AXES.index(b[0]) else (b, a)


def pairs_of(case_values):
    """Every pair of (axis, value) items in a (partial) case {axis: value}."""
    return {pair(a, b) for a, b in itertools.combinations(case_values.items(), 2)}


def valid_pairs(values):
    return sorted((pair((a, va), (b, vb)) for a, b in itertools.combinations(AXES, 2)
                   for va, vb in itertools.product(values[a], values[b])
                   if is_valid({a: va, b: vb})), key=repr)


def pairwise(values, seed=SEED, candidates=24):
    """Cases in which every valid pair of values of two axes meets at least once (a greedy
    covering array, AETG-style), in the order built: each case covers as many new pairs as the
    best of `candidates` seeded tries, so the first cases are the broadest sample."""
    rng = random.Random(seed)
    uncovered = valid_pairs(values)
    left = set(uncovered)

    def new_pairs(chosen, axis, value):
        if not is_valid(dict(chosen, **{axis: value})):
            return -1
        return sum(pair((axis, value), item) in left for item in chosen.items())

    def candidate():
        (a, va), (b, vb) = rng.choice(uncovered)       # starts from a pair still missing
        chosen = {a: va, b: vb}
        for axis in rng.sample([x for x in AXES if x not in chosen], len(AXES) - 2):
            chosen[axis] = max(values[axis],
                               key=lambda v: (new_pairs(chosen, axis, v), rng.random()))
        return chosen

    cases = []
    while uncovered:
        best = max((candidate() for _ in range(candidates)),
                   key=lambda chosen: len(pairs_of(chosen) & left))
        left -= pairs_of(best)
        uncovered = [p for p in uncovered if p in left]
        cases.append(Case(**best))
    return cases


def cases(full, modifier_types=None, sample=SAMPLE_SIZE):
    """The zoo's cases: the whole pairwise set (`full`), or its first `sample` cases."""
    values = axis_values(mesh_modifier_types() if modifier_types is None else modifier_types)
    drawn = pairwise(values)
    return drawn if full else drawn[:sample]


# --- what went wrong --------------------------------------------------------------------------

@dataclasses.dataclass
class Violation:
    step: str
    invariant: str
    message: str          # one line

    def line(self):
        return f"{self.step}: {self.invariant}: {self.message}"


TRACEBACK = "Traceback (most recent call last)"


def traceback_summary(text):
    """One line for the first traceback in `text`: its exception and the innermost place."""
    lines = text[text.index(TRACEBACK):].splitlines()[1:]
    place = ""
    for line in lines:
        match = re.match(r'\s*File "([^"]+)", line (\d+), in (\S+)', line)
        if match:
            place = f"{os.path.basename(match.group(1))}:{match.group(2)} in {match.group(3)}"
        elif line and not line[0].isspace():
            return f"{line.strip()} ({place})" if place else line.strip()
    return "a traceback without its exception line"


def first_line(exc):
    text = str(exc)
    if TRACEBACK in text:
        return traceback_summary(text)
    lines = [l for l in text.strip().splitlines() if l.strip()]
    return f"{type(exc).__name__}: {lines[0] if lines else ''}"


def normalised(message):
    """A message with its numbers and paths blurred, to group failures by cause."""
    message = re.sub(r"(/[^\s'\"]+)+", "<path>", message)
    message = re.sub(r"\d+(\.\d+)?(e[-+]?\d+)?", "#", message)
    return message


# --- inside Blender: captured output ----------------------------------------------------------

class Captured:
    """Everything written to file descriptors 1 and 2 (Python's and Blender's own prints)
    while inside, in `.text`; the harness's own writes go to the report file instead."""

    def __init__(self, folder):
        self.path = os.path.join(folder, "captured.txt")
        self.text = ""

    def __enter__(self):
        self._flush()
        self._file = open(self.path, "w+b")
        self._saved = os.dup(1), os.dup(2)
        os.dup2(self._file.fileno(), 1)
        os.dup2(self._file.fileno(), 2)
        return self

    def __exit__(self, *exc):
        self._flush()
        os.dup2(self._saved[0], 1)
        os.dup2(self._saved[1], 2)
        for fd in self._saved:
            os.close(fd)
        self._file.seek(0)
        self.text = self._file.read().decode(errors="replace")
        self._file.close()
        sys.stdout.write(self.text)        # still shown in the child's own output
        return False

    @staticmethod
    def _flush():
        sys.stdout.flush()
        sys.stderr.flush()
        ctypes.CDLL(None).fflush(None)     # Blender's C stdio buffers


# --- inside Blender: scene features -----------------------------------------------------------

def _bpy():
    import bpy
    return bpy


def _cube_mesh(name, centre, size):
    bpy = _bpy()
    c, h = np.asarray(centre, float), size / 2.0
    corners = [c + h * np.array(s) for s in itertools.product((-1, 1), repeat=3)]
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([tuple(v) for v in corners], [], faces)
    mesh.update()
    return mesh


def _add_object(name, data, location=(0.0, 0.0, 0.0)):
    bpy = _bpy()
    obj = bpy.data.objects.new(name, data)
    obj.location = location
    bpy.context.scene.collection.objects.link(obj)
    return obj


def target_mesh(name="Zoo Target", centre=(4.0, 0.5, 0.5), size=0.5):
    return _add_object(name, _cube_mesh(name, centre, size))


def empty(name, location):
    return _add_object(name, None, location)


def node_group(variant):
    """A Geometry Nodes group: pass-through, deforming (Set Position), instancing (a cube on
    every point, joined with the input) or generating (a separate cube joined with it)."""
    bpy = _bpy()
    group = bpy.data.node_groups.new(f"Zoo {variant}", 'GeometryNodeTree')
    group.interface.new_socket("Geometry", in_out='INPUT', socket_type='NodeSocketGeometry')
    group.interface.new_socket("Geometry", in_out='OUTPUT', socket_type='NodeSocketGeometry')
    nodes, links = group.nodes, group.links
    geometry = nodes.new('NodeGroupInput').outputs[0]
    output = nodes.new('NodeGroupOutput')
    if variant == "deform":
        move = nodes.new('GeometryNodeSetPosition')
        move.inputs["Offset"].default_value = (0.0, 0.0, 0.1)
        links.new(geometry, move.inputs["Geometry"])
        geometry = move.outputs["Geometry"]
    elif variant in ("instance", "generate"):
        cube = nodes.new('GeometryNodeMeshCube')
        cube.inputs["Size"].default_value = (0.1, 0.1, 0.1) if variant == "instance" else (1, 1, 1)
        join = nodes.new('GeometryNodeJoinGeometry')
        if variant == "instance":
            instances = nodes.new('GeometryNodeInstanceOnPoints')
            links.new(geometry, instances.inputs["Points"])
            links.new(cube.outputs["Mesh"], instances.inputs["Instance"])
            extra = instances.outputs["Instances"]
        else:
            moved = nodes.new('GeometryNodeTransform')
            moved.inputs["Translation"].default_value = (6.0, 0.5, 0.5)
            links.new(cube.outputs["Mesh"], moved.inputs["Geometry"])
            extra = moved.outputs["Geometry"]
        links.new(extra, join.inputs[0])
        links.new(geometry, join.inputs[0])
        geometry = join.outputs[0]
    links.new(geometry, output.inputs[0])
    return group


def _write_pc2(path, positions):
    """A user's own point cache: (F, n, 3) poses, start 0, rate 1."""
    positions = np.ascontiguousarray(positions, dtype="<f4")
    with open(path, "wb") as f:
        f.write(b"POINTCACHE2\0" + struct.pack("<iiffi", 1, positions.shape[1], 0.0, 1.0,
                                                 positions.shape[0]))
        f.write(positions.tobytes())


def _armature(obj):
    bpy = _bpy()
    rig = _add_object("Zoo Rig", bpy.data.armatures.new("Zoo Rig"))
    _with_active(rig, 'EDIT', lambda: _add_bone(rig))
    group = obj.vertex_groups.new(name="Bone")
    group.add(list(range(len(obj.data.vertices))), 1.0, 'REPLACE')
    return rig


def _add_bone(rig):
    bone = rig.data.edit_bones.new("Bone")
    bone.head, bone.tail = (0.0, 0.5, 0.5), (4.0, 0.5, 0.5)


def _with_active(obj, mode, action):
    """Run `action` with `obj` active in `mode`, then give the body back its place."""
    bpy = _bpy()
    body = bpy.context.view_layer.objects.active
    bpy.context.view_layer.objects.active = obj
    bpy.ops.object.mode_set(mode=mode)
    try:
        return action()
    finally:
        bpy.ops.object.mode_set(mode='OBJECT')
        bpy.context.view_layer.objects.active = body


def _lattice():
    bpy = _bpy()
    lattice = _add_object("Zoo Lattice", bpy.data.lattices.new("Zoo Lattice"), (2.0, 0.5, 0.5))
    lattice.scale = (4.4, 1.2, 1.2)
    return lattice


def _curve():
    bpy = _bpy()
    curve = bpy.data.curves.new("Zoo Curve", 'CURVE')
    curve.dimensions = '3D'
    spline = curve.splines.new('POLY')
    spline.points.add(2)
    for point, x in zip(spline.points, (0.0, 2.0, 4.0)):
        point.co = (x, 0.0, 0.2 * x * x / 4.0, 1.0)
    return _add_object("Zoo Curve", curve)


def _volume():
    """A volume object made from a mesh by its own Mesh to Volume modifier."""
    bpy = _bpy()
    volume = _add_object("Zoo Volume", bpy.data.volumes.new("Zoo Volume"))
    modifier = volume.modifiers.new("To Volume", 'MESH_TO_VOLUME')
    modifier.object = target_mesh("Zoo Volume Source", (2.0, 0.5, 0.5), 1.0)
    return volume


def _bind(operator, modifier):
    """Bind a deform modifier the way its Bind button does (the body is active)."""
    operator(modifier=modifier.name)


def add_modifier(obj, label, folder):
    """The modifier `label` on the body, with a minimal valid setup."""
    bpy = _bpy()
    if label == "none":
        return None
    if label.startswith("NODES_"):
        modifier = obj.modifiers.new("GeometryNodes", 'NODES')
        modifier.node_group = node_group(label[len("NODES_"):])
        return modifier
    if label == 'EXPLODE':
        obj.modifiers.new("Particles", 'PARTICLE_SYSTEM')
    modifier = obj.modifiers.new(label.title(), label)
    setup = _SETUPS.get(label)
    if setup is not None:
        setup(obj, modifier, folder)
    return modifier


def _hook(obj, modifier, folder):
    hook = empty("Zoo Hook", (4.0, 0.5, 0.5))
    modifier.object, modifier.vertex_group = hook, "Zoo Weights"
    _bpy().context.view_layer.update()
    # What Reset does: the hook starts where it is, so the mesh moves only when it moves.
    modifier.matrix_inverse = hook.matrix_world.inverted() @ obj.matrix_world


def _mesh_cache(obj, modifier, folder):
    rest = np.array([v.co[:] for v in obj.data.vertices])
    path = os.path.join(folder, "user_cache.pc2")
    _write_pc2(path, np.stack([rest, rest + (0.0, 0.0, 0.05)]))
    modifier.cache_format, modifier.filepath = 'PC2', path


def _multires(obj, modifier, folder):
    _bpy().ops.object.multires_subdivide(modifier=modifier.name, mode='CATMULL_CLARK')


def _particle_instance(obj, modifier, folder):
    source = target_mesh("Zoo Emitter", (0.0, 3.0, 0.0), 0.5)
    source.modifiers.new("Particles", 'PARTICLE_SYSTEM').particle_system.settings.count = 4
    modifier.object = source


_SETUPS = {
    'ARMATURE': lambda obj, m, folder: setattr(m, "object", _armature(obj)),
    'BOOLEAN': lambda obj, m, folder: setattr(m, "object", target_mesh()),
    'CURVE': lambda obj, m, folder: setattr(m, "object", _curve()),
    'DATA_TRANSFER': lambda obj, m, folder: setattr(m, "object", target_mesh()),
    'DECIMATE': lambda obj, m, folder: setattr(m, "ratio", 0.5),
    'FLUID': lambda obj, m, folder: setattr(m, "fluid_type", 'EFFECTOR'),
    'HOOK': _hook,
    'LAPLACIANDEFORM': lambda obj, m, folder: (
        setattr(m, "vertex_group", "Pin"), _bind(_bpy().ops.object.laplaciandeform_bind, m)),
    'LATTICE': lambda obj, m, folder: setattr(m, "object", _lattice()),
    'MASK': lambda obj, m, folder: setattr(m, "vertex_group", "Zoo Weights"),
    'MESH_CACHE': _mesh_cache,
    'MESH_DEFORM': lambda obj, m, folder: (
        setattr(m, "object", target_mesh("Zoo Cage", (2.0, 0.5, 0.5), 5.0)),
        setattr(m, "precision", 2), _bind(_bpy().ops.object.meshdeform_bind, m)),
    'MULTIRES': _multires,
    'PARTICLE_INSTANCE': _particle_instance,
    'SHRINKWRAP': lambda obj, m, folder: setattr(m, "target", target_mesh()),
    'SURFACE_DEFORM': lambda obj, m, folder: (
        setattr(m, "target", target_mesh("Zoo Surface", (2.0, 0.5, 0.5), 1.2)),
        _bind(_bpy().ops.object.surfacedeform_bind, m)),
    'VERTEX_WEIGHT_EDIT': lambda obj, m, folder: setattr(m, "vertex_group", "Zoo Weights"),
    'VERTEX_WEIGHT_MIX': lambda obj, m, folder: setattr(m, "vertex_group_a", "Zoo Weights"),
    'VERTEX_WEIGHT_PROXIMITY': lambda obj, m, folder: (
        setattr(m, "vertex_group", "Zoo Weights"), setattr(m, "target", target_mesh()),
        setattr(m, "proximity_mode", 'OBJECT')),
    'VOLUME_TO_MESH': lambda obj, m, folder: setattr(m, "object", _volume()),
    'WARP': lambda obj, m, folder: (
        setattr(m, "object_from", empty("Zoo Warp From", (2.0, 0.5, 0.5))),
        setattr(m, "object_to", empty("Zoo Warp To", (2.0, 0.5, 0.8)))),
}


def apply_transform(obj, kind, frames):
    if kind == "nonuniform":
        obj.scale = (1.0, 1.5, 0.5)
    elif kind == "negscale":
        obj.scale = (1.0, 1.0, -1.0)
    elif kind == "animparent":
        parent = empty("Zoo Parent", (0.0, 0.0, 0.0))
        for frame, location, turn in ((1, (0.0, 0.0, 0.0), 0.0), (frames, (0.0, 0.5, 1.0), 0.3)):
            parent.location, parent.rotation_euler = location, (0.0, 0.0, turn)
            parent.keyframe_insert("location", frame=frame)
            parent.keyframe_insert("rotation_euler", frame=frame)
        obj.parent = parent


def build_body(case, folder):
    """The body of `case` in the open (empty) file: a coarse pinned bar with its features."""
    bpy = _bpy()
    from blender_helpers import make_bar, vertices
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, case.frames
    obj = make_bar()
    settings = obj.rs_elastic
    settings.edge_length, settings.num_modes = 0.15, 6
    settings.use_scene_range = False
    settings.frame_start, settings.frame_end = 1, case.frames
    settings.bake_to = case.target.upper()
    # A generating modifier (Skin on a closed bar) can hand the mesher a surface it works on for
    # minutes: the time limit the user would set keeps the case within its bound, refused.
    settings.mesher_time_limit = 10.0
    x = vertices(obj)[:, 0]
    obj.vertex_groups.new(name="Tip").add([int(i) for i in np.flatnonzero(x > 4.0 - 1e-9)],
                                          1.0, 'REPLACE')
    obj.vertex_groups.new(name="Zoo Weights").add([int(i) for i in np.flatnonzero(x > 2.0)],
                                                  0.5, 'REPLACE')
    apply_transform(obj, case.transform, case.frames)
    bpy.context.view_layer.update()
    if case.added == "first":
        add_modifier(obj, case.modifier, folder)
    bpy.context.view_layer.objects.active = obj
    return obj


def link_from_library(case, lib_path):
    """Open an empty file and bring in the library's collection: linked, or overridden."""
    bpy = _bpy()
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, case.frames
    with bpy.data.libraries.load(str(lib_path), link=True) as (_, into):
        into.collections = ["Zoo"]
    collection = into.collections[0]
    scene.collection.children.link(collection)
    if case.linkage == "override":
        collection.override_hierarchy_create(scene, bpy.context.view_layer,
                                             do_fully_editable=True)
        if collection.name in scene.collection.children:
            scene.collection.children.unlink(collection)
    bpy.context.view_layer.update()


def build_scene(case, folders):
    """Build the case's scene and save it as scene/shot.blend. Returns nothing: the body is
    found again by name (`body()`)."""
    bpy = _bpy()
    from blender_helpers import make_active
    bpy.ops.wm.read_homefile(use_empty=True)
    obj = build_body(case, str(folders["scene"]))
    if case.linkage == "linked_dup":
        twin = obj.copy()                        # Alt+D: the mesh is shared
        twin.name = "Bar Twin"
        twin.location.y += 3.0
        bpy.context.scene.collection.objects.link(twin)
    elif case.linkage in ("library", "override"):
        scene = bpy.context.scene
        zoo = bpy.data.collections.new("Zoo")
        scene.collection.children.link(zoo)
        for other in list(scene.collection.objects):
            zoo.objects.link(other)
            scene.collection.objects.unlink(other)
        lib = folders["lib"] / "lib.blend"
        bpy.ops.wm.save_as_mainfile(filepath=str(lib))
        link_from_library(case, lib)
    bpy.context.scene.frame_set(1)           # every animated object where its keys put it
    make_active(body())
    bpy.ops.wm.save_as_mainfile(filepath=str(folders["scene"] / "shot.blend"))


def body():
    bpy = _bpy()
    return bpy.context.view_layer.objects.get("Bar")


# --- inside Blender: what the state is --------------------------------------------------------

def files_state(folders):
    """{path: sha1} of every file the case's scene owns on disk."""
    state = {}
    for name in ("scene", "other", "lib", "cli"):
        for path in sorted(folders[name].rglob("*")):
            if path.is_file():
                state[str(path.relative_to(folders["root"]))] = hashlib.sha1(
                    path.read_bytes()).hexdigest()
    return state


def modifiers_state(obj):
    rows = []
    for m in obj.modifiers:
        row = [m.name, m.type, m.show_viewport, m.show_render]
        if m.type == 'MESH_CACHE':    # what it plays (a save-as plays the new file's own copy)
            path = _bpy().path.abspath(m.filepath)
            content = hashlib.sha1(open(path, "rb").read()).hexdigest() \
                if os.path.isfile(path) else "no file"
            row += [content, m.frame_start]
        rows.append(tuple(row))
    return rows


def mesh_and_settings(obj):
    """Hash of a mesh object's vertices, faces, every shape key (the extension's too: data,
    value, mute, tags) and every setting and result in obj.rs_elastic."""
    from blender_helpers import _rna_values, vertices
    h = hashlib.sha256(vertices(obj).tobytes())
    h.update(repr([p.vertices[:] for p in obj.data.polygons]).encode())
    keys = obj.data.shape_keys
    if keys is not None:
        tags = keys.get("rs_elastic")
        h.update(repr(None if tags is None else tags.to_dict()).encode())
        for block in keys.key_blocks:
            co = np.empty(len(block.data) * 3)
            block.data.foreach_get("co", co)
            h.update(repr((block.name, block.value, block.mute)).encode() + co.tobytes())
    # Where the bake's file is (it moves with a save-as): the modifier's row says what it plays.
    h.update(repr(_rna_values(obj.rs_elastic, skip=("cache_bake_file",))).encode())
    return h.hexdigest()


def scene_state(folders=None):
    """What a refused operator must leave alone: the objects, the user's data, each mesh
    object's mesh, shape keys, settings, results and modifiers, and (with `folders`) the files
    on disk."""
    bpy = _bpy()
    from blender_helpers import user_fingerprint
    state = {"the objects": repr(sorted((o.name, o.library.name if o.library else "")
                                        for o in bpy.data.objects)),
             "the user's data": user_fingerprint()}
    for obj in sorted(bpy.data.objects, key=lambda o: (o.name, repr(o.library))):
        if obj.type == 'MESH':
            where = f" ({obj.library.name})" if obj.library else ""
            state[f"'{obj.name}'{where}: mesh, keys, settings"] = mesh_and_settings(obj)
            state[f"'{obj.name}'{where}: modifiers"] = repr(modifiers_state(obj))
    if folders is not None:
        state["files"] = files_state(folders)
    return state


# A stage a refused Prepare finished stays in the cache, keyed by its inputs: the Prepare after the
# fix (pins, say) reuses it. Only these files may appear when Prepare or Tetrahedralize refuse.
STAGE_FILE = re.compile(r"blendcache_[^/]+/[^/]+\.(tets|modes|reduced|energy)\.[0-9a-f]{16}\.npz")


def state_difference(before, after, new_files_allowed=None):
    """One line naming what changed between two states (new files matching the regular
    expression `new_files_allowed` aside)."""
    changed = []
    for key in before.keys() | after.keys():
        if key == "files":
            continue
        if before.get(key) != after.get(key):
            changed.append(key)
    if "files" in before and before["files"] != after.get("files"):
        a, b = before["files"], after["files"]
        names = sorted({p for p in a.keys() | b.keys() if a.get(p) != b.get(p)
                        if not (new_files_allowed and p not in a
                                and new_files_allowed.fullmatch(p.split("/", 1)[-1]))})
        if names:
            changed.append("files " + ", ".join(names[:4]) + (" …" if len(names) > 4 else ""))
    return "; ".join(sorted(changed))


# --- inside Blender: the bake as it plays -----------------------------------------------------

class BakeRecorder:
    """Records every bake the extension writes (object name, frames, poses), by wrapping
    `bridge.bake.write_bake`, which every operator bakes through."""

    def __init__(self, ext):
        self.calls = []
        bake = ext.bridge.bake
        original = bake.write_bake

        def write_bake(obj, frames, positions):
            result = original(obj, frames, positions)
            self.calls.append((obj.name, [int(f) for f in frames],
                               np.array(positions, dtype=np.float64)))
            return result
        bake.write_bake = write_bake

    def save(self, path):
        if self.calls:
            name, frames, poses = self.calls[-1]
            np.savez(path, frames=np.array(frames), poses=poses)


def played(obj, frames):
    """(len(frames), n, 3) evaluated positions of the body's bake: a copy of the object that
    keeps only the extension's own modifier (so the user's modifiers, generating or simulating,
    do not blur what the bake plays), evaluated through the depsgraph on each frame."""
    bpy = _bpy()
    from blender_helpers import evaluated_vertices
    scene = bpy.context.scene
    current = scene.frame_current
    probe = obj.copy()
    probe.name = "Zoo Playback Probe"
    probe.parent = None
    for modifier in list(probe.modifiers):
        if not (modifier.type == 'MESH_CACHE' and modifier.name == "RS Elastic Bake"):
            probe.modifiers.remove(modifier)
    scene.collection.objects.link(probe)
    try:
        out = []
        for frame in frames:
            scene.frame_set(frame)
            out.append(evaluated_vertices(probe))
        return np.array(out)
    finally:
        bpy.data.objects.remove(probe)
        scene.frame_set(current)


def sample_frames(frames):
    return sorted({frames[0], frames[1], frames[len(frames) // 2], frames[-1]})


# --- inside Blender: one case ------------------------------------------------------------------

class Run:
    """One case, step by step; each step's violations go to the report as they are found."""

    def __init__(self, ext, case, folders, user_dir, report):
        self.ext, self.case, self.folders, self.user_dir = ext, case, folders, user_dir
        self.report = report
        self.recorder = BakeRecorder(ext)
        self.reference = None          # (frames, poses) of the bake that should play
        self.user_before_bake = None
        self.violations = []
        self.panel_failures = set()
        self.last_refusal = ""         # the refusal whose advice is being followed

    # -- reporting
    def _say(self, step, outcome, violations, seconds):
        record = {"step": step, "outcome": outcome, "seconds": round(seconds, 2),
                  "violations": [dataclasses.asdict(v) for v in violations]}
        self.report.write(json.dumps(record) + "\n")
        self.report.flush()

    def _begin(self, step):
        self.report.write(json.dumps({"begin": step}) + "\n")
        self.report.flush()

    def _clean(self, text):
        return text.replace(str(self.folders["root"]), "<case>")

    def violation(self, found, step, invariant, message):
        found.append(Violation(step, invariant, self._clean(message)))

    # -- the pieces of a step
    def enter_mode(self, mode=None):
        """Make the body active in `mode` (a MODES value; default: the case's)."""
        bpy = _bpy()
        from blender_helpers import make_active
        make_active(body())
        mode = BLENDER_MODE[mode or self.case.mode]
        if mode != 'OBJECT':
            bpy.ops.object.mode_set(mode=mode)

    def leave_mode(self):
        """Back to Object Mode (as the user does to play the bake)."""
        bpy = _bpy()
        from blender_helpers import make_active
        obj = body()
        if obj is not None and obj.mode != 'OBJECT':
            make_active(obj)
            bpy.ops.object.mode_set(mode='OBJECT')

    def draw_panels(self, found, step):
        """Draw every panel (test_panels' recording layout); a panel that fails is reported
        at the first step where it fails, not again at every later one."""
        from test_panels import draw_all
        try:
            draw_all()
        except Exception:             # noqa: BLE001 - any error in a panel is a finding
            message = f"a panel's draw raised {traceback_summary(traceback.format_exc())}"
            if message not in self.panel_failures:
                self.panel_failures.add(message)
                self.violation(found, step, "panel", message)

    def check_output(self, found, step, text):
        """A traceback printed during the step (by a handler, a draw callback, an update
        function), unless it is the one the operator raised, already found."""
        if TRACEBACK not in text:
            return
        summary = self._clean(traceback_summary(text))
        if not any(v.step == step and summary in v.message for v in found):
            self.violation(found, step, "traceback", f"a traceback was printed: {summary}")

    def call_operator(self, found, step, call):
        """Run the operator; its outcome: 'FINISHED', 'CANCELLED', 'refused' or 'raised'."""
        try:
            result = call()
        except RuntimeError as exc:
            text = str(exc)
            lines = [l.removeprefix("Error: ") for l in text.strip().splitlines() if l.strip()]
            if TRACEBACK in text:
                self.violation(found, step, "traceback",
                               f"raised a traceback: {traceback_summary(text)}")
                return "raised"
            if len(lines) != 1:
                self.violation(found, step, "traceback",
                               f"raised {len(lines)} lines: {' | '.join(lines[:3])}")
                return "raised"
            return "refused: " + lines[0]
        except Exception as exc:       # noqa: BLE001 - anything but RuntimeError reached the user
            self.violation(found, step, "traceback", f"raised {first_line(exc)}")
            return "raised"
        if result not in ({'FINISHED'}, {'CANCELLED'}):
            self.violation(found, step, "traceback", f"returned {sorted(result)}")
        return next(iter(result))

    def operator_step(self, step, call, after=None, mode=None):
        """Run an operator in the case's mode (or `mode`), leave the mode, and check: no
        traceback, a refusal changed nothing, the panels draw. `after(found)` adds the step's
        own checks when it finished. Returns the outcome."""
        self._begin(step)
        start = time.monotonic()
        found = []
        before = scene_state(self.folders)
        calls_before = len(self.recorder.calls)
        with Captured(self.folders["harness"]) as out:
            try:
                self.enter_mode(mode)
            except Exception as exc:   # noqa: BLE001
                self.violation(found, step, "harness",
                               f"could not enter {mode or self.case.mode} mode: "
                               f"{first_line(exc)}")
                self._say(step, "harness", found, time.monotonic() - start)
                self.violations += found
                return "harness"
            outcome = self.call_operator(found, step, call)
            self.draw_panels(found, step + " (in mode)")
            self.leave_mode()
            self.draw_panels(found, step)
        self.check_output(found, step, out.text)
        if outcome == "CANCELLED" or outcome.startswith("refused") or outcome == "raised":
            allowed = STAGE_FILE if step.startswith(("prepare", "tetrahedralize")) else None
            difference = state_difference(before, scene_state(self.folders), allowed)
            if difference:
                why = "failed with a traceback" if outcome == "raised" else \
                    f"refused ({outcome.removeprefix('refused: ')})"
                self.violation(found, step, "refusal", f"{why}, yet changed {difference}")
        if outcome == "FINISHED":
            if len(self.recorder.calls) > calls_before:
                _, frames, poses = self.recorder.calls[-1]
                self.reference = (frames, poses)
            if after is not None:
                after(found)
        self._say(step, outcome, found, time.monotonic() - start)
        self.violations += found
        return outcome

    def user_step(self, step, call, after=None):
        """`operator_step`, then, while the operator refuses with advice (switch to Object Mode,
        make it single-user, make it local, prepare again), follow it as the user would and run it
        again: the advice must cure its refusal. So every case reaches the bake whatever its
        mode and linkage, and each refusal's advice is checked to work."""
        outcome, mode = self.operator_step(step, call, after), None
        for _ in range(len(ADVICE) + 1):
            advice = advice_in(outcome)
            if advice is None:
                break
            if advice == "object mode":
                mode = "object"
            elif advice == "prepare":      # an operator itself, checked as one; it may refuse
                prepare = _bpy().ops.rs_elastic.prepare
                if self.operator_step(f"prepare (advised by {step})", prepare,
                                      mode="object") != "FINISHED":
                    break
            else:
                self.last_refusal = outcome
                self.plain_step(f"follow the advice: {advice}", lambda: self.follow(advice))
            again = self.operator_step(f"{step} (after: {advice})", call, after, mode=mode)
            if advice_in(again) == advice:
                found = [Violation(step, "advice", f"following the advice '{advice}' did not "
                                   f"cure the refusal: {again}")]
                self._say(f"{step} (after: {advice})", "advice", found, 0.0)
                self.violations += found
                break
            outcome = again
        return outcome

    def follow(self, advice):
        """Do what the refusal says, through Blender's own operators (the menu items it names)."""
        bpy = _bpy()
        from blender_helpers import make_active
        self.leave_mode()
        make_active(body())
        if advice == "single user":
            bpy.ops.object.make_single_user(type='SELECTED_OBJECTS', object=True, obdata=True)
        elif advice == "local":
            whole = "Make Local > All" in self.last_refusal
            bpy.ops.object.make_local(type='ALL' if whole else 'SELECT_OBDATA')
        make_active(body())

    def plain_step(self, step, action, checks=()):
        """A user action that is not an operator (save, open, undo, a property): no traceback,
        then `checks` (each `check(found, step)`), then the panels."""
        self._begin(step)
        start = time.monotonic()
        found = []
        with Captured(self.folders["harness"]) as out:
            try:
                action()
                outcome = "done"
            except Exception as exc:   # noqa: BLE001
                self.violation(found, step, "traceback", f"raised {first_line(exc)}")
                outcome = "raised"
            if outcome == "done":
                for check in checks:
                    check(found, step)
            self.draw_panels(found, step)
        self.check_output(found, step, out.text)
        self._say(step, outcome, found, time.monotonic() - start)
        self.violations += found
        return outcome

    # -- invariants over the bake
    def check_playback(self, found, step):
        if self.reference is None:
            return
        frames, poses = self.reference
        obj = body()
        if obj is None:
            self.violation(found, step, "playback", "the body is gone")
            return
        from blender_helpers import diagonal
        seen = self.ext.bridge.bake.bake_frames(obj)
        if seen != frames:
            self.violation(found, step, "playback",
                           f"the bake's frames are {_span(seen)}, the operator baked "
                           f"{_span(frames)}")
        picked = sample_frames(frames)
        got = played(obj, picked)
        want = poses[[frames.index(f) for f in picked]]
        if got.shape != want.shape:
            self.violation(found, step, "playback",
                           f"the bake plays {got.shape[1]} vertices, it baked {want.shape[1]}")
            return
        error = np.abs(got - want).max(axis=(1, 2)) / diagonal(poses[0])
        worst = int(np.argmax(error))
        if error[worst] > TOLERANCE:
            self.violation(found, step, "playback",
                           f"frame {picked[worst]} plays {error[worst]:.2g} of the diagonal "
                           "away from what was baked")

    def expect_state(self, expected, invariant, what):
        def check(found, step):
            difference = state_difference(expected, scene_state())
            if difference:
                self.violation(found, step, invariant, f"{what}: {difference} differ")
        return check

    # -- the sequence
    def run(self):
        bpy = _bpy()
        ops = bpy.ops.rs_elastic
        self.user_step("tetrahedralize", ops.tetrahedralize)
        self.user_step("prepare", ops.prepare)
        if self.case.added == "afterprep":
            self.plain_step("add the modifier", self.add_modifier_now)
        if self.user_step("add_handle",
                              lambda: ops.add_handle(vertex_group="Tip")) == "FINISHED":
            self.plain_step("key the handle", self.key_handle)
        self.preview_step()
        if self.case.baker.startswith("cli_"):
            self.cli_bake()
        else:
            self.blender_bake()
        self.save_and_reopen("save, reopen", None)
        self.save_and_reopen("save-as another folder, reopen",
                             self.folders["other"] / "shot.blend")
        self.clear_step()
        self.user_step("keep_take", ops.keep_take)
        self.user_step("interpolate_shape_keys", self.interpolate)
        self.reference = None          # the take replaced the bake
        self.save_and_reopen("final save, reopen", None, [no_unplayed_bakes])

    def add_modifier_now(self):
        """What the user does after Prepare: add the case's modifier to the body."""
        from blender_helpers import make_active
        obj = body()
        make_active(obj)
        add_modifier(obj, self.case.modifier, str(self.folders["scene"]))
        make_active(obj)

    def key_handle(self):
        handles = body().rs_elastic.handles
        if not len(handles) or handles[-1].empty is None:
            return
        empty_ = handles[-1].empty
        empty_.keyframe_insert("location", frame=1)
        empty_.location.z += 0.4
        empty_.keyframe_insert("location", frame=self.case.frames)
        scene = _bpy().context.scene
        scene.frame_set(scene.frame_current)     # the Empty where its keys put it

    def preview_step(self):
        """The mode preview ticked and unticked in the case's mode: it must leave nothing."""
        obj = body()
        if not _editable(obj):
            return                    # Blender greys out a linked object's settings
        before = scene_state()

        def tick(value):
            return lambda: self.in_mode(lambda: setattr(body().rs_elastic, "preview_enabled",
                                                        value))
        self.plain_step("mode preview on", tick(True))
        self.plain_step("mode preview off", tick(False),
                        [self.expect_state(before, "preview", "the preview left behind")])

    def in_mode(self, action):
        self.enter_mode()
        try:
            action()
        finally:
            self.leave_mode()

    def blender_bake(self):
        bpy = _bpy()
        ops = bpy.ops.rs_elastic
        operator = ops.simulate if self.case.baker == "simulate" else ops.solve_spacetime
        self.user_before_bake = scene_state()["the user's data"]
        before = scene_state()
        bpy.ops.ed.undo_push(message="zoo: before the bake")
        outcome = self.user_step(self.case.baker, operator, after=self.baked_checks)
        if outcome != "FINISHED":
            return
        after = scene_state()
        bpy.ops.ed.undo_push(message=self.case.baker)
        self.plain_step("undo the bake", bpy.ops.ed.undo,
                        [self.expect_state(before, "undo", "undo left")])
        self.plain_step("redo the bake", bpy.ops.ed.redo,
                        [self.expect_state(after, "undo", "redo left"), self.check_playback])

    def baked_checks(self, found):
        if self.reference is None:
            self.violation(found, self.case.baker, "playback", "finished but baked nothing")
            return
        self.check_playback(found, self.case.baker)

    def cli_bake(self, step=None):
        """Save the file in the case's mode, run the command line on it in a new Blender, and
        open what it saved; on a refusal with advice (make it single-user, make it local),
        follow it and run the command line again."""
        bpy = _bpy()
        self.user_before_bake = scene_state()["the user's data"]
        step = step or self.case.baker
        shot = self.folders["scene"] / "shot.blend"
        output = self.folders["cli"] / "out.blend"
        poses = self.folders["harness"] / "cli_poses.npz"
        self._begin(step)
        start = time.monotonic()
        found = []
        try:
            self.enter_mode()
            bpy.ops.wm.save_mainfile()
            self.leave_mode()
        except Exception as exc:       # noqa: BLE001
            self.violation(found, step, "harness", f"could not save in mode: {first_line(exc)}")
        saved = shot.read_bytes()
        argv = ["bake", "--object", "Bar", "--mode", self.case.baker.removeprefix("cli_"),
                "--frames", f"1-{self.case.frames}", "--bake-to", self.case.target,
                "--output", str(output)]
        result = run_cli(self.user_dir, shot, argv, poses)
        text = result.stdout + result.stderr
        errors = [l for l in result.stderr.splitlines() if l.startswith("rs_elastic: error:")]
        if TRACEBACK in text:
            self.violation(found, step, "traceback", f"printed {traceback_summary(text)}")
        if result.returncode not in (0, 1, 2):
            self.violation(found, step, "traceback", f"exit code {result.returncode}")
        elif result.returncode == 0:
            if errors or "rs_elastic: baked frames" not in result.stdout:
                self.violation(found, step, "traceback", "exit code 0 without its one line")
        else:
            if len(errors) != 1 and TRACEBACK not in text:
                self.violation(found, step, "traceback",
                               f"exit code {result.returncode} with {len(errors)} error lines")
            if shot.read_bytes() != saved or output.exists():
                self.violation(found, step, "refusal",
                               f"exit code {result.returncode}, yet a .blend was saved")
        outcome = f"exit {result.returncode}" + (f": {errors[0]}" if errors else "")
        self._say(step, outcome, found, time.monotonic() - start)
        self.violations += found
        advice = advice_in(outcome)
        if advice is not None and step == self.case.baker:
            self.last_refusal = outcome
            self.plain_step(f"follow the advice: {advice}", lambda: self.follow(advice))
            self.cli_bake(f"{step} (after: {advice})")
            return
        if result.returncode != 0 or not output.exists():
            return
        if poses.exists():
            data = np.load(poses)
            self.reference = ([int(f) for f in data["frames"]], data["poses"])
        checks = [self.check_playback]
        if self.reference is None:
            checks = [lambda found, step: self.violation(found, step, "playback",
                                                         "the command line baked nothing")]
        def open_output():
            bpy.ops.wm.open_mainfile(filepath=str(output))
            self.leave_mode()          # the file was saved in the case's mode
        self.plain_step("open the command line's output", open_output, checks)

    def save_and_reopen(self, step, path, checks=()):
        bpy = _bpy()
        before = scene_state()

        def action():
            if path is None:
                bpy.ops.wm.save_mainfile()
                target = bpy.data.filepath
            else:
                bpy.ops.wm.save_as_mainfile(filepath=str(path))
                target = str(path)
            bpy.ops.wm.open_mainfile(filepath=target)
            self.leave_mode()          # a file saved in Edit Mode opens in it
        self.plain_step(step, action,
                        [self.expect_state(before, "reopen", "reopened, these"),
                         self.check_playback, *checks])

    def clear_step(self):
        bpy = _bpy()
        before = scene_state()
        cache = self.cache_file()
        bpy.ops.ed.undo_push(message="zoo: before Clear Bake")
        outcome = self.user_step("clear_bake", bpy.ops.rs_elastic.clear_bake,
                                     after=lambda found: self.cleared_checks(found, cache))
        if outcome != "FINISHED":
            return
        bpy.ops.ed.undo_push(message="Clear Bake")
        self.plain_step("undo Clear Bake", bpy.ops.ed.undo,
                        [self.expect_state(before, "undo", "undo left"), self.check_playback])

    def cache_file(self):
        obj = body()
        modifier = obj.modifiers.get("RS Elastic Bake") if obj is not None else None
        return None if modifier is None else _bpy().path.abspath(modifier.filepath)

    def cleared_checks(self, found, cache):
        obj = body()
        step = "clear_bake"
        if self.ext.bridge.bake.bake_frames(obj) or obj.modifiers.get("RS Elastic Bake"):
            self.violation(found, step, "clear", "finished, yet the bake is still there")
        if self.user_before_bake is not None and \
                scene_state()["the user's data"] != self.user_before_bake:
            self.violation(found, step, "clear",
                           "the bake and Clear Bake changed the user's data")

    def interpolate(self):
        obj = body()
        keys = obj.data.shape_keys
        names = [] if keys is None else [k.name for k in keys.key_blocks]
        takes = [n for n in names if n.startswith("RS Take ")]
        return _bpy().ops.rs_elastic.interpolate_shape_keys(
            key_from=names[0] if names else "Basis", key_to=takes[-1] if takes else "Basis",
            output='KEYS', count=2)


ADVICE = (("switch to Object Mode", "object mode"), ("make it single-user", "single user"),
          ("make it local", "local"), (": prepare again", "prepare"))


def advice_in(outcome):
    """The advice a refusal gives ("object mode", "single user", "local"), or None."""
    if not outcome.startswith(("refused", "exit 1")):
        return None
    return next((advice for words, advice in ADVICE if words in outcome), None)


def no_unplayed_bakes(found, step):
    """After a save: the open .blend's bakes folder holds only files a Mesh Cache plays."""
    bpy = _bpy()
    folder = os.path.join(os.path.dirname(bpy.data.filepath),
                          f"blendcache_{pathlib.Path(bpy.data.filepath).stem}", "bakes")
    played = {os.path.realpath(bpy.path.abspath(m.filepath)) for o in bpy.data.objects
              for m in o.modifiers if m.type == 'MESH_CACHE'}
    left = [name for name in (sorted(os.listdir(folder)) if os.path.isdir(folder) else [])
            if os.path.realpath(os.path.join(folder, name)) not in played]
    if left:
        found.append(Violation(step, "clear", f"saved, the bakes folder keeps {len(left)} "
                                              f"file(s) nothing plays: {left[0]}"))


def _editable(obj):
    """Whether Blender lets the user change the object's settings (not library data)."""
    return obj is not None and obj.library is None


def _span(frames):
    return f"{frames[0]}-{frames[-1]}" if frames else "none"


# --- the command line, in its own Blender ------------------------------------------------------

CLI_SCRIPT = """
import sys
sys.path.insert(0, {tools!r})
sys.path.insert(0, {tests!r})
import blender_session
ext = blender_session.start(user_dir={user_dir!r})
import bpy
import zoo
bpy.ops.wm.open_mainfile(filepath={blend!r})
recorder = zoo.BakeRecorder(ext)
code = ext.bridge.cli.main({argv!r})
recorder.save({poses!r})
blender_session.exit_child(code)
"""


def run_cli(user_dir, blend, argv, poses):
    """`blender -b FILE -c rs_elastic ARGV` as the tests run it: the handler in a new Blender
    process; the poses it baked are saved to `poses` (.npz)."""
    script = CLI_SCRIPT.format(tools=str(ROOT / "tools"), tests=str(HERE), user_dir=user_dir,
                               blend=str(blend), argv=argv, poses=str(poses))
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=600)


# --- the child's entry point -------------------------------------------------------------------

def folders_of(root):
    root = pathlib.Path(root)
    folders = {"root": root}
    for name in ("scene", "other", "lib", "cli", "harness"):
        folders[name] = root / name
        folders[name].mkdir(parents=True, exist_ok=True)
    return folders


def run(spec):
    """Run one case (a child process's whole work): build, then the steps; write each step's
    record to harness/report.jsonl and end with a record {"done": true}."""
    import blender_session
    ext = blender_session.start(user_dir=spec["user_dir"])
    case = Case(**spec["case"])
    folders = folders_of(spec["folder"])
    import tempfile
    tempfile.tempdir = str(folders["harness"])
    with open(folders["harness"] / "report.jsonl", "w") as report:
        zoo_run = Run(ext, case, folders, spec["user_dir"], report)
        start = time.monotonic()
        try:
            zoo_run._begin("build the scene")
            with Captured(str(folders["harness"])) as out:
                build_scene(case, folders)
            setup = []
            zoo_run.check_output(setup, "build the scene", out.text)
            zoo_run._say("build the scene", "done", setup, time.monotonic() - start)
            zoo_run.violations += setup
            zoo_run.run()
        except Exception:              # noqa: BLE001 - the zoo itself failed: say where
            text = traceback.format_exc()
            zoo_run._say("harness", "raised", [Violation("harness", "harness",
                                                         zoo_run._clean(traceback_summary(text)))],
                         time.monotonic() - start)
            sys.stderr.write(text)
        report.write(json.dumps({"done": True}) + "\n")
    blender_session.exit_child(0)


def read_report(path):
    """(step records, the last step begun, whether the case ended) of a harness/report.jsonl."""
    records, begun, done = [], None, False
    if os.path.exists(path):
        for line in pathlib.Path(path).read_text().splitlines():
            record = json.loads(line)
            if record.get("done"):
                done = True
            elif "begin" in record:
                begun = record["begin"]
            else:
                records.append(record)
    return records, begun, done
