"""The farm end to end: Flamenco's manager and a worker, built from source, bake shots submitted
through the Flamenco add-on with the rs-elastic-bake job type (farm/rs_elastic_bake.js, written
into the manager's scripts folder by the extension's operator). The worker's Blender is
tools/bpy-blender, and so is the command line the bakes are compared with: the same bakes run one
after another on a copy of the same file. Bakes are compared as float64 poses (recorded by
tools/bpy-blender for its `bake` commands) to 1e-10 of each body's diagonal, and each bake the
collected shot plays (a .pc2, or shape keys) holds exactly the farm's poses in float32. Each
body's file is the one its job named at submission (the plan's `bake_file`).

Every wait is bounded and fails with the manager's account of the job; the manager and the
worker are stopped (their process groups killed) on every way out."""
import json
import os
import pathlib
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest

import bpy
import farm_shot
import flamenco_farm
from conftest import EXTENSION, FLAMENCO_BIN, ROOT, USER_DIR

BLENDER = ROOT / "tools" / "bpy-blender"
JOB_TYPE = "rs-elastic-bake"
PLAN = [("Slab", "simulate", []), ("Drop", "simulate", ["Slab"]), ("Whip", "spacetime", ["Slab"])]
JOB_TIMEOUT = 420           # seconds for a whole job on one worker
TOLERANCE = 1e-10           # of a body's diagonal
# BLAS on one thread in the worker's Blender and the command line's alike: a product's rounding
# depends on how many threads split it (Whip's command-line bake moved by 7e-11 of its diagonal
# between one and two BLAS threads), so both sides use the same count.
BLAS_THREADS = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}


class Farm:
    def __init__(self, root):
        self.root = root
        self.storage = root / "storage"
        self.poses = root / "farm_poses"
        self.poses.mkdir(parents=True)
        self.manager = flamenco_farm.Manager(str(root / "manager"), str(FLAMENCO_BIN),
                                             str(self.storage), str(BLENDER))
        self.worker = flamenco_farm.Worker(
            str(root / "worker"), str(FLAMENCO_BIN), None,
            env={"BLENDER_USER_RESOURCES": USER_DIR, "RS_ELASTIC_RECORD_POSES": str(self.poses),
                 "RS_ELASTIC_BPY_PYTHON": sys.executable, **BLAS_THREADS})

    def account(self, job):
        return flamenco_farm.job_account(self.manager, job["id"])


@pytest.fixture(scope="module")
def farm(tmp_path_factory):
    """A manager (its job type written by the extension's operator) and a worker that the tests
    start when their job is queued; both stopped whatever happens."""
    farm = Farm(tmp_path_factory.mktemp("farm"))
    try:
        farm.manager.start()
        farm.worker.manager_url = farm.manager.url
        # The operator, given the manager's folder, writes into the scripts folder beside it.
        assert bpy.ops.rs_elastic.write_farm_job_type(directory=farm.manager.folder) == {'FINISHED'}
        assert (pathlib.Path(farm.manager.scripts) / "rs_elastic_bake.js").is_file()
        yield farm
    finally:
        farm.worker.stop()
        farm.manager.stop()


def submit(farm, blend, job_name, steps="prepare and bake", paused=False):
    """Submit through the Flamenco add-on's own submission code (flamenco_farm.submit_with_addon),
    which evaluates the job type's settings in this Blender."""
    return flamenco_farm.submit_with_addon(farm.manager, blend, job_name, JOB_TYPE,
                                           settings={"steps": steps}, paused=paused)


def save_shot(path):
    path.parent.mkdir(parents=True, exist_ok=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    return path


def cli_bake(blend, body, mode, poses):
    """The command line on `blend`, as an artist runs it (saving the file)."""
    poses.mkdir(parents=True, exist_ok=True)
    out = subprocess.run(
        [str(BLENDER), "-b", "-y", str(blend), "-c", "rs_elastic", "bake", "--object", body,
         "--mode", mode, "--bake-to", "cache"],
        capture_output=True, text=True, timeout=300, cwd=blend.parent,
        env={**os.environ, "BLENDER_USER_RESOURCES": USER_DIR,
             "RS_ELASTIC_RECORD_POSES": str(poses), "RS_ELASTIC_BPY_PYTHON": sys.executable,
             **BLAS_THREADS})
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]


