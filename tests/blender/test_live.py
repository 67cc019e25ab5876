"""Live re-solve: moving a handle's Empty re-solves into the preview, never into the bake."""

import numpy as np
import pytest
import bpy

from blender_helpers import diagonal, evaluated_vertices, fingerprint, vertices
from test_spacetime import lifted, prepared_bar_with_tip_handle, world_tip


def bake_bits(ext, obj):
    """Bytes of every RS Bake key's positions, value and F-curve points (the bake, bit for bit)."""
    keys = obj.data.shape_keys
    parts = []
    for block in ext.bridge.bake.owned_keys(obj, "bake"):
        co = np.empty(len(block.data) * 3, dtype=np.float32)
        block.data.foreach_get("co", co)
        parts.append(block.name.encode() + co.tobytes() + repr(block.value).encode())
    for curve in ext.bridge.animation.fcurves(keys):
        if "RS Bake" in curve.data_path:
            parts.append(repr([tuple(p.co) for p in curve.keyframe_points]).encode())
    return parts


def test_live_moves_the_preview_onto_the_new_target_and_leaves_the_bake(ext):
    live = ext.bridge.live
    obj, empty, tip = prepared_bar_with_tip_handle({20: (0, 0, 0), 40: (0, 0, 0)})
    old = {20: np.array(lifted(obj, 1.0)), 40: np.array(lifted(obj, -0.5))}
    for frame, target in old.items():
        empty.location = target
        empty.keyframe_insert("location", frame=frame)
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    bpy.context.scene.frame_set(20)
    before_live = fingerprint(obj)
    baked = bake_bits(ext, obj)
    size = diagonal(vertices(obj))

    obj.rs_elastic.live = True              # background: no timer, so it waits for flush()
    assert live.flush() == [obj.name]       # the first live solve is cold
    assert live.status(obj).startswith("Live: cold")
    bpy.context.scene.frame_set(25)         # playing the animation is not an edit
    bpy.context.view_layer.update()
    assert obj.name not in live._PENDING

    # Move the Empty at the keyed frame 20 and re-key it; the registered handler must notice.
    new = old[20] + np.array([0.0, 0.0, 0.4])
    empty.location = new
    empty.keyframe_insert("location", frame=20)
    bpy.context.view_layer.update()
    assert obj.name in live._PENDING, "depsgraph handler did not notice the Empty move"
    assert live.flush() == [obj.name]
    assert live.status(obj).startswith("Live: warm")

    bpy.context.scene.frame_set(20)
    miss = np.linalg.norm(world_tip(obj, tip)[:3] - new)
    assert miss < 1e-3 * size, miss
    # The bake alone still puts the tip on the old target (so the check above could fail).
    assert np.linalg.norm(old[20] - new) > 100 * miss
    assert bake_bits(ext, obj) == baked

    # Off: the live preview goes and the mesh is exactly as before Live.
    obj.rs_elastic.live = False
    bpy.context.scene.frame_set(20)
    assert fingerprint(obj) == before_live
    assert np.linalg.norm(world_tip(obj, tip)[:3] - old[20]) < 1e-3 * size


@pytest.mark.parametrize("setting, value", [("density", 4400.0), ("poisson_ratio", 0.3)])
def test_after_a_prepare_of_another_material_live_starts_cold_and_meets_the_moved_handle(
        ext, setting, value):
    """Another density rescales the modal coordinates (the modes at rho are those at 1 kg/m³
    over sqrt(rho)); another Poisson's ratio makes other modes. Either way the last live
    solution is in coordinates the new preparation does not share: the next re-solve starts
    cold, not from it, and meets the moved handle; the one after is warm again."""
    live = ext.bridge.live
    obj, empty, tip = prepared_bar_with_tip_handle({})
    empty.location = lifted(obj, 0.8)
    empty.keyframe_insert("location", frame=30)
    bpy.context.view_layer.update()
    obj.rs_elastic.live = True
    assert live.flush() == [obj.name]
    assert live.status(obj).startswith("Live: cold")
    assert getattr(obj.rs_elastic, setting) != value
    setattr(obj.rs_elastic, setting, value)
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    if setting == "density":
        assert ext.bridge.stage_cache.stats["modes"] == 1         # the modes were moved
    for height in (-0.6, -0.5):
        target = np.array(lifted(obj, height))
        empty.location = target
        empty.keyframe_insert("location", frame=30)
        bpy.context.view_layer.update()
        assert live.flush() == [obj.name]
        assert live.status(obj).startswith("Live: cold" if height == -0.6 else "Live: warm"), \
            live.status(obj)
        bpy.context.scene.frame_set(30)
        assert np.linalg.norm(world_tip(obj, tip)[:3] - target) < 1e-3 * diagonal(vertices(obj))
    obj.rs_elastic.live = False


def test_live_without_a_bake_shows_the_solve_and_off_restores_the_mesh(ext):
    live = ext.bridge.live
    obj, empty, tip = prepared_bar_with_tip_handle({})
    target = np.array(lifted(obj, 0.8))
    empty.location = target
    empty.keyframe_insert("location", frame=30)
    bpy.context.view_layer.update()          # the edit is evaluated (and noticed) before Live
    user = fingerprint(obj)
    obj.rs_elastic.live = True               # queued; drive the timer's worker path by hand
    if live._tick() is not None:             # started the worker thread, still running
        thread, _, _ = live._RUNNING[obj.name]
        thread.join(timeout=60)
        assert live._tick() is None, (live._PENDING, live._RUNNING, live.ERRORS)
    assert not live._RUNNING and not live._PENDING
    assert live.status(obj).startswith("Live: cold"), live.status(obj)
    assert ext.bridge.bake.bake_frames(obj) == []          # Live never bakes
    bpy.context.scene.frame_set(30)
    assert np.linalg.norm(world_tip(obj, tip)[:3] - target) < 1e-3 * diagonal(vertices(obj))
    assert np.abs(evaluated_vertices(obj) - vertices(obj)).max() > 0.1
    obj.rs_elastic.live = False
    assert fingerprint(obj) == user
