"""Rigged bodies end to end (issue 13): a keyed creature (tools/creature.py: body, belly, two ears,
three bones) simulates on its rig and bakes, on the command line too.

Oracles: the bake is a rest-space deviation the Armature modifier carries, so on the Follow Rig
vertices it is exactly zero (they are pinned) and the evaluated mesh there is the rig's own
pose; the free flesh lags the rig (the flicked ear's tip keeps moving forward after its bone
stops dead, then swings back); the user's actions, bones and keys are untouched
(``user_fingerprint``); and the whole motion keeps the creature's volume.
"""
import numpy as np
import pytest
import bpy

import creature
from blender_helpers import closed_volume, diagonal, evaluated_vertices, make_active, \
    user_fingerprint, vertices
from test_spacetime import run_cli


def prepared_creature(num_modes=12):
    obj, rig = creature.build(bpy, np)
    settings = obj.rs_elastic
    settings.pin_group = "Follow Rig"
    settings.edge_length, settings.num_modes = 0.06, num_modes
    settings.youngs_modulus, settings.density = 3.0e5, 1000.0       # soft flesh: it jiggles
    settings.damping_mass, settings.damping_stiffness = 0.0, 0.002
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 36
    make_active(obj)
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    return obj, rig


def poses(obj, frames):
    out = []
    for frame in frames:
        bpy.context.scene.frame_set(frame)
        out.append(evaluated_vertices(obj))
    return np.array(out)


def rig_only(obj, frames):
    """The evaluated mesh with the bake muted: the rig's own motion."""
    keys = obj.data.shape_keys
    saved = [] if keys is None else [(b, b.mute) for b in keys.key_blocks]
    for block, _ in saved[1:]:
        block.mute = True
    try:
        return poses(obj, frames)
    finally:
        for block, mute in saved:
            block.mute = mute


def test_a_rigged_creature_simulates_on_its_rig_and_keeps_the_users_animation(ext):
    obj, rig = prepared_creature()
    before = user_fingerprint()
    make_active(obj)
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    assert user_fingerprint() == before
    frames = list(range(1, 37))
    assert ext.bridge.bake.bake_frames(obj) == frames
    baked, rigged = poses(obj, frames), rig_only(obj, frames)
    rest = vertices(obj)
    follow = np.zeros(len(rest), dtype=bool)
    group = obj.vertex_groups["Follow Rig"].index
    follow[[v.index for v in obj.data.vertices for g in v.groups if g.group == group]] = True
    # Follow Rig vertices are exactly where the rig puts them.
    assert np.abs(baked[:, follow] - rigged[:, follow]).max() < 1e-5
    # The flicked ear's tip lags, overshoots once its bone stops (frame 10) and swings back.
    tip = (rest[:, 0] > 0.1) & (rest[:, 2] > creature.EAR_TOP - 1e-6)
    lag = (baked[:, tip] - rigged[:, tip]).mean(axis=1)                     # (F, 3)
    forward = lag[:, 1] if abs(lag[:, 1]).max() > abs(lag[:, 2]).max() else lag[:, 2]
    swing = np.abs(lag).max()
    print(f"ear tip deviation: largest {swing:.3f} m; belly {np.abs(baked - rigged).max():.3f} m")
    assert swing > 0.01
    settled = forward[10:] - forward[-8:].mean()        # about where gravity lets it hang
    assert np.any(np.diff(np.sign(settled)) != 0)       # it rings after the stop
    # Volume of the whole creature, rig plus flesh, stays that of the rest shape.
    volume = np.array([closed_volume(obj, p) for p in baked]) / closed_volume(obj, rigged[0])
    print(f"volume ratio {volume.min():.4f}-{volume.max():.4f}")
    assert np.abs(volume - 1.0).max() < 0.03


def test_a_rigged_body_needs_its_follow_group(ext):
    obj, rig = creature.build(bpy, np)
    obj.rs_elastic.edge_length, obj.rs_elastic.num_modes = 0.08, 4
    make_active(obj)
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}         # a free body prepares...
    with pytest.raises(RuntimeError, match="Follow Rig"):    # ...but cannot ride the rig
        bpy.ops.rs_elastic.simulate()
    assert ext.bridge.bake.bake_frames(obj) == []


def test_command_line_bakes_a_rigged_creature_from_a_saved_file(ext, tmp_path):
    obj, rig = prepared_creature()
    name = obj.name
    blend = tmp_path / "critter.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    result = run_cli(blend, ["bake", "--mode", "simulate", "--object", name])
    assert result.returncode == 0, result.stdout + result.stderr
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    obj = bpy.data.objects[name]
    assert ext.bridge.bake.bake_frames(obj) == list(range(1, 37))


