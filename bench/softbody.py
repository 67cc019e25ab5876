"""Blender's built-in Soft Body on a pinned 4:1:1 bar: the per-frame time a user would otherwise
pay. Prints one JSON line. Run by run_bench.py in its own process (it imports bpy).

    python bench/softbody.py FRAMES CUTS
"""
import json
import os
import sys
import tempfile
import time


def main(frames=100, cuts=12, stiff=0):
    """stiff=1: no air friction and the stiffest springs (pull, push 0.999), so the bar rings
    rather than hanging like a rope, for the energy comparison; else Soft Body's defaults."""
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="rs_bench_user_"))
    import bpy
    import numpy as np
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.mesh.primitive_cube_add(size=1.0)
    bar = bpy.context.active_object
    bpy.ops.object.mode_set(mode='EDIT')
    bpy.ops.mesh.subdivide(number_cuts=cuts)
    bpy.ops.object.mode_set(mode='OBJECT')
    co = np.empty(len(bar.data.vertices) * 3)
    bar.data.vertices.foreach_get("co", co)
    co = (co.reshape(-1, 3) + (0.5, 0.0, 0.0)) * (4.0, 1.0, 1.0)
    bar.data.vertices.foreach_set("co", co.ravel())
    pin = bar.vertex_groups.new(name="Pin")
    pin.add([int(i) for i in np.flatnonzero(co[:, 0] < 1e-6)], 1.0, 'REPLACE')
    modifier = bar.modifiers.new("Softbody", 'SOFT_BODY')
    settings = modifier.settings
    settings.use_goal = True
    settings.vertex_group_goal = "Pin"
    settings.goal_default = 1.0
    settings.goal_min = 0.0
    settings.use_edges = True
    settings.use_stiff_quads = True
    if stiff:
        settings.friction = 0.0        # no air friction: the damping left is the solver's own
        settings.pull = settings.push = 0.999
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, frames
    modifier.point_cache.frame_end = frames
    start = time.perf_counter()
    for frame in range(1, frames + 1):
        scene.frame_set(frame)
    seconds = time.perf_counter() - start
    depsgraph = bpy.context.evaluated_depsgraph_get()
    moved = np.empty(len(bar.data.vertices) * 3)
    bar.evaluated_get(depsgraph).data.vertices.foreach_get("co", moved)
    sag = float(co[:, 2].min() - moved.reshape(-1, 3)[:, 2].min())
    tip = int(np.argmax(co[:, 0] + 1e-3 * co[:, 2]))
    tip_z = []
    for frame in range(1, frames + 1):         # replayed from the point cache just filled
        scene.frame_set(frame)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        tip_z.append(bar.evaluated_get(depsgraph).data.vertices[tip].co.z)
    print(json.dumps(dict(vertices=len(bar.data.vertices), frames=frames, seconds=seconds,
                          ms_per_frame=1000.0 * seconds / frames, tip_sag_m=sag,
                          tip_z=tip_z)))


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:4]))
