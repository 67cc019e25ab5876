"""Numbers and inputs (issue 26, item 5): whatever number the scene holds, an operator either
refuses it in one line (and changes nothing) or gives it a documented meaning that works.

- Non-finite input (a NaN key, a NaN vertex, weight or frame rate, a collider gone wrong) is
  refused, naming what and where.
- Zero weights: a handle or take at weight 0 is ignored; a pin group whose weights all stay
  below the pin threshold pins nothing and is refused.
- The smallest frame range, 3 frames, solves as well as it simulates.
- Mirroring transforms (negative determinant) simulate and solve as exactly the mirror image:
  each is checked against its twin in a mirrored world (the same prepared body, so the same
  tets, with the world reflected instead of the object), which physics says must move alike in
  the body's own space.
"""
import math

import bpy
import numpy as np
import pytest

from blender_helpers import (add_tip_handle, diagonal, evaluated_vertices, link_mesh, make_active,
                             vertices)
from test_faults import prepared_bar, refusal, small_bar

NAN = float("nan")


def baked_poses(obj, frames):
    """(F, n, 3) object-space positions the bake plays on each frame."""
    poses = []
    for frame in frames:
        bpy.context.scene.frame_set(frame)
        poses.append(evaluated_vertices(obj))
    return np.array(poses)


def tip_centroid(obj, pose):
    return pose[vertices(obj)[:, 0] > 4.0 - 1e-9].mean(axis=0)


# --- non-finite numbers are refused, naming what and where ----------------------------------------

def test_a_handle_key_that_is_not_a_number_is_refused_naming_the_handle_and_the_frame():
    obj = prepared_bar(frames=(1, 10))
    empty, _ = add_tip_handle(obj, {4: (4.0, 0.5, 1.0), 8: (NAN, 0.5, 0.5)})
    bpy.context.scene.frame_set(1)
    assert refusal(bpy.ops.rs_elastic.solve_spacetime) == (
        f"The transform of handle '{empty.name}' on frame 8 is not a finite number: check the "
        "keys, drivers and parents that move it")


def key_frame_three(id_block, path, value, rest):
    """Key `path` to `value` on frame 3 alone and to `rest` on frames 1 and 4, with constant
    interpolation, so that frame 3 is the only frame that holds `value`."""
    for frame, v in ((1, rest), (3, value), (4, rest)):
        setattr(id_block, path, v)
        id_block.keyframe_insert(path, frame=frame)
    for curve in animation().fcurves(id_block):
        for point in curve.keyframe_points:
            point.interpolation = 'CONSTANT'
    bpy.context.scene.frame_set(1)


def animation():
    import importlib
    return importlib.import_module("bl_ext.user_default.rs_elastic.bridge.animation")


def nan_body_key(obj):
    key_frame_three(obj, "location", (NAN, 0.0, 0.0), (0.0, 0.0, 0.0))


def zero_scale_key(obj):
    key_frame_three(obj, "scale", (1.0, 0.0, 1.0), (1.0, 1.0, 1.0))


def nan_frame_rate(obj):
    bpy.context.scene.render.fps_base = NAN


def nan_pose_key(obj):
    obj.shape_key_add(name="Basis")
    droop = obj.shape_key_add(name="Droop", from_mix=False)
    co = vertices(obj)
    co[0, 2] = NAN
    droop.data.foreach_set("co", co.astype(np.float32).ravel())
    droop.value = 1.0
    droop.keyframe_insert("value", frame=3)


def wall(location=(6.0, 0.0, 0.0)):
    """A Collision plane facing -x, off the bar's tip."""
    bpy.ops.mesh.primitive_plane_add(size=4.0, location=location, rotation=(0.0, -math.pi / 2, 0))
    plane = bpy.context.active_object
    plane.name = "Wall"
    plane.modifiers.new("Collision", 'COLLISION')
    return plane


def nan_collider_key(obj):
    key_frame_three(wall(), "location", (NAN, 0.0, 0.0), (6.0, 0.0, 0.0))
    make_active(obj)


def nan_collider_thickness(obj):
    wall().collision.thickness_outer = NAN
    make_active(obj)


