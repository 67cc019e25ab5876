"""Stale and damaged state: every operator that uses a prepared body refuses with one line that says
what changed, and changes nothing of the user's; damaged or mixed cache files are rebuilt with one
warning; an undo that brings back a pruned preparation quietly recomputes it."""
import pathlib
import shutil
import time

import numpy as np
import pytest
import bpy

from blender_helpers import add_tip_handle, make_active, make_bar, user_fingerprint, vertices

TIP_KEYS = {10: (4.0, 0.5, 1.5), 20: (4.0, 0.5, 0.0)}


@pytest.fixture(scope="module")
def prepared_file(tmp_path_factory):
    """A saved .blend (and its cache folder): a pinned bar with a keyed tip handle, prepared."""
    bpy.ops.wm.read_homefile(use_empty=True)
    obj = make_bar(cuts=3)
    obj.rs_elastic.edge_length = 0.1
    obj.rs_elastic.num_modes = 5
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    add_tip_handle(obj, TIP_KEYS)
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 24
    folder = tmp_path_factory.mktemp("stale")
    bpy.ops.wm.save_as_mainfile(filepath=str(folder / "shot.blend"))
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}       # its cache, next to the file
    bpy.ops.wm.save_mainfile()
    return folder


@pytest.fixture
def bar(prepared_file, tmp_path, ext):
    """The prepared bar, opened from this test's own copy of the file and its cache."""
    shutil.copy(prepared_file / "shot.blend", tmp_path / "shot.blend")
    shutil.copytree(prepared_file / "blendcache_shot", tmp_path / "blendcache_shot")
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "shot.blend"))
    ext.bridge.stage_cache._MEMORY.clear()
    ext.bridge.stage_cache.stats.clear()
    obj = bpy.data.objects["Bar"]
    make_active(obj)
    return obj


def warnings_in(capfd):
    """The WARNING reports printed since the last call, except a solve's convergence status
    (about the solve, not the cache; test_spacetime checks it)."""
    return [line[len("Warning: "):] for line in capfd.readouterr().out.splitlines()
            if line.startswith("Warning: ") and not line.startswith("Warning: Solve did not")]


def x_at(obj, x):
    return [int(i) for i in np.flatnonzero(np.abs(vertices(obj)[:, 0] - x) < 1e-9)]


def move_tip_vertex(obj):
    v = obj.data.vertices[x_at(obj, 4.0)[0]]
    v.co.z += 0.05
    obj.data.update()


def add_a_ring_to_the_pins(obj):
    obj.vertex_groups["Pin"].add(x_at(obj, 1.0), 1.0, 'REPLACE')


def rename_the_pin_group(obj):
    obj.vertex_groups["Pin"].name = "Clamp"


def add_displace(obj):
    obj.modifiers.new("Displace", 'DISPLACE').strength = 0.1


def change_the_material(obj):
    obj.rs_elastic.youngs_modulus *= 2.0


def subdivide_after_a_solve(obj):
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    before = len(obj.data.vertices)
    bpy.ops.object.mode_set(mode='EDIT')
    bpy.ops.mesh.select_all(action='SELECT')
    bpy.ops.mesh.subdivide(number_cuts=1)
    bpy.ops.object.mode_set(mode='OBJECT')
    return f"({before} → {len(obj.data.vertices)})"


STALE_ROWS = [
    (move_tip_vertex, "'Bar': the mesh's vertices moved since Prepare Body: prepare again"),
    (add_a_ring_to_the_pins, "'Bar': the pin group changed since Prepare Body: prepare again"),
    (rename_the_pin_group, "'Bar': pin group 'Pin' no longer exists (renamed or deleted since "
                           "Prepare Body): set Pin Group and prepare again"),
    (add_displace, "'Bar': the modifiers changed since Prepare Body: prepare again"),
    (change_the_material, "'Bar': the material changed since Prepare Body: prepare again"),
    (subdivide_after_a_solve, "'Bar': the vertex count changed since Prepare Body {counts}: "
                              "prepare again"),
]


