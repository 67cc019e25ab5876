"""The body cache: next to the saved .blend, reused by a new process, rebuilt when stale or corrupt."""
import json
import os
import pathlib
import re
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest
import bpy

from blender_helpers import fingerprint, make_bar
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
print("RESULT " + json.dumps(dict(result=sorted(result), stats=dict(ext.bridge.stage_cache.stats),
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
    assert ext.bridge.stage_cache.stats["modes"] == 1
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


def test_a_save_as_to_another_folder_takes_the_cache_along_at_once(ext, tmp_path):
    """The stages go to the new file's blendcache folder with the save (from the folder the file
    kept them in before), not later when an operator happens to load them."""
    obj = prepare_bar(ext)
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "a" / "shot.blend"))
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}       # the cache now lives in a/
    first = sorted(p.name for p in (tmp_path / "a" / "blendcache_shot").iterdir())
    assert len(first) == 3
    temp = ext.bridge.stage_cache.cache_dirs()[-1]       # as in a new session: only a/ has them
    for name in first:
        pathlib.Path(temp, name).unlink(missing_ok=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "b" / "take2.blend"))
    folder = tmp_path / "b" / "blendcache_take2"
    assert sorted(p.name for p in folder.iterdir()) == first
    settings = obj.rs_elastic
    assert ext.bridge.stage_cache.cache.stored_key(
        str(folder / f"Bar.modes.{settings.prepared_key[:16]}.npz")) == settings.prepared_key


def test_stale_cache_is_rebuilt_per_stage(ext):
    obj = prepare_bar(ext)
    stats = ext.bridge.stage_cache.stats
    assert (stats["tetrahedralize"], stats["modes"]) == (1, 1)
    obj.rs_elastic.poisson_ratio = 0.3                  # material: only the modes are stale
    ext.bridge.stage_cache._MEMORY.clear()
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert (stats["tetrahedralize"], stats["modes"]) == (1, 2)
    obj.data.vertices[0].co.x -= 0.2                    # mesh: everything is stale
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert (stats["tetrahedralize"], stats["modes"]) == (2, 3)


@pytest.mark.parametrize("setting, factor", [("youngs_modulus", 4.0), ("density", 0.25)])
def test_a_change_of_youngs_modulus_or_density_reuses_the_modes_and_the_reduced_stage(
        ext, setting, factor):
    """The modes and the deformer are cached at 1 Pa and 1 kg/m³: a Young's modulus 4 times or a
    density a quarter of the prepared one moves them (eigenvalues times E / rho: 4 either way;
    vectors over sqrt(rho)) and computes nothing (read from their files here, as in a new
    session). The modes equal an independent modal analysis at the new material, and the moved
    deformer puts the same displacement at the same pose (z times sqrt(rho' / rho) is one)."""
    obj = prepare_bar(ext)
    stats, settings = ext.bridge.stage_cache.stats, obj.rs_elastic
    before, density = ext.bridge.prepared.for_object(obj), settings.density
    keys, prepared = (settings.prepared_key, settings.reduced_key), getattr(settings, setting)
    setattr(settings, setting, factor * prepared)
    assert ext.bridge.prepared.for_object(obj) is None          # stale until Prepare
    ext.bridge.stage_cache._MEMORY.clear()
    files = sorted(os.listdir(ext.bridge.stage_cache.cache_dirs()[0]))
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert (stats["tetrahedralize"], stats["modes"], stats["reduced"]) == (1, 1, 1)
    assert sorted(os.listdir(ext.bridge.stage_cache.cache_dirs()[0])) == files
    assert (settings.prepared_key, settings.reduced_key) == keys
    after = ext.bridge.prepared.for_object(obj)
    assert after is not before
    pose_scale = np.sqrt(settings.density / density)             # 1 for Young's modulus
    np.testing.assert_allclose(after.linear_modes.vectors, before.linear_modes.vectors / pose_scale,
                               rtol=1e-15, atol=0.0)
    np.testing.assert_allclose(after.linear_modes.eigenvalues,
                               4.0 * before.linear_modes.eigenvalues, rtol=1e-12)
    np.testing.assert_allclose(settings.frequencies, after.linear_modes.frequencies_hz, rtol=1e-6)
    X, T = after.tet_body.nodes, after.tet_body.tets
    K = ext.solver.fem.stiffness_matrix(X, T, settings.youngs_modulus, settings.poisson_ratio)
    reference = ext.solver.modes.linear_modes(
        K, after.tet_body.lumped_masses(settings.density), settings.num_modes,
        after.linear_modes.pinned_nodes, rest_positions=X)
    np.testing.assert_allclose(after.linear_modes.eigenvalues, reference.eigenvalues, rtol=1e-9)
    np.testing.assert_allclose(after.linear_modes.vectors, reference.vectors,
                               atol=1e-7 * np.abs(reference.vectors).max())
    z = 2.0 / np.sqrt(before.linear_modes.eigenvalues)          # large: the RS part matters
    moved, kept = after.deformer.q(pose_scale * z), before.deformer.q(z)
    assert np.abs(kept[settings.num_modes:]).max() > 1e-3 * np.abs(kept).max()
    np.testing.assert_allclose(moved, kept, rtol=1e-10, atol=1e-12 * np.abs(kept).max())
    setattr(settings, setting, prepared)                          # back: nothing computed either
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert (stats["modes"], stats["reduced"]) == (1, 1)
    np.testing.assert_allclose(ext.bridge.prepared.for_object(obj).linear_modes.eigenvalues,
                               before.linear_modes.eigenvalues, rtol=1e-12)


