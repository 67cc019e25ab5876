"""GUI tests: a real, interactive Blender (Debian trixie's, in a window under Xvfb) with the
extension installed from its zip through Blender's own installer. Run through `make test-ui`.

One Blender serves the session; each test starts from an empty file with the 3D viewport's sidebar
open on the RS Elastic tab, and fails if Blender printed a Python traceback while it ran. Each
test's screenshots and the session's Blender log go to build/ui-artifacts/.

Where this machine cannot build the root (not root, no network), every test is skipped with the
reason; with RS_ELASTIC_REQUIRE_UI=1 (CI) that is a failure instead.
"""
import os
import pathlib
import re
import shutil
import subprocess

import pytest

from blender_gui import PROJECT, BlenderGUI
from sidebar import open_sidebar

ROOT = pathlib.Path(os.environ.get("RS_ELASTIC_UI_ROOT", PROJECT / "build" / "ui-root"))
ARTIFACTS = pathlib.Path(os.environ.get("RS_ELASTIC_UI_ARTIFACTS",
                                        PROJECT / "build" / "ui-artifacts"))
CANNOT_BUILD = 77            # tools/ui/build_root.sh: this machine cannot build the root


def _root_or_skip():
    """Build the root or find it up to date (seconds); skip, or fail under
    RS_ELASTIC_REQUIRE_UI=1, if this machine cannot build it."""
    done = subprocess.run([str(PROJECT / "tools" / "ui" / "build_root.sh"), str(ROOT)],
                          capture_output=True, text=True)
    if done.returncode == CANNOT_BUILD:
        reason = done.stderr.strip().splitlines()[-1]
        if os.environ.get("RS_ELASTIC_REQUIRE_UI") == "1":
            pytest.fail(f"{reason} (RS_ELASTIC_REQUIRE_UI=1: the GUI tier must run)",
                        pytrace=False)
        pytest.skip(reason)
    if done.returncode != 0:
        pytest.fail(f"building the GUI test root failed:\n{done.stdout}{done.stderr}",
                    pytrace=False)


@pytest.fixture(scope="session")
def blender():
    """The running Blender, with the zip installed and enabled through Blender's installer."""
    zip_path = os.environ.get("RS_ELASTIC_ZIP")
    if not zip_path:
        raise pytest.UsageError("RS_ELASTIC_ZIP is not set: run the GUI tests with `make test-ui`")
    _root_or_skip()
    shutil.rmtree(ARTIFACTS, ignore_errors=True)
    gui = BlenderGUI(ROOT, ARTIFACTS)
    try:
        gui.start()
        installed = gui.run_dir / "files" / pathlib.Path(zip_path).name
        shutil.copy(PROJECT / zip_path, installed)
        gui.install_result = gui.run(f"""
with override():
    result = sorted(bpy.ops.extensions.package_install_files(
        filepath={gui.run_in + '/files/' + installed.name!r}, repo='user_default',
        enable_on_install=True))
""", timeout=300)
        gui.install_log_end = len(gui.log_text())
        # The Blender tests' scene builders and fingerprints, inside this Blender.
        (gui.run_dir / "helpers").mkdir()
        shutil.copy(PROJECT / "tests" / "blender" / "blender_helpers.py", gui.run_dir / "helpers")
        gui.run(f"import sys; sys.path.insert(0, {gui.run_in + '/helpers'!r})")
        gui.run("watch_panels()")
        yield gui
    finally:
        gui.stop()


@pytest.fixture
def gui(blender, request):
    """The session's Blender, reset to an empty file with the RS Elastic sidebar tab open; the
    test's screenshots go to build/ui-artifacts/<test>/, and a traceback in Blender's log while
    the test ran fails it."""
    name = re.sub(r"[^\w.-]+", "_", request.node.name)
    blender.shots = ARTIFACTS / name
    blender.shots.mkdir(parents=True, exist_ok=True)
    blender.run("""
with override():
    bpy.ops.wm.read_homefile(use_empty=True, load_ui=False)
""")
    open_sidebar(blender)
    start = len(blender.log_text())
    yield blender
    blender.screenshot("end")
    found = blender.tracebacks(since=start)
    assert not found, "Blender printed a traceback during the test:\n" + "\n".join(found)
    assert blender.process.poll() is None, "Blender exited during the test"
