"""A Flamenco farm on this machine, for the farm tests and the farm bench: the manager and workers
built from source (`make flamenco`, into build/flamenco), each started on 127.0.0.1 in a folder
of its own, and the REST calls that watch their jobs.

    manager = Manager(folder, bin_dir, storage, blender="tools/bpy-blender", job_types=[js])
    manager.start()
    worker = Worker(folder, bin_dir, manager.url, env={...})
    worker.start()
    ...
    job = wait_for_job(manager, job_id, timeout=300)
    worker.stop(); manager.stop()

Every process runs in its own process group, so stopping or killing one ends what it started
(a worker's Blender too). Every wait is bounded and fails with the manager's account of the job
(`job_account`): job and task statuses, activities and the tails of the task logs.
"""
import json
import os
import shutil
import signal
import socket
import subprocess
import time
import urllib.error
import urllib.request


class FarmError(AssertionError):
    """A farm that did not do what was waited for; the message says what the manager says."""


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(predicate, timeout, account, interval=0.25):
    """predicate()'s first true value, polled until `timeout` seconds; FarmError(account()) then."""
    end = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > end:
            raise FarmError(f"gave up after {timeout:.0f} s: {account()}")
        time.sleep(interval)


class _Process:
    """A program started in its own process group, its output in folder/<name>.log."""

    def __init__(self, folder, name):
        self.folder, self.name, self.process = folder, name, None

    @property
    def log_path(self):
        return os.path.join(self.folder, f"{self.name}.log")

    def _launch(self, argv, env=None):
        log = open(self.log_path, "ab")
        try:
            self.process = subprocess.Popen(argv, cwd=self.folder, stdout=log,
                                            stderr=subprocess.STDOUT, start_new_session=True,
                                            env=None if env is None else {**os.environ, **env})
        finally:
            log.close()

    def running(self):
        return self.process is not None and self.process.poll() is None

    def _signal_group(self, signum):
        try:
            os.killpg(self.process.pid, signum)
        except ProcessLookupError:
            pass

    def kill(self):
        """SIGKILL the whole process group at once (a crash), and reap it."""
        if self.process is None:
            return
        self._signal_group(signal.SIGKILL)
        self.process.wait(timeout=30)

    def stop(self, grace=15.0):
        """SIGTERM the group, then SIGKILL what is left after `grace` seconds."""
        if self.process is None:
            return
        if self.process.poll() is None:
            self._signal_group(signal.SIGTERM)
            try:
                self.process.wait(timeout=grace)
            except subprocess.TimeoutExpired:
                pass
        self._signal_group(signal.SIGKILL)      # anything the program left behind in its group
        self.process.wait(timeout=30)

    def log_tail(self, lines=20):
        try:
            with open(self.log_path, errors="replace") as f:
                return "".join(f.readlines()[-lines:])
        except OSError:
            return ""


def _place_binary(source, folder):
    """The program inside `folder` (hard-linked, else copied): the manager looks for job types in
    a `scripts` folder beside its own executable."""
    target = os.path.join(folder, os.path.basename(source))
    try:
        os.link(source, target)
    except OSError:
        shutil.copy2(source, target)
    return target