def test_prepare_reads_the_rest_pose_whatever_frame_the_rig_is_on(ext):
    """Oracle: the tet mesh prepared at frame 7 (the creature mid-hop, 0.35 m up) is the one
    prepared at rest: same surface key, nodes within the rest mesh's bounds."""
    obj, rig = creature.build(bpy, np)
    obj.rs_elastic.edge_length, obj.rs_elastic.pin_group = 0.08, "Follow Rig"
    make_active(obj)
    bpy.context.scene.frame_set(7)
    assert evaluated_vertices(obj)[:, 2].min() > vertices(obj)[:, 2].min() + 0.3   # posed
    assert bpy.ops.rs_elastic.tetrahedralize() == {'FINISHED'}
    posed_key = obj.rs_elastic.tets_key
    bpy.context.scene.frame_set(1)
    inputs = ext.bridge.bodies.read_inputs(obj, bpy.context.evaluated_depsgraph_get())
    assert inputs.tets_key == posed_key
    assert abs(inputs.surface_vertices[:, 2].min() - vertices(obj)[:, 2].min()) < 1e-6
    assert obj.modifiers["Armature"].show_viewport                    # put back as it was


def world(obj, local):
    M = np.array(obj.matrix_world)
    return local @ M[:3, :3].T + M[:3, 3]


def test_a_space_time_edit_puts_an_ear_on_its_empty_while_the_body_follows_the_rig(ext):
    """The ear tip keyed 4 cm ahead of where the rig carries it on frame 20: the baked ear tip
    meets the Empty within 1e-3 of the diagonal, the Follow Rig part is exactly the rig's, and
    the free flesh away from that ear (the other ear, the belly) moves as in the same edit with
    the Empty keyed where the rig carries the tip (within 1 mm: the edit is local).
    A rig's handles are met by the method of multipliers (spacetime.solve exact_handles).
    The default 20 modes reach this target on every tet mesh tried (16 of 16); with 12 modes
    9 of 40 meshes could meet it only by throwing the body up to 1 m off its motion, which
    the solve now refuses (spacetime, "Out of reach")."""
    obj, rig = prepared_creature(num_modes=20)
    rest = vertices(obj)
    tip = (rest[:, 0] > 0.1) & (rest[:, 2] > creature.EAR_TOP - 0.1)
    obj.vertex_groups.new(name="Ear Tip").add([int(i) for i in np.flatnonzero(tip)], 1.0,
                                              'REPLACE')
    make_active(obj)
    assert bpy.ops.rs_elastic.add_handle(vertex_group="Ear Tip") == {'FINISHED'}
    empty = obj.rs_elastic.handles[0].empty
    bpy.context.scene.frame_set(20)
    carried = world(obj, evaluated_vertices(obj)[tip]).mean(axis=0)
    follow = np.zeros(len(rest), dtype=bool)
    group = obj.vertex_groups["Follow Rig"].index
    follow[[v.index for v in obj.data.vertices for g in v.groups if g.group == group]] = True
    far_flesh = ~follow & (rest[:, 0] < 0.1)        # the other ear and the belly
    frames = list(range(1, 37))
    obj.rs_elastic.iterations = 60      # the rig's loads make a stiffer problem (see README)
    baked = {}
    for offset in (0.0, 0.04):
        target = carried + (offset, 0.0, 0.0)
        empty.location = tuple(target)
        empty.keyframe_insert("location", frame=20)
        make_active(obj)
        assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
        converged, reason = ext.bridge.spacetime_inputs.LAST_STATUS[obj.name]
        print(reason)
        assert converged, reason
        baked[offset] = poses(obj, frames)
    rigged = rig_only(obj, frames)
    bpy.context.scene.frame_set(20)
    met = world(obj, evaluated_vertices(obj)[tip]).mean(axis=0)
    miss = np.linalg.norm(met - target) / diagonal(rest)
    moved = np.linalg.norm(baked[0.04][:, far_flesh] - baked[0.0][:, far_flesh], axis=2).max()
    print(f"ear tip miss {miss:.2e} of the diagonal; Follow Rig off the rig by "
          f"{np.abs(baked[0.04][:, follow] - rigged[:, follow]).max():.1e} m; the flesh away "
          f"from the ear moved {moved * 1e3:.2f} mm by the edit")
    assert miss < 1e-3
    assert np.abs(baked[0.04][:, follow] - rigged[:, follow]).max() < 1e-5
    assert moved < 1e-3