@pytest.mark.parametrize("change, message", STALE_ROWS, ids=[r[0].__name__ for r in STALE_ROWS])
def test_a_stale_body_is_refused_with_what_changed(ext, bar, change, message):
    staleness = ext.bridge.staleness
    assert staleness.stale_reason(bar, cached=True) is None      # fills the panel's cache
    counts = change(bar)
    message = message.format(counts=counts)
    bpy.context.view_layer.update()
    # The panel sees it at once (its cached fingerprint is dropped by the depsgraph update).
    assert f"'Bar': {staleness.stale_reason(bar, cached=True)}" == message
    if bar.data.shape_keys is None:
        bar.shape_key_add(name="Basis")
        bar.shape_key_add(name="Other")
    user = user_fingerprint(bar)
    for operator, arguments in ((bpy.ops.rs_elastic.solve_spacetime, {}),
                                (bpy.ops.rs_elastic.simulate, {}),
                                (bpy.ops.rs_elastic.interpolate_shape_keys,
                                 dict(key_from="Basis", key_to="Other"))):
        with pytest.raises(RuntimeError) as refused:
            operator(**arguments)
        assert str(refused.value).strip().splitlines() == [f"Error: {message}"]
        assert user_fingerprint(bar) == user
    assert ext.bridge.prepared.for_object(bar) is None          # nor does the preview use it


def test_the_command_line_path_prepares_again_and_then_solves(ext, bar):
    """What the CLI does: Prepare first, which rebuilds whatever changed."""
    ring = x_at(bar, 1.0)
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    assert np.abs(_baked_pose(bar, 10)[ring] - vertices(bar)[ring]).max() > 1e-3  # free ring moves
    add_a_ring_to_the_pins(bar)
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert ext.bridge.stage_cache.stats["modes"] == 1 and ext.bridge.stage_cache.stats["tetrahedralize"] == 0
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    moved = np.abs(_baked_pose(bar, 10)[ring] - vertices(bar)[ring]).max()
    assert moved < 1e-6, moved                   # the new pins hold


def test_the_command_line_rebuilds_a_stale_file(ext, bar, tmp_path):
    """The saved file's pins changed after Prepare: `-c rs_elastic bake` prepares again."""
    from test_spacetime import run_cli
    add_a_ring_to_the_pins(bar)
    bpy.ops.wm.save_mainfile()
    out = tmp_path / "baked.blend"
    result = run_cli(tmp_path / "shot.blend", ["bake", "--object", "Bar", "--output", str(out)])
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    bpy.ops.wm.open_mainfile(filepath=str(out))
    bar = bpy.data.objects["Bar"]
    assert ext.bridge.staleness.stale_reason(bar) is None
    ring = x_at(bar, 1.0)
    moved = max(np.abs(_baked_pose(bar, f)[ring] - vertices(bar)[ring]).max() for f in (10, 20))
    assert moved < 1e-6, moved                   # the new pins hold


def _baked_pose(obj, frame):
    block = obj.data.shape_keys.key_blocks[f"RS Bake {frame:04d}"]
    co = np.empty(len(block.data) * 3)
    block.data.foreach_get("co", co)
    return co.reshape(-1, 3)


def _stage_file(ext, obj, stage):
    settings = obj.rs_elastic
    key = {"tets": settings.tets_key, "modes": settings.prepared_key,
           "reduced": settings.reduced_key}[stage]
    stage_cache = ext.bridge.stage_cache
    return pathlib.Path(stage_cache.cache_file(stage_cache.cache_dirs()[0], obj.name, stage, key))


def _drop_pins(a):
    a.pop("pinned_nodes")
    return "has no array 'pinned_nodes'"


def _poison_a_mode(a):
    a["vectors"][0, 0] = np.nan
    return ": array 'vectors' is not finite"


def _cut_the_modes(a):
    a["vectors"] = a["vectors"][:, :2]
    return f": array 'vectors' has shape {a['vectors'].shape}"


DAMAGE_ROWS = [_drop_pins, _poison_a_mode, _cut_the_modes]