OTHER_VERSION = ("'Bar': it was prepared by another version of RS Elastic, whose cached stages "
                 "this one cannot read: prepare again")


@pytest.mark.parametrize("how", ["rules changed", "no rules recorded"])
def test_a_body_prepared_by_another_version_is_stale_until_prepared_again(ext, monkeypatch, how):
    """A file prepared by another version: here the modes' rules changed since (as a version that
    moves them would), or its record has no rules (a version before they were recorded). Its
    stages cannot be read under this version's keys, so it is stale: the panel's line says so
    before any operator runs, Simulate refuses with it and changes nothing, and Prepare Body
    mends it."""
    obj = prepare_bar(ext)
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 3
    ext.bridge.stage_cache._MEMORY.clear()
    ext.bridge.prepared._BODIES.clear()
    if how == "rules changed":
        monkeypatch.setattr(ext.bridge.stage_rules, "MODES_RULES", "modes of another version")
    else:
        record = json.loads(obj.rs_elastic["prepared_inputs"])
        del record["version of the stages"]
        obj.rs_elastic["prepared_inputs"] = json.dumps(record, sort_keys=True)
    assert ext.bridge.staleness.stale_reason(obj, cached=True) == OTHER_VERSION[len("'Bar': "):]
    before = fingerprint(obj)
    with pytest.raises(RuntimeError, match=re.escape(OTHER_VERSION)):
        bpy.ops.rs_elastic.simulate()
    assert fingerprint(obj) == before
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert ext.bridge.staleness.stale_reason(obj, cached=True) is None
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}


def test_a_preparation_that_cannot_be_rebuilt_asks_to_be_prepared_again(ext, monkeypatch):
    """Not stale, but its stages cannot be rebuilt (here the rebuild fails): Simulate refuses
    with one line that says so and changes nothing; Prepare Body mends it."""
    obj = prepare_bar(ext)
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 3
    ext.bridge.stage_cache._MEMORY.clear()
    ext.bridge.prepared._BODIES.clear()
    rebuild = ext.bridge.bodies.prepare

    def failing(inputs, job):
        raise RuntimeError("the eigensolver did not converge")

    monkeypatch.setattr(ext.bridge.bodies, "prepare", failing)
    assert ext.bridge.staleness.stale_reason(obj) is None
    before = fingerprint(obj)
    with pytest.raises(RuntimeError, match=re.escape(
            "'Bar' must be prepared again: its preparation could not be rebuilt (the system "
            "console says why): run Prepare Body")):
        bpy.ops.rs_elastic.simulate()
    assert fingerprint(obj) == before
    monkeypatch.setattr(ext.bridge.bodies, "prepare", rebuild)
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}


