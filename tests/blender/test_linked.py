"""Linked and overridden data (issue 26 item 3): a file saves nothing of a datablock linked from
a library, and an override keeps neither the extension's settings nor shape keys added to its
mesh. So every operator refuses such a body in one line and changes nothing; once it is made
local (the fix the line names), Prepare and a bake work and survive a save and reopen.

Before: with a library-linked object, Prepare, Simulate and Clear Bake all reported FINISHED,
and after a save and reopen the preparation and the bake were gone without a word.

Each test writes a library .blend in its tmp_path (a small bar, 'Bar', with its mesh 'Cube')
and links from it.
"""
import bpy
import pytest

from blender_helpers import make_active, user_fingerprint
from test_faults import key_names, refusal, small_bar

MAKE_LOCAL = "make it local first (Object > Relations > Make Local > Selected Objects and Data)"
LINKED_OBJECT = ("'Bar' is linked from the library 'library.blend', so nothing done to it can "
                 f"be saved in this file: {MAKE_LOCAL}")
OVERRIDE = ("'Bar' is a library override, which cannot keep its preparation or bake when the "
            f"file is saved: {MAKE_LOCAL}")
LINKED_MESH = ("The mesh 'Cube' of 'Local' is linked from the library 'library.blend', so a bake "
               f"(shape keys of the mesh) cannot be saved in this file: {MAKE_LOCAL}")
OVERRIDDEN_MESH = ("The mesh 'Cube' of 'Local' is a library override, which cannot keep a bake "
                   f"(shape keys of the mesh) when the file is saved: {MAKE_LOCAL}")


@pytest.fixture
def library(tmp_path):
    """library.blend with a small bar pinned at x = 0, frames 1-4; the test starts from an empty
    file again, saved next to it (so paths to the library are relative, as an artist's are)."""
    bar = small_bar(use_scene_range=False, frame_start=1, frame_end=4)
    path = tmp_path / "library.blend"
    bpy.data.libraries.write(str(path), {bar}, fake_user=True)
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "shot.blend"))
    return path


def link(library, **what):
    """Link the named datablocks (objects=["Bar"], meshes=["Cube"]) from the library."""
    with bpy.data.libraries.load(str(library), link=True) as (source, target):
        for kind, names in what.items():
            setattr(target, kind, names)
    return {kind: getattr(target, kind) for kind in what}


def linked_object(library):
    obj = link(library, objects=["Bar"])["objects"][0]
    bpy.context.scene.collection.objects.link(obj)
    return obj


def overridden_object(library):
    linked = linked_object(library)
    return linked.override_create(remap_local_usages=True)


def local_object(mesh):
    obj = bpy.data.objects.new("Local", mesh)
    bpy.context.scene.collection.objects.link(obj)
    obj.rs_elastic.edge_length, obj.rs_elastic.num_modes = 0.15, 6
    return obj


def local_object_linked_mesh(library):
    return local_object(link(library, meshes=["Cube"])["meshes"][0])


def local_object_overridden_mesh(library):
    mesh = link(library, meshes=["Cube"])["meshes"][0]
    return local_object(mesh.override_create(remap_local_usages=True))


CASES = [("linked object", linked_object, LINKED_OBJECT),
         ("library override", overridden_object, OVERRIDE),
         ("linked mesh", local_object_linked_mesh, LINKED_MESH),
         ("overridden mesh", local_object_overridden_mesh, OVERRIDDEN_MESH)]

OPERATORS = [("prepare", {}), ("tetrahedralize", {}), ("simulate", {}), ("solve_spacetime", {}),
             ("clear_bake", {}), ("keep_take", {}), ("add_handle", dict(vertex_group="Pin")),
             ("interpolate_shape_keys", dict(key_from="Basis", key_to="Key 1")),
             ("follow_bones", {}), ("apply_material_preset", dict(preset="RUBBER"))]


@pytest.mark.parametrize("make, message", [pytest.param(*case[1:], id=case[0]) for case in CASES])
def test_every_operator_refuses_what_would_not_be_saved(library, tmp_path, make, message):
    obj = make(library)
    make_active(obj)
    name = obj.name
    assert obj.library or obj.override_library or obj.data.library or obj.data.override_library
    for operator, arguments in OPERATORS:
        assert refusal(lambda: getattr(bpy.ops.rs_elastic, operator)(**arguments)) == message, \
            operator
    assert not obj.rs_elastic.is_prepared and key_names(obj) == []
    before = user_fingerprint()
    bpy.ops.wm.save_mainfile()
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "shot.blend"))
    obj = bpy.data.objects[name]
    assert not obj.rs_elastic.is_prepared and key_names(obj) == []
    assert user_fingerprint() == before


