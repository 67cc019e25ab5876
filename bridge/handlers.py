"""Application handlers: keep each body's cache next to the .blend it belongs to, drop the
panel's cached fingerprints when what they describe may have changed, follow Live's handles,
and the reactions to settings that set off work (the mode preview, Live, the tet overlay)."""
import bpy
from bpy.app.handlers import persistent

from . import live, preview, properties, stage_cache, staleness, tet_overlay


@persistent
def _move_cache_after_save(*_args):
    # A file saved under a new name gets its own blendcache folder; copy the prepared stages
    # there so reopening it reuses them.
    for obj in bpy.data.objects:
        if obj.type == 'MESH' and obj.rs_elastic.tets_key:
            stage_cache.persist(obj)


@persistent
def _forget_fingerprints(scene, depsgraph):
    # The panel's staleness check caches each body's geometry fingerprint until it changes.
    staleness.forget_fingerprints(depsgraph.updates)


@persistent
def _forget_all_fingerprints(*_args):
    # After a load or an undo step, objects may sit at addresses that other objects had.
    staleness.forget_fingerprints(None)


@persistent
def _live_resolve(scene, depsgraph):
    # A live body re-solves when its handles' Empties or keyframes change (bridge/live.py).
    live.on_depsgraph_update(scene, depsgraph)


@persistent
def _live_frame(scene, *_args):
    live.on_frame_change(scene)


def _live_toggled(settings, context):
    # On: solve once now (via the timer); off: drop the live preview so the mesh is as before.
    if settings.live:
        live.request(settings.id_data.name)
    else:
        live.stop(settings.id_data)


_ALL_FINGERPRINTS_GONE = ("load_post", "undo_post", "redo_post")


def register():
    properties.set_reaction("preview", lambda settings, context: preview.refresh(settings.id_data))
    properties.set_reaction("live", _live_toggled)
    properties.set_reaction("show_tets", lambda settings, context: tet_overlay.tag_redraw(context))
    bpy.app.handlers.save_post.append(_move_cache_after_save)
    bpy.app.handlers.depsgraph_update_post.append(_forget_fingerprints)
    bpy.app.handlers.depsgraph_update_post.append(_live_resolve)
    bpy.app.handlers.frame_change_post.append(_live_frame)
    for name in _ALL_FINGERPRINTS_GONE:
        getattr(bpy.app.handlers, name).append(_forget_all_fingerprints)


def unregister():
    if _move_cache_after_save in bpy.app.handlers.save_post:
        bpy.app.handlers.save_post.remove(_move_cache_after_save)
    if _forget_fingerprints in bpy.app.handlers.depsgraph_update_post:
        bpy.app.handlers.depsgraph_update_post.remove(_forget_fingerprints)
    live.cancel()
    for name, handler in (("depsgraph_update_post", _live_resolve),
                          ("frame_change_post", _live_frame)):
        if handler in getattr(bpy.app.handlers, name):
            getattr(bpy.app.handlers, name).remove(handler)
    for name in _ALL_FINGERPRINTS_GONE:
        handlers = getattr(bpy.app.handlers, name)
        if _forget_all_fingerprints in handlers:
            handlers.remove(_forget_all_fingerprints)
