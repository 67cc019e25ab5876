"""A long shot baked to a Mesh Cache in Blender (issue 14): a pinned 4:1:1 bar whose surface has
about 50,000 vertices, simulated for FRAMES frames and baked to a .pc2, with the extension
installed from its zip. Prints one JSON line. Run by run_bench.py in its own process.

    python bench/mesh_cache_shot.py ZIP FRAMES CUTS

Reported: Prepare and Simulate-and-Bake seconds, how much the saved .blend grew, the .pc2's
size, and the largest difference between what the Mesh Cache modifier plays and the solver's
poses in the file, at five frames, as a fraction of the diagonal.
"""
import json
import os
import pathlib
import shutil
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

import blender_session  # noqa: E402


def bar(bpy, np, cuts):
    bpy.ops.mesh.primitive_cube_add(size=1.0)
    obj = bpy.context.active_object
    obj.name = "Long Shot Bar"
    bpy.ops.object.mode_set(mode='EDIT')
    bpy.ops.mesh.subdivide(number_cuts=cuts)
    bpy.ops.object.mode_set(mode='OBJECT')
    co = np.empty(len(obj.data.vertices) * 3)
    obj.data.vertices.foreach_get("co", co)
    co = (co.reshape(-1, 3) + (0.5, 0.5, 0.5)) * (4.0, 1.0, 1.0)
    obj.data.vertices.foreach_set("co", co.ravel())
    obj.data.update()
    obj.vertex_groups.new(name="Pin").add([int(i) for i in np.flatnonzero(co[:, 0] < 1e-6)],
                                          1.0, 'REPLACE')
    obj.rs_elastic.pin_group = "Pin"
    return obj


def main(zip_path, frames=1000, cuts=90):
    ext = blender_session.start(zip_path)
    import bpy
    import numpy as np
    folder = pathlib.Path(tempfile.mkdtemp(prefix="rs_bench_cache_"))
    bpy.ops.wm.read_homefile(use_empty=True)
    obj = bar(bpy, np, cuts)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, frames
    blend = folder / "long_shot.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    obj = bpy.data.objects["Long Shot Bar"]
    bpy.context.view_layer.objects.active = obj
    settings = obj.rs_elastic
    settings.edge_length, settings.num_modes = 0.1, 10
    settings.youngs_modulus, settings.damping_mass = 5e5, 0.2
    start = time.perf_counter()
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    prepare_seconds = time.perf_counter() - start
    bpy.ops.wm.save_mainfile()
    before = os.path.getsize(blend)
    settings.bake_to = 'CACHE'
    start = time.perf_counter()
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    bake_seconds = time.perf_counter() - start
    bpy.ops.wm.save_mainfile()
    grown = os.path.getsize(blend) - before
    path = bpy.path.abspath(settings.cache_bake_file)
    samples, _ = ext.bridge.mesh_cache.read_pc2(path)
    rest = ext.bridge.scene.base_vertices(obj)
    diagonal = float(np.linalg.norm(rest.max(axis=0) - rest.min(axis=0)))
    worst = 0.0
    for frame in np.linspace(1, frames, 5).astype(int):
        scene.frame_set(int(frame))
        mesh = obj.evaluated_get(bpy.context.evaluated_depsgraph_get()).data
        played = np.empty(len(mesh.vertices) * 3)
        mesh.vertices.foreach_get("co", played)
        worst = max(worst, float(np.abs(played.reshape(-1, 3) - samples[frame - 1]).max()))
    print(json.dumps(dict(vertices=len(obj.data.vertices), frames=frames,
                          tets=settings.tet_count, prepare_seconds=prepare_seconds,
                          simulate_and_bake_seconds=bake_seconds, blend_growth_bytes=grown,
                          pc2_bytes=os.path.getsize(path),
                          shape_key_bytes=ext.bridge.mesh_cache.shape_key_bytes(
                              frames, len(obj.data.vertices)),
                          playback_error=worst / diagonal)))
    shutil.rmtree(folder, ignore_errors=True)                 # the .pc2 is 12 bytes per point
    shutil.rmtree(os.environ["BLENDER_USER_RESOURCES"], ignore_errors=True)
    blender_session.exit_child(0)


if __name__ == "__main__":
    main(sys.argv[1], *(int(a) for a in sys.argv[2:]))
