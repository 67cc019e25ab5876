"""The body cache: next to the saved .blend, reused by a new process, rebuilt when stale or corrupt."""
import json
import os
import pathlib
import shutil
import subprocess
import sys

import numpy as np
import bpy

from blender_helpers import make_bar
from conftest import ROOT, USER_DIR

REOPEN_SCRIPT = """
import json, sys
sys.path.insert(0, {tools!r})
import blender_session
ext = blender_session.start(user_dir={user_dir!r})
import bpy
bpy.ops.wm.open_mainfile(filepath={blend!r})
obj = bpy.data.objects["Bar"]
bpy.context.view_layer.objects.active = obj
result = bpy.ops.rs_elastic.prepare()
print("RESULT " + json.dumps(dict(result=sorted(result), stats=dict(ext.bridge.bodies.stats),
                                  frequencies=list(obj.rs_elastic.frequencies))))
"""


def prepare_bar(ext):
    obj = make_bar()
    obj.rs_elastic.edge_length = 0.08
    obj.rs_elastic.num_modes = 5
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    return obj


def test_saved_file_keeps_its_cache_in_blendcache_folder_and_a_new_process_reuses_it(ext, tmp_path):
    obj = prepare_bar(ext)
    blend = tmp_path / "shot.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    # Prepare again now that the file has a name: the cache moves next to it, nothing recomputed.
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert ext.bridge.bodies.stats["modes"] == 1
    folder = tmp_path / "blendcache_shot"
    files = {p.name: p.stat().st_mtime_ns for p in folder.iterdir()}
    settings = obj.rs_elastic
    assert set(files) == {f"Bar.tets.{settings.tets_key[:16]}.npz",
                          f"Bar.modes.{settings.prepared_key[:16]}.npz",
                          f"Bar.reduced.{settings.reduced_key[:16]}.npz"}
    bpy.ops.wm.save_mainfile()

    script = REOPEN_SCRIPT.format(tools=str(ROOT / "tools"), user_dir=USER_DIR, blend=str(blend))
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    line = [l for l in out.stdout.splitlines() if l.startswith("RESULT ")]
    assert line, out.stdout + out.stderr
    child = json.loads(line[0][7:])
    assert child["result"] == ["FINISHED"]
    assert all(child["stats"].get(stage, 0) == 0 for stage in ("tetrahedralize", "modes", "reduced"))
    assert all(child["stats"][f"{stage}_cache_hits"] == 1 for stage in ("tets", "modes", "reduced"))
    np.testing.assert_allclose(child["frequencies"], obj.rs_elastic.frequencies, rtol=1e-12)
    assert {p.name: p.stat().st_mtime_ns for p in folder.iterdir()} == files


def test_stale_cache_is_rebuilt_per_stage(ext):
    obj = prepare_bar(ext)
    stats = ext.bridge.bodies.stats
    assert (stats["tetrahedralize"], stats["modes"]) == (1, 1)
    obj.rs_elastic.density *= 2.0                       # material: only the modes are stale
    ext.bridge.bodies._MEMORY.clear()
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert (stats["tetrahedralize"], stats["modes"]) == (1, 2)
    obj.data.vertices[0].co.x -= 0.2                    # mesh: everything is stale
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert (stats["tetrahedralize"], stats["modes"]) == (2, 3)


def test_corrupt_cache_file_is_reported_and_rebuilt(ext):
    obj = prepare_bar(ext)
    before = np.array(obj.rs_elastic.frequencies)
    path = pathlib.Path(ext.bridge.bodies.cache_file(ext.bridge.bodies.cache_dirs()[0], "Bar", "modes",
                                                     obj.rs_elastic.prepared_key))
    path.write_bytes(b"this is not a cache file")
    ext.bridge.bodies._MEMORY.clear()
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert ext.bridge.bodies.stats["modes"] == 2
    np.testing.assert_allclose(obj.rs_elastic.frequencies, before, rtol=1e-10)
    assert ext.solver.cache.load(str(path), obj.rs_elastic.prepared_key) is not None