def bake_files(job):
    """{body: the bake file name its job named} from the plan the add-on evaluated."""
    return {body["name"]: body["bake_file"]
            for body in json.loads(job["settings"]["bodies"])["bodies"]}


def bakes_folder(blend):
    return blend.parent / f"blendcache_{blend.stem}" / "bakes"


def poses(folder, blend, body):
    return np.load(folder / f"{blend.stem}.{body}.npy")


def diagonal(pose):
    return float(np.linalg.norm(pose.max(axis=0) - pose.min(axis=0)))


def assert_same_bake(farm_poses, local_poses, name):
    size = diagonal(local_poses[0])
    bound = TOLERANCE * size
    difference = float(np.abs(farm_poses - local_poses).max())
    print(f"{name}: farm against command line {difference:.3g} m = {difference / size:.3g} of "
          f"its diagonal (bound {bound:.3g} m)")
    assert farm_poses.shape == local_poses.shape
    assert difference <= bound


def assert_pc2_holds(path, recorded):
    """The .pc2 is exactly the recorded float64 poses in float32."""
    baked, _ = EXTENSION.bridge.mesh_cache.read_pc2(str(path))
    np.testing.assert_array_equal(baked, recorded.astype(np.float32))


def assert_keys_hold(obj, frames, recorded):
    """The shape-key bake is exactly the recorded float64 poses in float32."""
    blocks = obj.data.shape_keys.key_blocks
    for frame, pose in zip(frames, recorded):
        co = np.empty(len(obj.data.vertices) * 3, dtype=np.float32)
        blocks[EXTENSION.bridge.bake.bake_key_name(frame)].data.foreach_get("co", co)
        np.testing.assert_array_equal(co.reshape(-1, 3), pose.astype(np.float32))


def task_args(farm, task):
    full = farm.manager.get(f"/api/v3/tasks/{task['id']}")
    (command,) = full["commands"]
    assert command["name"] == "blender-render"
    return command["parameters"]


def blender_processes(blend):
    """PIDs of tools/bpy-blender processes working on `blend`."""
    found = []
    for entry in pathlib.Path("/proc").iterdir():
        try:
            argv = (entry / "cmdline").read_bytes().split(b"\0")
        except (OSError, ValueError):
            continue
        if any(a.endswith(b"bpy_blender.py") for a in argv) and str(blend).encode() in argv:
            found.append(int(entry.name))
    return found


def test_the_job_type_turns_the_plan_into_tasks(farm, tmp_path):
    """Submitted paused, nothing runs: the tasks of each Steps choice, their command lines and
    their order, and a shot whose bodies need each other's bakes is refused at submission."""
    farm_shot.build(bpy)
    blend = save_shot(farm.storage / "plans" / "plan.blend")
    expected_order = [name for name, _, _ in PLAN]
    for steps, verb, only in (("prepare and bake", "bake", []),
                              ("bake only", "bake", ["--only", "bake"]),
                              ("prepare only", "prepare", ["--only", "prepare"])):
        job = submit(farm, blend, f"plan {steps}", steps=steps, paused=True)
        assert job["settings"]["blendfile"] == str(blend)
        files = bake_files(job)
        for name, file_name in files.items():
            assert EXTENSION.bridge.mesh_cache.identity_of(bpy.data.objects[name], file_name)
        found = flamenco_farm.tasks(farm.manager, job["id"])
        names = [f"{verb} {name}" for name in expected_order]
        assert sorted(found) == sorted(names + (["collect bakes"] if verb == "bake" else []))
        # Priorities fall along the plan, so one worker runs it in this order.
        assert [found[n]["priority"] for n in names] == sorted(
            (found[n]["priority"] for n in names), reverse=True)
        for name, mode, after in PLAN:
            parameters = task_args(farm, found[f"{verb} {name}"])
            assert parameters["blendfile"] == str(blend)
            expected = ["-c", "rs_elastic", "bake", f"--object={name}"] + only
            if verb == "bake":
                expected += ["--mode", mode, "--frames", f"1-{farm_shot.FRAMES}", "--bake-to",
                             "cache", f"--bake-file={files[name]}"] + [
                    f"--with-bake={other}={files[other]}" for other in after]
            assert parameters["args"] == expected + ["--no-save"]
        if verb == "bake":
            assert task_args(farm, found["collect bakes"])["args"] == [
                "-c", "rs_elastic", "collect"] + [f"--bake={n}={files[n]}" for n in expected_order]

    # Drop collides with Slab and Slab with Drop: no order bakes both after the other.
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    bpy.data.objects["Drop"].modifiers.new("Collision", 'COLLISION')
    circle = save_shot(farm.storage / "plans" / "circle.blend")
    from flamenco.manager.exceptions import ApiException
    with pytest.raises(ApiException) as refused:
        submit(farm, circle, "circle")
    assert refused.value.status == 400
    assert ("need each other's bakes in a circle ('Drop' needs 'Slab'; 'Slab' needs 'Drop')"
            in refused.value.body), refused.value.body
    assert flamenco_farm.job_by_name(farm.manager, "circle") is None


