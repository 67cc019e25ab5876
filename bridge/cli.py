"""The command line: `blender -b shot.blend -c rs_elastic bake --object NAME …`, and
`… fit --object NAME [--source OBJECT] [--frames A-B] [--continue-to FRAME]` (Take from
Animation, Fit Material, Continue: batch fits).

`main(argv)` is the registered handler and what the tests call (the bpy module cannot take `-c`).
Every argument is checked before any work. It prepares what is missing, solves (space-time edit)
or simulates, bakes, and saves, and returns the exit code: 0 on success, 2 with one readable line
for a bad argument (unknown object, malformed or unbounded --frames, unusable --output or bake
target), 1 with one line for a failure. Saving is the last step: what it reports is read before,
so a failure never leaves a saved file behind, and never overwrites the open file.

Farm tasks (bridge/farm.py, farm/rs_elastic_bake.js) bake the bodies of one file side by side
without saving it: `bake --bake-to cache --no-save --bake-file FILE [--with-bake OTHER=FILE …]
[--only prepare|bake]` writes only the body's .pc2 under the name its job gave it (or, prepare
only, the cache) while the bakes it reads play, and `collect --bake NAME=FILE …` makes every
body's file its bake, checks that it plays, and saves the file.
"""
import argparse
import contextlib
import os
import re
import sys

import bpy

from . import bake, farm, mesh_cache, spacetime_inputs, take, writes
from .properties import LAST_FRAME
from .scene import MAX_FRAMES, InputError

OPERATORS = {"spacetime": "solve_spacetime", "simulate": "simulate"}


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
    bake_cmd.add_argument("--frames", help=f"frame range A-B (negative frames too: -10-20, "
                                           f"-20--10), at least 3 and at most {MAX_FRAMES} "
                                           "frames (default: the body's or the scene's)")
    bake_cmd.add_argument("--bake-to", choices=("keys", "cache"), default=None,
                          help="shape keys in the .blend, or a Mesh Cache (.pc2 next to the "
                               "opened .blend, played by a Mesh Cache modifier); default: the "
                               "object's Bake To setting")
    bake_cmd.add_argument("--output", help="save to this .blend (default: overwrite the open file)")
    _farm_arguments(bake_cmd, commands)
    fit_cmd = commands.add_parser("fit", help="take an animation, fit the material, continue "
                                              "and save")
    fit_cmd.add_argument("--object", required=True, help="name of the body (a mesh object)")
    fit_cmd.add_argument("--source", help="the object whose motion is the take (default: the "
                                          "body's Take Source, else the body itself)")
    fit_cmd.add_argument("--frames", help="the take's frame range A-B (default: the scene's); "
                                          "the whole take is fitted")
    fit_cmd.add_argument("--continue-to", type=int, metavar="FRAME",
                         help="bake the fitted material's motion after the take up to FRAME")
    fit_cmd.add_argument("--output", help="save to this .blend (default: overwrite the open file)")
    return parser


# --- for farm tasks (bridge/farm.py): bodies of one file baked side by side -----------------------

def _farm_arguments(bake_cmd, commands):
    bake_cmd.add_argument("--only", choices=("prepare", "bake"),
                          help="prepare only (the cache next to the .blend), or bake only: "
                               "compute no preparation; a body whose preparation is not in the "
                               "file and its cache fails")
    bake_cmd.add_argument("--bake-file", metavar="FILE",
                          help="the Mesh Cache file to write, a bake file name of the body's "
                               "(NAME.<16 hex digits>.pc2 in the bakes folder), as a farm job "
                               "names it")
    bake_cmd.add_argument("--with-bake", metavar="OBJECT=FILE", action="append", default=[],
                          help="play this Mesh Cache file of the bakes folder as OBJECT's bake "
                               "while baking (a body whose bake this one reads); repeatable")
    bake_cmd.add_argument("--no-save", action="store_true",
                          help="leave the .blend as it is: keep only the Mesh Cache file "
                               "(--bake-to cache) or, with --only prepare, the cache")
    collect_cmd = commands.add_parser(
        "collect", help="make each listed Mesh Cache file its body's bake (in the body's Bake To "
                        "form), check that it plays, and save")
    collect_cmd.add_argument("--bake", metavar="OBJECT=FILE", action="append", required=True,
                             help="a body and the file of the bakes folder a farm task baked it "
                                  "to; repeatable")
    collect_cmd.add_argument("--output", help="save to this .blend (default: overwrite the open "
                                              "file)")


