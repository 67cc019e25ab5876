"""Big space-time edits of a character (issue 12 item 2): does the tool tell bending from stretch?

The shared cow (cow.off: 1 m long along x, y up), standing on pinned hooves, E = 1e7 Pa, 20
modes and the automatic (O(m^2)) basis, with two handles: the head and the tail ends.
Oracles: a *reachable* edit takes its targets from a full-RS pose of the body (the RS mode
preview, which bends without stretching), so a solve meeting them has no reason to change the
volume: the baked surface keeps its closed volume within 3 % on every frame, and nothing is
reported as a stretch. A *stretching* edit pulls the head handle straight away from the body to
1.2 times its distance from the hooves' centre: no bending meets that, and the solve reports the
head handle's stretch (a lower bound of the 20 % pull, measured along zigzag tet-edge paths:
7 to 13 % on the meshes seen, above the 5 % at which it is reported) and not the tail's, which
is keyed where it rests.
"""
import re

import numpy as np
import bpy

from blender_helpers import closed_volume, evaluated_vertices, import_shared, make_active, \
    preview_pose, vertices


def prepared_cow():
    obj = import_shared("cow.off")
    settings = obj.rs_elastic
    settings.basis_size, settings.cubature_tets, settings.training_poses = 0, 150, 80
    settings.youngs_modulus, settings.num_modes = 1.0e7, 20
    rest = vertices(obj)
    hooves = np.flatnonzero(rest[:, 1] < rest[:, 1].min() + 0.06)
    obj.vertex_groups.new(name="Hooves").add([int(i) for i in hooves], 1.0, 'REPLACE')
    settings.pin_group = "Hooves"
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    return obj, rest, hooves


def add_handle(obj, name, mask):
    obj.vertex_groups.new(name=name).add([int(i) for i in np.flatnonzero(mask)], 1.0, 'REPLACE')
    make_active(obj)
    assert bpy.ops.rs_elastic.add_handle(vertex_group=name) == {'FINISHED'}
    empty = obj.rs_elastic.handles[-1].empty
    empty.name = name
    return empty


def key(empty, frames_locations):
    for frame, location in frames_locations:
        empty.location = tuple(location)
        empty.keyframe_insert("location", frame=frame)


def ends(rest):
    x = rest[:, 0]
    return x > x.max() - 0.12, x < x.min() + 0.12


def solve(obj, capfd):
    capfd.readouterr()
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    return capfd.readouterr().out


def volumes(obj, rest, frames):
    out = []
    for frame in frames:
        bpy.context.scene.frame_set(frame)
        out.append(closed_volume(obj, evaluated_vertices(obj)))
    return np.array(out) / closed_volume(obj, rest)


def test_reachable_two_handle_edit_keeps_volume_and_reports_no_stretch(ext, capfd):
    obj, rest, _ = prepared_cow()
    head, tail = ends(rest)
    obj.rs_elastic.preview_mode = 1
    bent = preview_pose(obj, 'RS', 0.3)
    handles = [add_handle(obj, "Head", head), add_handle(obj, "Tail", tail)]
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 40
    for empty, mask in zip(handles, (head, tail)):
        key(empty, [(1, rest[mask].mean(axis=0)), (25, bent[mask].mean(axis=0))])
    out = solve(obj, capfd)
    ratio = volumes(obj, rest, range(1, 41))
    residuals = [h.residual for h in obj.rs_elastic.handles]
    print(f"moved by {np.linalg.norm(bent[head].mean(0) - rest[head].mean(0)):.3f} m, "
          f"volume {ratio.min():.4f}-{ratio.max():.4f}, residuals {residuals}\n{out}")
    assert np.abs(ratio - 1.0).max() < 0.03
    assert "asks the body to stretch" not in out


def test_a_handle_pulled_20_percent_away_is_reported_as_a_stretch(ext, capfd):
    obj, rest, hooves = prepared_cow()
    head, tail = ends(rest)
    handles = [add_handle(obj, "Head", head), add_handle(obj, "Tail", tail)]
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 40
    base = rest[hooves].mean(axis=0)
    pulled = base + 1.2 * (rest[head].mean(axis=0) - base)
    key(handles[0], [(1, rest[head].mean(axis=0)), (25, pulled)])
    key(handles[1], [(1, rest[tail].mean(axis=0)), (25, rest[tail].mean(axis=0))])
    out = solve(obj, capfd)
    print(out)
    found = re.search(r"Handle .Head. asks the body to stretch by at least (\d+) %", out)
    assert found and 5 < int(found.group(1)) <= 25      # reported; a lower bound of the 20 %
    assert "Handle 'Tail' asks" not in out
