"""Run Blender's own extension tool (blender_ext.py, shipped inside the bpy wheel) with the
given arguments, from whichever bpy this interpreter has: `python tools/ext_tool.py validate .`"""
import importlib.util
import pathlib
import runpy
import sys


def ext_tool_path():
    spec = importlib.util.find_spec("bpy")          # finds the wheel without starting Blender
    if spec is None or spec.origin is None:
        sys.exit("ext_tool: this Python has no bpy module; run it from the test venv")
    found = sorted(pathlib.Path(spec.origin).parent.glob(
        "*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    if not found:
        sys.exit(f"ext_tool: no blender_ext.py inside {pathlib.Path(spec.origin).parent}")
    return found[-1]


if __name__ == "__main__":
    tool = ext_tool_path()
    sys.argv = [str(tool), *sys.argv[1:]]
    runpy.run_path(str(tool), run_name="__main__")
