"""The extension runs as users run it: installed from its zip, on its bundled wheels."""
import pathlib

import bpy

from conftest import USER_DIR


def test_extension_installed_from_zip_into_the_temporary_user_folder(ext):
    assert pathlib.Path(ext.__file__).is_relative_to(USER_DIR)
    assert "bl_ext.user_default.rs_elastic" in bpy.context.preferences.addons
    assert hasattr(bpy.ops.rs_elastic, "prepare")


def test_scipy_libigl_pytetwild_come_from_the_bundled_wheels(ext):
    import igl
    import pytetwild
    import scipy
    for module in (scipy, igl, pytetwild):
        assert pathlib.Path(module.__file__).is_relative_to(USER_DIR), module.__file__


def test_registration_is_reversible(ext):
    import addon_utils
    addon_utils.disable("bl_ext.user_default.rs_elastic")
    assert not hasattr(bpy.types.Object, "rs_elastic")
    addon_utils.enable("bl_ext.user_default.rs_elastic")
    assert hasattr(bpy.types.Object, "rs_elastic")


def test_blender_picks_one_wheel_per_package_for_its_own_python(ext):
    """The zip carries wheels for Python 3.11 and 3.13; Blender's own filter, run on this zip's
    list, keeps exactly scipy, libigl and pytetwild once each, built for this Python."""
    import sys
    import tomllib
    import zipfile
    import bl_pkg.bl_extension_ops as extension_ops
    from conftest import ROOT, ZIP
    with zipfile.ZipFile(ROOT / ZIP) as archive:
        manifest = tomllib.loads(archive.read("blender_manifest.toml").decode())
    kept = extension_ops._extensions_wheel_filter_for_this_system(manifest["wheels"])
    names = sorted(pathlib.PurePosixPath(w).name.split("-")[0] for w in kept)
    assert names == ["libigl", "pytetwild", "scipy"], kept
    this = f"cp{sys.version_info[0]}{sys.version_info[1]}"
    for wheel in kept:
        python_tag, abi_tag = pathlib.PurePosixPath(wheel).name.split("-")[2:4]
        assert python_tag == this or abi_tag == "abi3", wheel
    other_python = {pathlib.PurePosixPath(w).name.split("-")[2] for w in manifest["wheels"]}
    assert other_python == {"cp311", "cp312", "cp313"}        # cp312: the abi3 wheels for 3.13