def test_a_three_body_shot_bakes_as_on_the_command_line_and_survives_a_killed_worker(farm,
                                                                                    tmp_path):
    farm_shot.build(bpy)
    bpy.data.objects["Slab"].rs_elastic.bake_to = 'CACHE'       # the others keep Shape Keys
    blend = save_shot(farm.storage / "shots" / "alpha.blend")
    job = submit(farm, blend, "alpha")
    files = bake_files(job)
    local = tmp_path / "local" / blend.name
    local.parent.mkdir()
    shutil.copyfile(blend, local)                 # the file as submitted (the add-on saved it)
    untouched = tmp_path / "untouched" / blend.name
    untouched.parent.mkdir()
    shutil.copyfile(blend, untouched)

    started = time.monotonic()
    farm.worker.start()
    try:
        # Kill the worker (and its Blender) in the middle of Drop's task, then start it again:
        # the manager hands the unfinished task back to it, and it bakes Drop from the start.
        # The kill waits for Drop's Blender to run, not for a fixed time: a bake can take less
        # than any fixed wait.
        flamenco_farm.wait_for_task(farm.manager, job["id"], "bake Drop", ("active",),
                                    timeout=JOB_TIMEOUT)
        deadline = time.monotonic() + JOB_TIMEOUT
        while not blender_processes(blend) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert blender_processes(blend), "Drop's task never started Blender"
        assert flamenco_farm.tasks(farm.manager, job["id"])["bake Drop"]["status"] == "active"
        assert not (bakes_folder(blend) / files["Drop"]).exists()
        farm.worker.kill()
        assert blender_processes(blend) == []
        farm.worker.start()
        done = flamenco_farm.wait_for_job(farm.manager, job["id"], timeout=JOB_TIMEOUT)
    finally:
        farm.worker.stop()
    farm_seconds = time.monotonic() - started
    assert done["status"] == "completed", farm.account(job)
    found = flamenco_farm.tasks(farm.manager, job["id"])
    drop_log = flamenco_farm.task_log(farm.manager, found["bake Drop"]["id"])
    assert drop_log.count("Task assigned to worker") == 2, drop_log
    print(f"farm: {farm_seconds:.1f} s from the worker's start to the job's end, one kill")

    # The same bakes on the command line, one after another, each saving the file.
    reference = tmp_path / "local_poses"
    for name, mode, _ in PLAN:
        cli_bake(local, name, mode, reference)
    for name, _, _ in PLAN:
        assert_same_bake(poses(farm.poses, blend, name), poses(reference, local, name), name)

    # The dependencies mattered: without Slab's bake, Drop lands elsewhere and Whip stays put.
    cli_bake(untouched, "Drop", "simulate", tmp_path / "untouched_poses")
    drop, alone = poses(farm.poses, blend, "Drop"), poses(tmp_path / "untouched_poses",
                                                          untouched, "Drop")
    assert np.abs(drop - alone).max() > 0.05 * diagonal(drop[0])
    whip = poses(farm.poses, blend, "Whip")
    assert np.abs(whip - whip[0]).max() > 0.05 * diagonal(whip[0])

    # The collected shot plays every bake: Slab's Mesh Cache (the file its job named, played by
    # its bake modifier and recorded), Drop's and Whip's shape keys; nothing plays the farm's
    # files of those two any more, so they went once the shot was saved.
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    frames = list(range(1, farm_shot.FRAMES + 1))
    for name, _, _ in PLAN:
        obj, recorded = bpy.data.objects[name], poses(farm.poses, blend, name)
        assert EXTENSION.bridge.bake.bake_frames(obj) == frames, name
        assert EXTENSION.bridge.farm.playback_error(
            obj, bpy.context.scene, frames, recorded.astype(np.float32)) <= 1e-6, name
    slab = bpy.data.objects["Slab"]
    slab_pc2 = bakes_folder(blend) / files["Slab"]
    assert EXTENSION.bridge.mesh_cache.owned_modifier(slab) == slab.modifiers[0]
    assert EXTENSION.bridge.mesh_cache.bake_file(slab) == str(slab_pc2)
    assert os.path.normpath(bpy.path.abspath(slab.rs_elastic.cache_bake_file)) == str(slab_pc2)
    assert_pc2_holds(slab_pc2, poses(farm.poses, blend, "Slab"))
    for name in ("Drop", "Whip"):
        assert_keys_hold(bpy.data.objects[name], frames, poses(farm.poses, blend, name))
    assert sorted(p.name for p in bakes_folder(blend).iterdir()) == [files["Slab"]]


