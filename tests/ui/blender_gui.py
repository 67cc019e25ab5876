"""A real, interactive Blender under test: Xvfb and Debian's Blender inside the GUI test root
(tools/ui/build_root.sh), driven from the host.

    gui = BlenderGUI(root, artifacts); gui.start()
    gui.run("result = bpy.app.version_string")     # Python on Blender's main thread
    gui.click(*gui.point("view", 0.5, 0.5)); gui.key("Escape")   # real X input (xdotool)
    gui.screenshot("name"); gui.tracebacks(); gui.stop()

Blender and Xvfb run in a private mount and PID namespace (tools/ui/in_root.sh), so they die
with this process whatever way it ends. The host and Blender share one folder inside the root
(`self.run_dir` here, `self.run_in` inside): the command channel (tests/ui/ui_server.py), the
throw-away Blender user folder, the files a test saves, and Blender's temp folder.
"""
import json
import os
import pathlib
import shutil
import subprocess
import tempfile
import time

HERE = pathlib.Path(__file__).resolve().parent
PROJECT = HERE.parents[1]
IN_ROOT = PROJECT / "tools" / "ui" / "in_root.sh"
TRACEBACK = "Traceback (most recent call last)"


class BlenderError(AssertionError):
    """Code sent to Blender raised; carries Blender's traceback."""