def test_corrupt_cache_file_is_reported_and_rebuilt(ext):
    obj = prepare_bar(ext)
    before = np.array(obj.rs_elastic.frequencies)
    path = pathlib.Path(ext.bridge.stage_cache.cache_file(ext.bridge.stage_cache.cache_dirs()[0], "Bar", "modes",
                                                     obj.rs_elastic.prepared_key))
    path.write_bytes(b"this is not a cache file")
    ext.bridge.stage_cache._MEMORY.clear()
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert ext.bridge.stage_cache.stats["modes"] == 2
    np.testing.assert_allclose(obj.rs_elastic.frequencies, before, rtol=1e-10)
    assert ext.solver.cache.load(str(path), obj.rs_elastic.prepared_key) is not None


def test_unsaved_file_uses_the_temp_folder(ext):
    assert bpy.data.filepath == ""
    import tempfile
    assert ext.bridge.stage_cache.cache_dirs() == [os.path.join(tempfile.gettempdir(), "rs_elastic_cache")]
    obj = prepare_bar(ext)
    assert sorted(os.listdir(ext.bridge.stage_cache.cache_dirs()[0])) == sorted(
        [f"Bar.modes.{obj.rs_elastic.prepared_key[:16]}.npz",
         f"Bar.tets.{obj.rs_elastic.tets_key[:16]}.npz",
         f"Bar.reduced.{obj.rs_elastic.reduced_key[:16]}.npz"])


def test_files_of_old_keys_are_pruned_once_a_new_preparation_is_applied(ext):
    obj = prepare_bar(ext)
    folder = ext.bridge.stage_cache.cache_dirs()[0]
    old = set(os.listdir(folder))
    obj.rs_elastic.poisson_ratio = 0.3                # new modes (Young's modulus or density
                                                      # would not do)
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    new = set(os.listdir(folder))
    assert len(new) == 3 and len(old & new) == 1      # the tets are shared; old modes, reduced gone


def stored_tets(ext, obj):
    group = obj.rs_elastic.get(ext.bridge.stage_cache.TET_MESH)
    return group["key"], np.array(group["nodes"]), np.array(group["tets"])


def test_the_tet_mesh_stays_with_the_file_until_the_surface_or_mesher_settings_change(ext):
    obj = prepare_bar(ext)
    stats, stage_cache = ext.bridge.stage_cache.stats, ext.bridge.stage_cache
    key, nodes, tets = stored_tets(ext, obj)
    assert key == obj.rs_elastic.tets_key and len(tets) == 4 * obj.rs_elastic.tet_count
    assert nodes.dtype == np.float64 and len(nodes) == 3 * obj.rs_elastic.tet_node_count
    # Material, pins, mode count and reduced settings keep it, with no cache at all.
    obj.rs_elastic.youngs_modulus *= 2
    obj.rs_elastic.num_modes = 4
    obj.vertex_groups["Pin"].add(list(range(len(obj.data.vertices))[:3]), 1.0, 'REPLACE')
    obj.rs_elastic.cubature_tets = 50
    shutil.rmtree(stage_cache.cache_dirs()[0])
    stage_cache._MEMORY.clear()
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
    bodies, stage_cache = ext.bridge.bodies, ext.bridge.stage_cache
    pinned = bodies.load_prepared(obj).linear_modes.pinned_nodes
    assert len(pinned) > 0
    np.testing.assert_array_equal(stage_cache.load_pinned_nodes(obj), pinned)
    stage_cache._MEMORY.clear()
    np.testing.assert_array_equal(stage_cache.load_pinned_nodes(obj), pinned)      # from the file
    assert stage_cache.stats["modes"] == 1
    nodes = stage_cache.load_tet_body(obj).nodes
    assert np.abs(nodes[pinned, 0]).max() < 0.5        # on the pinned end face, not beyond


# --- the energy cubature (StVK / Fung): the fourth stage ------------------------------------------

SIMULATE_SCRIPT = """
import json, sys
sys.path.insert(0, {tools!r})
import blender_session
ext = blender_session.start(user_dir={user_dir!r})
import bpy
import numpy as np
bpy.ops.wm.open_mainfile(filepath={blend!r})
obj = bpy.data.objects["Bar"]
bpy.context.view_layer.objects.active = obj

def no_training(*args, **kwargs):
    raise AssertionError("the energy cubature was trained again")

ext.solver.materials.train_energy_cubature = no_training
result = bpy.ops.rs_elastic.simulate()
sim = ext.bridge.simulation_inputs
inputs = sim.gather(obj, bpy.context.scene)
potential = inputs.simulation.potential
while hasattr(potential, "barrier"):                  # the material's, inside the barriers
    potential = potential.potential
poses = sim.run(inputs, ext.bridge.jobs.Job(None))
np.savez({out!r}, tets=potential.tets, weights=potential.weights,
         strain_modes=potential.strain_modes, poses=poses)
print("RESULT " + json.dumps(dict(result=sorted(result), stats=dict(ext.bridge.stage_cache.stats))))
"""


