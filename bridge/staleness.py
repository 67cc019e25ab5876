"""Whether a prepared body still matches its object: Prepare records a fingerprint of what it read
(mesh, modifiers, pins, a painted stiffness, settings, and the rules its stages were built by:
`stage_rules`) in `obj.rs_elastic["prepared_inputs"]`; `stale_reason` compares it with the object
now (main thread).

The material model is not part of it: Simulate trains (or loads) the energy cubature of whichever
model is set (`bodies.energy_stage`).
"""
import json

import bpy
import numpy as np

from ..solver import cache
from . import mesh_cache, stage_rules
from .scene import InputError, pin_weights, stiffness_weights
from .stage_cache import PREPARED_INPUTS

# Properties that do not change what a modifier makes: its name (the stack is read in order),
# the panel's layout, statistics, and the render-only switch (Prepare reads the viewport result).
_SKIPPED_PROPS = {"rna_type", "name", "show_expanded", "is_active", "show_in_editmode",
                  "show_on_cage", "show_render", "use_pin_to_last", "persistent_uid",
                  "is_override_data_editable", "is_override_data", "execution_time",
                  "use_apply_on_spline", "show_group_selector", "show_manage_panel"}
_NODE_BASE_PROPS = None     # bpy.types.Node's own properties (layout: location, label, colour...)


def _plain(value):
    """A property value as plain data whose repr is the same in every session (no addresses):
    IDs by name, arrays, vectors and ID property groups as tuples, enum sets sorted, booleans
    as 0 or 1 (an ID property saved as True is read back as 1)."""
    if isinstance(value, bool):
        return int(value)
    if value is None or isinstance(value, (int, float, str)):
        return value
    if isinstance(value, bpy.types.ID):
        return value.name
    if isinstance(value, (set, frozenset)):
        return tuple(sorted(value))
    if hasattr(value, "to_dict"):               # an ID property group (Blender 4.2 GN inputs)
        value = value.to_dict()
    elif hasattr(value, "to_list"):             # an ID property array (a vector input)
        value = value.to_list()
    if isinstance(value, dict):
        return tuple(sorted((key, _plain(item)) for key, item in value.items()))
    try:
        return tuple(_plain(item) for item in value)
    except TypeError:
        return type(value).__name__


def _id_properties(struct):
    """(key, value) of a struct's ID properties: a Geometry Nodes modifier's inputs up to
    Blender 4.x. Structs without ID properties (modifiers from Blender 5.0 on) raise TypeError."""
    try:
        keys = sorted(struct.keys())
    except TypeError:
        return []
    return [(key, _plain(struct[key])) for key in keys]


def _struct_values(struct, seen, skipped=_SKIPPED_PROPS):
    """(identifier, value) of what a struct's properties hold, through RNA only, so it reads any
    modifier type: editable values, IDs by name (a node group by its nodes), nested structs (a
    Geometry Nodes modifier's inputs from Blender 5.0 on) read in turn, each struct once."""
    values = []
    for prop in struct.bl_rna.properties:
        name = prop.identifier
        if name in skipped or name.startswith("open_") or prop.type == 'COLLECTION':
            continue
        if prop.type != 'POINTER':
            if not prop.is_readonly:
                values.append((name, _plain(getattr(struct, name, None))))
            continue
        value = getattr(struct, name, None)
        if value is None or isinstance(value, bpy.types.ID):
            if not prop.is_readonly:
                values.append((name, _id_value(value, seen)))
        elif (value.bl_rna.identifier, value.as_pointer()) not in seen:
            # RNA may wrap the same data as several types (a GN modifier's inputs): key both.
            seen.add((value.bl_rna.identifier, value.as_pointer()))
            values.append((name, _struct_values(value, seen, skipped)))
    return values + _id_properties(struct)


def _id_value(value, seen):
    """An ID a modifier points to: a node group by what it computes, any other by its name."""
    if isinstance(value, bpy.types.NodeTree):
        return _node_tree_values(value, seen)
    return _plain(value)


def _node_tree_values(tree, seen):
    """What a node group computes: each node's type, settings and input values, and the links
    (not the layout); nested groups read once each."""
    global _NODE_BASE_PROPS
    if ("NodeTree", tree.as_pointer()) in seen:
        return tree.name
    seen.add(("NodeTree", tree.as_pointer()))
    if _NODE_BASE_PROPS is None:
        _NODE_BASE_PROPS = frozenset(p.identifier for p in bpy.types.Node.bl_rna.properties)
    skipped = _SKIPPED_PROPS | _NODE_BASE_PROPS
    nodes = []
    for node in sorted(tree.nodes, key=lambda n: n.name):
        inputs = [(socket.identifier, _plain(getattr(socket, "default_value", None)))
                  for socket in node.inputs]
        nodes.append((node.bl_idname, node.name, node.mute, _struct_values(node, seen, skipped),
                      inputs))
    links = sorted((link.from_node.name, link.from_socket.identifier, link.to_node.name,
                    link.to_socket.identifier, link.is_muted) for link in tree.links)
    return (tree.name, nodes, links)


def _modifier_stack(obj):
    """A text describing the modifier stack: every modifier's type and settings, read the same
    way for every type (``_struct_values``), Geometry Nodes with its node group and inputs."""
    parts = []
    for m in obj.modifiers:
        if mesh_cache.is_bake_modifier(obj, m):     # the bake's own player is not an input
            continue
        parts.append((m.type, m.name, _struct_values(m, set())))
    return repr(parts)


