"""Reduced RS in the installed extension: preview, cache stage, cancellation."""
import time

import numpy as np
import bpy

from blender_helpers import diagonal, make_bar, preview_pose, vertices


def test_reduced_preview_matches_full_rs_at_large_amplitude(ext):
    obj = make_bar(cuts=3)
    settings = obj.rs_elastic
    settings.edge_length, settings.num_modes = 0.08, 6
    settings.basis_size, settings.cubature_tets, settings.training_poses = 0, 150, 80
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert settings.reduced_basis_count > settings.num_modes and settings.cubature_count > 0
    rest = vertices(obj)
    for mode, amplitude in ((1, 0.3), (2, -0.3), (3, 0.2)):
        settings.preview_mode = mode
        full, reduced = preview_pose(obj, 'RS', amplitude), preview_pose(obj, 'REDUCED', amplitude)
        error = np.linalg.norm(full - reduced, axis=1).max() / diagonal(rest)
        print(f"mode {mode}: reduced vs full RS {error:.2e} of the diagonal")
        assert error < 0.01
        assert np.abs(full - rest).max() > 0.1        # a large pose, not a trivial one
        pinned = rest[:, 0] < 1e-9
        assert np.abs(reduced[pinned] - rest[pinned]).max() < 1e-6    # the pins hold


def test_cancelling_a_preparation_keeps_the_previous_cache_usable(ext):
    obj = make_bar(cuts=3)
    obj.rs_elastic.edge_length, obj.rs_elastic.num_modes = 0.08, 5
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    keys = (obj.rs_elastic.tets_key, obj.rs_elastic.prepared_key, obj.rs_elastic.reduced_key)
    frequencies = obj.rs_elastic.frequencies
    # A new material, prepared on a worker thread as the UI does, cancelled during the
    # reduced stage (the same Job the modal operator runs; Esc calls job.cancel()).
    obj.rs_elastic.poisson_ratio = 0.3          # (Young's modulus or density reuse the stages)
    bodies, jobs = ext.bridge.bodies, ext.bridge.jobs
    inputs = bodies.read_inputs(obj, bpy.context.evaluated_depsgraph_get())
    ext.bridge.stage_cache._MEMORY.clear()
    job = jobs.Job(lambda j: bodies.prepare(inputs, j))
    job.start()
    deadline = time.monotonic() + 120
    while not job.message.startswith("Reduced RS") and time.monotonic() < deadline:
        time.sleep(0.01)
    job.cancel()
    while not job.done:
        time.sleep(0.01)
    assert isinstance(job.error, jobs.Cancelled)
    assert (obj.rs_elastic.tets_key, obj.rs_elastic.prepared_key, obj.rs_elastic.reduced_key) == keys
    assert obj.rs_elastic.frequencies == frequencies
    obj.rs_elastic.poisson_ratio = 0.45       # back to what was prepared (else it is stale)
    ext.bridge.stage_cache._MEMORY.clear()
    body = bodies.load_prepared(obj)          # from the old files on disk
    assert body is not None and body.deformer is not None
    assert body.deformer.num_coords == 5