def energy_files(folder):
    return sorted(name for name in os.listdir(folder) if ".energy." in name)


def same_quadrature(a, b):
    """Whether two potentials were moved from one cubature in memory (neither trained nor read
    again): they share its tets array (the strain per unit coordinate is scaled to the body's
    density on each move, ``preparation.energy_at``)."""
    return a.tets is b.tets


def simulate_frames(ext, obj):
    """Simulate frames 1..4 through the operator; the potential it used."""
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 4
    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    tools = ext.bridge.prepared.for_object(obj)
    return ext.bridge.simulation_inputs.potential_for(tools, obj.rs_elastic)


def fresh_poses(ext, obj):
    """(potential, poses (4, n, 3)) of frames 1..4 gathered and run outside the operator."""
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 4
    sim = ext.bridge.simulation_inputs
    inputs = sim.gather(obj, bpy.context.scene)
    material = inputs.simulation.potential
    while hasattr(material, "barrier"):                # inside the volume barriers
        material = material.potential
    return material, sim.run(inputs, ext.bridge.jobs.Job(None))


def test_a_new_session_loads_the_stvk_energy_cubature_that_prepare_trained(ext, tmp_path):
    obj = make_bar()
    obj.rs_elastic.edge_length, obj.rs_elastic.num_modes = 0.08, 5
    obj.rs_elastic.material_model = 'STVK'
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    stats = ext.bridge.stage_cache.stats
    assert stats["energy"] == 1                        # trained by Prepare ...
    blend = tmp_path / "stvk.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))   # (its file moves next to the .blend)
    folder = tmp_path / "blendcache_stvk"
    assert len(energy_files(folder)) == 1
    trained = simulate_frames(ext, obj)
    assert stats["energy"] == 1                        # ... so Simulate did not train it
    potential, poses = fresh_poses(ext, obj)
    assert same_quadrature(potential, trained) and len(trained.tets) > 0
    bpy.ops.wm.save_mainfile()

    out = tmp_path / "child.npz"
    script = SIMULATE_SCRIPT.format(tools=str(ROOT / "tools"), user_dir=USER_DIR, blend=str(blend),
                                    out=str(out))
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=300)
    line = [l for l in run.stdout.splitlines() if l.startswith("RESULT ")]
    assert line, run.stdout + run.stderr
    child = json.loads(line[0][7:])
    assert child["result"] == ["FINISHED"]
    assert child["stats"].get("energy", 0) == 0 and child["stats"]["energy_cache_hits"] == 1
    loaded = np.load(out)
    for name in ("tets", "weights", "strain_modes"):   # bit for bit what Prepare trained
        np.testing.assert_array_equal(loaded[name], getattr(trained, name))
    np.testing.assert_array_equal(loaded["poses"], poses)   # and the same bake, exactly


