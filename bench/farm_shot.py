"""The farm's overhead (issue 29): the three-body shot of tools/farm_shot.py baked by a Flamenco
manager and one worker (built from source by `make flamenco`), against the same three bakes run
one after another on the command line. Prints one JSON line. Run by run_bench.py in its own
process.

    python bench/farm_shot.py ZIP FLAMENCO_SRC FLAMENCO_BIN

The worker is awake and idle when the job is submitted through the Flamenco add-on, as on a farm;
the worker's and the command line's Blender are tools/bpy-blender. Reported, in seconds:
- pickup: from the submission to the first task's start (an idle worker asks for work every 20 s);
- farm: from the first task's start to the job's end (three bake tasks and the collect task,
  each a new Blender, the worker pausing between tasks);
- command line: the three bakes one after another, each a new Blender saving the file;
and each task's time from its start to its end as the manager reports them (polled every 0.1 s).
"""
import json
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

import blender_session  # noqa: E402
import farm_shot  # noqa: E402
import flamenco_farm  # noqa: E402

BLENDER = ROOT / "tools" / "bpy-blender"
PLAN = (("Slab", "simulate"), ("Drop", "simulate"), ("Whip", "spacetime"))
TIMEOUT = 600


def command_line_bakes(blend, env):
    """Seconds of the three bakes run one after another on `blend` (each saves it)."""
    start = time.perf_counter()
    for name, mode in PLAN:
        out = subprocess.run([str(BLENDER), "-b", "-y", str(blend), "-c", "rs_elastic", "bake",
                              "--object", name, "--mode", mode, "--bake-to", "cache"],
                             capture_output=True, text=True, timeout=TIMEOUT, env=env)
        if out.returncode != 0:
            raise RuntimeError(f"command line bake of {name} failed: "
                               + (out.stderr.strip().splitlines() or ["?"])[-1])
    return time.perf_counter() - start


def watch(manager, job_id, started, timeout=TIMEOUT):
    """Poll the job's tasks every 0.1 s until the job ends. Returns (job, {task: (seconds from
    `started` to the task's start, to its end)})."""
    seen, end = {}, time.perf_counter() + timeout
    while True:
        now = time.perf_counter() - started
        for name, task in flamenco_farm.tasks(manager, job_id).items():
            if task["status"] != "queued" and name not in seen:
                seen[name] = [now, None]
            if task["status"] in ("completed", "failed", "canceled") and seen[name][1] is None:
                seen[name][1] = now
        job = manager.get(f"/api/v3/jobs/{job_id}")
        if job["status"] in ("completed", "failed", "canceled"):
            return job, seen
        if time.perf_counter() > end:
            raise RuntimeError(flamenco_farm.job_account(manager, job_id))
        time.sleep(0.1)


def wait_until_awake(manager, timeout=60):
    def awake():
        workers = manager.get("/api/v3/worker-mgt/workers")["workers"]
        return any(worker["status"] == "awake" for worker in workers)
    flamenco_farm.wait_until(awake, timeout, lambda: "no worker became awake")


def main(zip_path, flamenco_src, flamenco_bin):
    blender_session.start(zip_path)
    user_dir = os.environ["BLENDER_USER_RESOURCES"]
    import bpy
    flamenco_farm.enable_flamenco_addon(flamenco_src)
    root = pathlib.Path(tempfile.mkdtemp(prefix="rs_bench_farm_"))
    storage = root / "storage"
    manager = flamenco_farm.Manager(str(root / "manager"), flamenco_bin, str(storage),
                                    str(BLENDER), job_types=[str(ROOT / "farm" /
                                                                 "rs_elastic_bake.js")])
    env = {"BLENDER_USER_RESOURCES": user_dir, "RS_ELASTIC_BPY_PYTHON": sys.executable}
    worker = flamenco_farm.Worker(str(root / "worker"), flamenco_bin, None, env=env)
    try:
        manager.start()
        worker.manager_url = manager.url
        farm_shot.build(bpy)
        (storage / "shots").mkdir(parents=True)
        blend = storage / "shots" / "shot.blend"
        bpy.ops.wm.save_as_mainfile(filepath=str(blend))
        local = root / "local" / blend.name
        local.parent.mkdir()
        shutil.copyfile(blend, local)
        worker.start()
        wait_until_awake(manager)
        submitted = time.perf_counter()
        job = flamenco_farm.submit_with_addon(manager, blend, "bench", "rs-elastic-bake")
        done, seen = watch(manager, job["id"], submitted)
        if done["status"] != "completed":
            raise RuntimeError(flamenco_farm.job_account(manager, job["id"]))
    finally:
        worker.stop()
        manager.stop()
    command_line = command_line_bakes(local, {**os.environ, **env})
    first = min(start for start, _ in seen.values())
    farm = max(end for _, end in seen.values()) - first
    shutil.rmtree(root, ignore_errors=True)
    shutil.rmtree(user_dir, ignore_errors=True)
    return dict(bodies=len(PLAN), frames=farm_shot.FRAMES, pickup_seconds=first,
                farm_seconds=farm, command_line_seconds=command_line,
                overhead_seconds=farm - command_line,
                task_seconds={name: end - start for name, (start, end) in seen.items()})


if __name__ == "__main__":
    row = main(*sys.argv[1:4])
    print(json.dumps(row))
    blender_session.exit_child(0)