def _bake_pair(text, option):
    """(body, path) of an OBJECT=FILE argument (the name may hold '=', a bake file name not)."""
    name, equals, file_name = text.rpartition("=")
    if not equals:
        raise UsageError(f"{option} must be OBJECT=FILE, got '{text}'")
    obj = _body(name)
    try:
        return obj, farm.bake_path(obj, file_name)
    except InputError as exc:
        raise UsageError(f"{option} {text}: {exc}") from None


def _farm_options(args, obj, bake_to):
    """The farm bakes that play while `obj` bakes ([(body, path)]); UsageError for options that
    contradict each other or do not fit."""
    if args.no_save and args.output:
        raise UsageError("--no-save and --output contradict each other")
    if args.no_save and args.only != "prepare" and bake_to != 'CACHE':
        raise UsageError("--no-save keeps a bake only as a Mesh Cache: add --bake-to cache")
    if args.bake_file is not None:
        if bake_to != 'CACHE' or args.only == "prepare":
            raise UsageError("--bake-file names a Mesh Cache bake: add --bake-to cache (and no "
                             "--only prepare)")
        if mesh_cache.identity_of(obj, args.bake_file) is None:
            raise UsageError(f"--bake-file '{args.bake_file}' is not a bake file name of "
                             f"'{obj.name}' ({mesh_cache.bake_name(obj, '<16 hex digits>')})")
    playing = [_bake_pair(text, "--with-bake") for text in args.with_bake]
    if any(other == obj for other, _ in playing):
        raise UsageError(f"--with-bake '{obj.name}' is the body being baked")
    return playing


def _farm_task(args, obj):
    """What a farm task's bake runs inside: its file's identity pinned (--bake-file). (Bake files
    are deleted only when the .blend is saved, so a --no-save task deletes none.)"""
    stack = contextlib.ExitStack()
    if args.bake_file is not None:
        stack.enter_context(mesh_cache.pinned_identities(
            {obj.name: mesh_cache.identity_of(obj, args.bake_file)}))
    return stack


def collect_command(args):
    """Check the bodies, their files' names and the output first (UsageError), then collect,
    save, and delete the files the saved shot no longer plays."""
    bakes = [_bake_pair(text, "--bake") for text in args.bake]
    output = _output_path(args.output)
    try:
        unplayed = farm.collect(bakes, bpy.context.scene)
    except InputError as exc:
        raise CommandError(str(exc)) from None
    report = (f"collected the farm bakes of {', '.join(repr(obj.name) for obj, _ in bakes)} "
              f"(each plays) into {output}")
    _save(output)
    mesh_cache.discard(unplayed)
    return report


def parse_arguments(argv):
    """The parsed arguments (argparse.Namespace); UsageError for bad ones. A --frames value that
    starts with a minus (a negative first frame) is taken as the value, not as an option."""
    joined, rest = [], list(argv)
    while rest:
        arg = rest.pop(0)
        if arg == "--frames" and rest and re.match(r"\s*-\d", rest[0]):
            arg = f"--frames={rest.pop(0)}"
        joined.append(arg)
    return _parser().parse_args(joined)


def _frame_range(text):
    match = re.fullmatch(r"\s*(-?\d+)\s*-\s*(-?\d+)\s*", text)
    if not match:
        raise UsageError(f"--frames must look like 1-120, got '{text}'")
    start, end = int(match.group(1)), int(match.group(2))
    if end - start + 1 < 3:
        raise UsageError(f"--frames {start}-{end} has fewer than 3 frames (start before end)")
    if end > LAST_FRAME or end - start + 1 > MAX_FRAMES:
        raise UsageError(f"--frames {start}-{end} is too long: at most {MAX_FRAMES} frames, "
                         f"ending by frame {LAST_FRAME}")
    if start < -LAST_FRAME:
        raise UsageError(f"--frames {start}-{end} starts before Blender's first frame, "
                         f"{-LAST_FRAME}")
    return start, end


def _writable(path):
    """Whether a file can be written at `path`: its folder is a writable folder, and a file
    already there is writable."""
    folder = os.path.dirname(path)
    return (os.path.isdir(folder) and os.access(folder, os.W_OK)
            and (not os.path.exists(path) or os.access(path, os.W_OK)))