def test_a_failing_body_fails_its_task_with_its_reason_and_the_other_bakes_stand(farm,
                                                                                tmp_path):
    farm_shot.build(bpy)
    for name in ("Drop", "Whip", "Whip Handle"):
        bpy.data.objects.remove(bpy.data.objects[name])
    wreck = farm_shot.add_broken_body(bpy)                          # "Wreck", baked after Slab
    blend = save_shot(farm.storage / "shots" / "beta.blend")
    # An earlier Mesh Cache bake of Wreck, which the shot plays and the failing task must leave.
    wreck.rs_elastic.bake_to = 'CACHE'
    vertices = len(wreck.data.vertices)
    earlier = pathlib.Path(EXTENSION.bridge.mesh_cache.write(wreck, [1, 2, 3],
                                                             np.full((3, vertices, 3), 0.25)))
    bpy.ops.wm.save_mainfile()
    earlier_bytes = earlier.read_bytes()
    job = submit(farm, blend, "beta")
    files = bake_files(job)
    submitted = blend.read_bytes()
    local = tmp_path / "local" / blend.name
    local.parent.mkdir()
    shutil.copyfile(blend, local)

    farm.worker.start()
    try:
        done = flamenco_farm.wait_for_job(farm.manager, job["id"], timeout=JOB_TIMEOUT)
    finally:
        farm.worker.stop()
    assert done["status"] == "failed", farm.account(job)
    found = flamenco_farm.tasks(farm.manager, job["id"])
    statuses = {name: task["status"] for name, task in found.items()}
    assert statuses == {"bake Slab": "completed", "bake Wreck": "failed",
                        "collect bakes": "canceled"}, farm.account(job)
    log = flamenco_farm.task_log(farm.manager, found["bake Wreck"]["id"])
    assert "rs_elastic: error: Pin group 'Pin' does not exist on 'Wreck'" in log, log

    assert earlier.read_bytes() == earlier_bytes                      # left as it was
    assert sorted(p.name for p in earlier.parent.iterdir()) == sorted([files["Slab"],
                                                                       earlier.name])
    assert blend.read_bytes() == submitted                           # never collected
    cli_bake(local, "Slab", "simulate", tmp_path / "local_poses")
    assert_same_bake(poses(farm.poses, blend, "Slab"), poses(tmp_path / "local_poses", local,
                                                             "Slab"), "Slab")
    assert_pc2_holds(bakes_folder(blend) / files["Slab"], poses(farm.poses, blend, "Slab"))
