"""`blender` for a farm worker that has no Blender build: the bpy module of this Python behind
Blender's own command line, as much of it as Flamenco's blender-render tasks and the tests use.

    bpy-blender [-b] [-y] [--factory-startup] [FILE.blend] [--python-expr EXPR]
                [--python-exit-code N] [-c rs_elastic ARGS…]

Arguments are taken in order, as Blender does: FILE opens the file, --python-expr runs EXPR (bpy
imported) and -c passes everything after it to the extension's command-line handler, whose exit
code is this program's. The extension must be installed and enabled in the Blender user folder
that BLENDER_USER_RESOURCES names, as on a worker with Blender. A real Blender takes the same
arguments: point the Flamenco Manager's `blender` variable at it instead of tools/bpy-blender.

Test instrumentation: with RS_ELASTIC_RECORD_POSES set to a folder, the float64 poses of every
`-c rs_elastic bake` (as handed to bridge.bake.write_bake, before a .pc2 or shape keys round them
to float32) are saved there as <.blend name>.<object>.npy, so that bakes can be compared to better
than float32. Other commands are not recorded: `collect` writes bakes again from their float32
files, and would overwrite a bake's record with its float32 rounding.
"""
import os
import sys
import traceback

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import blender_session  # noqa: E402

IGNORED = {"-b", "--background", "-y", "--enable-autoexec", "--factory-startup", "-noaudio"}


def record_poses(ext, folder):
    """Save each bake's poses to folder/<.blend name>.<object>.npy (written whole, then renamed)."""
    import bpy
    import numpy as np
    write_bake = ext.bridge.bake.write_bake

    def recording(obj, frames, positions):
        stem = os.path.splitext(os.path.basename(bpy.data.filepath))[0]
        path = os.path.join(folder, f"{stem}.{obj.name}.npy")
        with open(path + ".part", "wb") as f:
            np.save(f, np.asarray(positions, dtype=np.float64))
        os.replace(path + ".part", path)
        return write_bake(obj, frames, positions)

    ext.bridge.bake.write_bake = recording


def run(argv):
    """Blender's argument loop; returns the exit code."""
    user_dir = os.environ.get("BLENDER_USER_RESOURCES")
    if not user_dir:
        print("bpy-blender: BLENDER_USER_RESOURCES must name the Blender user folder the "
              "extension is installed in", file=sys.stderr)
        return 1
    ext = blender_session.start(user_dir=user_dir)
    import bpy
    failure_code, args = 0, list(argv)
    while args:
        arg = args.pop(0)
        if arg in IGNORED:
            continue
        if arg in ("-c", "--command"):
            if not args or args[0] != "rs_elastic":
                print(f"bpy-blender: unknown command {args[:1]}: only rs_elastic", file=sys.stderr)
                return 1
            if os.environ.get("RS_ELASTIC_RECORD_POSES") and args[1:2] == ["bake"]:
                record_poses(ext, os.environ["RS_ELASTIC_RECORD_POSES"])
            return ext.bridge.cli.main(args[1:])
        if arg == "--python-exit-code":
            failure_code = int(args.pop(0))
        elif arg == "--python-expr":
            try:
                exec(args.pop(0), {"bpy": bpy, "__name__": "__main__"})
            except Exception:            # Blender prints the error and goes on
                traceback.print_exc()
                if failure_code:
                    return failure_code
        elif arg.endswith(".blend"):
            bpy.ops.wm.open_mainfile(filepath=os.path.abspath(arg))
        else:
            print(f"bpy-blender: unsupported argument {arg!r}", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    blender_session.exit_child(run(sys.argv[1:]))