def nan_collider_vertex(obj):
    plane = wall()
    plane.data.vertices[0].co = (NAN, 0.0, 0.0)
    make_active(obj)


TRANSFORM = ("The transform of {what} on frame 3 is not a finite number: check the keys, drivers "
             "and parents that move it")
INPUTS = [
    ("body transform nan", nan_body_key, "simulate", TRANSFORM.format(what="'Bar'")),
    ("body transform nan", nan_body_key, "solve_spacetime", TRANSFORM.format(what="'Bar'")),
    ("body scaled to zero", zero_scale_key, "simulate",
     "'Bar' is scaled to zero on frame 3, so its transform has no inverse: give it a scale "
     "on every axis"),
    ("body scaled to zero", zero_scale_key, "solve_spacetime",
     "'Bar' is scaled to zero on frame 3, so its transform has no inverse: give it a scale "
     "on every axis"),
    ("frame rate nan", nan_frame_rate, "simulate",
     "The scene's frame rate (24 / nan frames per second) is not a finite, positive number"),
    ("frame rate nan", nan_frame_rate, "solve_spacetime",
     "The scene's frame rate (24 / nan frames per second) is not a finite, positive number"),
    ("pose key nan", nan_pose_key, "solve_spacetime",
     "Shape key 'Droop' of 'Bar' holds positions that are not finite numbers: fix or delete it"),
    ("collider transform nan", nan_collider_key, "simulate",
     TRANSFORM.format(what="collider 'Wall'")),
    ("collider thickness nan", nan_collider_thickness, "simulate",
     "Collider 'Wall': its Outer Thickness is nan; it must be a finite number"),
    ("collider vertex nan", nan_collider_vertex, "simulate",
     "Collider 'Wall': its mesh has positions that are not finite numbers"),
]


@pytest.mark.parametrize("setup, operator, message",
                         [pytest.param(*row[1:], id=f"{row[0]}-{row[2]}") for row in INPUTS])
def test_non_finite_input_is_refused_in_one_line(setup, operator, message):
    obj = prepared_bar(frames=(1, 6))
    add_tip_handle(obj, {3: (4.0, 0.5, 1.0)})
    setup(obj)
    assert refusal(getattr(bpy.ops.rs_elastic, operator)) == message


def test_an_interpolation_to_a_shape_key_that_is_not_a_number_is_refused():
    obj = prepared_bar()
    nan_pose_key(obj)
    assert refusal(lambda: bpy.ops.rs_elastic.interpolate_shape_keys(
        key_from="Basis", key_to="Droop", output='KEYS', count=3)) == (
        "Shape key 'Droop' of 'Bar' holds positions that are not finite numbers: fix or delete it")


def nan_vertex(obj):
    obj.data.vertices[3].co = (NAN, 0.0, 0.0)


def nan_pin_weight(obj):
    obj.vertex_groups["Pin"].add([0], NAN, 'REPLACE')


@pytest.mark.parametrize("setup, message", [
    pytest.param(nan_vertex, "'Bar': the surface has non-finite vertex coordinates",
                 id="vertex nan"),
    pytest.param(nan_pin_weight, "Pin group 'Pin' has a weight that is not a number (vertex 0): "
                                 "paint it again", id="pin weight nan"),
])
def test_non_finite_mesh_data_is_refused_by_prepare(setup, message):
    setup(small_bar())
    assert refusal(bpy.ops.rs_elastic.prepare) == message


# --- zero weights ---------------------------------------------------------------------------------

def test_the_only_handle_at_weight_zero_leaves_nothing_to_solve_for():
    obj = prepared_bar(frames=(1, 10))
    empty, _ = add_tip_handle(obj, {8: (4.0, 0.5, 1.5)})
    obj.rs_elastic.handles[0].weight = 0.0
    assert refusal(bpy.ops.rs_elastic.solve_spacetime) == (
        "Nothing to solve for on 'Bar': key a handle's Empty, key a shape key to 1 on a frame, "
        f"or edit a take (Handle '{empty.name}': its weight is 0, so it is ignored)")