def test_simulate_trains_a_cubature_per_material_and_prune_keeps_the_current_ones(ext):
    obj = prepare_bar(ext)                             # Linear: no cubature, no file
    stats, folder = ext.bridge.stage_cache.stats, ext.bridge.stage_cache.cache_dirs()[0]
    simulate_frames(ext, obj)
    assert stats["energy"] == 0 and energy_files(folder) == []
    assert ext.bridge.bodies.energy_ready(obj) is None
    obj.rs_elastic.material_model = 'STVK'              # changed since Prepare: Simulate trains
    assert ext.bridge.bodies.energy_ready(obj) is False   # what the Simulation panel says
    stvk = simulate_frames(ext, obj)
    assert stats["energy"] == 1 and len(energy_files(folder)) == 1
    assert ext.bridge.bodies.energy_ready(obj) is True
    assert ext.panels.simulate.energy_label(obj) == "Energy cubature: cached with the body"
    obj.rs_elastic.fung_stiffening = 25.0               # StVK does not read it: reused
    assert same_quadrature(simulate_frames(ext, obj), stvk) and stats["energy"] == 1
    obj.rs_elastic.material_model = 'FUNG'              # another material: a second file
    fung = simulate_frames(ext, obj)
    assert stats["energy"] == 2 and len(energy_files(folder)) == 2
    assert isinstance(fung.material, ext.solver.materials.Fung)
    obj.rs_elastic.fung_stiffening = 5.0                # Fung does: a third one
    simulate_frames(ext, obj)
    assert stats["energy"] == 3 and len(energy_files(folder)) == 3
    # A new session: all three are loaded, none trained.
    ext.bridge.stage_cache._MEMORY.clear()
    ext.bridge.prepared._BODIES.clear()
    assert ext.bridge.bodies.energy_ready(obj) is True     # from its file
    for kind, stiffening in (('STVK', 5.0), ('FUNG', 25.0), ('FUNG', 5.0)):
        obj.rs_elastic.material_model, obj.rs_elastic.fung_stiffening = kind, stiffening
        simulate_frames(ext, obj)
    assert stats["energy"] == 3 and stats["energy_cache_hits"] == 3
    # Preparing the same body again keeps them; a new preparation drops them.
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert stats["energy"] == 3 and len(energy_files(folder)) == 3
    obj.rs_elastic.poisson_ratio = 0.3
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert stats["energy"] == 4 and len(energy_files(folder)) == 1


@pytest.mark.parametrize("setting, factors", [("youngs_modulus", (3.0, 0.5)),
                                              ("density", (2.0, 4.0))])
def test_a_change_of_youngs_modulus_or_density_reuses_the_energy_cubature(ext, setting, factors):
    """The energy cubature is trained at 1 Pa in the modes at 1 kg/m³: a Fung body given another
    Young's modulus or density trains nothing (in this session, nor in a new one reading the
    file), and simulates with its material at the new values: the energy of one displacement
    (z times sqrt(rho' / rho) is one pose) is E' / E times what it was, and the exact all-tet
    energy of that material within the fit."""
    obj = make_bar()
    settings = obj.rs_elastic
    settings.edge_length, settings.num_modes, settings.material_model = 0.08, 5, 'FUNG'
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    stats, folder = ext.bridge.stage_cache.stats, ext.bridge.stage_cache.cache_dirs()[0]
    trained = simulate_frames(ext, obj)
    assert stats["energy"] == 1 and len(energy_files(folder)) == 1
    z = 0.3 / np.sqrt(ext.bridge.prepared.for_object(obj).linear_modes.eigenvalues)
    youngs, density, prepared = settings.youngs_modulus, settings.density, getattr(settings, setting)
    for factor, new_session in zip(factors, (False, True)):
        setattr(settings, setting, factor * prepared)
        if new_session:
            ext.bridge.stage_cache._MEMORY.clear()
            ext.bridge.prepared._BODIES.clear()
        assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
        assert (stats["modes"], stats["reduced"]) == (1, 1)
        potential = simulate_frames(ext, obj)
        assert stats["energy"] == 1 and len(energy_files(folder)) == 1
        np.testing.assert_array_equal(potential.tets, trained.tets)
        np.testing.assert_array_equal(potential.weights, trained.weights)
        pose = np.sqrt(settings.density / density) * z
        np.testing.assert_allclose(potential.energy(pose),
                                   settings.youngs_modulus / youngs * trained.energy(z), rtol=1e-6)
        body = ext.bridge.prepared.for_object(obj)
        exact = ext.solver.materials.ReducedPotential.exact(
            body.material('FUNG', settings.youngs_modulus, settings.poisson_ratio,
                          settings.fung_stiffening), body.modal_rs, body.volumes)
        np.testing.assert_allclose(potential.energy(pose), exact.energy(pose), rtol=1e-2)
    assert stats["energy_cache_hits"] == 1                        # the new session read it


def _garbage(path, arrays):
    path.write_bytes(b"PK\x03\x04 not really a zip")
    return " is unreadable ("


def _negative_weight(path, arrays):
    arrays["weights"][0] = -arrays["weights"][0]
    return " is inconsistent (negative tet index or weight)"


def _wrong_shape(path, arrays):
    arrays["strain_modes"] = arrays["strain_modes"][:, :5]
    return ": array 'strain_modes' has shape"


