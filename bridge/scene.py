"""Read a Blender object into numpy arrays for the solver (main thread only)."""
import math

import numpy as np


class InputError(Exception):
    """Bad user input: the message is shown as-is in the UI and on the command line."""


def require_mesh_object(obj):
    """Raise InputError unless `obj` is a mesh object of this file (``require_local``) with
    faces and a mesh of its own (``require_single_user``)."""
    if obj is None:
        raise InputError("No active object: select a mesh object")
    if obj.type != 'MESH':
        kind = obj.type.lower().replace("_", " ")
        article = "an" if kind[0] in "aeiou" else "a"
        raise InputError(f"'{obj.name}' is {article} {kind}, not a mesh")
    require_local(obj)
    if obj.mode == 'EDIT':
        # Edit-mode changes are not in obj.data until the mode is left.
        obj.update_from_editmode()
    if len(obj.data.vertices) == 0 or len(obj.data.polygons) == 0:
        raise InputError(f"'{obj.name}' has an empty mesh (no faces)")
    require_single_user(obj)
    return obj


MAKE_LOCAL = "make it local first (Object > Relations > Make Local > Selected Objects and Data)"


def _make_local(obj):
    """How to make a linked object local. Only in linked collections, Make Local > Selected would
    make a local copy that no collection of the scene holds: its collection must come too."""
    collections = obj.users_collection
    if collections and all(c.library is not None for c in collections):
        return (f"make it local first, with its collection '{collections[0].name}' (Object > "
                "Relations > Make Local > All)")
    return MAKE_LOCAL


def require_local(obj):
    """Refuse an object or mesh that is linked from a library or is a library override: a file
    saves nothing of a linked datablock (it is read from its library again on load), and an
    override keeps only overridable properties (not the extension's settings, nor shape keys
    added to its mesh). So a preparation or a bake would be lost without a word on save."""
    if obj.library is not None:
        raise InputError(f"'{obj.name}' is linked from the library '{obj.library.name}', so "
                         f"nothing done to it can be saved in this file: {_make_local(obj)}")
    if obj.override_library is not None:
        raise InputError(f"'{obj.name}' is a library override, which cannot keep its "
                         f"preparation or bake when the file is saved: {MAKE_LOCAL}")
    mesh = obj.data
    if mesh.library is not None:
        raise InputError(f"The mesh '{mesh.name}' of '{obj.name}' is linked from the library "
                         f"'{mesh.library.name}', so a bake (shape keys of the mesh) cannot be "
                         f"saved in this file: {MAKE_LOCAL}")
    if mesh.override_library is not None:
        raise InputError(f"The mesh '{mesh.name}' of '{obj.name}' is a library override, which "
                         f"cannot keep a bake (shape keys of the mesh) when the file is saved: "
                         f"{MAKE_LOCAL}")


def require_single_user(obj):
    """Refuse a mesh shared by linked duplicates: its shape keys belong to every object using
    it, so one object's bake would replace the other's."""
    mesh = obj.data
    users = mesh.users - int(mesh.use_fake_user)
    if users > 1:
        raise InputError(f"'{obj.name}' shares its mesh '{mesh.name}' with {users - 1} "
                         "other object(s): make it single-user first (Object > Relations > "
                         "Make Single User > Object & Data)")


# Modifiers that copy the geometry. The bake lives in the base mesh's shape keys, so a copy can
# only repeat (or mirror) the base's motion, which is wrong for any asymmetric motion.
COPYING_MODIFIERS = {'MIRROR', 'ARRAY', 'SCREW', 'PARTICLE_INSTANCE'}

# Limits beyond any real material: above them the solver's numbers are meaningless.
MATERIAL_LIMITS = {"youngs_modulus": ("Young's modulus", 1e13, "Pa"),
                   "density": ("Density", 1e6, "kg/m³")}


def require_body(obj):
    """Everything an operator that tetrahedralises, prepares, solves or simulates needs of the
    object before it reads anything: a single-user mesh object, no modifier that copies its
    geometry or replaces it, and finite, physical settings. Raises InputError."""
    require_mesh_object(obj)
    for modifier in obj.modifiers:
        if modifier.show_viewport or modifier.show_render:
            refuse_modifier(obj, modifier)
    check_settings(obj)
    return obj


def refuse_modifier(obj, modifier):
    """InputError for a modifier whose result would not play the bake: one that copies the
    geometry (COPYING_MODIFIERS), or an Ocean that generates its own grid in place of the mesh
    (its Displace geometry deforms the mesh, and is a deformer like any other)."""
    kind = modifier.type.replace("_", " ").title()
    if modifier.type in COPYING_MODIFIERS:
        raise InputError(f"'{obj.name}' has a {kind} modifier ('{modifier.name}'), which "
                         f"would copy the baked motion: apply the {kind} modifier first")
    if modifier.type == 'OCEAN' and modifier.geometry_mode == 'GENERATE':
        raise InputError(f"'{obj.name}' has an Ocean modifier ('{modifier.name}') that "
                         "generates its own surface in place of the mesh, so a bake of the mesh "
                         "would not show: set its Geometry to Displace, or remove it")