def test_the_command_line_refuses_a_linked_body_in_one_line(ext, library, capsys):
    make_active(linked_object(library))
    bpy.ops.wm.save_mainfile()
    saved = (library.parent / "shot.blend").read_bytes()
    capsys.readouterr()
    assert ext.bridge.cli.main(["bake", "--object", "Bar", "--mode", "simulate"]) == 1
    assert capsys.readouterr().err.splitlines() == [f"rs_elastic: error: {LINKED_OBJECT}"]
    assert (library.parent / "shot.blend").read_bytes() == saved


@pytest.mark.parametrize("make", [linked_object, overridden_object],
                         ids=["linked object", "library override"])
def test_made_local_it_prepares_bakes_and_keeps_both(library, tmp_path, make):
    """Object > Relations > Make Local > Selected Objects and Data, the fix the refusal names:
    then Prepare and Simulate work, and the file keeps the preparation and the bake."""
    make_active(make(library))
    assert bpy.ops.object.make_local(type='SELECT_OBDATA') == {'FINISHED'}
    obj = bpy.context.active_object
    assert not (obj.library or obj.override_library or obj.data.library
                or obj.data.override_library)
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    baked = key_names(obj)
    assert len(baked) == 1 + 4
    bpy.ops.wm.save_mainfile()
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "shot.blend"))
    obj = bpy.data.objects["Bar"]
    make_active(obj)
    assert obj.rs_elastic.is_prepared and key_names(obj) == baked
    assert bpy.ops.rs_elastic.clear_bake() == {'FINISHED'}
    assert key_names(obj) == []


def collection_library(tmp_path):
    """collection.blend whose collection 'Props' holds a small bar; the test starts from an empty
    file saved next to it."""
    bar = small_bar(use_scene_range=False, frame_start=1, frame_end=4)
    props = bpy.data.collections.new("Props")
    props.objects.link(bar)
    path = tmp_path / "collection.blend"
    bpy.data.libraries.write(str(path), {props}, fake_user=True)
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "shot.blend"))
    return path


def test_a_body_in_a_linked_collection_is_told_to_bring_its_collection(tmp_path):
    """Make Local > Selected on an object that only a linked collection holds makes a local
    copy no collection of the scene holds; the refusal names the fix that works."""
    props = link(collection_library(tmp_path), collections=["Props"])["collections"][0]
    bpy.context.scene.collection.children.link(props)
    obj = props.objects["Bar"]
    make_active(obj)
    assert refusal(bpy.ops.rs_elastic.prepare) == (
        "'Bar' is linked from the library 'collection.blend', so nothing done to it can be saved "
        "in this file: make it local first, with its collection 'Props' (Object > Relations > "
        "Make Local > All)")
    assert bpy.ops.object.make_local(type='ALL') == {'FINISHED'}
    obj = bpy.context.view_layer.objects["Bar"]
    make_active(obj)
    assert obj.library is None and bpy.ops.rs_elastic.prepare() == {'FINISHED'}


def test_a_handle_of_a_body_in_an_overridden_collection_goes_where_it_can_be_saved(tmp_path):
    """An overridden collection cannot take new objects: Add Handle raised a traceback there and
    left its Empty behind. Now the Empty goes into the scene's own collection."""
    props = link(collection_library(tmp_path), collections=["Props"])["collections"][0]
    bpy.context.scene.collection.children.link(props)
    override = props.override_hierarchy_create(bpy.context.scene, bpy.context.view_layer,
                                               do_fully_editable=True)
    if props.name in bpy.context.scene.collection.children:
        bpy.context.scene.collection.children.unlink(props)
    obj = override.objects["Bar"]
    make_active(obj)
    assert bpy.ops.object.make_local(type='SELECT_OBDATA') == {'FINISHED'}
    obj = bpy.context.view_layer.objects["Bar"]
    make_active(obj)
    assert obj.override_library is None and obj.library is None
    assert all(c.override_library is not None for c in obj.users_collection)
    obj.vertex_groups.new(name="Tip").add([0], 1.0, 'REPLACE')
    assert bpy.ops.rs_elastic.add_handle(vertex_group="Tip") == {'FINISHED'}
    empty = obj.rs_elastic.handles[0].empty
    assert list(empty.users_collection) == [bpy.context.scene.collection]
    name = empty.name
    bpy.ops.wm.save_mainfile()
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "shot.blend"))
    assert bpy.data.objects["Bar"].rs_elastic.handles[0].empty.name == name