def _output_path(text):
    """The absolute .blend path to save to; its folder must exist and be writable."""
    if text is None:
        if not bpy.data.filepath:
            raise UsageError("the open file was never saved: pass --output FILE.blend")
        if not _writable(bpy.data.filepath):
            raise UsageError(f"cannot save over the open file {bpy.data.filepath}: it or its "
                             "folder is not writable; pass --output FILE.blend")
        return bpy.data.filepath
    path = os.path.abspath(bpy.path.abspath(text))
    folder = os.path.dirname(path)
    if not path.lower().endswith(".blend"):
        raise UsageError(f"--output must be a .blend file, got '{text}'")
    if not os.path.isdir(folder):
        raise UsageError(f"--output: the folder {folder} does not exist")
    if os.path.isdir(path):
        raise UsageError(f"--output: {path} is a folder")
    if not _writable(path):
        raise UsageError(f"--output: {path} is not writable")
    return path


def _check_cache_target(obj, bake_to):
    """A Mesh Cache bake (`bake_to` 'CACHE') writes a .pc2 into the opened .blend's bakes folder
    (``mesh_cache.bakes_folder``): refuse, before any work, a file never saved, or a place where
    that folder cannot be made or written (a folder that is not writable, or a file in its
    place)."""
    if bake_to != 'CACHE':
        return
    try:
        folder = mesh_cache.bakes_folder()
    except InputError as exc:
        raise UsageError(f"{exc}, or pass --bake-to keys") from None
    problem = mesh_cache.folder_problem(folder)
    if problem is not None:
        raise UsageError(f"'{obj.name}' bakes to a Mesh Cache in {folder}, and {problem}: pass "
                         "--bake-to keys, or open a copy in a writable folder")


def _body(name):
    obj = bpy.data.objects.get(name)
    if obj is None:
        raise UsageError(f"no object named '{name}' in {bpy.data.filepath or 'the open file'}")
    if obj.type != 'MESH':
        raise UsageError(f"'{obj.name}' is a {obj.type.lower()}, not a mesh")
    if bpy.context.view_layer.objects.get(obj.name) is None:
        raise UsageError(f"'{obj.name}' is not in the active scene's view layer")
    return obj


def _leave_mode(obj):
    """Object Mode for the bake, with a note for the report ('' if it was in it already). A file
    saved in Edit, Sculpt or a paint mode opens in that mode; in the background no one is
    editing, and what the mode held was written into the mesh when the file was saved."""
    if obj.mode == 'OBJECT':
        return ""
    name = writes.mode_name(obj)
    bpy.ops.object.mode_set(mode='OBJECT')
    return f" ('{obj.name}' was saved in {name}: baked in Object Mode)"


def _operator_error(exc):
    """One line from the RuntimeError an operator raised: its report, or for a Python error
    (a bug: Blender has printed its traceback) the error's last line."""
    lines = [line.strip() for line in str(exc).strip().splitlines() if line.strip()]
    first = lines[0].removeprefix("Error: ") if lines else "unknown error"
    if first.startswith("Python: Traceback"):
        return f"internal error: {lines[-1]}"
    return first


def _run_operator(name, message, **properties):
    try:
        result = getattr(bpy.ops.rs_elastic, name)(**properties)
    except RuntimeError as exc:     # the operator reported an error
        raise CommandError(_operator_error(exc)) from None
    if result != {'FINISHED'}:
        raise CommandError(message)


def _save(output):
    """Save the file to `output`: the last step, after everything else has worked."""
    try:
        bpy.ops.wm.save_as_mainfile(filepath=output)
    except RuntimeError as exc:
        raise CommandError(f"could not save {output}: {_operator_error(exc)}; nothing was "
                           "saved") from None