def require_no_copies(obj, depsgraph):
    """Refuse a body whose Geometry Nodes make instances of its own mesh (Instance on Points of
    the group's input geometry, say): each would repeat the baked motion, as an Array does.
    Instances of other objects (a scatter on the body) ride along and are fine. An instance's
    mesh carries the name of the mesh it came from (its ``original`` is not the body's mesh).
    Realised instances are plain mesh and are not told apart from the body."""
    modifiers = [m for m in obj.modifiers if m.type == 'NODES' and m.show_viewport]
    if not modifiers:
        return
    for instance in depsgraph.object_instances:
        if (instance.is_instance and instance.parent is not None
                and instance.parent.original == obj and instance.object.type == 'MESH'
                and instance.object.data.name == obj.data.name):
            names = ", ".join(f"'{m.name}'" for m in modifiers)
            raise InputError(f"'{obj.name}' makes instances of its own mesh (Geometry Nodes "
                             f"{names}), which would repeat the baked motion as an Array does: "
                             "remove those instances first")


FLOAT32_MAX = float(np.finfo(np.float32).max)


def check_settings(obj):
    """Refuse non-finite numbers in any setting, and a material beyond MATERIAL_LIMITS."""
    settings = obj.rs_elastic
    for struct in [settings, *settings.handles]:
        for prop in struct.bl_rna.properties:
            if prop.type == 'FLOAT' and not prop.is_readonly and prop.array_length == 0:
                value = getattr(struct, prop.identifier)
                if abs(value) >= FLOAT32_MAX:     # Blender stores an infinity as ±FLOAT32_MAX
                    value = math.copysign(math.inf, value)
                if not math.isfinite(value):
                    raise InputError(f"'{obj.name}': {prop.name} is {value:g}; it must be a "
                                     "finite number")
    for name, (label, largest, unit) in MATERIAL_LIMITS.items():
        value = getattr(settings, name)
        if not 0.0 < value <= largest:
            raise InputError(f"{label} must be above 0 and at most {largest:g} {unit}, got "
                             f"{value:g} {unit}")


MAX_FRAMES = 10000   # a bake is one shape key per frame: beyond this it is not usable


def frame_range(obj, blender_scene):
    """The scene frames a solve or simulation of ``obj`` covers: its own range or the scene's.
    InputError when it has fewer than 3 or more than MAX_FRAMES frames."""
    settings = obj.rs_elastic
    if settings.use_scene_range:
        start, end = blender_scene.frame_start, blender_scene.frame_end
    else:
        start, end = settings.frame_start, settings.frame_end
    if end - start + 1 < 3:
        raise InputError(f"The frame range {start}–{end} has fewer than 3 frames")
    if end - start + 1 > MAX_FRAMES:
        raise InputError(f"The frame range {start}–{end} has more than {MAX_FRAMES} frames")
    return list(range(start, end + 1))


def frame_interval(blender_scene):
    """h [s]: the time from one frame to the next at the scene's frame rate. InputError for a
    rate that is not a finite, positive number (Blender keeps a NaN frame-rate base)."""
    fps, base = blender_scene.render.fps, blender_scene.render.fps_base
    if not (math.isfinite(base) and base > 0.0 and fps > 0):
        raise InputError(f"The scene's frame rate ({fps} / {base:g} frames per second) is not a "
                         "finite, positive number")
    return base / fps


GRAVITY_LIMIT = 1000.0    # m/s², about 100 g


def scene_gravity(blender_scene):
    """(3,) the scene's gravity (zero when turned off), refused if not finite or beyond 100 g."""
    if not blender_scene.use_gravity:
        return np.zeros(3)
    gravity = np.array(blender_scene.gravity, dtype=np.float64)
    magnitude = np.linalg.norm(gravity)
    if not magnitude <= GRAVITY_LIMIT:      # also catches inf and nan
        raise InputError(f"The scene's gravity is {magnitude:.3g} m/s²; it must be finite and "
                         f"at most {GRAVITY_LIMIT:g} m/s²")
    return gravity


def body_of_handle(empty, blender_scene):
    """The mesh of `blender_scene` with a handle bound to `empty`, or None (the first such
    mesh, in the scene's order, if several share the Empty)."""
    for obj in blender_scene.objects:
        if obj.type == 'MESH' and any(h.empty == empty for h in obj.rs_elastic.handles):
            return obj
    return None