@pytest.mark.parametrize("damage", DAMAGE_ROWS, ids=[f.__name__ for f in DAMAGE_ROWS])
def test_a_damaged_cache_file_is_rebuilt_with_one_warning(ext, bar, capfd, damage):
    path = _stage_file(ext, bar, "modes")
    key = bar.rs_elastic.prepared_key
    arrays = ext.solver.cache.load(str(path), key)
    problem = damage(arrays)
    ext.solver.cache.save(str(path), key, arrays)
    before = np.array(bar.rs_elastic.frequencies)
    user = user_fingerprint(bar)
    capfd.readouterr()
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    separator = "" if problem.startswith(":") else " "
    assert warnings_in(capfd) == [f"cache file {path}{separator}{problem}; rebuilding it"]
    assert ext.bridge.stage_cache.stats["modes"] == 1
    np.testing.assert_allclose(bar.rs_elastic.frequencies, before, rtol=1e-9)
    assert user_fingerprint(bar) == user
    assert ext.solver.cache.load(str(path), key)["pinned_nodes"].size
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}          # and it stays fixed
    assert warnings_in(capfd) == [] and ext.bridge.stage_cache.stats["modes"] == 1


def test_a_corrupt_cache_file_is_rebuilt_with_one_warning(ext, bar, capfd):
    path = _stage_file(ext, bar, "reduced")
    path.write_bytes(b"PK\x03\x04 not really a zip")
    user = user_fingerprint(bar)
    capfd.readouterr()
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    (line,) = warnings_in(capfd)
    assert line.startswith(f"cache file {path} is unreadable (") and line.endswith("; rebuilding it")
    assert ext.bridge.stage_cache.stats["reduced"] == 1 and ext.bridge.stage_cache.stats["modes"] == 0
    assert user_fingerprint(bar) == user
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}


def _reversed_nodes(tet_body_cls, tet_body):
    """The same tet mesh with its nodes numbered backwards: a different tet file, equally valid."""
    n = len(tet_body.nodes)
    order = np.arange(n)[::-1]
    new_index = np.empty(n, dtype=np.int64)
    new_index[order] = np.arange(n)
    return tet_body_cls(tet_body.nodes[order], new_index[tet_body.tets],
                        tet_body.embedding[:, order].tocsr())


def _replace_tets_file(ext, obj):
    TetBody = ext.solver.body.TetBody
    path = _stage_file(ext, obj, "tets")
    old = TetBody.from_arrays(ext.solver.cache.load(str(path), obj.rs_elastic.tets_key))
    new = _reversed_nodes(TetBody, old)
    ext.solver.cache.save(str(path), obj.rs_elastic.tets_key,
                          dict(new.to_arrays(), parent_digest=np.array("")))
    return old, new


def test_a_rebuilt_tets_file_is_ignored_when_the_blend_keeps_its_tet_mesh(ext, bar, capfd):
    keys = (bar.rs_elastic.tets_key, bar.rs_elastic.prepared_key, bar.rs_elastic.reduced_key)
    old, _ = _replace_tets_file(ext, bar)
    capfd.readouterr()
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert warnings_in(capfd) == []
    assert (bar.rs_elastic.tets_key, bar.rs_elastic.prepared_key, bar.rs_elastic.reduced_key) == keys
    stats = ext.bridge.stage_cache.stats
    assert (stats["tetrahedralize"], stats["modes"], stats["reduced"]) == (0, 0, 0)
    inputs = ext.bridge.bodies.read_inputs(bar, bpy.context.evaluated_depsgraph_get())
    body = ext.bridge.bodies.prepare(inputs, ext.bridge.jobs.Job(None))
    np.testing.assert_array_equal(body.tet_body.nodes, old.nodes)


def test_modes_of_an_old_tet_mesh_are_never_mixed_with_a_rebuilt_tets_file(ext, bar, capfd):
    """A file from before the tet mesh was kept in the .blend: the tets file is all there is."""
    del bar.rs_elastic[ext.bridge.stage_cache.TET_MESH]
    old_modes = bar.rs_elastic.prepared_key
    _, new = _replace_tets_file(ext, bar)
    capfd.readouterr()
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert warnings_in(capfd) == []
    assert bar.rs_elastic.prepared_key != old_modes        # the modes key follows the contents
    assert ext.bridge.stage_cache.stats["modes"] == 1
    inputs = ext.bridge.bodies.read_inputs(bar, bpy.context.evaluated_depsgraph_get())
    body = ext.bridge.bodies.prepare(inputs, ext.bridge.jobs.Job(None))
    np.testing.assert_array_equal(body.tet_body.nodes, new.nodes)
    assert body.linear_modes.vectors.shape[0] == 3 * len(new.nodes)
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    # And preparing again is stable: nothing is recomputed.
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert ext.bridge.stage_cache.stats["modes"] == 1