def _geometry_fingerprint(obj):
    """The costly part of the fingerprint: vertices, faces, modifiers, pin and stiffness
    weights (hashes)."""
    mesh = obj.data
    co = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", co)
    corners = np.empty(len(mesh.loops), dtype=np.int32)
    corner_vert = mesh.attributes.get(".corner_vert")     # 100× faster than mesh.loops
    if corner_vert is not None:
        corner_vert.data.foreach_get("value", corners)
    else:
        mesh.loops.foreach_get("vertex_index", corners)
    sizes = np.empty(len(mesh.polygons), dtype=np.int32)
    mesh.polygons.foreach_get("loop_start", sizes)
    return {"vertex count": str(len(mesh.vertices)), "faces": cache.content_key(corners, sizes),
            "vertices": cache.content_key(co), "modifiers": cache.content_key(_modifier_stack(obj)),
            "pin group": _group_fingerprint(obj, obj.rs_elastic.pin_group, pin_weights, "free"),
            **_stiffness_fingerprint(obj)}


def _group_fingerprint(obj, group, read_weights, unset):
    """``unset`` without a group, "missing" for one the object lacks, else its weights' hash."""
    if not group:
        return unset
    if obj.vertex_groups.get(group) is None:
        return "missing"
    return cache.content_key(read_weights(obj, group))


def _stiffness_fingerprint(obj):
    """The stiffness group's weights; no component at all for a uniform material, so a body
    prepared before painted stiffness existed reads as it did (and the ratio, which only a
    painted body reads, is in ``_settings_fingerprint`` on the same terms)."""
    group = obj.rs_elastic.stiffness_group
    if not group:
        return {}
    return {"stiffness group": _group_fingerprint(obj, group, stiffness_weights, "")}


def _settings_fingerprint(settings):
    painted = ({"stiffness ratio": repr(settings.stiffness_ratio)} if settings.stiffness_group
               else {})
    return {"tet mesh settings": repr((settings.edge_length, settings.envelope,
                                       settings.proxy_triangles)),
            "material": repr((settings.youngs_modulus, settings.poisson_ratio, settings.density)),
            **painted,
            "number of modes": repr(settings.num_modes),
            "reduced RS settings": repr((settings.basis_size, settings.cubature_tets,
                                         settings.cubature_tolerance, settings.training_poses))}


_RULES = "version of the stages"   # the component a Prepare by another version differs in
_GEOMETRY = {}   # object pointer -> (groups' names and indices..., geometry fingerprint), for draw


def fingerprint(obj, cached=False):
    """dict component -> text/hash of everything Prepare reads. `cached` reuses the geometry
    part until a depsgraph update of the object or its mesh (for the panel, which runs in draw)."""
    settings = obj.rs_elastic
    groups = [(name, getattr(obj.vertex_groups.get(name) if name else None, "index", None))
              for name in (settings.pin_group, settings.stiffness_group)]
    mesh = obj.data
    tag = (groups, len(mesh.vertices), len(mesh.polygons), len(obj.modifiers))
    entry = _GEOMETRY.get(obj.as_pointer()) if cached else None
    if entry is None or entry[0] != tag:
        entry = _GEOMETRY[obj.as_pointer()] = (tag, _geometry_fingerprint(obj))
    # The stages' rules first: under other rules every other component may read differently too.
    return {_RULES: stage_rules.prepared_rules(), **entry[1], **_settings_fingerprint(settings)}


def forget_fingerprints(depsgraph_updates):
    """Drop the cached geometry fingerprints once a mesh or an object's geometry changed (all of
    them for None: after a load or an undo)."""
    if depsgraph_updates is None:
        _GEOMETRY.clear()
        return
    for update in depsgraph_updates:
        if isinstance(update.id, (bpy.types.Mesh, bpy.types.Object)) and (
                update.is_updated_geometry or isinstance(update.id, bpy.types.Mesh)):
            _GEOMETRY.clear()     # cheap to rebuild for the few objects a panel shows
            return


_OLDER_VERSION = ("it was prepared by another version of RS Elastic, whose cached stages this one "
                  "cannot read: prepare again")
_PAINTED = ("stiffness group", "stiffness ratio")   # components only a painted body has


def _what_changed(obj, before, now):
    """What to tell the user about the first component that differs (one now has, or a painted
    stiffness's that only Prepare had: the group was cleared since), or None."""
    for name in [*now, *(name for name in _PAINTED if name in before and name not in now)]:
        value = now.get(name)
        if before.get(name) == value:
            continue
        if name == _RULES:
            return _OLDER_VERSION
        if name in ("pin group", "stiffness group") and value == "missing":
            group = getattr(obj.rs_elastic, name.replace(" ", "_"))
            return (f"{name} '{group}' no longer exists (renamed or deleted since Prepare Body): "
                    f"set {name.title()} and prepare again")
        if name == "vertex count":
            what = f"the vertex count changed since Prepare Body ({before.get(name)} → {value})"
        elif name == "vertices":
            what = "the mesh's vertices moved since Prepare Body"
        else:
            what = f"the {name} changed since Prepare Body"
        return what + ": prepare again"
    return None


def stale_reason(obj, cached=False):
    """Why the prepared body no longer matches the object, in words, or None if it does."""
    settings = obj.rs_elastic
    if not settings.is_prepared:
        return None
    record = settings.get(PREPARED_INPUTS)
    if record is None:
        return _OLDER_VERSION
    return _what_changed(obj, json.loads(record), fingerprint(obj, cached=cached))


def require_current(obj):
    """Raise InputError saying what changed if the object's preparation is stale."""
    reason = stale_reason(obj)
    if reason:
        raise InputError(f"'{obj.name}': {reason}")


def record_prepared(obj, prepared_fingerprint):
    obj.rs_elastic[PREPARED_INPUTS] = json.dumps(prepared_fingerprint, sort_keys=True)
