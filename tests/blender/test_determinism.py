"""The same file gives the same bake: twice in one process (bit for bit), in a new process and on
a machine without the cache folder (to 1e-10 of the bounding-box diagonal). The tet mesh travels
with the .blend, so fTetWild never runs again for it."""
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
import bpy

from blender_helpers import add_tip_handle, diagonal, make_bar, vertices
from conftest import ROOT, USER_DIR

# In a new Blender process: open the file, bake it as `bake_steps` says, dump every bake's
# float64 poses (what the operators hand to write_bake, before shape keys round them to float32).
CHILD_SCRIPT = """
import json, sys
import numpy as np
sys.path.insert(0, {tools!r})
import blender_session
ext = blender_session.start(user_dir={user_dir!r})
import bpy
bpy.ops.wm.open_mainfile(filepath={blend!r})
bakes = []
write_bake = ext.bridge.bake.write_bake
def recording(obj, frames, positions):
    bakes.append(np.array(positions, dtype=np.float64))
    return write_bake(obj, frames, positions)
ext.bridge.bake.write_bake = recording
obj = bpy.data.objects["Bar"]
bpy.context.view_layer.objects.active = obj
if {use_cli!r}:
    code = ext.bridge.cli.main(["bake", "--object", "Bar", "--output", {output!r}])
    assert code == 0, code
else:
    for operator in ("prepare", "simulate", "solve_spacetime"):
        assert getattr(bpy.ops.rs_elastic, operator)() == {{'FINISHED'}}, operator
body = ext.bridge.bodies.load_prepared(obj)
np.savez({dump!r}, nodes=body.tet_body.nodes, tets=body.tet_body.tets, *bakes)
print("STATS " + json.dumps(dict(ext.bridge.stage_cache.stats)))
blender_session.exit_child(0)
"""


def run_child(blend, dump, use_cli=False, output=""):
    script = CHILD_SCRIPT.format(tools=str(ROOT / "tools"), user_dir=USER_DIR, blend=str(blend),
                                 dump=str(dump), use_cli=use_cli, output=str(output))
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=600)
    stats = [line for line in out.stdout.splitlines() if line.startswith("STATS ")]
    assert out.returncode == 0 and stats, out.stdout[-3000:] + out.stderr[-3000:]
    data = np.load(dump)
    bakes = [data[f"arr_{i}"] for i in range(len(data.files) - 2)]
    return data["nodes"], data["tets"], bakes, json.loads(stats[0][6:])


@pytest.fixture
def recorder(ext, monkeypatch):
    """Every bake's float64 poses, in order, as handed to write_bake."""
    bakes = []
    write_bake = ext.bridge.bake.write_bake

    def recording(obj, frames, positions):
        bakes.append(np.array(positions, dtype=np.float64))
        return write_bake(obj, frames, positions)

    monkeypatch.setattr(ext.bridge.bake, "write_bake", recording)
    return bakes


def saved_scene(tmp_path):
    """A pinned bar with a keyed tip handle, prepared (so its tet mesh is in the file), saved."""
    obj = make_bar(cuts=3)
    obj.rs_elastic.edge_length = 0.1
    obj.rs_elastic.num_modes = 6
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    add_tip_handle(obj, {12: (3.6, 0.5, 1.8), 24: (3.8, 1.2, 0.4)})
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 30
    blend = tmp_path / "shot.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    return blend, diagonal(vertices(obj))


def forget_the_cache(ext, blend):
    """As on a machine that never saw this file: no cache folder, nothing in memory."""
    shutil.rmtree(blend.parent / f"blendcache_{blend.stem}", ignore_errors=True)
    shutil.rmtree(ext.bridge.stage_cache.cache_dirs()[-1], ignore_errors=True)
    ext.bridge.stage_cache._MEMORY.clear()
    ext.bridge.prepared._BODIES.clear()


def bake_here(ext, blend, recorder):
    """Open the file afresh, prepare from nothing, simulate and solve; returns the tet mesh and
    the two bakes."""
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    forget_the_cache(ext, blend)
    recorder.clear()
    obj = bpy.data.objects["Bar"]
    bpy.context.view_layer.objects.active = obj
    for operator in ("prepare", "simulate", "solve_spacetime"):
        assert getattr(bpy.ops.rs_elastic, operator)() == {'FINISHED'}, operator
    body = ext.bridge.bodies.load_prepared(obj)
    return body.tet_body.nodes.copy(), body.tet_body.tets.copy(), list(recorder)


def test_the_same_file_bakes_the_same_twice_in_one_process_and_in_a_new_one(ext, tmp_path,
                                                                             recorder):
    blend, size = saved_scene(tmp_path)
    ext.bridge.stage_cache.stats.clear()
    first = bake_here(ext, blend, recorder)
    second = bake_here(ext, blend, recorder)
    stats = ext.bridge.stage_cache.stats
    assert stats["tetrahedralize"] == 0 and stats["modes"] == 2      # really recomputed
    forget_the_cache(ext, blend)
    third = run_child(blend, tmp_path / "child.npz")
    assert third[3].get("tetrahedralize", 0) == 0
    # The tet mesh is the one kept in the file, every time.
    for other in (second, third):
        np.testing.assert_array_equal(other[0], first[0])
        np.testing.assert_array_equal(other[1], first[1])
    assert len(first[2]) == len(second[2]) == len(third[2]) == 2       # simulation, space-time
    for a, b in zip(first[2], second[2]):
        np.testing.assert_array_equal(a, b)                          # bit for bit
    for a, c in zip(first[2], third[2]):
        print(f"new process: largest difference {np.abs(a - c).max():.3g} m "
              f"(bound {1e-10 * size:.3g} m)")
        assert np.abs(a - c).max() <= 1e-10 * size
        assert np.abs(a - a[0]).max() > 1e-3 * size                  # a bake that moves


def test_a_farm_without_the_cache_folder_bakes_the_same(ext, tmp_path, recorder):
    blend, size = saved_scene(tmp_path)
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    here = recorder[-1]
    bpy.ops.wm.save_mainfile()
    forget_the_cache(ext, blend)
    nodes, tets, bakes, stats = run_child(blend, tmp_path / "farm.npz", use_cli=True,
                                          output=tmp_path / "farm.blend")
    assert stats.get("tetrahedralize", 0) == 0 and stats["modes"] == 1
    assert len(bakes) == 1
    print(f"farm: largest difference {np.abs(bakes[0] - here).max():.3g} m "
          f"(bound {1e-10 * size:.3g} m)")
    assert np.abs(bakes[0] - here).max() <= 1e-10 * size
    assert np.abs(here - here[0]).max() > 1e-3 * size
