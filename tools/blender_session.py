"""Start Blender (the bpy module) with a throw-away user folder and the extension installed from
its zip, exactly as a user installs it. Used by the Blender tests, the demo and the benchmarks.

    ext = blender_session.start(zip_path)   # returns the imported extension package

BLENDER_USER_RESOURCES must be set before bpy is imported, so call `start` before any
`import bpy`. Pass `user_dir` to reuse an installation (e.g. in a child process).
"""
import importlib
import os
import sys
import tempfile

EXTENSION_MODULE = "bl_ext.user_default.rs_elastic"


def start(zip_path=None, user_dir=None):
    if "bpy" in sys.modules and not user_dir:
        raise RuntimeError("blender_session.start() must run before bpy is imported")
    if user_dir is None:
        user_dir = tempfile.mkdtemp(prefix="rs_elastic_user_")
    os.environ["BLENDER_USER_RESOURCES"] = user_dir
    import bpy
    if zip_path is not None:
        result = bpy.ops.extensions.package_install_files(
            filepath=os.path.abspath(zip_path), repo="user_default", enable_on_install=True)
        if result != {'FINISHED'}:
            raise RuntimeError(f"installing {zip_path} failed: {result}")
    else:
        import addon_utils
        addon_utils.enable(EXTENSION_MODULE, default_set=True)
    return importlib.import_module(EXTENSION_MODULE)


def exit_child(code):
    """End a child Blender process (a test's stand-in for `blender -b … -c rs_elastic`) with `code`.

    Test harness only, never the product: the bpy *module* of Blender 4.2 and 4.3 crashes at
    interpreter exit (SIGSEGV in bpy_class_free, after Python has shut down) once any add-on has
    registered classes; an add-on with one panel does the same, and the Blender program does not.
    There the interpreter's teardown is skipped, after flushing, so the exit code is the handler's.
    """
    import bpy
    sys.stdout.flush()
    sys.stderr.flush()
    if bpy.app.version < (4, 4, 0):
        os._exit(code)
    sys.exit(code)