def test_a_handle_at_weight_zero_is_ignored_as_if_it_were_not_there():
    obj = prepared_bar(frames=(1, 10))
    add_tip_handle(obj, {8: (4.0, 0.5, 1.5)})
    middle = vertices(obj)[:, 0] == 2.0
    obj.vertex_groups.new(name="Middle").add([int(i) for i in np.flatnonzero(middle)], 1.0,
                                             'REPLACE')
    assert bpy.ops.rs_elastic.add_handle(vertex_group="Middle") == {'FINISHED'}
    obj.rs_elastic.handles[1].empty.location = (2.0, 2.0, 0.5)
    obj.rs_elastic.handles[1].empty.keyframe_insert("location", frame=5)
    obj.rs_elastic.handles[1].weight = 0.0
    make_active(obj)
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    with_zero = baked_poses(obj, range(1, 11))
    assert obj.rs_elastic.handles[1].residual == -1.0          # not solved for
    obj.rs_elastic.handles.remove(1)
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    np.testing.assert_array_equal(with_zero, baked_poses(obj, range(1, 11)))
    assert with_zero[-3, :, 2].max() > 1.2                     # the tip handle was met


def test_a_handle_on_pinned_vertices_alone_leaves_nothing_to_solve_for():
    """Nothing can move it (its constraint rows are zero): it divided by zero."""
    obj = prepared_bar(frames=(1, 10))
    pinned = vertices(obj)[:, 0] < 1e-9
    obj.vertex_groups.new(name="End").add([int(i) for i in np.flatnonzero(pinned)], 1.0,
                                          'REPLACE')
    assert bpy.ops.rs_elastic.add_handle(vertex_group="End") == {'FINISHED'}
    empty = obj.rs_elastic.handles[0].empty
    empty.location = (0.0, 0.5, 1.5)
    empty.keyframe_insert("location", frame=8)
    make_active(obj)
    assert refusal(bpy.ops.rs_elastic.solve_spacetime) == (
        "Nothing to solve for on 'Bar': key a handle's Empty, key a shape key to 1 on a frame, "
        f"or edit a take (Handle '{empty.name}': all its vertices are pinned, so nothing can "
        "move it; ignored)")


def test_a_take_at_weight_zero_is_not_followed():
    obj = prepared_bar(frames=(1, 10))
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    assert bpy.ops.rs_elastic.keep_take() == {'FINISHED'}
    obj.rs_elastic.use_take, obj.rs_elastic.take_weight = True, 0.0
    assert refusal(bpy.ops.rs_elastic.solve_spacetime) == (
        "Nothing to solve for on 'Bar': key a handle's Empty, key a shape key to 1 on a frame, "
        "or edit a take (Take Weight is 0, so the take is not followed)")


def test_a_pin_group_that_pins_nothing_is_refused_with_the_threshold():
    obj = small_bar()
    pinned = [i for i, v in enumerate(obj.data.vertices) if v.co.x < 1e-9]
    obj.vertex_groups["Pin"].add(pinned, 0.3, 'REPLACE')
    assert refusal(bpy.ops.rs_elastic.prepare) == (
        "Pin group 'Pin' pins nothing: only vertices weighted 0.5 or more are pinned, and its "
        "largest weight is 0.3; paint the pinned part 0.5 or more, or clear Pin Group for a "
        "free body")


# --- the smallest frame range ---------------------------------------------------------------------

def test_three_frames_solve_as_they_simulate():
    """Frames 1 and 2 are the start at rest; frame 3 is free and meets the handle."""
    obj = prepared_bar(frames=(1, 3))
    target = np.array([4.0, 0.5, 0.9])
    add_tip_handle(obj, {3: tuple(target)})
    make_active(obj)
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    poses = baked_poses(obj, (1, 2, 3))
    rest = vertices(obj)
    assert np.abs(poses[:2] - rest).max() < 1e-6
    miss = np.linalg.norm(tip_centroid(obj, poses[2]) - target)
    print(f"3-frame solve: tip misses its target by {miss:.2e} m of a 0.4 m edit")
    assert miss < 0.01 * 0.4
    assert 0.0 <= obj.rs_elastic.handles[0].residual < 0.01 * 0.4
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}


