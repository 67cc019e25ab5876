"""The shot the farm tests and the farm bench bake: three small bodies, two of which read the
third's bake.

- Slab: a pinned 4 x 1 x 1 m bar that sags and swings under gravity (simulation); it has a
  Collision modifier, so it is also a collider.
- Drop: a free 0.5 m jelly cube above Slab's tip that falls onto it (simulation with collisions).
  Colliders are read at the current frame, saved as the frame of Slab's lowest swing: Drop
  lands on Slab as Slab's bake has it then, so Drop needs Slab's bake.
- Whip: a pinned 2 m bar beside Slab whose tip handle's Empty (Follow Every Frame) is
  vertex-parented to Slab's tip: its space-time edit follows Slab's baked swing.

Each body is tetrahedralized before the file is saved, so its tet mesh travels with the .blend
and every machine prepares the same modes from it. Call `build` in a Blender session with the
extension installed (tools/blender_session.py).
"""
import numpy as np

BODIES = ("Slab", "Drop", "Whip")
FRAMES = 12
LOWEST = 6         # the frame of Slab's lowest swing: the current frame of the saved shot


def _box(bpy, name, size, corner, cuts=1):
    """A box mesh of `size` (x, y, z) [m] from `corner`, its faces subdivided by `cuts`."""
    bpy.ops.mesh.primitive_cube_add(size=1.0)
    obj = bpy.context.active_object
    obj.name = obj.data.name = name
    bpy.ops.object.mode_set(mode='EDIT')
    bpy.ops.mesh.subdivide(number_cuts=cuts)
    bpy.ops.object.mode_set(mode='OBJECT')
    co = np.empty(len(obj.data.vertices) * 3)
    obj.data.vertices.foreach_get("co", co)
    co = (co.reshape(-1, 3) + 0.5) * size + corner
    obj.data.vertices.foreach_set("co", co.ravel())
    obj.data.update()
    settings = obj.rs_elastic
    settings.edge_length, settings.num_modes = 0.12, 4
    settings.basis_size, settings.cubature_tets, settings.training_poses = 30, 60, 24
    return obj, co


def _pin(obj, mask, name="Pin"):
    obj.vertex_groups.new(name=name).add([int(i) for i in np.flatnonzero(mask)], 1.0, 'REPLACE')
    obj.rs_elastic.pin_group = name


def _select(bpy, obj):
    for other in bpy.context.view_layer.objects:
        other.select_set(False)
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)


def _tetrahedralize(bpy, obj):
    _select(bpy, obj)
    if bpy.ops.rs_elastic.tetrahedralize() != {'FINISHED'}:
        raise RuntimeError(f"could not tetrahedralize {obj.name}")


def build(bpy, frames=FRAMES):
    """Build the shot in an empty file; returns {name: object}. The caller saves it."""
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, frames

    slab, co = _box(bpy, "Slab", (4.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    _pin(slab, co[:, 0] < 1e-9)
    slab.rs_elastic.youngs_modulus, slab.rs_elastic.density = 2e7, 1000.0
    slab.modifiers.new("Collision", 'COLLISION')

    drop, _ = _box(bpy, "Drop", (0.5, 0.5, 0.5), (3.2, 0.25, 1.03))
    drop.rs_elastic.youngs_modulus, drop.rs_elastic.density = 2e5, 1000.0
    drop.rs_elastic.contact_samples = 64
    drop.rs_elastic.edge_length = 0.2

    whip, co = _box(bpy, "Whip", (2.0, 0.4, 0.4), (0.0, 2.0, 0.3))
    _pin(whip, co[:, 0] < 1e-9)
    whip.rs_elastic.youngs_modulus = 1e6
    tip = co[:, 0] > 2.0 - 1e-9
    whip.vertex_groups.new(name="Tip").add([int(i) for i in np.flatnonzero(tip)], 1.0, 'REPLACE')
    _select(bpy, whip)
    if bpy.ops.rs_elastic.add_handle(vertex_group="Tip") != {'FINISHED'}:
        raise RuntimeError("could not add Whip's handle")
    handle = whip.rs_elastic.handles[0]
    handle.follow = True
    # The Empty rides Slab's top corner at its tip, starting where Whip's tip is.
    slab_rest = np.array([v.co for v in slab.data.vertices])
    corner = int(np.argmax(slab_rest @ np.array([1.0, 0.0, 1.0]) - 1e-3 * slab_rest[:, 1]))
    empty = handle.empty
    empty.parent, empty.parent_type = slab, 'VERTEX'
    empty.parent_vertices[0] = corner
    empty.matrix_parent_inverse.identity()
    empty.location = tuple(co[tip].mean(axis=0) - slab_rest[corner])

    for obj in (slab, drop, whip):
        _tetrahedralize(bpy, obj)
    scene.frame_set(LOWEST)      # colliders are read at the current frame: Slab's lowest swing
    return {obj.name: obj for obj in (slab, drop, whip)}


def add_broken_body(bpy, name="Wreck"):
    """A tetrahedralized body whose pin group was deleted afterwards: its farm task fails in
    Prepare with one line naming it."""
    obj, co = _box(bpy, name, (1.0, 0.3, 0.3), (0.0, -2.0, 0.0))
    _pin(obj, co[:, 0] < 1e-9)
    _tetrahedralize(bpy, obj)
    obj.vertex_groups.remove(obj.vertex_groups["Pin"])
    return obj
