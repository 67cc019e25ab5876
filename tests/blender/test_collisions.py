"""Collisions in the installed extension: objects with a Collision modifier push simulated bodies
out. Oracles: free fall until contact (t = sqrt(2 d / g)), the collider's surface and thickness as
a bound on every baked vertex, the same shot without the collider as the control."""
import numpy as np
import pytest
import bpy

from blender_helpers import fingerprint, make_active, make_bar, vertices
from test_simulate import baked_positions, prepared

THICKNESS = 0.02


def add_plane_collider(name, location, rotation=(0.0, 0.0, 0.0), size=8.0, damping=0.5,
                       friction=0.0):
    """A square plane with a Collision modifier; its normal is the side bodies stay on."""
    bpy.ops.mesh.primitive_plane_add(size=size, location=location, rotation=rotation)
    plane = bpy.context.active_object
    plane.name = name
    plane.modifiers.new("Collision", 'COLLISION')
    plane.collision.thickness_outer = THICKNESS
    plane.collision.damping = damping
    plane.collision.cloth_friction = friction
    return plane


def world(obj, local):
    """(F, n, 3) world positions of object-space positions (F, n, 3) (the object is still)."""
    M = np.array(obj.matrix_world)
    return local @ M[:3, :3].T + M[:3, 3]


def test_a_dropped_body_lands_on_time_and_never_sinks_through_the_floor(ext):
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 36
    floor = add_plane_collider("Floor", (0.0, 0.0, -0.02))
    floor.scale = (0.5, 0.7, 1.0)                       # a scaled collider: distances in metres
    bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=2, radius=0.3, location=(0.0, 0.0, 0.5))
    ball = bpy.context.active_object
    ball.name = "Ball"
    make_active(ball)
    ball.rs_elastic.youngs_modulus = 2e5
    ball.rs_elastic.damping_mass = 1.0
    prepared(ball, num_modes=6, edge_length=0.12)
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    positions = world(ball, baked_positions(ball, range(1, 37)))
    lowest = positions[:, :, 2].min(axis=1)
    # Free fall of the lowest point from 0.5 - 0.3 = 0.2 m above the plane (z = -0.02) until it
    # reaches the contact band: t = sqrt(2 d / g).
    gap = lowest[0] - floor.location.z
    h = 1.0 / scene.render.fps
    touch = np.flatnonzero(lowest - floor.location.z < THICKNESS)[0] * h
    expected = np.sqrt(2.0 * (gap - THICKNESS) / 9.81)
    assert abs(touch - expected) <= h
    assert lowest.min() > floor.location.z - THICKNESS            # never through the floor
    assert positions[-1, :, 2].mean() > floor.location.z + 0.2    # resting on it, not below


def test_a_keyed_prop_swung_into_a_wall_stops_at_it(ext):
    scene = bpy.context.scene
    scene.use_gravity = False
    scene.frame_start, scene.frame_end = 1, 40
    obj = prepared(make_bar(name="Prop", cuts=3))
    obj.rs_elastic.damping_mass = 1.0
    # Carried along +y between frames 1 and 12, then held: the free end swings on past y = 3.5.
    obj.keyframe_insert("location", frame=1)
    obj.location = (0.0, 3.0, 0.0)
    obj.keyframe_insert("location", frame=12)
    rest = vertices(obj)
    tip = rest[:, 0] > 4.0 - 1e-9

    def tip_reach():
        """The tip's largest world y once the prop is held (object at y = 3 from frame 12)."""
        assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
        local = baked_positions(obj, range(12, 41))
        return local[:, tip, 1].max() + 3.0

    wall_y = 3.0 + 1.0 + 0.05       # the bar's far side at rest is y = 4.0 once held
    free_reach = tip_reach()
    assert free_reach > wall_y + 0.05                             # the control passes the wall
    wall = add_plane_collider("Wall", (2.0, wall_y, 0.5), rotation=(np.pi / 2.0, 0.0, 0.0))
    assert np.allclose(np.array(wall.matrix_world)[:3, 2], (0.0, -1.0, 0.0), atol=1e-6)
    make_active(obj)
    stopped_reach = tip_reach()
    assert stopped_reach < wall_y + THICKNESS
    assert stopped_reach > wall_y - 0.2                           # it did reach the wall
    obj.rs_elastic.use_collisions = False                         # the switch turns it off
    assert tip_reach() == pytest.approx(free_reach, abs=1e-9)


def test_only_the_collider_collection_collides(ext):
    obj = make_bar(name="Body", cuts=1)
    inside = add_plane_collider("Listed", (0.0, 0.0, -2.0))
    outside = add_plane_collider("Other", (0.0, 0.0, -3.0))
    found = ext.bridge.colliders.collider_objects(obj, bpy.context.scene)
    assert [o.name for o in found] == ["Listed", "Other"]
    collection = bpy.data.collections.new("Colliders")
    bpy.context.scene.collection.children.link(collection)
    collection.objects.link(inside)
    obj.rs_elastic.collider_collection = collection
    assert [o.name for o in ext.bridge.colliders.collider_objects(obj, bpy.context.scene)] == \
        ["Listed"]
    outside.modifiers.clear()
    obj.rs_elastic.collider_collection = None
    assert [o.name for o in ext.bridge.colliders.collider_objects(obj, bpy.context.scene)] == \
        ["Listed"]


def test_a_body_starting_inside_a_collider_is_refused_and_nothing_changes(ext):
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 10
    obj = prepared(make_bar(name="Sunk", cuts=1), num_modes=3, edge_length=0.15)
    add_plane_collider("Ground", (0.0, 0.0, 0.5))                 # cuts the bar in half
    make_active(obj)
    before = fingerprint(obj)
    with pytest.raises(RuntimeError, match="Ground"):
        bpy.ops.rs_elastic.simulate()
    assert fingerprint(obj) == before


def test_keyed_collider_motion_is_interpolated_between_frames(ext):
    """AffineMotion against the keyed matrices themselves, and a scale kept between keys."""
    plane = add_plane_collider("Lift", (0.0, 0.0, 0.0))
    plane.keyframe_insert("location", frame=1)
    plane.keyframe_insert("scale", frame=1)
    plane.location = (0.0, 0.0, 1.0)
    plane.scale = (2.0, 2.0, 2.0)
    plane.keyframe_insert("location", frame=11)
    plane.keyframe_insert("scale", frame=11)
    colliders = ext.bridge.colliders
    frames = list(range(1, 12))
    matrices = colliders._sampled_matrices([plane], bpy.context.scene, frames)[0]
    motion = colliders.AffineMotion(np.arange(11) / 24.0, matrices)
    for f in range(11):
        assert np.allclose(motion(f / 24.0), matrices[f], atol=1e-9)
    half = motion(0.5 / 24.0)                                      # between frames 1 and 2
    assert np.allclose(half, 0.5 * (matrices[0] + matrices[1]), atol=1e-9)
