"""Take from Animation, Fit Material and Continue (issue 28, items 1, 3, 4) end to end.

Oracles: the seed's experiment (SPEC.md section 5, "Recovering material"): a full-space linear
FEM reference (assembled in this file, Newmark) of the body's own tets with the painted
material's per-tet Young's modulus falling threefold from root to tip, played by a second object
through a Mesh Cache (.pc2 written here); the body takes frames 1-150 from it, fits and
continues to 300; its error on 151-300 against the reference and against the uniform material
continued the same way (the solver's fit without material optimisation); the take's keys against
the source's positions; the fitted material after save and reopen; one-line refusals that change
nothing.
"""
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import bpy

from blender_helpers import diagonal, make_bar, vertices
from test_faults import refusal
from test_panels import draw_each, fitted_table

ROOT_YOUNGS, UNIFORM_YOUNGS, RATIO, POISSON, DENSITY = 3.0e6, 2.0e6, 1.0 / 3.0, 0.3, 1000.0
RAYLEIGH, FPS, KEYED, FRAMES = (0.05, 0.002), 30, 150, 300


def reference_displacements(ext, X, T, pinned, tet_youngs, tip, frames, substeps=4):
    """(frames, N, 3) [m]: linear FEM with per-tet Young's modulus, Rayleigh damping, Newmark
    (average acceleration), from rest in the static deflection under an oblique tip load whose
    largest displacement is ``tip``."""
    K = ext.solver.fem.stiffness_matrix(X, T, tet_youngs, POISSON)
    free = np.repeat(~np.isin(np.arange(len(X)), pinned), 3)
    K = sp.csr_matrix(0.5 * (K + K.T))[free][:, free]
    M = np.repeat(ext.solver.fem.lumped_masses(X, T, DENSITY), 3)[free]
    C = RAYLEIGH[0] * sp.diags(M) + RAYLEIGH[1] * K
    load = np.zeros((len(X), 3))
    load[X[:, 0] > X[:, 0].max() - 1e-3] = [0.0, 0.6, 1.0]
    u = spla.spsolve(K.tocsc(), load.reshape(-1)[free])
    u *= tip / np.abs(u).max()
    v, dt = np.zeros_like(u), 1.0 / FPS / substeps
    a = -(K @ u) / M
    step = spla.splu((K + (2.0 / dt) * C + sp.diags(4.0 / dt ** 2 * M)).tocsc())
    out = np.zeros((frames, 3 * len(X)))
    out[0, free] = u
    for n in range(1, frames * substeps):                # the recurrence over time is inherent
        rhs = M * (4.0 / dt ** 2 * u + 4.0 / dt * v + a) + C @ (2.0 / dt * u + v)
        u_new = step.solve(rhs)
        a_new = 4.0 / dt ** 2 * (u_new - u) - 4.0 / dt * v - a
        v, u, a = v + 0.5 * dt * (a + a_new), u_new, a_new
        if n % substeps == 0:
            out[n // substeps, free] = u
    return out.reshape(frames, len(X), 3)


def uniform_body():
    obj = make_bar(name="Body", cuts=3)
    settings = obj.rs_elastic
    settings.edge_length, settings.num_modes, settings.youngs_modulus = 0.2, 12, UNIFORM_YOUNGS
    settings.poisson_ratio, settings.density = POISSON, DENSITY
    settings.damping_mass, settings.damping_stiffness = RAYLEIGH
    scene = bpy.context.scene
    scene.render.fps, scene.render.fps_base = FPS, 1.0
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    return obj


def playing_source(ext, obj, positions, path):
    """A copy of the body's mesh elsewhere in the scene, playing positions (F, n, 3) from scene
    frame 1 through a Mesh Cache modifier."""
    source = bpy.data.objects.new("Source", obj.data.copy())
    bpy.context.scene.collection.objects.link(source)
    source.location = (0.0, 3.0, 0.0)
    ext.bridge.mesh_cache.write_pc2(str(path), positions)
    modifier = source.modifiers.new("Reference", 'MESH_CACHE')
    modifier.cache_format, modifier.filepath = 'PC2', str(path)
    modifier.frame_start = 1.0
    return source


def key_positions(obj, names):
    blocks = obj.data.shape_keys.key_blocks
    out = np.empty((len(names), len(obj.data.vertices) * 3), dtype=np.float32)
    for row, name in zip(out, names):
        blocks[name].data.foreach_get("co", row)
    return out.reshape(len(names), -1, 3).astype(np.float64)


def rms(a, b):
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=-1))))