# --- mirroring and scaled transforms --------------------------------------------------------------

MIRROR = np.diag([1.0, 1.0, -1.0])


def test_a_still_mirrored_body_sags_as_its_twin_under_mirrored_gravity():
    """A bar mirrored by scale z = -1 under gravity -z is, in its own space, its unmirrored twin
    under gravity +z; in the world it sags down, as any bar does."""
    scene = bpy.context.scene
    obj = prepared_bar(frames=(1, 12))
    obj.scale = (1.0, 1.0, -1.0)
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    mirrored = baked_poses(obj, range(1, 13))
    obj.scale = (1.0, 1.0, 1.0)
    scene.gravity = MIRROR @ np.array(scene.gravity)
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    twin = baked_poses(obj, range(1, 13))
    rest = vertices(obj)
    sag = (MIRROR @ (tip_centroid(obj, mirrored[-1]) - tip_centroid(obj, rest)))[2]
    print(f"mirrored bar: tip sags {sag:.3f} m in the world; twin differs by "
          f"{np.abs(mirrored - twin).max():.1e} m")
    assert sag < -0.01 * diagonal(rest)
    assert np.abs(mirrored - twin).max() <= 1e-6 * diagonal(rest)


def test_a_still_mirrored_body_lands_on_a_floor_as_its_twin_on_the_mirrored_ceiling():
    """The mirrored bar (z = -1) falls on a Collision plane below its tip; its twin falls, under
    reflected gravity, on the reflected plane (a ceiling facing down). Their colliders reach the
    simulation through a mirroring transform, so the free side of each must stay where it was."""
    scene = bpy.context.scene
    obj = prepared_bar(frames=(1, 16))

    def floor(z, facing):
        """A Collision quad x in [0, 6], y in [-2.5, 3.5] at height z, facing +z or -z."""
        corners = [(0.0, -2.5, z), (6.0, -2.5, z), (6.0, 3.5, z), (0.0, 3.5, z)]
        plane = link_mesh("Floor", corners, [(0, 1, 2, 3) if facing > 0 else (3, 2, 1, 0)])
        plane.modifiers.new("Collision", 'COLLISION')
        make_active(obj)
        return plane

    obj.scale = (1.0, 1.0, -1.0)
    plane = floor(-1.4, facing=+1)
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    mirrored = baked_poses(obj, range(1, 17))
    bpy.data.objects.remove(plane)
    bpy.context.view_layer.update()
    obj.scale = (1.0, 1.0, 1.0)
    scene.gravity = MIRROR @ np.array(scene.gravity)
    floor(1.4, facing=-1)
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    twin = baked_poses(obj, range(1, 17))
    rest = vertices(obj)
    lowest = (mirrored @ MIRROR)[:, :, 2].min()              # world z of the mirrored bar
    print(f"mirrored bar on a floor at z = -1.4: lowest point {lowest:.3f} m; twin differs by "
          f"{np.abs(mirrored - twin).max():.1e} m")
    assert -1.45 < lowest < -1.3                          # it reached the floor, and stopped there
    assert np.abs(mirrored - twin).max() <= 1e-4 * diagonal(rest)


def key_motion(obj, angles, locations):
    """Key rotation about y (radians) and location on frames 1, 5 and 10."""
    for frame, angle, location in zip((1, 5, 10), angles, locations):
        obj.rotation_euler = (0.0, angle, 0.0)
        obj.location = location
        obj.keyframe_insert("rotation_euler", frame=frame)
        obj.keyframe_insert("location", frame=frame)


