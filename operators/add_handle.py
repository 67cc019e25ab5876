"""Bind a new Empty to some vertices of the body: a handle for space-time editing."""
import bpy
import numpy as np
from mathutils import Vector

from ..bridge import scene
from ..bridge.scene import InputError


def selected_vertices(obj):
    """(k,) indices of the vertices selected in Edit Mode."""
    obj.update_from_editmode()
    selected = np.zeros(len(obj.data.vertices), dtype=bool)
    obj.data.vertices.foreach_get("select", selected)
    return np.flatnonzero(selected)


def handle_vertices(obj, group_name):
    if group_name:
        return group_name, np.flatnonzero(scene.vertex_group_mask(obj, group_name))
    if obj.mode != 'EDIT':
        raise InputError("Select vertices in Edit Mode, or name a vertex group")
    indices = selected_vertices(obj)
    if len(indices) == 0:
        raise InputError("No vertices are selected")
    # Vertex groups cannot be filled in Edit Mode: step out and back in.
    bpy.ops.object.mode_set(mode='OBJECT')
    group = obj.vertex_groups.new(name="RS Handle")
    group.add([int(i) for i in indices], 1.0, 'REPLACE')
    bpy.ops.object.mode_set(mode='EDIT')
    return group.name, indices


def handle_collection(obj, scene):
    """Where the handle's Empty goes: the body's first collection that this file may change (a
    linked or overridden collection cannot take new objects), else the scene's own."""
    for collection in obj.users_collection:
        if collection.library is None and collection.override_library is None:
            return collection
    return scene.collection


class RS_ELASTIC_OT_add_handle(bpy.types.Operator):
    """Add an Empty at the centroid of the selected vertices (or a vertex group); its keyed
    locations become targets of the space-time solve"""
    bl_idname = "rs_elastic.add_handle"
    bl_label = "Add Handle"
    bl_options = {'REGISTER', 'UNDO'}

    vertex_group: bpy.props.StringProperty(
        name="Vertex Group", description="Bind to this vertex group instead of the selection")

    def execute(self, context):
        try:
            obj = scene.require_mesh_object(scene.acted_on(context))
            group_name, indices = handle_vertices(obj, self.vertex_group)
            if len(indices) == 0:
                raise InputError(f"Vertex group '{group_name}' has no vertices")
        except InputError as exc:
            self.report({'ERROR'}, str(exc))
            return {'CANCELLED'}
        rest = scene.base_vertices(obj)
        centroid = rest[indices].mean(axis=0)
        empty = bpy.data.objects.new(f"{obj.name} Handle", None)
        empty.empty_display_type = 'SPHERE'
        extent = np.linalg.norm(rest.max(axis=0) - rest.min(axis=0))
        empty.empty_display_size = 0.04 * extent * max(obj.matrix_world.to_scale())
        empty.location = obj.matrix_world @ Vector(centroid)
        handle_collection(obj, context.scene).objects.link(empty)
        handle = obj.rs_elastic.handles.add()
        handle.empty = empty
        handle.vertex_group = group_name
        obj.rs_elastic.active_handle = len(obj.rs_elastic.handles) - 1
        self.report({'INFO'}, f"Handle '{empty.name}' bound to {len(indices)} vertices of "
                              f"'{obj.name}'; key its location to set targets")
        return {'FINISHED'}


class RS_ELASTIC_OT_remove_handle(bpy.types.Operator):
    """Forget the active handle (its Empty and vertex group are kept)"""
    bl_idname = "rs_elastic.remove_handle"
    bl_label = "Remove Handle"
    bl_options = {'REGISTER', 'UNDO'}

    @classmethod
    def poll(cls, context):
        obj = scene.acted_on(context)
        return obj is not None and obj.type == 'MESH' and len(obj.rs_elastic.handles) > 0

    def execute(self, context):
        settings = scene.acted_on(context).rs_elastic
        index = min(settings.active_handle, len(settings.handles) - 1)
        settings.handles.remove(index)
        settings.active_handle = max(0, index - 1)
        return {'FINISHED'}


CLASSES = (RS_ELASTIC_OT_add_handle, RS_ELASTIC_OT_remove_handle)
