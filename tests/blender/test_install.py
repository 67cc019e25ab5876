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
