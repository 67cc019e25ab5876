"""The command line: `blender -b shot.blend -c rs_elastic bake --object NAME …`.

`main(argv)` is the registered handler and what the tests call (the bpy module cannot take `-c`).
Every argument is checked before any work. It prepares what is missing, solves (space-time edit)
or simulates, bakes, saves, and returns the exit code: 0 on success, 2 with one readable line for
a bad argument (unknown object, malformed or unbounded --frames, unusable --output), 1 with one
line for a failure. The file is saved only after a bake succeeded.
"""
import argparse
import os
import re
import sys

import bpy

from . import bake
from . import spacetime_inputs
from .scene import MAX_FRAMES

OPERATORS = {"spacetime": "solve_spacetime", "simulate": "simulate"}


MAX_FRAME = 1048574       # Blender's last frame


class UsageError(Exception):
    """A bad argument: exit code 2, before any work."""


class CommandError(Exception):
    """A failure while working: exit code 1."""


class _Parser(argparse.ArgumentParser):
    """argparse that raises instead of printing the usage and exiting, so a bad argument gives
    one line like every other error."""

    def error(self, message):
        raise UsageError(message)


def _parser():
    parser = _Parser(prog="blender -b FILE.blend -c rs_elastic",
                     description="RS Elastic on the command line")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    bake_cmd = commands.add_parser("bake", help="prepare, solve or simulate, bake and save")
    bake_cmd.add_argument("--object", required=True, help="name of the body (a mesh object)")
    bake_cmd.add_argument("--mode", choices=sorted(OPERATORS), default="spacetime",
                          help="space-time edit (default) or simulation")
    bake_cmd.add_argument("--frames", help=f"frame range A-B, at least 3 and at most "
                                           f"{MAX_FRAMES} frames (default: the body's or the "
                                           "scene's)")
    bake_cmd.add_argument("--bake-to", choices=("keys", "cache"), default=None,
                          help="shape keys in the .blend, or a Mesh Cache (.pc2 next to the "
                               "opened .blend, played by a Mesh Cache modifier); default: the "
                               "object's Bake To setting")
    bake_cmd.add_argument("--output", help="save to this .blend (default: overwrite the open file)")
    return parser


def _frame_range(text):
    match = re.fullmatch(r"\s*(\d+)\s*-\s*(\d+)\s*", text)
    if not match:
        raise UsageError(f"--frames must look like 1-120, got '{text}'")
    start, end = int(match.group(1)), int(match.group(2))
    if end - start + 1 < 3:
        raise UsageError(f"--frames {start}-{end} has fewer than 3 frames (start before end)")
    if end > MAX_FRAME or end - start + 1 > MAX_FRAMES:
        raise UsageError(f"--frames {start}-{end} is too long: at most {MAX_FRAMES} frames, "
                         f"ending by frame {MAX_FRAME}")
    return start, end


def _output_path(text):
    """The absolute .blend path to save to; its folder must exist and be writable."""
    if text is None:
        if not bpy.data.filepath:
            raise UsageError("the open file was never saved: pass --output FILE.blend")
        return bpy.data.filepath
    path = os.path.abspath(bpy.path.abspath(text))
    folder = os.path.dirname(path)
    if not path.lower().endswith(".blend"):
        raise UsageError(f"--output must be a .blend file, got '{text}'")
    if not os.path.isdir(folder):
        raise UsageError(f"--output: the folder {folder} does not exist")
    if not os.access(folder, os.W_OK) or (os.path.exists(path) and not os.access(path, os.W_OK)):
        raise UsageError(f"--output: {path} is not writable")
    if os.path.isdir(path):
        raise UsageError(f"--output: {path} is a folder")
    return path


def _body(name):
    obj = bpy.data.objects.get(name)
    if obj is None:
        raise UsageError(f"no object named '{name}' in {bpy.data.filepath or 'the open file'}")
    if obj.type != 'MESH':
        raise UsageError(f"'{obj.name}' is a {obj.type.lower()}, not a mesh")
    if bpy.context.view_layer.objects.get(obj.name) is None:
        raise UsageError(f"'{obj.name}' is not in the active scene's view layer")
    return obj


def _run_operator(name, message):
    try:
        result = getattr(bpy.ops.rs_elastic, name)()
    except RuntimeError as exc:     # the operator reported an error
        raise CommandError(str(exc).replace("Error: ", "").strip().splitlines()[0]) from None
    if result != {'FINISHED'}:
        raise CommandError(message)


def bake_command(args):
    """Check every argument first (UsageError), then work; save only after everything worked,
    so a failure never overwrites the open file."""
    obj = _body(args.object)
    frames = None if args.frames is None else _frame_range(args.frames)
    output = _output_path(args.output)
    bpy.context.view_layer.objects.active = obj
    if args.bake_to is not None:
        obj.rs_elastic.bake_to = args.bake_to.upper()
    if frames is not None:
        obj.rs_elastic.use_scene_range = False
        obj.rs_elastic.frame_start, obj.rs_elastic.frame_end = frames
    # Prepare is cheap when the cache is valid: it only checks and loads.
    _run_operator("prepare", f"could not prepare '{obj.name}'")
    _run_operator(OPERATORS[args.mode], f"the {args.mode} bake of '{obj.name}' did not finish")
    try:
        bpy.ops.wm.save_as_mainfile(filepath=output)
    except RuntimeError as exc:
        raise CommandError(f"could not save {output}: "
                           f"{str(exc).replace('Error: ', '').strip().splitlines()[0]}") from None
    frames = bake.bake_frames(obj)
    status = spacetime_inputs.LAST_STATUS.get(obj.name) if args.mode == "spacetime" else None
    return (f"baked frames {frames[0]}-{frames[-1]} of '{obj.name}' into {output}"
            + ("" if status is None else f"\nrs_elastic: {status[1]}"))


def _say_error(message):
    print(f"rs_elastic: error: {message}", file=sys.stderr, flush=True)


def main(argv):
    try:
        args = _parser().parse_args(argv)
        message = bake_command(args)
    except SystemExit as exc:          # --help
        return int(exc.code or 0)
    except UsageError as exc:
        _say_error(exc)
        return 2
    except CommandError as exc:
        _say_error(exc)
        return 1
    print(f"rs_elastic: {message}", flush=True)
    return 0


_registered = None


def register():
    global _registered
    if hasattr(bpy.utils, "register_cli_command"):
        _registered = bpy.utils.register_cli_command("rs_elastic", main)


def unregister():
    global _registered
    if _registered is not None:
        bpy.utils.unregister_cli_command(_registered)
        _registered = None