@pytest.mark.parametrize("damage", [_garbage, _negative_weight, _wrong_shape],
                         ids=["garbage", "negative_weight", "wrong_shape"])
def test_a_damaged_energy_file_is_rebuilt_with_one_warning(ext, capfd, damage):
    obj = make_bar()
    obj.rs_elastic.edge_length, obj.rs_elastic.num_modes = 0.08, 5
    obj.rs_elastic.material_model = 'STVK'
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    stage_cache = ext.bridge.stage_cache
    (name,) = energy_files(stage_cache.cache_dirs()[0])
    path = pathlib.Path(stage_cache.cache_dirs()[0]) / name
    key = json.loads(obj.rs_elastic[stage_cache.ENERGY_RECORD])["keys"][0]
    trained = ext.solver.cache.load(str(path), key)
    _, poses = fresh_poses(ext, obj)
    arrays = {name: a.copy() for name, a in trained.items()}
    problem = damage(path, arrays)
    if problem.startswith(" is inconsistent") or problem.startswith(":"):
        ext.solver.cache.save(str(path), key, arrays)
    stage_cache._MEMORY.clear()
    capfd.readouterr()
    rebuilt = simulate_frames(ext, obj)
    warnings = [line for line in capfd.readouterr().out.splitlines()
                if line.startswith("Warning: ")]
    assert len(warnings) == 1 and problem in warnings[0] and str(path) in warnings[0]
    assert warnings[0].endswith("; rebuilding it")
    assert stage_cache.stats["energy"] == 2 and stage_cache.stats["energy_cache_hits"] == 0
    moved = dict(trained, strain_modes=trained["strain_modes"]   # to the body's density
                 * ext.bridge.prepared.for_object(obj).mode_scale)
    for name in ("tets", "weights", "strain_modes"):   # trained again, to the same bits
        np.testing.assert_array_equal(getattr(rebuilt, name), moved[name])
        np.testing.assert_array_equal(ext.solver.cache.load(str(path), key)[name], trained[name])
    np.testing.assert_array_equal(fresh_poses(ext, obj)[1], poses)


def test_esc_cancels_the_energy_training_and_writes_nothing(ext):
    obj = prepare_bar(ext)
    obj.rs_elastic.material_model = 'FUNG'
    work = ext.bridge.simulation_inputs.energy_work(obj)
    assert work is not None
    job = ext.bridge.jobs.Job(work)
    job.start()
    deadline = time.monotonic() + 60
    while "energy cubature" not in job.message and not job.done and time.monotonic() < deadline:
        time.sleep(0.005)
    assert job.message.startswith("Fung energy cubature")
    job.cancel()
    while not job.done:
        time.sleep(0.01)
    assert isinstance(job.error, ext.bridge.jobs.Cancelled)
    assert energy_files(ext.bridge.stage_cache.cache_dirs()[0]) == []
    assert ext.bridge.simulation_inputs.energy_work(obj) is not None     # still to be trained


def test_duplicates_with_other_youngs_moduli_share_the_stages_not_the_body(ext):
    """A prepared object duplicated (Shift+D: its mesh copied, its tet mesh kept with it) and
    given another Young's modulus: its Prepare computes nothing, and each object's body has its
    own eigenvalues (the in-memory bodies are not mixed up although their prepared keys are
    the same)."""
    obj = prepare_bar(ext)
    twin = obj.copy()
    twin.data = obj.data.copy()
    bpy.context.scene.collection.objects.link(twin)
    twin.rs_elastic.youngs_modulus = 9.0 * obj.rs_elastic.youngs_modulus
    bpy.context.view_layer.objects.active = twin
    stats = ext.bridge.stage_cache.stats
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert (stats["tetrahedralize"], stats["modes"], stats["reduced"]) == (1, 1, 1)
    assert twin.rs_elastic.prepared_key == obj.rs_elastic.prepared_key
    mine = ext.bridge.prepared.for_object(obj).linear_modes.eigenvalues
    theirs = ext.bridge.prepared.for_object(twin).linear_modes.eigenvalues
    np.testing.assert_allclose(theirs, 9.0 * mine, rtol=1e-6)    # float32 moduli
    np.testing.assert_allclose(twin.rs_elastic.frequencies,
                               3.0 * np.array(obj.rs_elastic.frequencies), rtol=1e-6)
