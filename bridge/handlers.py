"""Application handlers: keep each body's cache and bakes next to the .blend they belong to, drop
the panel's cached fingerprints when what they describe may have changed, follow Live's handles,
show previews held back outside Object Mode, and the reactions to settings that set off work
(the mode preview, Live, the tet overlay)."""
import bpy
from bpy.app.handlers import persistent

from . import live, mesh_cache, preview, properties, stage_cache, staleness, tet_overlay
from .scene import InputError


@persistent
def _bakes_before_save(filepath="", *_args):
    # A file saved under a new folder or name gets its own copy of each Mesh Cache bake, played
    # by its modifiers, so clearing a bake in one .blend never breaks another's.
    mesh_cache.before_save(filepath)
    stage_cache.note_folders_before_save()


@persistent
def _bakes_after_load(*_args):
    # Another file: what this session wrote or released is no longer its to delete.
    mesh_cache.forget_session()


@persistent
def _bakes_after_save(filepath="", *_args):
    mesh_cache.after_save(filepath)


@persistent
def _bakes_after_failed_save(filepath="", *_args):
    mesh_cache.after_failed_save(filepath)


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
def _show_waiting_previews(scene, *_args):
    # A preview or live pose that changed outside Object Mode was not written (leaving Edit Mode
    # would overwrite it); back in Object Mode it is.
    for name in list(preview.WAITING):
        obj = bpy.data.objects.get(name)
        if obj is not None and obj.mode != 'OBJECT':
            continue
        preview.WAITING.discard(name)
        if obj is None:
            continue
        try:
            if not obj.rs_elastic.live:
                preview.refresh(obj)
            elif obj.name in live.SOLUTIONS:
                live.show(obj, scene)
            else:
                live.request(obj.name)
        except InputError as error:
            print(f"RS Elastic: {error}")


@persistent
def _live_resolve(scene, depsgraph):
    # A live body re-solves when its handles' Empties or keyframes change (bridge/live.py).
    live.on_depsgraph_update(scene, depsgraph)


@persistent
def _live_frame(scene, *_args):
    live.on_frame_change(scene)


def _preview_changed(settings, context):
    try:
        preview.refresh(settings.id_data)
    except InputError as error:      # a setting's update cannot report: the console says why
        print(f"RS Elastic: {error}")


def _live_toggled(settings, context):
    # On: solve once now (via the timer); off: drop the live preview so the mesh is as before.
    if settings.live:
        live.request(settings.id_data.name)
        return
    try:
        live.stop(settings.id_data)
    except InputError as error:
        print(f"RS Elastic: {error}")


_ALL_FINGERPRINTS_GONE = ("load_post", "undo_post", "redo_post")
_SAVE_HANDLERS = (("save_pre", _bakes_before_save), ("save_post", _bakes_after_save),
                  ("save_post_fail", _bakes_after_failed_save),
                  ("save_post", _move_cache_after_save), ("load_post", _bakes_after_load))
_UPDATE_HANDLERS = (("depsgraph_update_post", _forget_fingerprints),
                    ("depsgraph_update_post", _show_waiting_previews),
                    ("depsgraph_update_post", _live_resolve),
                    ("frame_change_post", _live_frame))


def register():
    properties.set_reaction("preview", _preview_changed)
    properties.set_reaction("live", _live_toggled)
    properties.set_reaction("show_tets", lambda settings, context: tet_overlay.tag_redraw(context))
    for name, handler in _SAVE_HANDLERS + _UPDATE_HANDLERS:
        handlers = getattr(bpy.app.handlers, name, None)     # save_post_fail: Blender 4.x on
        if handlers is not None:
            handlers.append(handler)
    for name in _ALL_FINGERPRINTS_GONE:
        getattr(bpy.app.handlers, name).append(_forget_all_fingerprints)


def unregister():
    live.cancel()
    for name, handler in _SAVE_HANDLERS + _UPDATE_HANDLERS:
        handlers = getattr(bpy.app.handlers, name, None)
        if handlers is not None and handler in handlers:
            handlers.remove(handler)
    for name in _ALL_FINGERPRINTS_GONE:
        handlers = getattr(bpy.app.handlers, name)
        if _forget_all_fingerprints in handlers:
            handlers.remove(_forget_all_fingerprints)