def test_unsaved_file_uses_the_temp_folder(ext):
    assert bpy.data.filepath == ""
    import tempfile
    assert ext.bridge.bodies.cache_dirs() == [os.path.join(tempfile.gettempdir(), "rs_elastic_cache")]
    obj = prepare_bar(ext)
    assert sorted(os.listdir(ext.bridge.bodies.cache_dirs()[0])) == sorted(
        [f"Bar.modes.{obj.rs_elastic.prepared_key[:16]}.npz",
         f"Bar.tets.{obj.rs_elastic.tets_key[:16]}.npz",
         f"Bar.reduced.{obj.rs_elastic.reduced_key[:16]}.npz"])


def test_files_of_old_keys_are_pruned_once_a_new_preparation_is_applied(ext):
    obj = prepare_bar(ext)
    folder = ext.bridge.bodies.cache_dirs()[0]
    old = set(os.listdir(folder))
    obj.rs_elastic.youngs_modulus *= 3
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    new = set(os.listdir(folder))
    assert len(new) == 3 and len(old & new) == 1      # the tets are shared; old modes, reduced gone


def stored_tets(ext, obj):
    group = obj.rs_elastic.get(ext.bridge.bodies.TET_MESH)
    return group["key"], np.array(group["nodes"]), np.array(group["tets"])


def test_the_tet_mesh_stays_with_the_file_until_the_surface_or_mesher_settings_change(ext):
    obj = prepare_bar(ext)
    stats, bodies = ext.bridge.bodies.stats, ext.bridge.bodies
    key, nodes, tets = stored_tets(ext, obj)
    assert key == obj.rs_elastic.tets_key and len(tets) == 4 * obj.rs_elastic.tet_count
    assert nodes.dtype == np.float64 and len(nodes) == 3 * obj.rs_elastic.tet_node_count
    # Material, pins, mode count and reduced settings keep it, with no cache at all.
    obj.rs_elastic.youngs_modulus *= 2
    obj.rs_elastic.num_modes = 4
    obj.vertex_groups["Pin"].add(list(range(len(obj.data.vertices))[:3]), 1.0, 'REPLACE')
    obj.rs_elastic.cubature_tets = 50
    shutil.rmtree(bodies.cache_dirs()[0])
    bodies._MEMORY.clear()
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert stats["tetrahedralize"] == 1 and stats["modes"] == 2
    assert stored_tets(ext, obj)[0] == key
    np.testing.assert_array_equal(stored_tets(ext, obj)[1], nodes)
    # The mesher settings make a new one; undo brings the old one back.
    bpy.ops.ed.undo_push(message="before")
    obj.rs_elastic.edge_length = 0.1
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    bpy.ops.ed.undo_push(message="Prepare Body")
    assert stats["tetrahedralize"] == 2 and stored_tets(ext, obj)[0] != key
    bpy.ops.ed.undo()
    obj = bpy.data.objects["Bar"]
    assert stored_tets(ext, obj)[0] == key
    np.testing.assert_array_equal(stored_tets(ext, obj)[2], tets)
    # And the surface makes a new one.
    obj.data.vertices[0].co.x -= 0.1
    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert stats["tetrahedralize"] == 3 and stored_tets(ext, obj)[0] != key


def test_the_overlay_reads_the_pinned_nodes_without_recomputing(ext):
    obj = prepare_bar(ext)
    bodies = ext.bridge.bodies
    pinned = bodies.load_prepared(obj).linear_modes.pinned_nodes
    assert len(pinned) > 0
    np.testing.assert_array_equal(bodies.load_pinned_nodes(obj), pinned)
    bodies._MEMORY.clear()
    np.testing.assert_array_equal(bodies.load_pinned_nodes(obj), pinned)      # from the file
    assert bodies.stats["modes"] == 1
    nodes = bodies.load_tet_body(obj).nodes
    assert np.abs(nodes[pinned, 0]).max() < 0.5        # on the pinned end face, not beyond
