"""Scene builders and fingerprints shared by the Blender tests."""
import hashlib
import pathlib

import bpy
import numpy as np

MESHES = pathlib.Path(__file__).resolve().parents[3] / "shared" / "data" / "meshes"


def quick_reduced(obj):
    """Small reduced-RS settings for tests that do not measure its accuracy (faster prepare)."""
    settings = obj.rs_elastic
    settings.basis_size, settings.cubature_tets, settings.training_poses = 30, 60, 24
    return obj


def link_mesh(name, vertices, faces):
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([tuple(v) for v in vertices], [], [tuple(f) for f in faces])
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    make_active(obj)
    return quick_reduced(obj)


def make_active(obj):
    for other in bpy.context.view_layer.objects:
        other.select_set(False)
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)


def make_bar(name="Bar", length=4.0, width=1.0, pin_end=True, cuts=1):
    """A box `length` × `width` × `width` along +x from the origin, its faces subdivided by `cuts`
    so that the pin group (all vertices at x = 0) holds a whole end face."""
    bpy.ops.mesh.primitive_cube_add(size=1.0)
    obj = bpy.context.active_object
    obj.name = name
    bpy.ops.object.mode_set(mode='EDIT')
    bpy.ops.mesh.subdivide(number_cuts=cuts)
    bpy.ops.object.mode_set(mode='OBJECT')
    co = np.empty(len(obj.data.vertices) * 3)
    obj.data.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3) + 0.5
    co *= (length, width, width)
    obj.data.vertices.foreach_set("co", co.ravel())
    obj.data.update()
    if pin_end:
        group = obj.vertex_groups.new(name="Pin")
        group.add([int(i) for i in np.flatnonzero(co[:, 0] < 1e-9)], 1.0, 'REPLACE')
        obj.rs_elastic.pin_group = "Pin"
    return quick_reduced(obj)


def read_off(path):
    """Vertices and faces of an OFF file (what the shared cow and knight use)."""
    tokens = [line.split() for line in pathlib.Path(path).read_text().splitlines()
              if line.strip() and not line.startswith("#")]
    assert tokens[0][0] == "OFF"
    nv, nf = int(tokens[1][0]), int(tokens[1][1])
    V = np.array(tokens[2:2 + nv], dtype=float)
    F = [[int(i) for i in row[1:1 + int(row[0])]] for row in tokens[2 + nv:2 + nv + nf]]
    return V, F


def import_shared(name):
    path = MESHES / name
    if path.suffix == ".off":
        V, F = read_off(path)
        return link_mesh(path.stem, V, F)
    bpy.ops.wm.obj_import(filepath=str(path))
    obj = bpy.context.selected_objects[0]
    make_active(obj)
    return quick_reduced(obj)


def vertices(obj):
    co = np.empty(len(obj.data.vertices) * 3)
    obj.data.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


def evaluated_vertices(obj):
    depsgraph = bpy.context.evaluated_depsgraph_get()
    mesh = obj.evaluated_get(depsgraph).data
    co = np.empty(len(mesh.vertices) * 3)
    mesh.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


def fingerprint(obj):
    """Everything a refused operator must leave alone: mesh, shape keys, settings."""
    h = hashlib.sha256()
    if obj.type == 'MESH':
        h.update(vertices(obj).tobytes())
        h.update(repr([(p.vertices[:]) for p in obj.data.polygons]).encode())
        keys = obj.data.shape_keys
        if keys is not None:
            for block in keys.key_blocks:
                co = np.empty(len(block.data) * 3)
                block.data.foreach_get("co", co)
                h.update(block.name.encode() + co.tobytes() + repr(block.value).encode())
        s = obj.rs_elastic
        h.update(repr((s.tets_key, s.prepared_key, s.tet_count, s.tet_node_count, s.frequencies,
                       s.mnf)).encode())
    h.update(repr(sorted(o.name for o in bpy.data.objects)).encode())
    return h.hexdigest()


def diagonal(points):
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


def closed_volume(obj, positions):
    """Volume enclosed by the object's (closed) polygons at the given vertex positions."""
    total = 0.0
    for polygon in obj.data.polygons:
        idx = list(polygon.vertices)
        a = positions[idx[0]]
        for b, c in zip(positions[idx[1:-1]], positions[idx[2:]]):
            total += np.dot(a, np.cross(b, c)) / 6.0
    return total


def preview_pose(obj, method, amplitude):
    """Evaluated vertices of the mode preview with this method and amplitude (then turned off)."""
    obj.rs_elastic.preview_method = method
    obj.rs_elastic.preview_amplitude = amplitude
    obj.rs_elastic.preview_enabled = True
    pose = evaluated_vertices(obj)
    obj.rs_elastic.preview_enabled = False
    return pose
