"""Blender tests: the extension is built, installed from its zip into a throw-away Blender user
folder and enabled, before any test imports bpy. Run through `make test-blender`."""
import os
import pathlib
import shutil
import sys
import tempfile

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))

import blender_session  # noqa: E402

ZIP = os.environ.get("RS_ELASTIC_ZIP")
if not ZIP:
    raise pytest.UsageError("RS_ELASTIC_ZIP is not set: run the Blender tests with `make test-blender`")
EXTENSION = blender_session.start(ROOT / ZIP)
USER_DIR = os.environ["BLENDER_USER_RESOURCES"]

import bpy  # noqa: E402


@pytest.fixture
def ext():
    """The installed extension package (bl_ext.user_default.rs_elastic)."""
    return EXTENSION


@pytest.fixture(autouse=True)
def empty_scene(tmp_path):
    """Every test starts from an empty, unsaved file."""
    bpy.ops.wm.read_homefile(use_empty=True)
    EXTENSION.bridge.stage_cache.stats.clear()
    EXTENSION.bridge.stage_cache._MEMORY.clear()
    # Unsaved files cache in the temp folder: give each test its own.
    (tmp_path / "tmp").mkdir()
    tempfile.tempdir = str(tmp_path / "tmp")
    yield


_exit_status = 0


def pytest_sessionfinish(session, exitstatus):
    global _exit_status
    _exit_status = int(exitstatus)


def pytest_unconfigure(config):
    """Test harness only: the bpy module of Blender 4.2 and 4.3 crashes at interpreter exit once an
    add-on has registered classes (see blender_session.exit_child), which would turn a green run
    into a SIGSEGV. There the run ends here, after pytest has reported, with pytest's own status.
    The throw-away Blender user folder (the installed extension, ~270 MB) goes first, on every
    version, so repeated runs do not fill the temp folder."""
    shutil.rmtree(USER_DIR, ignore_errors=True)
    if bpy.app.version < (4, 4, 0):
        blender_session.exit_child(_exit_status)
