"""Viewport overlay of tet-mesh edges for objects with `Show Tets` on, with the tet nodes the pins
hold drawn as points in a colour of their own.

Drawn by one POST_VIEW handler; the object's data is never touched. The GPU batches of each tet
mesh are built once per cache key. Nothing is drawn in background mode (there is no viewport).
"""
import bpy
import numpy as np

from . import stage_cache

_handler = None
_batches = {}   # (tets_key, prepared_key) -> (shader, edge batch, pinned-node batch or None)
EDGE_COLOUR = (0.1, 0.6, 1.0, 0.6)
PINNED_COLOUR = (1.0, 0.35, 0.05, 1.0)


def _tet_edges(tets):
    """(k, 2) unique edges of (E, 4) tets."""
    pairs = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)])
    edges = np.sort(tets[:, pairs].reshape(-1, 2), axis=1)
    return np.unique(edges, axis=0)


def _batch(obj):
    settings = obj.rs_elastic
    key = (settings.tets_key, settings.prepared_key)
    if key not in _batches:
        import gpu
        from gpu_extras.batch import batch_for_shader
        tet_body = stage_cache.load_tet_body(obj)
        if tet_body is None:
            _batches[key] = None
        else:
            shader = gpu.shader.from_builtin('UNIFORM_COLOR')
            nodes = tet_body.nodes.astype(np.float32)
            edges = batch_for_shader(shader, 'LINES', {"pos": nodes},
                                     indices=_tet_edges(tet_body.tets).astype(np.int32))
            pinned = stage_cache.load_pinned_nodes(obj) if settings.prepared_key else None
            points = None
            if pinned is not None and len(pinned) and pinned.max() < len(nodes):
                points = batch_for_shader(shader, 'POINTS', {"pos": nodes[pinned]})
            _batches[key] = (shader, edges, points)
    return _batches[key]


def _draw():
    import gpu
    context = bpy.context
    for obj in context.visible_objects:
        if obj.type != 'MESH' or not obj.rs_elastic.show_tets or not obj.rs_elastic.tets_key:
            continue
        entry = _batch(obj)
        if entry is None:
            continue
        shader, edges, points = entry
        gpu.matrix.push()
        gpu.matrix.multiply_matrix(obj.matrix_world)
        gpu.state.blend_set('ALPHA')
        shader.uniform_float("color", EDGE_COLOUR)
        edges.draw(shader)
        if points is not None:
            gpu.state.point_size_set(6.0)
            shader.uniform_float("color", PINNED_COLOUR)
            points.draw(shader)
            gpu.state.point_size_set(1.0)
        gpu.state.blend_set('NONE')
        gpu.matrix.pop()


def tag_redraw(context):
    screen = getattr(context, "screen", None)
    if screen is None:
        return
    for area in screen.areas:
        if area.type == 'VIEW_3D':
            area.tag_redraw()


def register():
    global _handler
    if not bpy.app.background:
        _handler = bpy.types.SpaceView3D.draw_handler_add(_draw, (), 'WINDOW', 'POST_VIEW')


def unregister():
    global _handler
    if _handler is not None:
        bpy.types.SpaceView3D.draw_handler_remove(_handler, 'WINDOW')
        _handler = None
    _batches.clear()