def test_undo_of_a_re_prepare_quietly_recomputes_the_pruned_files(ext, bar, capfd):
    first = (bar.rs_elastic.prepared_key, bar.rs_elastic.reduced_key)
    frequencies = np.array(bar.rs_elastic.frequencies)
    old_files = [_stage_file(ext, bar, stage) for stage in ("modes", "reduced")]
    bpy.ops.ed.undo_push(message="before")
    bar.rs_elastic.poisson_ratio = 0.3  # new modes (Young's modulus or density reuse them)
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    bpy.ops.ed.undo_push(message="Prepare Body")
    assert not any(path.exists() for path in old_files)            # pruned
    bpy.ops.ed.undo()
    bar = bpy.data.objects["Bar"]
    make_active(bar)
    assert (bar.rs_elastic.prepared_key, bar.rs_elastic.reduced_key) == first
    ext.bridge.stage_cache._MEMORY.clear()
    ext.bridge.prepared._BODIES.clear()
    user = user_fingerprint(bar)
    capfd.readouterr()
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    assert warnings_in(capfd) == []
    assert ext.bridge.stage_cache.stats["tetrahedralize"] == 0          # the tet mesh is in the file
    assert old_files[0].exists()                                     # recomputed, same key
    # The deformer's key hashes the modes' arrays: the same unless the eigensolver's signs vary.
    assert _stage_file(ext, bar, "reduced").exists()
    assert bar.rs_elastic.prepared_key == first[0]
    body = ext.bridge.bodies.load_prepared(bar)
    np.testing.assert_allclose(body.linear_modes.frequencies_hz, frequencies, rtol=1e-6)  # float32
    assert bpy.ops.rs_elastic.clear_bake() == {'FINISHED'}
    assert user_fingerprint(bar) == user


def test_panel_stale_check_cost_on_a_50k_vertex_mesh(ext):
    """The panel calls stale_reason in draw: cached, it must cost well under a frame."""
    bpy.ops.mesh.primitive_grid_add(x_subdivisions=230, y_subdivisions=230, size=2.0)
    obj = bpy.context.active_object
    bpy.ops.object.modifier_add(type='SOLIDIFY')
    group = obj.vertex_groups.new(name="Pin")
    group.add(list(range(0, len(obj.data.vertices), 7)), 1.0, 'REPLACE')
    obj.rs_elastic.pin_group = "Pin"
    staleness = ext.bridge.staleness
    assert len(obj.data.vertices) >= 50_000
    obj.rs_elastic.prepared_key = "pretend"            # a prepared body, as far as the panel cares
    staleness.record_prepared(obj, staleness.fingerprint(obj))
    t0 = time.perf_counter()
    assert staleness.stale_reason(obj) is None
    fresh = time.perf_counter() - t0
    staleness.stale_reason(obj, cached=True)
    t0 = time.perf_counter()
    for _ in range(100):
        assert staleness.stale_reason(obj, cached=True) is None
    cached = (time.perf_counter() - t0) / 100
    obj.data.vertices[0].co.z += 0.1
    obj.data.update()
    bpy.context.view_layer.update()
    t0 = time.perf_counter()
    assert staleness.stale_reason(obj, cached=True) == ("the mesh's vertices moved since Prepare "
                                                        "Body: prepare again")
    after_edit = time.perf_counter() - t0
    print(f"stale check on {len(obj.data.vertices)} vertices: {1e3 * fresh:.1f} ms fresh, "
          f"{1e3 * cached:.3f} ms per draw cached, {1e3 * after_edit:.1f} ms on the first draw "
          "after an edit")
    assert cached < 2e-3
