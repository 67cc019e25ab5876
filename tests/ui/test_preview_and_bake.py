"""The mode preview and a bake in the real window: the preview never adds itself on top of a
shape-key bake (the mesh at a baked frame is the bake, or the preview alone, never their sum)."""
import numpy as np

BAKED_BAR = """
import sys, blender_helpers as h
import numpy as np
bridge = sys.modules["bl_ext.user_default.rs_elastic.bridge"]
with override():
    obj = h.make_bar(cuts=3)
obj.rs_elastic.edge_length = 0.1
obj.rs_elastic.num_modes = 3
bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 8
with override():
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
"""

MESH = """
obj = bpy.data.objects["Bar"]
bpy.context.view_layer.update()
result = {"mesh": h.evaluated_vertices(obj).tolist(), "keys": [b.name for b in
          obj.data.shape_keys.key_blocks] if obj.data.shape_keys else [],
          "baked": bridge.bake.bake_frames(obj)}
"""


def test_the_mode_preview_never_adds_itself_on_top_of_a_bake(gui):
    gui.run(BAKED_BAR, timeout=300)
    gui.run("obj.rs_elastic.preview_amplitude = 0.3; obj.rs_elastic.preview_enabled = True")
    preview_alone = np.array(gui.run(MESH)["mesh"])
    rest = np.array(gui.run("result = h.vertices(obj).tolist()"))
    assert np.abs(preview_alone - rest).max() > 0.1           # the preview shows

    # Simulate and Bake with the preview on, as from the button (the bake droops under gravity).
    gui.run("with override():\n    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}",
            timeout=300)
    gui.run("bpy.context.scene.frame_set(8)")
    gui.settle()
    gui.screenshot("baked_with_preview_on")
    shown = gui.run(MESH)
    assert shown["baked"] == list(range(1, 9)), shown["baked"]
    gui.run("obj.rs_elastic.preview_enabled = False")
    bake_alone = np.array(gui.run(MESH)["mesh"])
    assert np.abs(bake_alone - rest).max() > 1e-3              # the bake moves the bar
    mesh = np.array(shown["mesh"])
    stacked = bake_alone + preview_alone - rest
    # Their sum differs from each alone (so the check below can fail).
    assert min(np.abs(stacked - bake_alone).max(), np.abs(stacked - preview_alone).max()) > 0.1
    assert (np.abs(mesh - bake_alone).max() < 1e-5
            or np.abs(mesh - preview_alone).max() < 1e-5), \
        f"at a baked frame the mesh is {np.abs(mesh - stacked).max():.3g} from the bake plus " \
        "the preview: the preview adds itself on top of the bake"

    # Turned on over the bake: the same.
    gui.run("obj.rs_elastic.preview_enabled = True")
    gui.settle()
    gui.screenshot("preview_turned_on_over_the_bake")
    mesh = np.array(gui.run(MESH)["mesh"])
    assert (np.abs(mesh - bake_alone).max() < 1e-5
            or np.abs(mesh - preview_alone).max() < 1e-5), np.abs(mesh - stacked).max()
    # Clear Bake: the preview shows again, on its own.
    gui.run("with override():\n    assert bpy.ops.rs_elastic.clear_bake() == {'FINISHED'}")
    mesh = np.array(gui.run(MESH)["mesh"])
    assert np.abs(mesh - preview_alone).max() < 1e-5
