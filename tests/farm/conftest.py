"""Farm tests: a Flamenco manager and worker built from source run on 127.0.0.1 and bake shots
that this process (the artist's Blender: the extension installed from its zip, and the Flamenco
add-on of the same Flamenco) submits through the add-on. Run through `make test-farm`."""
import os
import pathlib
import shutil
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))

import blender_session  # noqa: E402

ZIP = os.environ.get("RS_ELASTIC_ZIP")
FLAMENCO_SRC = pathlib.Path(os.environ.get("FLAMENCO_SRC", ROOT.parent / "shared" / "flamenco")).resolve()
FLAMENCO_BIN = pathlib.Path(os.environ.get("FLAMENCO_BIN", ROOT / "build" / "flamenco")).resolve()
if not ZIP:
    raise pytest.UsageError("RS_ELASTIC_ZIP is not set: run the farm tests with `make test-farm`")
for program in ("flamenco-manager", "flamenco-worker"):
    if not (FLAMENCO_BIN / program).is_file():
        raise pytest.UsageError(f"{FLAMENCO_BIN / program} is missing: run `make test-farm`, "
                                "which builds it")
EXTENSION = blender_session.start(ROOT / ZIP)
USER_DIR = os.environ["BLENDER_USER_RESOURCES"]

import bpy  # noqa: E402
import flamenco_farm  # noqa: E402

flamenco_farm.enable_flamenco_addon(str(FLAMENCO_SRC))


_exit_status = 0


def pytest_sessionfinish(session, exitstatus):
    global _exit_status
    _exit_status = int(exitstatus)


def pytest_unconfigure(config):
    """The throw-away Blender user folder goes; on Blender 4.2 and 4.3 the bpy module would crash
    at interpreter exit (see blender_session.exit_child), so the run ends here."""
    shutil.rmtree(USER_DIR, ignore_errors=True)
    if bpy.app.version < (4, 4, 0):
        blender_session.exit_child(_exit_status)