def bake_command(args):
    """Check every argument first (UsageError), then work; read the report, and save last, so
    a failure never leaves a saved file behind or overwrites the open file."""
    obj = _body(args.object)
    frames = None if args.frames is None else _frame_range(args.frames)
    bake_to = obj.rs_elastic.bake_to if args.bake_to is None else args.bake_to.upper()
    playing = _farm_options(args, obj, bake_to)
    output = None if args.no_save else _output_path(args.output)
    if args.only != "prepare":
        _check_cache_target(obj, bake_to)
    bpy.context.view_layer.objects.active = obj
    mode_note = _leave_mode(obj)
    obj.rs_elastic.bake_to = bake_to
    if frames is not None:
        obj.rs_elastic.use_scene_range = False
        obj.rs_elastic.frame_start, obj.rs_elastic.frame_end = frames
    with _farm_task(args, obj):
        report = _prepare_and_bake(args, obj, playing, output, mode_note)
    if output is not None:
        _save(output)
    return report


def _prepare_and_bake(args, obj, playing, output, mode_note=""):
    """Play the bakes `playing` reads, prepare (only load, with --only bake), bake unless
    --only prepare; returns the report (ending with `mode_note`)."""
    try:
        farm.play_bakes(playing, bpy.context.scene)
    except InputError as exc:
        raise CommandError(str(exc)) from None
    # Prepare is cheap when the cache is valid: it only checks and loads.
    _run_operator("prepare", f"could not prepare '{obj.name}'", cached_only=args.only == "bake")
    if args.only == "prepare":
        return f"prepared '{obj.name}'" + ("" if output is None else f" into {output}")
    _run_operator(OPERATORS[args.mode], f"the {args.mode} bake of '{obj.name}' did not finish")
    baked = bake.bake_frames(obj)
    if not baked:
        raise CommandError(f"the {args.mode} bake of '{obj.name}' left no bake to save")
    status = spacetime_inputs.LAST_STATUS.get(obj.name) if args.mode == "spacetime" else None
    where = output if output is not None else mesh_cache.bake_file(obj)
    return (f"baked frames {baked[0]}-{baked[-1]} of '{obj.name}' into {where}{mode_note}"
            + ("" if status is None else f"\nrs_elastic: {status[1]}"))


def fit_command(args):
    """Take from Animation, Fit Material and (--continue-to) Continue on one body, then save;
    the scene's frame range is put back before saving."""
    obj = _body(args.object)
    source = None if args.source is None else _body(args.source)
    frames = None if args.frames is None else _frame_range(args.frames)
    output = _output_path(args.output)
    if args.continue_to is not None:
        _check_cache_target(obj, obj.rs_elastic.bake_to)
    bpy.context.view_layer.objects.active = obj
    mode_note = _leave_mode(obj)
    if source is not None:
        obj.rs_elastic.take_source = source
    scene = bpy.context.scene
    scene_range = scene.frame_start, scene.frame_end
    if frames is not None:
        scene.frame_start, scene.frame_end = frames
    try:
        _run_operator("prepare", f"could not prepare '{obj.name}'")
        _run_operator("take_from_animation", f"could not take the animation of '{obj.name}'")
        obj.rs_elastic.fit_frame_start = obj.rs_elastic.fit_frame_end = 0   # the whole take
        _run_operator("fit_material", f"could not fit the material of '{obj.name}'")
        if args.continue_to is not None:
            _run_operator("continue_motion", f"could not continue '{obj.name}'",
                          frame_end=args.continue_to)
    finally:
        scene.frame_start, scene.frame_end = scene_range
    fitted = take.fitted_material(obj)
    report = (f"fitted the material of '{obj.name}' to frames {fitted.first_frame}-"
              f"{fitted.last_frame} (residual {fitted.residual:.3g} m, worst frame "
              f"{fitted.worst_frame}; first frequency {fitted.prepared_frequencies[0]:.3g} -> "
              f"{fitted.frequencies[0]:.3g} Hz)")
    if args.continue_to is not None:
        report += f", continued to frame {args.continue_to}"
    _save(output)
    return f"{report} into {output}{mode_note}"


def _say_error(message):
    print(f"rs_elastic: error: {message}", file=sys.stderr, flush=True)


COMMANDS = {"bake": bake_command, "collect": collect_command, "fit": fit_command}


def main(argv):
    try:
        args = parse_arguments(argv)
        message = COMMANDS[args.command](args)
    except SystemExit as exc:          # --help
        return int(exc.code or 0)
    except UsageError as exc:
        _say_error(exc)
        return 2
    except CommandError as exc:
        _say_error(exc)
        return 1
    except Exception as exc:     # a bug: still one line; saving, the last step, was not reached
        _say_error(f"internal error: {type(exc).__name__}: {exc}; nothing was saved")
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