class Manager(_Process):
    """Flamenco Manager on 127.0.0.1 with a SQLite database and the shared storage `storage`;
    `blender` is what its `blender` variable names (the workers' Blender), `job_types` the .js
    files put in its scripts folder (more can be written there later)."""

    def __init__(self, folder, bin_dir, storage, blender, job_types=(), blender_args="-b -y"):
        super().__init__(folder, "manager")
        self.bin_dir, self.storage, self.blender = bin_dir, storage, blender
        self.blender_args, self.job_types = blender_args, list(job_types)
        self.port = None

    @property
    def url(self):
        return f"http://127.0.0.1:{self.port}"

    @property
    def scripts(self):
        return os.path.join(self.folder, "scripts")

    def _config(self):
        return "\n".join([
            "_meta:", "  version: 3",
            "manager_name: RS Elastic farm test",
            "database: flamenco-manager.sqlite",
            f"listen: 127.0.0.1:{self.port}",
            "autodiscoverable: false",
            "local_manager_storage_path: ./manager-storage",
            f"shared_storage_path: {json.dumps(self.storage)}",
            "shaman:", "  enabled: false",
            "task_timeout: 10m", "worker_timeout: 1m",
            "variables:",
            "  blender:", "    values:",
            "    - platform: all", f"      value: {json.dumps(self.blender)}",
            "  blenderArgs:", "    values:",
            "    - platform: all", f"      value: {json.dumps(self.blender_args)}",
            ""])

    def start(self, timeout=60):
        os.makedirs(self.scripts, exist_ok=True)
        os.makedirs(self.storage, exist_ok=True)
        for path in self.job_types:
            shutil.copyfile(path, os.path.join(self.scripts, os.path.basename(path)))
        program = _place_binary(os.path.join(self.bin_dir, "flamenco-manager"), self.folder)
        self.port = free_port()
        with open(os.path.join(self.folder, "flamenco-manager.yaml"), "w") as f:
            f.write(self._config())
        self._launch([program])
        wait_until(lambda: self._answers(), timeout,
                   lambda: f"the manager did not answer on {self.url}:\n{self.log_tail()}")

    def _answers(self):
        if not self.running():
            raise FarmError(f"the manager exited ({self.process.returncode}):\n{self.log_tail()}")
        try:
            return self.get("/api/v3/version")
        except (OSError, urllib.error.URLError):
            return None

    def request(self, method, path, body=None, raw=False, timeout=30):
        data = None if body is None else json.dumps(body).encode()
        request = urllib.request.Request(self.url + path, data=data, method=method,
                                         headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(request, timeout=timeout) as response:
            text = response.read().decode(errors="replace")
        if raw:
            return text
        return json.loads(text) if text.strip() else None

    def get(self, path, **kwargs):
        return self.request("GET", path, **kwargs)


class Worker(_Process):
    """A Flamenco Worker of `manager_url` in `folder` (its credentials too, so a worker started
    again in the same folder is the same worker), running blender tasks with `env` added."""

    def __init__(self, folder, bin_dir, manager_url, env=None, name="worker"):
        super().__init__(folder, name)
        self.bin_dir, self.manager_url, self.env = bin_dir, manager_url, dict(env or {})

    def start(self):
        os.makedirs(self.folder, exist_ok=True)
        with open(os.path.join(self.folder, "flamenco-worker.yaml"), "w") as f:
            f.write(f"manager_url: {self.manager_url}/\n"
                    "task_types: [blender, file-management, misc]\n")
        program = os.path.join(self.bin_dir, "flamenco-worker")
        self._launch([program, "-manager", self.manager_url + "/"],
                     env={"FLAMENCO_HOME": os.path.join(self.folder, "home"), **self.env})


# --- jobs -------------------------------------------------------------------------------------

def job_by_name(manager, name):
    jobs = [job for job in manager.get("/api/v3/jobs")["jobs"] if job["name"] == name]
    return max(jobs, key=lambda job: job["created"]) if jobs else None


def tasks(manager, job_id):
    """{task name: task summary} of a job."""
    return {task["name"]: task
            for task in manager.get(f"/api/v3/jobs/{job_id}/tasks")["tasks"]}


def task_log(manager, task_id):
    """The task's whole log (as the workers sent it so far), or ""."""
    info = manager.get(f"/api/v3/tasks/{task_id}/log")
    if not info:
        return ""
    return manager.get(info["url"] if info["url"].startswith("/") else "/" + info["url"],
                       raw=True)


def job_account(manager, job_id, log_lines=12):
    """What the manager says of a job: its status and activity, then each task's status,
    activity and the tail of its log."""
    try:
        job = manager.get(f"/api/v3/jobs/{job_id}")
        lines = [f"job '{job['name']}' {job['status']}: {job.get('activity', '')}"]
        for name, task in sorted(tasks(manager, job_id).items()):
            full = manager.get(f"/api/v3/tasks/{task['id']}")
            lines.append(f"  task '{name}' {task['status']}: {full.get('activity', '')}")
            tail = task_log(manager, task["id"]).strip().splitlines()[-log_lines:]
            lines += [f"    | {line}" for line in tail]
        return "\n".join(lines)
    except (OSError, urllib.error.URLError, KeyError, ValueError) as exc:
        return f"the manager gave no account of job {job_id}: {exc}"


def wait_for_job(manager, job_id, statuses=("completed", "failed", "canceled"), timeout=600):
    """The job once its status is one of `statuses` (FarmError after `timeout` s)."""
    def settled():
        job = manager.get(f"/api/v3/jobs/{job_id}")
        return job if job["status"] in statuses else None
    return wait_until(settled, timeout, lambda: job_account(manager, job_id))


def wait_for_task(manager, job_id, name, statuses, timeout=300):
    """The task summary once task `name` has one of `statuses`."""
    def reached():
        task = tasks(manager, job_id).get(name)
        return task if task is not None and task["status"] in statuses else None
    return wait_until(reached, timeout, lambda: job_account(manager, job_id), interval=0.1)


# --- the artist's side: the Flamenco add-on in this Blender (bpy) ---------------------------------

def enable_flamenco_addon(flamenco_src):
    """Install the Flamenco add-on of the Flamenco source `flamenco_src` into this Blender's user
    scripts and enable it (call after blender_session.start)."""
    import addon_utils
    import bpy
    addons = bpy.utils.user_resource('SCRIPTS', path="addons", create=True)
    shutil.copytree(os.path.join(flamenco_src, "addon", "flamenco"),
                    os.path.join(addons, "flamenco"), dirs_exist_ok=True)
    bpy.utils.refresh_script_paths()
    if addon_utils.enable("flamenco", default_set=True) is None:
        raise FarmError(f"the Flamenco add-on in {flamenco_src} did not enable")


def submit_with_addon(manager, blend, job_name, job_type, settings=None, paused=False):
    """Submit the saved shot `blend` (inside the shared storage) as the Flamenco add-on's Submit
    button does for such a file, with the add-on's own code: the manager pinged (job types), the
    scene's Flamenco settings, the file saved, the job built from the scene, its hidden settings
    evaluated in this Blender (the job type's `eval`), the file's path, the manager's check, the
    submission. Returns the manager's job.

    Not the operator itself: called from Python (its execute path), the 3.9-beta1 add-on submits
    a file inside the shared storage twice (in _use_blendfile_directly, then again in
    bat_v2_packer_finalize_and_quit); its Submit button (invoke) submits it once, as here."""
    import bpy
    from flamenco import comms, job_submission
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    bpy.context.preferences.addons["flamenco"].preferences.manager_url = manager.url + "/"
    if bpy.ops.flamenco.ping_manager() != {'FINISHED'}:
        raise FarmError(f"the add-on could not reach {manager.url}")
    scene = bpy.context.scene
    scene.flamenco_job_type = job_type
    scene.flamenco_job_name = job_name
    scene.flamenco_job_submit_as_paused = paused
    for key, value in (settings or {}).items():
        setattr(scene.flamenco_job_settings, key, value)
    bpy.ops.wm.save_mainfile()
    if not job_submission.is_file_inside_job_storage(bpy.context, blend):
        raise FarmError(f"{blend} is not inside the manager's shared storage")
    client = comms.flamenco_api_client(manager.url + "/")
    job = job_submission.job_for_scene(scene)
    propgroup = scene.flamenco_job_settings
    propgroup.eval_hidden_settings_of_job(bpy.context, job)
    job_submission.set_blend_file(propgroup.job_type, job, str(blend))
    job_submission.submit_job_check(job, client)
    job_submission.submit_job(job, client)
    found = job_by_name(manager, job_name)
    if found is None:
        raise FarmError(f"no job '{job_name}' on the manager after submitting it")
    return found