def test_a_take_from_a_mesh_cache_fits_and_continues_closer_than_the_uniform_material(
        ext, tmp_path):
    obj = uniform_body()
    body = ext.bridge.prepared.require(obj)
    rest = vertices(obj)
    X, T = body.nodes, body.tets
    scale = ext.solver.preparation.stiffness_scale(body.tet_body, 1.0 - rest[:, 0] / 4.0, RATIO)
    U = reference_displacements(ext, X, T, body.pinned_nodes, ROOT_YOUNGS * scale, 0.24, FRAMES)
    reference = rest + np.einsum("vn,fnk->fvk", body.embedding.toarray(), U)
    source = playing_source(ext, obj, reference, tmp_path / "reference.pc2")
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, KEYED
    obj.rs_elastic.take_source = source
    bpy.context.view_layer.objects.active = obj

    assert bpy.ops.rs_elastic.take_from_animation() == {'FINISHED'}
    frames, take = ext.bridge.bake.take_poses(obj)
    assert frames == list(range(1, KEYED + 1))
    np.testing.assert_allclose(take, reference[:KEYED], atol=1e-6 * diagonal(rest))
    inputs, residuals = ext.solver.take.take_to_modal(body, rest, take)

    assert bpy.ops.rs_elastic.fit_material() == {'FINISHED'}
    fitted = ext.bridge.take.fitted_material(obj)
    assert (fitted.first_frame, fitted.last_frame) == (1, KEYED)
    assert bpy.ops.rs_elastic.continue_motion(frame_end=FRAMES) == {'FINISHED'}
    continued = key_positions(obj, [f"RS Bake {f:04d}" for f in range(KEYED + 1, FRAMES + 1)])
    np.testing.assert_array_equal(ext.bridge.bake.take_poses(obj)[1], take)   # take untouched

    uniform = ext.solver.take.fit_material(body, rest, frames, take, inputs, 1.0 / FPS,
                                           *RAYLEIGH, optimise=False)
    uniform_continued = body.surface_positions(
        rest, ext.solver.take.continue_motion(uniform, FRAMES - KEYED))
    error, uniform_error = rms(continued, reference[KEYED:]), rms(uniform_continued,
                                                                   reference[KEYED:])
    size = diagonal(rest)
    print(f"take from a Mesh Cache: modes miss the take by {residuals.max():.4f} m at worst "
          f"(frame {frames[int(np.argmax(residuals))]}), fit residual {fitted.residual:.4f} m; "
          f"frames {KEYED + 1}-{FRAMES} RMS uniform {uniform_error:.4f} m, fitted {error:.4f} m "
          f"(ratio {error / uniform_error:.3f}, {100 * error / size:.2f} % of the diagonal); "
          f"Hz prepared {np.round(fitted.prepared_frequencies[:2], 3)} -> fitted "
          f"{np.round(fitted.frequencies[:2], 3)}")
    assert residuals.max() < 0.01 * size
    assert error <= uniform_error / 3.0
    assert error < 0.02 * size

    obj.rs_elastic.use_fitted_material = True            # the editor and the simulation
    edit = ext.bridge.spacetime_inputs.settings_of(obj, scene)
    assert edit.fitted is not None
    np.testing.assert_array_equal(ext.solver.problems.material_of(body, edit)[0],
                                  fitted.eigenvalues)
    linear = ext.solver.problems.linear_potential(body, UNIFORM_YOUNGS, POISSON)
    potential, simulated = ext.bridge.take.simulated_material(
        obj, body, linear, ext.bridge.simulation_inputs.settings_of(obj, scene, np.zeros(3)))
    S = fitted.sampling
    restricted = np.linalg.eigvals(np.linalg.solve(S.T @ S, S.T @ potential.rest_hessian @ S))
    np.testing.assert_allclose(np.sort(restricted.real), np.sort(fitted.eigenvalues), rtol=1e-8)
    assert (simulated.damping_mass, simulated.damping_stiffness) == \
        ext.solver.take.fitted_rayleigh(fitted)

    shown = draw_each()["RS_ELASTIC_PT_take"]            # the panel: prepared vs fitted
    facts, rows = fitted_table(shown)
    assert rows[0][0] == "1"
    np.testing.assert_allclose(rows[0][1], (fitted.prepared_frequencies[0],
                                            fitted.frequencies[0]), rtol=5e-3)
    np.testing.assert_allclose(rows[0][2], (fitted.prepared_damping[0], fitted.damping[0]),
                               rtol=5e-3, atol=5e-4)
    assert ("operator", "rs_elastic.continue_motion") in shown
    assert facts["Residual"] == f"{fitted.residual:.3g} m"

    blend = tmp_path / "take.blend"                      # the fitted material is in the .blend
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    reopened = ext.bridge.take.fitted_material(bpy.data.objects["Body"])
    np.testing.assert_array_equal(reopened.eigenvalues, fitted.eigenvalues)
    np.testing.assert_array_equal(reopened.sampling, fitted.sampling)