def acted_on(context):
    """The object RS Elastic's panels and operators work on: the active object or, when that is
    a handle's Empty, the mesh whose handle it is (the sidebar shows that body, so F3 and
    shortcuts act on it too), or None."""
    obj = context.active_object
    if obj is not None and obj.type == 'EMPTY':
        return body_of_handle(obj, context.scene) or obj
    return obj


def active_mesh_or_report(operator, context):
    """The mesh the operator acts on (``acted_on``), or None after reporting why not (for
    short operators)."""
    try:
        return require_mesh_object(acted_on(context))
    except InputError as exc:
        operator.report({'ERROR'}, str(exc))
        return None


def base_vertices(obj):
    """(n, 3) float64 object-space positions of the mesh's own vertices (what shape keys move)."""
    mesh = obj.data
    co = np.empty(len(mesh.vertices) * 3, dtype=np.float64)
    mesh.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


def key_block_positions(block):
    """(n, 3) float64 object-space positions a shape key holds."""
    co = np.empty(len(block.data) * 3, dtype=np.float32)
    block.data.foreach_get("co", co)
    return co.reshape(-1, 3).astype(np.float64)


def shape_key_positions(obj, name):
    """(n, 3) float64 positions of the object's shape key ``name``; InputError if it has none,
    or if they are not finite numbers."""
    keys = obj.data.shape_keys
    block = keys.key_blocks.get(name) if keys is not None else None
    if block is None:
        raise InputError(f"'{name}' is not a shape key of '{obj.name}'")
    positions = key_block_positions(block)
    if not np.isfinite(positions).all():
        raise InputError(f"Shape key '{name}' of '{obj.name}' holds positions that are not "
                         "finite numbers: fix or delete it")
    return positions


def base_triangles(obj):
    """(t, 3) int64 triangles of the mesh's own faces (over ``base_vertices``)."""
    mesh = obj.data
    mesh.calc_loop_triangles()
    F = np.empty(len(mesh.loop_triangles) * 3, dtype=np.int64)
    mesh.loop_triangles.foreach_get("vertices", F)
    return F.reshape(-1, 3)


def evaluated_triangles(obj, depsgraph):
    """Object-space triangle soup of the evaluated mesh (modifiers applied).

    Returns V (n, 3) float64 and F (m, 3) int64.
    """
    evaluated = obj.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    try:
        mesh.calc_loop_triangles()
        V = np.empty(len(mesh.vertices) * 3, dtype=np.float64)
        mesh.vertices.foreach_get("co", V)
        F = np.empty(len(mesh.loop_triangles) * 3, dtype=np.int64)
        mesh.loop_triangles.foreach_get("vertices", F)
    finally:
        evaluated.to_mesh_clear()
    if len(F) == 0:
        raise InputError(f"'{obj.name}' has no faces after its modifiers")
    return V.reshape(-1, 3), F.reshape(-1, 3)


def group_weights(obj, group_name, label="Vertex group"):
    """(n,) float64 weights of the named vertex group over the mesh's vertices (0 outside it).
    InputError "<label> '<name>' does not exist" when the object has no such group."""
    group = obj.vertex_groups.get(group_name)
    if group is None:
        raise InputError(f"{label} '{group_name}' does not exist on '{obj.name}'")
    return group_weight_matrix(obj, [group.index])[:, 0]


def vertex_group_mask(obj, group_name):
    """(n,) bool: vertices with a non-zero weight in the named group."""
    return group_weights(obj, group_name) > 0.0


def pin_weights(obj, group_name):
    """(n,) float32 weights of the pin group (Blender keeps weights as float32, so this is
    exact; they are hashed into the modes key and the staleness fingerprint)."""
    return group_weights(obj, group_name, label="Pin group").astype(np.float32)


def stiffness_weights(obj, group_name):
    """(n,) float32 weights of the stiffness group (0 outside it), hashed like the pin weights
    into the modes key and the staleness fingerprint; InputError "Stiffness group '<name>' does
    not exist on '<object>'" when there is no such group."""
    return group_weights(obj, group_name, label="Stiffness group").astype(np.float32)


def group_weight_matrix(obj, group_indices):
    """(n, k) float64 weights of the vertex groups with these indices (k,) over the mesh's
    vertices (0 outside a group). Blender has no bulk accessor for group weights, so this
    walks the memberships once, for all the groups at the same time."""
    column = {int(g): k for k, g in enumerate(group_indices)}
    rows, columns, values = [], [], []
    for v in obj.data.vertices:
        for g in v.groups:
            k = column.get(g.group)
            if k is not None:
                rows.append(v.index)
                columns.append(k)
                values.append(g.weight)
    weights = np.zeros((len(obj.data.vertices), len(column)))
    weights[rows, columns] = values
    return weights