def test_follow_weights_below_the_pin_threshold_hold_the_flesh_partly(ext):
    """The belly painted in Follow Rig (springs to the rig, solver.rig.follow_stiffness) lags
    the rig less the higher its weight, and still moves (it is not pinned). Oracle: the lag
    falls monotonically with the spring, whose frequency grows as sqrt(w / (1 - w))."""
    obj, rig = prepared_creature()
    rest = vertices(obj)
    belly = rest[:, 1] < -0.25
    frames = list(range(1, 37))
    deviations = []
    for weight in (None, 0.2, 0.45):
        if weight is not None:
            obj.vertex_groups["Follow Rig"].add([int(i) for i in np.flatnonzero(belly)], weight,
                                                'REPLACE')
            make_active(obj)
            assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
        make_active(obj)
        assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
        baked, rigged = poses(obj, frames), rig_only(obj, frames)
        deviations.append(np.linalg.norm(baked[:, belly] - rigged[:, belly], axis=2).max())
    print("belly lag: free {:.4f} m, Follow Rig 0.2 {:.4f} m, 0.45 {:.4f} m".format(*deviations))
    free, light, firm = deviations
    assert 1e-4 < firm < light < free
    # 0.53 to 0.69 measured on five tet meshes (the Follow Rig region ends where its paint
    # does: pins no longer hold a tet beyond the painted faces, embed.pin_surface)
    assert firm < 0.8 * free


def test_follow_selected_bones_makes_the_follow_group_from_their_weights(ext):
    """Oracle: the creature's vertex groups. Selecting Body gives weight 1 on the body sphere
    and nothing on the ears; nothing selected, or an unrigged mesh, is refused unchanged."""
    obj, rig = creature.build(bpy, np)
    make_active(obj)
    ext.bridge.armature.select_bones(rig, [])
    with pytest.raises(RuntimeError, match="Select the bones"):
        bpy.ops.rs_elastic.follow_bones()
    assert obj.rs_elastic.pin_group == ""
    ext.bridge.armature.select_bones(rig, ["Body"])
    assert bpy.ops.rs_elastic.follow_bones() == {'FINISHED'}
    assert obj.rs_elastic.pin_group == "Follow Rig"
    weights = ext.bridge.scene.group_weights(obj, "Follow Rig")
    body = ext.bridge.scene.group_weights(obj, "Body")
    np.testing.assert_array_equal(weights, body)
    ears = ext.bridge.scene.group_weights(obj, "Ear.L") > 0
    assert weights.max() == 1.0 and weights[ears].max() == 0.0
    bpy.ops.mesh.primitive_cube_add()
    with pytest.raises(RuntimeError, match="no Armature modifier"):
        bpy.ops.rs_elastic.follow_bones()


def test_a_flicked_ear_stops_at_a_collider_in_its_way(ext):
    """Colliders act on rigged flesh: its contact samples are skinned to the world. A 0.3 m
    Collision cube waits 2.7 cm past where the rig stops the flicked ear's tip (frame 10; 2 mm
    past the ear's front), in the direction the ear swings (level: the creature is landing
    then, and the rig's own path goes down past the cube's face, never into it; checked).
    Oracles: the free flesh (collisions off, the control) overshoots into the cube or up to it,
    at least 5 mm further than with collisions on; with them no baked vertex enters it, and
    the Follow Rig part still moves exactly with the rig. (A rig that itself drives flesh deep into a collider can ask for more bending
    than the modes hold: README, limits.)"""
    obj, rig = prepared_creature()
    rest = vertices(obj)
    tip = (rest[:, 0] > 0.1) & (rest[:, 2] > creature.EAR_TOP - 1e-6)
    frames = list(range(1, 37))
    rigged = world(obj, rig_only(obj, frames))
    stop = rigged[9, tip].mean(axis=0)                              # frame 10
    swing = stop - rigged[8, tip].mean(axis=0)
    swing[2] = 0.0                                                  # the hop is vertical
    swing /= np.linalg.norm(swing)
    half = 0.15
    centre = stop + (0.027 + half) * swing
    bpy.ops.mesh.primitive_cube_add(size=2 * half, location=tuple(centre))
    cube = bpy.context.active_object
    cube.modifiers.new("Collision", 'COLLISION')
    cube.collision.thickness_outer = 0.01

    def depth(positions):
        """(F,) largest depth [m] of any of the world positions (F, n, 3) inside the cube."""
        return (half - np.abs(positions - centre).max(axis=2)).max(axis=1)

    def depth_in_cube():
        make_active(obj)
        assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
        return depth(world(obj, poses(obj, frames)))

    assert depth(rigged).max() < 0.0              # the rig alone keeps clear of the cube

    obj.rs_elastic.use_collisions = False
    free = depth_in_cube()
    obj.rs_elastic.use_collisions = True
    stopped = depth_in_cube()
    baked = world(obj, poses(obj, frames))
    follow = ext.bridge.scene.group_weights(obj, "Follow Rig") >= 0.5
    print(f"ear into the cube: {free.max():.3f} m free, {stopped.max():.4f} m with collisions")
    assert free.max() > stopped.max() + 0.005     # the control: the collider holds it back
    assert stopped.max() < 0.0
    assert np.abs(baked[:, follow] - rigged[:, follow]).max() < 1e-5