@pytest.mark.parametrize("scale, twin_angle", [
    pytest.param((1.0, 1.0, -1.0), lambda a: -a, id="mirrored in z"),
    pytest.param((1.0, 2.0, -1.0), lambda a: -a, id="mirrored and stretched"),
    pytest.param((-1.0, 1.0, 1.0), lambda a: math.pi - a, id="mirrored in x"),
])
def test_a_body_on_a_mirroring_animated_parent_moves_as_its_twin_in_a_mirrored_world(scale,
                                                                                     twin_angle):
    """The bar rides a keyed parent that mirrors it. Reflecting the whole world by W = diag(1, 1,
    -1) makes its transform W Ry(a) S proper, with S the constant mirror and stretch: the twin
    is the same bar on that motion (rotation `twin_angle(a)` about y, locations reflected),
    under reflected gravity. In its own space the body must move exactly alike."""
    scene = bpy.context.scene
    obj = prepared_bar(frames=(1, 16))
    obj.rs_elastic.damping_mass = 0.5
    angles = (0.0, 0.6, -0.2)
    locations = ((0.0, 0.0, 0.0), (1.0, 0.5, 2.0), (0.5, -1.0, 3.0))
    bpy.ops.object.empty_add()
    parent = bpy.context.active_object
    parent.scale = scale
    key_motion(parent, angles, locations)
    obj.parent = parent
    make_active(obj)
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    mirrored = baked_poses(obj, range(1, 17))

    obj.parent = None
    bpy.data.objects.remove(parent)
    bpy.context.view_layer.update()
    key_motion(obj, [twin_angle(a) for a in angles], [MIRROR @ np.array(l) for l in locations])
    scene.gravity = MIRROR @ np.array(scene.gravity)
    make_active(obj)
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    twin = baked_poses(obj, range(1, 17))
    rest = vertices(obj)
    swing = np.abs(twin - rest).max()
    print(f"parent scale {scale}: the twin swings {swing:.3f} m, the mirrored body differs by "
          f"{np.abs(mirrored - twin).max():.1e} m")
    assert swing > 0.02 * diagonal(rest)                        # the keyed motion swings it
    # The two differ by round-off, which the step's float32 products make visible through
    # where each run's Newton stops (within its tolerance, 1.2e-4 of the swing measured over
    # this keyed swing); a mirror handled wrongly is off by a part of the swing itself.
    assert np.abs(mirrored - twin).max() <= 1e-3 * swing


@pytest.mark.parametrize("orientation", [False, True], ids=["position", "orientation"])
def test_a_mirrored_body_solves_as_its_twin_with_mirrored_targets(orientation):
    """A handle keyed at world targets T on a bar mirrored by z = -1 asks, in the bar's own
    space, what targets W T ask of the unmirrored bar (and an Empty turned by Ry(a), what one
    turned by W Ry(a) W = Ry(-a) asks)."""
    obj = prepared_bar(frames=(1, 10))
    keys = {4: np.array([3.8, 0.5, -1.0]), 9: np.array([3.5, 1.5, -0.2])}
    turns = {4: 0.4, 9: -0.3}

    def solve(scale, targets, angle):
        obj.scale = scale
        obj.rs_elastic.handles.clear()
        empty, _ = add_tip_handle(obj, {f: tuple(t) for f, t in targets.items()})
        obj.rs_elastic.handles[0].orientation = orientation
        for frame, turn in turns.items():
            empty.rotation_euler = (0.0, angle(turn), 0.0)
            empty.keyframe_insert("rotation_euler", frame=frame)
        make_active(obj)
        assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
        return baked_poses(obj, range(1, 11)), obj.rs_elastic.handles[0].residual

    mirrored, mirrored_miss = solve((1.0, 1.0, -1.0), keys, lambda a: a)
    obj.vertex_groups.remove(obj.vertex_groups["Tip"])
    twin, twin_miss = solve((1.0, 1.0, 1.0), {f: MIRROR @ t for f, t in keys.items()},
                            lambda a: -a)
    rest = vertices(obj)
    print(f"mirrored solve: residual {mirrored_miss:.2e} m (twin {twin_miss:.2e} m), poses "
          f"differ by {np.abs(mirrored - twin).max():.1e} m")
    assert np.abs(twin - rest).max() > 0.1
    assert np.abs(mirrored - twin).max() <= 1e-5 * diagonal(rest)
    assert mirrored_miss >= 0.0 and mirrored_miss == pytest.approx(twin_miss, rel=1e-3, abs=1e-9)
