"""Scene builders and fingerprints shared by the Blender tests."""
import hashlib
import importlib
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


# Results the operators write on success; everything else in obj.rs_elastic is the user's.
RESULT_SETTINGS = {"tet_node_count", "tet_count", "tets_key", "prepared_key", "reduced_key",
                   "reduced_basis_count", "cubature_count", "mode_results", "mnf",
                   "solve_history", "residual", "preview_made_basis", "use_take",
                   "cache_bake_file"}


def _rna_values(struct, skip=()):
    """Plain values of a struct's editable properties (pointers by name, collections flattened)."""
    values = []
    for prop in struct.bl_rna.properties:
        if prop.identifier in ("rna_type", "name") or prop.identifier in skip:
            continue
        value = getattr(struct, prop.identifier)
        if prop.type == 'POINTER':
            value = getattr(value, "name", None) if isinstance(value, bpy.types.ID) else None
        elif prop.type == 'COLLECTION':
            value = [_rna_values(item, skip) for item in value]
        elif getattr(prop, "is_array", False):
            value = tuple(value)
        values.append((prop.identifier, value))
    return values


def _curves(id_block, skip_paths=()):
    """(data path, index, keyframes) of every F-curve animating `id_block`, read through the
    extension's own Blender-version-independent accessor."""
    animation = importlib.import_module("bl_ext.user_default.rs_elastic.bridge.animation")
    curves = animation.fcurves(id_block, create=False)
    rows = []
    for curve in curves or []:
        if curve.data_path in skip_paths:
            continue
        co = np.empty(len(curve.keyframe_points) * 2)
        curve.keyframe_points.foreach_get("co", co)
        rows.append((curve.data_path, curve.array_index, co.tobytes()))
    return sorted(rows)


def _is_extension_key(keys, block):
    tags = keys.get("rs_elastic")
    return tags is not None and block.name in tags.keys()


def user_fingerprint(obj=None):
    """Hash of everything the user owns, which the extension must never change: each object's
    transform, modifiers, vertex groups and its animation; each mesh's vertices, faces and the
    user's shape keys (name, value, mute, relative key, data and keyframes); obj.rs_elastic's
    settings (not the results operators write). Keys the extension tagged as its own are left
    out, so a bake and its Clear Bake must leave the fingerprint as it was. `obj` is accepted
    for symmetry with `fingerprint`; every object in the file is covered."""
    h = hashlib.sha256()
    for other in sorted(bpy.data.objects, key=lambda o: o.name):
        h.update(repr((other.name, other.type, tuple(map(tuple, other.matrix_basis)),
                       other.parent.name if other.parent else None,
                       [(m.name, m.type, m.show_viewport) for m in other.modifiers
                        if not (m.type == 'MESH_CACHE' and m.name == "RS Elastic Bake")],
                       [g.name for g in other.vertex_groups], _curves(other))).encode())
        if other.type != 'MESH':
            continue
        mesh = other.data
        h.update(mesh.name.encode() + vertices(other).tobytes())
        h.update(repr([p.vertices[:] for p in mesh.polygons]).encode())
        h.update(repr([[(g.group, g.weight) for g in v.groups] for v in mesh.vertices]).encode())
        keys = mesh.shape_keys
        if keys is not None:
            own = [b for b in keys.key_blocks if _is_extension_key(keys, b)]
            skip = {f'key_blocks["{b.name}"].value' for b in own}
            for block in keys.key_blocks:
                if block in own:
                    continue
                co = np.empty(len(block.data) * 3)
                block.data.foreach_get("co", co)
                h.update(repr((block.name, block.value, block.mute, block.relative_key.name,
                               block.slider_min, block.slider_max)).encode() + co.tobytes())
            curves = _curves(keys, skip)
            if curves:
                h.update(repr(curves).encode())
        h.update(repr(_rna_values(other.rs_elastic, RESULT_SETTINGS)).encode())
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


def add_tip_handle(obj, keys):
    """Bind a handle to the bar's tip (the vertices at x = 4) and key its Empty at `keys`
    {frame: location}. Returns (empty, tip mask)."""
    tip = vertices(obj)[:, 0] > 4.0 - 1e-9
    obj.vertex_groups.new(name="Tip").add([int(i) for i in np.flatnonzero(tip)], 1.0, 'REPLACE')
    assert bpy.ops.rs_elastic.add_handle(vertex_group="Tip") == {'FINISHED'}
    empty = obj.rs_elastic.handles[0].empty
    for frame, location in keys.items():
        empty.location = location
        empty.keyframe_insert("location", frame=frame)
    return empty, tip


def disk_fingerprint(folder):
    """[(path under `folder`, sha256)] of every file below it, and every folder (hash None)."""
    folder = pathlib.Path(folder)
    rows = []
    for path in sorted(folder.rglob("*")):
        digest = hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else None
        rows.append((str(path.relative_to(folder)), digest))
    return rows


def _id_property_value(value):
    if isinstance(value, (list, tuple)):
        return [_id_property_value(v) for v in value]
    if hasattr(value, "to_dict"):
        return {k: _id_property_value(v) for k, v in sorted(value.items())}
    if hasattr(value, "to_list"):
        return hashlib.sha256(np.asarray(value.to_list()).tobytes()).hexdigest()
    return value


def _modifier_settings(modifier):
    values = [(modifier.name, modifier.type)]
    for prop in modifier.bl_rna.properties:
        if prop.is_readonly or prop.type == 'COLLECTION' or prop.identifier == "rna_type":
            continue
        value = getattr(modifier, prop.identifier)
        if prop.type == 'POINTER':
            value = getattr(value, "name", None)
        elif getattr(prop, "is_array", False):
            value = tuple(value)
        values.append((prop.identifier, value))
    return values


def state_fingerprint(folder=None):
    """Everything, the extension's own data included, that a failed write must leave as it was:
    `user_fingerprint`, then per mesh object every shape key (name, value, mute, relative key,
    data), the Key's tags and every F-curve, every modifier with its settings, the results in
    obj.rs_elastic and its ID properties (tet mesh, Prepare's records), the file's actions; and
    with `folder`, every file and folder below it."""
    rows = [user_fingerprint(), sorted(a.name for a in bpy.data.actions)]
    for obj in sorted(bpy.data.objects, key=lambda o: o.name):
        rows.append([_modifier_settings(m) for m in obj.modifiers])
        if obj.type != 'MESH':
            continue
        settings = obj.rs_elastic
        rows.append([(name, repr(getattr(settings, name))) for name in sorted(RESULT_SETTINGS)
                     if hasattr(settings, name) and name not in ("mode_results", "solve_history")])
        rows.append([m.frequency_hz for m in settings.mode_results])
        rows.append([v.value for v in settings.solve_history])
        rows.append([h.residual for h in settings.handles])
        rows.append({k: _id_property_value(v) for k, v in settings.items()
                     if k not in settings.bl_rna.properties})     # settings: compared above
        keys = obj.data.shape_keys
        if keys is None:
            rows.append(None)
            continue
        for block in keys.key_blocks:
            co = np.empty(len(block.data) * 3)
            block.data.foreach_get("co", co)
            rows.append((block.name, block.value, block.mute, block.relative_key.name,
                         hashlib.sha256(co.tobytes()).hexdigest()))
        tags = keys.get("rs_elastic")
        rows.append(None if tags is None else tags.to_dict())
        rows.append(_curves(keys))
    if folder is not None:
        rows.append(disk_fingerprint(folder))
    return rows