def test_a_source_with_other_vertices_is_refused_and_nothing_changes(ext):
    obj = make_bar(name="Body", cuts=1)
    obj.rs_elastic.edge_length, obj.rs_elastic.num_modes = 0.3, 4
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    other = make_bar(name="Other", cuts=2)
    obj.rs_elastic.take_source = other
    bpy.context.view_layer.objects.active = obj
    line = refusal(bpy.ops.rs_elastic.take_from_animation)
    assert "same vertices" in line and "'Other'" in line, line

    rest = vertices(obj)                                  # same mesh, vertices renumbered
    order = np.arange(len(rest))[::-1]
    new_index = np.argsort(order)
    faces = [[int(new_index[v]) for v in face.vertices] for face in obj.data.polygons]
    mesh = bpy.data.meshes.new("Shuffled")
    mesh.from_pydata([tuple(v) for v in rest[order]], [], faces)
    shuffled = bpy.data.objects.new("Shuffled", mesh)
    bpy.context.scene.collection.objects.link(shuffled)
    obj.rs_elastic.take_source = shuffled
    line = refusal(bpy.ops.rs_elastic.take_from_animation)
    assert "order" in line, line

    obj.rs_elastic.take_source = None
    assert "fitted material" in refusal(lambda: bpy.ops.rs_elastic.continue_motion(frame_end=9))
    assert "no take" in refusal(bpy.ops.rs_elastic.fit_material)
    obj.rs_elastic.use_fitted_material = True
    assert "fitted material" in refusal(bpy.ops.rs_elastic.simulate)
    assert "fitted material" in refusal(bpy.ops.rs_elastic.solve_spacetime)


def test_the_body_takes_its_own_shape_key_animation_without_its_bake(ext):
    """The body itself as the source: its user's animated shape key is the take (each frame
    rest + value (key - rest), value from the key's own F-curve); the extension's bake on the
    same body, which would add 0.3 m, is muted while reading and plays again after."""
    obj = make_bar(name="Body", cuts=1)
    obj.rs_elastic.edge_length, obj.rs_elastic.num_modes = 0.3, 4
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    rest = vertices(obj)
    frames = list(range(1, 6))
    ext.bridge.bake.write_bake(obj, frames, np.repeat(rest[None] + 0.3, len(frames), axis=0))
    bend = obj.shape_key_add(name="Bend", from_mix=False)
    bent = rest + np.stack([np.zeros(len(rest)), np.zeros(len(rest)),
                            0.05 * (rest[:, 0] / 4.0) ** 2], axis=1)
    bend.data.foreach_set("co", bent.ravel())
    for frame, value in ((1, 0.0), (5, 1.0)):
        bend.value = value
        bend.keyframe_insert("value", frame=frame)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = frames[0], frames[-1]
    scene.frame_set(3)
    assert bpy.ops.rs_elastic.take_from_animation() == {'FINISHED'}
    curve = ext.bridge.animation.fcurves(obj.data.shape_keys, create=False).find(
        'key_blocks["Bend"].value')
    values = [curve.evaluate(f) for f in frames]
    expected = rest[None] + np.array(values)[:, None, None] * (bent - rest)[None]
    np.testing.assert_allclose(ext.bridge.bake.take_poses(obj)[1], expected, atol=1e-6)
    assert scene.frame_current == 3
    assert not any(block.mute for block in ext.bridge.bake.owned_keys(obj, "bake"))


def test_the_command_line_takes_fits_continues_and_saves(ext, tmp_path):
    """`fit --object Body --source Source --frames 1-12 --continue-to 20`: the saved file holds
    the take (frames 1-12, the source's positions), the fitted material of those frames and the
    continuation's bake 13-20; the scene's range is as before; a bad --source is refused (2)."""
    from test_spacetime import run_cli
    obj = make_bar(name="Body", cuts=1)
    obj.rs_elastic.edge_length, obj.rs_elastic.num_modes = 0.3, 4
    rest = vertices(obj)
    wave = rest[None] + np.outer(0.05 * np.sin(np.arange(12) / 2.0),
                                 (rest[:, 0] / 4.0) ** 2)[:, :, None] * [0.0, 0.0, 1.0]
    source = playing_source(ext, obj, wave, tmp_path / "wave.pc2")
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 250
    blend, out = tmp_path / "shot.blend", tmp_path / "fitted.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))

    run = run_cli(blend, ["fit", "--object", "Body", "--source", source.name, "--frames", "1-12",
                          "--continue-to", "20", "--output", str(out)])
    assert run.returncode == 0, run.stdout + run.stderr
    assert "rs_elastic: fitted the material of 'Body' to frames 1-12" in run.stdout, run.stdout
    bpy.ops.wm.open_mainfile(filepath=str(out))
    body = bpy.data.objects["Body"]
    frames, take = ext.bridge.bake.take_poses(body)
    assert frames == list(range(1, 13))
    np.testing.assert_allclose(take, wave, atol=1e-6)
    fitted = ext.bridge.take.fitted_material(body)
    assert (fitted.first_frame, fitted.last_frame) == (1, 12)
    assert ext.bridge.bake.bake_frames(body) == list(range(13, 21))
    assert (bpy.context.scene.frame_start, bpy.context.scene.frame_end) == (1, 250)

    bad = run_cli(blend, ["fit", "--object", "Body", "--source", "Nobody"])
    assert bad.returncode == 2, bad.stderr
