"""Every bad input is refused with one clear message, and nothing changes."""
import pytest
import bpy

from blender_helpers import fingerprint, link_mesh, make_bar


def refused(operator, match, obj=None):
    before = fingerprint(obj) if obj is not None else None
    files_before = sorted(o.name for o in bpy.data.objects)
    with pytest.raises(RuntimeError, match=match):
        operator()
    if obj is not None:
        assert fingerprint(obj) == before
    assert sorted(o.name for o in bpy.data.objects) == files_before


OPERATORS = [bpy.ops.rs_elastic.prepare, bpy.ops.rs_elastic.tetrahedralize]


@pytest.mark.parametrize("operator", OPERATORS)
def test_no_active_object(operator):
    bpy.context.view_layer.objects.active = None
    refused(operator, "No active object")


@pytest.mark.parametrize("operator", OPERATORS)
def test_not_a_mesh(operator):
    bpy.ops.object.camera_add()
    refused(operator, "not a mesh", bpy.context.active_object)


@pytest.mark.parametrize("operator", OPERATORS)
def test_empty_mesh(operator):
    obj = link_mesh("Empty", [], [])
    refused(operator, "empty mesh", obj)


@pytest.mark.parametrize("operator", OPERATORS)
def test_flat_mesh(operator):
    bpy.ops.mesh.primitive_grid_add()
    refused(operator, "flat", bpy.context.active_object)


@pytest.mark.parametrize("value, match", [(0.5, "Poisson"), (0.7, "Poisson"), (-1.0, "Poisson"),
                                          (-3.0, "Poisson")])
def test_bad_poisson_ratio(value, match):
    obj = make_bar()
    obj.rs_elastic.poisson_ratio = value
    refused(bpy.ops.rs_elastic.prepare, match, obj)


@pytest.mark.parametrize("value", [0.0, -1e6])
def test_bad_youngs_modulus(value):
    obj = make_bar()
    obj.rs_elastic.youngs_modulus = value
    refused(bpy.ops.rs_elastic.prepare, "Young", obj)


@pytest.mark.parametrize("value", [0.0, -5.0])
def test_bad_density(value):
    obj = make_bar()
    obj.rs_elastic.density = value
    refused(bpy.ops.rs_elastic.prepare, "Density", obj)


def test_missing_pin_group():
    obj = make_bar()
    obj.rs_elastic.pin_group = "Nope"
    refused(bpy.ops.rs_elastic.prepare, "Pin group 'Nope' does not exist", obj)


def test_every_vertex_pinned():
    obj = make_bar()
    obj.vertex_groups["Pin"].add(list(range(len(obj.data.vertices))), 1.0, 'REPLACE')
    refused(bpy.ops.rs_elastic.prepare, "nothing is left free", obj)


def test_more_modes_than_the_body_has():
    obj = make_bar()
    obj.rs_elastic.edge_length = 0.2
    obj.rs_elastic.num_modes = 100000
    refused(bpy.ops.rs_elastic.prepare, "modes", obj)
