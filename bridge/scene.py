"""Read a Blender object into numpy arrays for the solver (main thread only)."""
import numpy as np


class InputError(Exception):
    """Bad user input: the message is shown as-is in the UI and on the command line."""


def require_mesh_object(obj):
    """Raise InputError unless `obj` is a mesh object."""
    if obj is None:
        raise InputError("No active object: select a mesh object")
    if obj.type != 'MESH':
        raise InputError(f"'{obj.name}' is a {obj.type.lower()}, not a mesh")
    if obj.mode == 'EDIT':
        # Edit-mode changes are not in obj.data until the mode is left.
        obj.update_from_editmode()
    if len(obj.data.vertices) == 0 or len(obj.data.polygons) == 0:
        raise InputError(f"'{obj.name}' has an empty mesh (no faces)")
    return obj


def active_mesh_or_report(operator, context):
    """The active mesh object, or None after reporting why not (for short operators)."""
    try:
        return require_mesh_object(context.active_object)
    except InputError as exc:
        operator.report({'ERROR'}, str(exc))
        return None


def base_vertices(obj):
    """(n, 3) float64 object-space positions of the mesh's own vertices (what shape keys move)."""
    mesh = obj.data
    co = np.empty(len(mesh.vertices) * 3, dtype=np.float64)
    mesh.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


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


def vertex_group_mask(obj, group_name):
    """(n,) bool: vertices of the mesh with a non-zero weight in the named group.

    Read once per preparation; Blender has no bulk accessor for group weights, so this walks
    the vertices' group memberships a single time.
    """
    group = obj.vertex_groups.get(group_name)
    if group is None:
        raise InputError(f"Pin group '{group_name}' does not exist on '{obj.name}'")
    index = group.index
    mask = np.zeros(len(obj.data.vertices), dtype=bool)
    members = [v.index for v in obj.data.vertices
               for g in v.groups if g.group == index and g.weight > 0.0]
    mask[members] = True
    return mask
