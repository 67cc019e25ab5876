"""A small rigged creature for the demo and the Blender tests: a round body with a belly and two
ears, skinned to three bones (Body, Ear.L, Ear.R) and keyed to hop and flick its ears.

    mesh, rig = creature.build(bpy, np, "Critter", location=(0, 0, 0))

The mesh is one object of three closed parts (body sphere, two ear boxes that sink into it);
fTetWild meshes their union. Vertex groups: one per bone (weight 1 where the bone moves the
vertex) and "Follow Rig": the body's back half and the ears' roots, which move exactly with
the bones; the belly (the front, -y) and the ear tips are free flesh. Keys: the Body bone hops
up and lands (frames 1-13), Ear.L swings 50 degrees forward and stops dead (frames 4-10).
"""
import math

EAR_X, EAR_BASE, EAR_TOP = 0.24, 0.25, 0.85      # ear centre x and height span [m]


def _ear(np, sign):
    """Vertices and quads of a 0.12 x 0.08 box from EAR_BASE to EAR_TOP, 6 cuts high."""
    rings = np.linspace(EAR_BASE, EAR_TOP, 7)
    corners = np.array([(-0.06, -0.04), (0.06, -0.04), (0.06, 0.04), (-0.06, 0.04)])
    V = np.array([(sign * EAR_X + x, y, z) for z in rings for x, y in corners])
    faces = []
    for r in range(len(rings) - 1):
        for k in range(4):
            a, b = 4 * r + k, 4 * r + (k + 1) % 4
            faces.append((a, b, b + 4, a + 4))
    faces += [(3, 2, 1, 0), (len(V) - 4, len(V) - 3, len(V) - 2, len(V) - 1)]
    return V, faces


def _body(np):
    """A UV sphere of radius 0.45 (24 segments, 12 rings)."""
    V = [(0.0, 0.0, -0.45)]
    faces = []
    rings, segments = 12, 24
    for i in range(1, rings):
        theta = math.pi * i / rings
        for j in range(segments):
            phi = 2 * math.pi * j / segments
            V.append((0.45 * math.sin(theta) * math.cos(phi), 0.45 * math.sin(theta) * math.sin(phi),
                      -0.45 * math.cos(theta)))
    V.append((0.0, 0.0, 0.45))
    top = len(V) - 1

    def ring(i, j):
        return 1 + (i - 1) * segments + j % segments
    for j in range(segments):
        faces.append((0, ring(1, j + 1), ring(1, j)))
        faces.append((top, ring(rings - 1, j), ring(rings - 1, j + 1)))
    for i in range(1, rings - 1):
        for j in range(segments):
            faces.append((ring(i, j), ring(i, j + 1), ring(i + 1, j + 1), ring(i + 1, j)))
    return np.array(V), faces


def build(bpy, np, name="Critter", location=(0.0, 0.0, 0.0)):
    """Create the creature's mesh and armature at ``location``; returns (mesh object, rig)."""
    body_V, body_F = _body(np)
    parts = [(body_V, body_F), _ear(np, 1.0), _ear(np, -1.0)]
    V, F, offset, part_of = [], [], 0, []
    for k, (v, f) in enumerate(parts):
        V += [tuple(p) for p in v]
        F += [tuple(i + offset for i in face) for face in f]
        part_of += [k] * len(v)
        offset += len(v)
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(V, [], F)
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    V, part_of = np.array(V), np.array(part_of)

    groups = {bone: obj.vertex_groups.new(name=bone) for bone in ("Body", "Ear.L", "Ear.R")}
    for k, bone in enumerate(("Body", "Ear.L", "Ear.R")):
        groups[bone].add([int(i) for i in np.flatnonzero(part_of == k)], 1.0, 'REPLACE')
    follow = ((part_of == 0) & (V[:, 1] > -0.1)) | ((part_of > 0) & (V[:, 2] < 0.45))
    obj.vertex_groups.new(name="Follow Rig").add([int(i) for i in np.flatnonzero(follow)], 1.0,
                                                 'REPLACE')

    armature = bpy.data.armatures.new(name + " Rig")
    rig = bpy.data.objects.new(name + " Rig", armature)
    bpy.context.scene.collection.objects.link(rig)
    bpy.context.view_layer.objects.active = rig
    bpy.ops.object.mode_set(mode='EDIT')
    body = armature.edit_bones.new("Body")
    body.head, body.tail = (0.0, 0.0, -0.45), (0.0, 0.0, 0.2)
    for bone, sign in (("Ear.L", 1.0), ("Ear.R", -1.0)):
        ear = armature.edit_bones.new(bone)
        ear.head, ear.tail = (sign * EAR_X, 0.0, EAR_BASE), (sign * EAR_X, 0.0, EAR_TOP)
        ear.parent = body
    bpy.ops.object.mode_set(mode='OBJECT')
    obj.parent = rig
    modifier = obj.modifiers.new("Armature", 'ARMATURE')
    modifier.object = rig
    rig.location = location

    pose = rig.pose.bones
    for frame, height in ((1, 0.0), (7, 0.35), (13, 0.0)):
        pose["Body"].location = (0.0, height, 0.0)         # bone y is the body's up
        pose["Body"].keyframe_insert("location", frame=frame)
    pose["Ear.L"].rotation_mode = 'XYZ'
    for frame, angle in ((4, 0.0), (10, math.radians(50.0))):
        pose["Ear.L"].rotation_euler = (angle, 0.0, 0.0)
        pose["Ear.L"].keyframe_insert("rotation_euler", frame=frame)
    for fcurve in _fcurves(rig):
        for point in fcurve.keyframe_points:
            point.interpolation = 'LINEAR'
    return obj, rig


def _fcurves(obj):
    """The F-curves of the object's action, on the layered actions of Blender 4.4+ too."""
    action = obj.animation_data.action
    if hasattr(action, "fcurves") and len(action.fcurves):
        return list(action.fcurves)
    out = []
    for layer in getattr(action, "layers", []):
        for strip in layer.strips:
            for bag in getattr(strip, "channelbags", []):
                out += list(bag.fcurves)
    return out
