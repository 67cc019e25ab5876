"""Live mode preview as a temporary shape key.

Linear: the rest pose plus the scaled mode, X + s·w. RS: the same modal coordinate sent through
rotation-strain coordinates and reconstructed, Ψ(s·Q w), which curls where the linear mode
stretches. Reduced RS: the same through the reduced basis and cubature, Φ B q(s·e_k), whose
cost does not grow with the mesh. The scale s makes the linear mode's largest displacement the
chosen amplitude.

The preview owns one shape key, named PREVIEW_KEY and tagged as the extension's, and the Basis key
if the mesh had none (see bake.py on ownership). Turning the preview off removes exactly those, so
the mesh is left as it was; the base vertices and the user's keys are never written. A mesh shared
by linked duplicates shows no preview: its keys belong to every object using it.

Outside Object Mode the key is not written (leaving Edit Mode would write the mode's own copy of
the keys over it): the object waits in ``WAITING`` and its preview is brought in line once it is
back in Object Mode (bridge/handlers.py).
"""
import numpy as np

from . import bake, mesh_cache, prepared, scene, writes
from .scene import InputError

PREVIEW_KEY = bake.PREVIEW_KEY
WAITING = set()      # names of objects whose preview changed outside Object Mode


def refresh(obj):
    """Bring the preview key in line with obj.rs_elastic (called from the property updates)."""
    if obj.rs_elastic.preview_enabled:
        show(obj)
    else:
        hide(obj)


def preview_positions(obj, body):
    """(n, 3) base-vertex positions for the selected mode, amplitude and method."""
    settings = obj.rs_elastic
    rest = scene.base_vertices(obj)
    modes = body.linear_modes
    index = min(settings.preview_mode, modes.vectors.shape[1]) - 1
    linear = body.surface_mode(index)
    peak = np.linalg.norm(linear, axis=1).max()
    if peak == 0.0:
        return rest
    diagonal = np.linalg.norm(rest.max(axis=0) - rest.min(axis=0))
    scale = settings.preview_amplitude * diagonal / peak
    if settings.preview_method == 'LINEAR':
        return rest + scale * linear
    if settings.preview_method == 'REDUCED' and body.deformer is not None:
        z = np.zeros(body.deformer.num_coords)
        z[index] = scale
        return body.surface_positions(rest, z)
    y = body.modal_rs[:, :, index] * scale
    return rest + body.surface(body.reconstruction.reconstruct(y))


def in_object_mode(obj):
    """Whether the preview key may be written now; if not, the object waits for Object Mode."""
    if obj.mode == 'OBJECT':
        return True
    WAITING.add(obj.name)
    return False


def under_bake(obj):
    """Whether a shape-key bake is in place: its keys add to the preview's, so on a baked frame
    the mesh would show their sum. The mode preview then does not show (the panel says so). A
    Mesh Cache bake is no obstacle: it is hidden while the preview shows."""
    return obj.type == 'MESH' and bool(bake.owned_keys(obj, "bake"))


def show(obj):
    body = prepared.for_object(obj)
    if body is None:
        return False  # not prepared for this mesh; the panel says so
    if under_bake(obj):
        hide(obj)
        return False  # the panel says why
    try:
        scene.require_single_user(obj)
    except InputError:
        return False  # linked duplicates: the panel's Prepare already refuses them
    if not in_object_mode(obj):
        return False
    write_key(obj, preview_positions(obj, body))
    return True


def write_key(obj, positions):
    """Show base-vertex positions (n, 3) on the preview key (made if missing), over a cache
    bake (which would overwrite the key while it plays). A failure changes nothing."""
    with writes.transaction(f"Showing the preview of '{obj.name}'") as transaction:
        key = _preview_key(obj)
        if key is None:
            key, = bake.add_keys(obj, [PREVIEW_KEY], "preview", transaction)
        else:
            before = np.empty(len(key.data) * 3, dtype=np.float32)
            key.data.foreach_get("co", before)
            transaction.undo(lambda: key.data.foreach_set("co", before))
            writes.keep_values(transaction, key, ["value"])
        key.data.foreach_set("co", np.asarray(positions, dtype=np.float32).ravel())
        key.value = 1.0
        _show_cache_bake(obj, False, transaction)
        obj.data.update()


def hide(obj):
    if obj.type != 'MESH' or not in_object_mode(obj):
        return
    with writes.transaction(f"Hiding the preview of '{obj.name}'") as transaction:
        bake.remove_keys_later(obj, [b.name for b in bake.owned_keys(obj, "preview")],
                               transaction)
        _show_cache_bake(obj, True, transaction)
        obj.data.update()


def _show_cache_bake(obj, visible, transaction):
    modifier = mesh_cache.owned_modifier(obj)
    if modifier is not None and modifier.show_viewport != visible:
        writes.keep_values(transaction, modifier, ["show_viewport"])
        modifier.show_viewport = visible


def is_shown(obj):
    return _preview_key(obj) is not None


def _preview_key(obj):
    if obj.type != 'MESH':
        return None
    owned = bake.owned_keys(obj, "preview")
    return owned[0] if owned else None
