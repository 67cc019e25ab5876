"""A Blender whose Python lacks numpy (a distribution's package may) says so in one clear line
when the extension is enabled, instead of a bare "No module named 'numpy'" and a greyed-out
entry. Its own Blender: numpy is hidden from this one only."""
import pathlib
import shutil

import pytest

from blender_gui import BlenderGUI
from conftest import ARTIFACTS, ROOT, _root_or_skip

LINE = "RS Elastic needs numpy"


@pytest.fixture
def numpyless(request):
    import os
    zip_path = os.environ["RS_ELASTIC_ZIP"]
    _root_or_skip()
    gui = BlenderGUI(ROOT, ARTIFACTS / "no_numpy")
    try:
        gui.start(hide_numpy=True)
        shutil.copy(zip_path, gui.run_dir / "files")
        gui.zip_in = gui.run_in + "/files/" + pathlib.Path(zip_path).name
        yield gui
    finally:
        gui.stop()


def test_enabling_without_numpy_says_so_in_one_line(numpyless):
    gui = numpyless
    assert gui.run("""
try:
    import numpy
    result = False
except ImportError:
    result = True
"""), "numpy is not hidden"
    # As from Install from Disk: what the installer reports (an error report reaches a Python
    # caller as the RuntimeError's text; in the window it shows in the status bar).
    said = gui.run(f"""
with override():
    try:
        bpy.ops.extensions.package_install_files(filepath={gui.zip_in!r}, repo='user_default',
                                                 enable_on_install=True)
        result = []
    except RuntimeError as error:
        result = str(error).splitlines()
result = [line for line in result + reports() if {LINE!r} in line]
""", timeout=300)
    gui.settle()
    gui.screenshot("enabled_without_numpy")
    assert said, "no line said that numpy is missing"
    assert "python3-numpy" in said[0] and len(said[0]) < 220, said[0]
    assert not gui.run("result = 'bl_ext.user_default.rs_elastic' in "
                       "bpy.context.preferences.addons")
