"""The command line: `blender -b shot.blend -c rs_elastic bake --object NAME …`.

`main(argv)` is the registered handler and what the tests call (the bpy module cannot take `-c`).
It prepares what is missing, solves (space-time edit) or simulates, bakes, saves, and returns the
exit code: 0 on success, 1 with one readable line on failure, 2 for bad arguments.
"""
import argparse
import re
import sys

import bpy

from . import bake

OPERATORS = {"spacetime": "solve_spacetime", "simulate": "simulate"}


def _parser():
    parser = argparse.ArgumentParser(prog="blender -b FILE.blend -c rs_elastic",
                                     description="RS Elastic on the command line")
    commands = parser.add_subparsers(dest="command", required=True)
    bake_cmd = commands.add_parser("bake", help="prepare, solve or simulate, bake and save")
    bake_cmd.add_argument("--object", required=True, help="name of the body (a mesh object)")
    bake_cmd.add_argument("--mode", choices=sorted(OPERATORS), default="spacetime",
                          help="space-time edit (default) or simulation")
    bake_cmd.add_argument("--frames", help="frame range A-B (default: the body's or the scene's)")
    bake_cmd.add_argument("--output", help="save to this .blend (default: overwrite the open file)")
    return parser


class CommandError(Exception):
    pass


def _frame_range(text):
    match = re.fullmatch(r"\s*(\d+)\s*-\s*(\d+)\s*", text or "")
    if not match or int(match.group(2)) <= int(match.group(1)):
        raise CommandError(f"--frames must look like 1-120 (start before end), got '{text}'")
    return int(match.group(1)), int(match.group(2))


def _run_operator(name, message):
    try:
        result = getattr(bpy.ops.rs_elastic, name)()
    except RuntimeError as exc:     # the operator reported an error
        raise CommandError(str(exc).replace("Error: ", "").strip()) from None
    if result != {'FINISHED'}:
        raise CommandError(message)


def bake_command(args):
    obj = bpy.data.objects.get(args.object)
    if obj is None:
        raise CommandError(f"no object named '{args.object}' in "
                           f"{bpy.data.filepath or 'the open file'}")
    if obj.type != 'MESH':
        raise CommandError(f"'{obj.name}' is a {obj.type.lower()}, not a mesh")
    view_layer = bpy.context.view_layer
    if view_layer.objects.get(obj.name) is None:
        raise CommandError(f"'{obj.name}' is not in the active scene's view layer")
    view_layer.objects.active = obj
    if args.frames:
        start, end = _frame_range(args.frames)
        obj.rs_elastic.use_scene_range = False
        obj.rs_elastic.frame_start, obj.rs_elastic.frame_end = start, end
    # Prepare is cheap when the cache is valid: it only checks and loads.
    _run_operator("prepare", f"could not prepare '{obj.name}'")
    _run_operator(OPERATORS[args.mode], f"the {args.mode} bake of '{obj.name}' did not finish")
    output = args.output or bpy.data.filepath
    if not output:
        raise CommandError("the file was never saved: pass --output FILE.blend")
    bpy.ops.wm.save_as_mainfile(filepath=output)
    frames = bake.bake_frames(obj)
    return f"baked frames {frames[0]}-{frames[-1]} of '{obj.name}' into {output}"


def main(argv):
    try:
        args = _parser().parse_args(argv)
    except SystemExit as exc:          # argparse printed the usage and the error
        return int(exc.code or 0) and 2
    try:
        message = bake_command(args)
    except CommandError as exc:
        print(f"rs_elastic: error: {exc}", file=sys.stderr, flush=True)
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