class BlenderGUI:
    def __init__(self, root, artifacts):
        self.root = pathlib.Path(root).resolve()
        self.artifacts = pathlib.Path(artifacts)
        self.artifacts.mkdir(parents=True, exist_ok=True)
        self.log_path = self.artifacts / "blender.log"
        self.shots = self.artifacts      # where screenshot() writes (a test may point it elsewhere)
        self.process = None
        self.display = None
        self.origin = (0, 0)        # the Blender window's top-left corner on the X screen
        self._count = 0
        tmp = self.root / "tmp"
        self.run_dir = pathlib.Path(tempfile.mkdtemp(prefix="rs-ui-", dir=tmp))
        self.run_in = "/" + str(self.run_dir.relative_to(self.root))
        for name in ("channel", "user", "home", "tmp", "files"):
            (self.run_dir / name).mkdir()
        shutil.copy(HERE / "ui_server.py", self.run_dir / "ui_server.py")
        shutil.copy(HERE / "launch.sh", self.run_dir / "launch.sh")

    # --- life ------------------------------------------------------------------------------------
    def start(self, timeout=120.0, hide_numpy=False):
        """Start Xvfb and Blender; return once the command channel answers.

        `hide_numpy`: a package that raises ModuleNotFoundError is mounted over the root's numpy
        for this Blender only (a Blender without numpy, as Debian's package allows)."""
        inside = self.run_in
        env = [f"HOME={inside}/home", f"TMPDIR={inside}/tmp", "PYTHONUNBUFFERED=1",
               f"BLENDER_USER_RESOURCES={inside}/user", f"RS_UI_CHANNEL={inside}/channel"]
        blender = ["-p", "0", "0", "1920", "1080", "--no-window-focus", "-noaudio",
                   "--python", f"{inside}/ui_server.py"]
        command = ["/usr/bin/env", *env, "/bin/sh", f"{inside}/launch.sh", inside, *blender]
        if hide_numpy:
            (self.run_dir / "no_numpy").mkdir()
            (self.run_dir / "no_numpy" / "__init__.py").write_text(
                "raise ModuleNotFoundError(\"No module named 'numpy'\", name='numpy')\n")
            command = ["/bin/sh", "-c", f"mount --bind {inside}/no_numpy "
                       "/usr/lib/python3/dist-packages/numpy && exec \"$@\"", "sh", *command]
        self._log = open(self.log_path, "wb")
        self.process = subprocess.Popen([str(IN_ROOT), str(self.root), *command],
                                        stdout=self._log, stderr=subprocess.STDOUT,
                                        stdin=subprocess.PIPE, start_new_session=True)
        # Never written: launch.sh kills Blender and Xvfb when it closes, i.e. when this
        # process ends, however it ends.
        deadline = time.monotonic() + timeout
        ready = self.run_dir / "channel" / "ready"
        while not ready.exists():
            self._check_alive("while starting")
            if time.monotonic() > deadline:
                raise TimeoutError(f"Blender did not start in {timeout:.0f} s:\n{self.log_tail()}")
            time.sleep(0.2)
        self.display = ":" + (self.run_dir / "display").read_text().strip()
        window = self.xdotool("search", "--sync", "--onlyvisible", "--class", "Blender",
                              "getwindowgeometry", "--shell").stdout
        fields = dict(line.split("=", 1) for line in window.split())
        self.origin = (int(fields["X"]), int(fields["Y"]))
        # Blender draws, and its timers run, once it has had a first input event.
        self.mouse_move(960, 540)
        self.mouse_move(961, 541)
        self.version = self.run("result = bpy.app.version_string", timeout=timeout)
        return self

    def stop(self, timeout=20.0):
        """Quit Blender (through its own quit), then Xvfb; kill the namespace if either hangs.
        Bounded: returns within about `timeout` + 5 s whatever state Blender is in."""
        if self.process is None:
            return
        try:
            if self.process.poll() is None:
                self._send("bpy.app.timers.register(lambda: bpy.ops.wm.quit_blender() and None, "
                           "first_interval=0.1)")
                try:
                    self.process.wait(timeout)
                except subprocess.TimeoutExpired:
                    pass
        finally:
            if self.process.poll() is None:
                os.killpg(self.process.pid, 9)    # the namespace's processes go with it
                self.process.wait(5)
            self.process.stdin.close()
            self._log.close()
            shutil.rmtree(self.run_dir, ignore_errors=True)

    def _check_alive(self, doing):
        if self.process.poll() is not None:
            raise AssertionError(f"Blender exited ({self.process.returncode}) {doing}:\n"
                                 f"{self.log_tail()}")

    # --- the command channel ---------------------------------------------------------------------
    def _send(self, code):
        self._count += 1
        number = f"{self._count:06d}"
        channel = self.run_dir / "channel"
        partial = channel / f"req-{number}.part"
        partial.write_text(json.dumps({"code": code}))
        partial.rename(channel / f"req-{number}.json")
        return channel / f"res-{number}.json"

    def run(self, code, timeout=60.0):
        """Run `code` on Blender's main thread; return what it left in `result` (JSON values).
        Raises BlenderError with Blender's traceback if it raised."""
        answer = self._send(code)
        deadline = time.monotonic() + timeout
        while not answer.exists():
            self._check_alive(f"while running:\n{code}")
            if time.monotonic() > deadline:
                raise TimeoutError(f"no answer from Blender in {timeout:.0f} s to:\n{code}")
            time.sleep(0.02)
        reply = json.loads(answer.read_text())
        answer.unlink()
        if not reply["ok"]:
            raise BlenderError(f"in Blender:\n{code}\n{reply['error']}")
        return reply["result"]

    def wait_for(self, expression, timeout=60.0, interval=0.2, setup=""):
        """Poll a Python expression in Blender until it is true; return its value."""
        deadline = time.monotonic() + timeout
        while True:
            value = self.run(f"{setup}\nresult = {expression}")
            if value:
                return value
            if time.monotonic() > deadline:
                raise TimeoutError(f"{expression} still {value!r} after {timeout:.0f} s")
            time.sleep(interval)

    # --- real input (X events through xdotool) ---------------------------------------------------
    def x_client(self, program, *args, **kwargs):
        """Run an X client of the root (xdotool, import) against Blender's display. It needs no
        mounts: it reaches Xvfb through its socket."""
        return subprocess.run(["chroot", str(self.root), "/usr/bin/env", "-i",
                               "PATH=/usr/bin:/bin", f"DISPLAY={self.display}", program,
                               *map(str, args)], check=True, capture_output=True, timeout=30,
                              **kwargs)

    def xdotool(self, *args):
        result = self.x_client("xdotool", *args, text=True)
        return result

    def screen_xy(self, x, y):
        return round(self.origin[0] + x), round(self.origin[1] + y)

    def mouse_move(self, x, y):
        """Move the pointer to window pixel (x, y)."""
        self.xdotool("mousemove", "--sync", *self.screen_xy(x, y))

    def click(self, x, y, button=1):
        self.mouse_move(x, y)
        self.xdotool("click", button)

    def drag(self, start, end, steps=20, button=1, pause=0.02):
        """Press at `start`, move in `steps` events to `end`, release: what a hand does."""
        self.mouse_move(*start)
        self.xdotool("mousedown", button)
        for i in range(1, steps + 1):
            t = i / steps
            self.mouse_move(start[0] + t * (end[0] - start[0]), start[1] + t * (end[1] - start[1]))
            time.sleep(pause)
        self.xdotool("mouseup", button)

    def key(self, *keys):
        """Press and release each key (xdotool names: Escape, ctrl+z, ctrl+shift+z, ...)."""
        self.xdotool("key", "--delay", "50", *keys)

    def settle(self, seconds=0.3, at=(120, 700)):
        """Let Blender handle events and redraw: two small pointer moves over the viewport
        (Blender redraws on events) `seconds` apart. Panels that changed size take a few redraws
        to move into place."""
        for dx in (0, 1):
            self.mouse_move(at[0] + dx, at[1])
            time.sleep(seconds)

    # --- geometry --------------------------------------------------------------------------------
    def rects(self):
        return self.run("result = rects()")

    def point(self, name, fx, fy):
        """Window pixel at fractions (fx, fy) of rectangle `name` (see ui_server.rects)."""
        x, y, w, h = self.rects()[name]
        return x + fx * w, y + fy * h

    # --- what Blender shows and says -------------------------------------------------------------
    def screenshot(self, name):
        """The whole X screen as build/ui-artifacts/<test>/<name>.png; returns the path."""
        path = self.shots / f"{name}.png"
        with open(path, "wb") as out:
            subprocess.run(["chroot", str(self.root), "/usr/bin/env", "-i", "PATH=/usr/bin:/bin",
                            f"DISPLAY={self.display}", "import", "-window", "root", "png:-"],
                           stdout=out, check=True, timeout=60)
        return path

    def log_text(self):
        self._log.flush()
        return self.log_path.read_text(errors="replace")

    def log_tail(self, lines=40):
        return "\n".join(self.log_text().splitlines()[-lines:])

    def tracebacks(self, since=0):
        """Python tracebacks Blender printed after log offset `since` (each as its text)."""
        text = self.log_text()[since:]
        parts = text.split(TRACEBACK)[1:]
        return [TRACEBACK + part[:2000] for part in parts]
