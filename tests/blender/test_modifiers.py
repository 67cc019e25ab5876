"""Every modifier type Blender has, on a small closed bar (issue 26 item 4): Prepare either works
or refuses in one line, within a time bound, and the panels (which read the staleness
fingerprint on every redraw) draw with it before and after.

The sweep is parametrised over ``bpy.types.Modifier``'s own enum, so a new Blender's new type is
tested without a change here: it must work or refuse in one line. Types with a known outcome are
held to it (EXPECTED). Each modifier is added with its defaults, plus the least it needs to do
something (a target object, a node group, a subdivision level): see SETUP.
"""
import time

import bpy
import numpy as np
import pytest

from blender_helpers import make_active, user_fingerprint, vertices
from test_faults import refusal, small_bar
from test_panels import draw_all

MODIFIER_TYPES = [item.identifier
                  for item in bpy.types.Modifier.bl_rna.properties["type"].enum_items]
TIME_LIMIT = 20.0        # [s] the bar's mesher time limit in the sweep
TIME_BOUND = TIME_LIMIT + 60.0   # [s] for a whole Prepare (modes and reduced RS come after)

def copying(kind, name):
    return (f"'Bar' has a {kind} modifier ('{name}'), which would copy the baked motion: apply "
            f"the {kind} modifier first")


# What Prepare does with each type (from the sweep on Blender 4.2 and 5.2). A type not listed
# (a new Blender's) must work or refuse in one line.
WORKS, SLOW, UNKNOWN = "works", "works, or stops at the time limit", "works, or one line"
WORKING_TYPES = {
    # deforming: the body is prepared in the shape they give it
    "ARMATURE", "CAST", "CURVE", "DISPLACE", "HOOK", "LAPLACIANDEFORM", "LATTICE", "MESH_DEFORM",
    "SHRINKWRAP", "SIMPLE_DEFORM", "SMOOTH", "CORRECTIVE_SMOOTH", "LAPLACIANSMOOTH",
    "SURFACE_DEFORM", "WARP", "WAVE", "MESH_CACHE", "MESH_SEQUENCE_CACHE",
    # generating from the mesh: the body is what they make of it
    "BEVEL", "BOOLEAN", "DECIMATE", "EDGE_SPLIT", "MASK", "MULTIRES", "REMESH", "SUBSURF",
    "TRIANGULATE", "WELD", "NODES",
    # data only (normals, UVs, weights) or physics that has not moved at the first frame
    "DATA_TRANSFER", "NORMAL_EDIT", "WEIGHTED_NORMAL", "UV_PROJECT", "UV_WARP",
    "VERTEX_WEIGHT_EDIT", "VERTEX_WEIGHT_MIX", "VERTEX_WEIGHT_PROXIMITY", "CLOTH", "COLLISION",
    "DYNAMIC_PAINT", "EXPLODE", "FLUID", "PARTICLE_SYSTEM", "SOFT_BODY", "SURFACE",
}
REFUSED = {
    "ARRAY": copying("Array", "Array"),
    "MIRROR": copying("Mirror", "Mirror"),
    "SCREW": copying("Screw", "Screw"),
    "PARTICLE_INSTANCE": copying("Particle Instance", "Particle_Instance"),
    "OCEAN": "'Bar' has an Ocean modifier ('Ocean') that generates its own surface in place of "
             "the mesh, so a bake of the mesh would not show: set its Geometry to Displace, or "
             "remove it",
    "BUILD": "'Bar' has no faces after its modifiers",          # it starts with none
    "VOLUME_TO_MESH": "'Bar' has no faces after its modifiers",   # no volume to mesh
}
# Skin (tubes around every edge), Solidify (a thin hollow shell of a closed bar) and Wireframe
# make self-intersecting or very thin surfaces: fTetWild takes minutes on them (Skin 79 s,
# Solidify 191 s on this bar and machine), so with the sweep's 20 s limit they stop there.
SLOW_TYPES = {"SKIN", "SOLIDIFY", "WIREFRAME"}
# Grease Pencil and volume modifiers cannot be added to a mesh.
NOT_FOR_MESHES = {"MESH_TO_VOLUME", "VOLUME_DISPLACE", "LINEART"}


def expected(kind):
    if kind in REFUSED:
        return REFUSED[kind]
    if kind in SLOW_TYPES:
        return SLOW
    return WORKS if kind in WORKING_TYPES else UNKNOWN


def cube(name, location, size=0.5):
    bpy.ops.mesh.primitive_cube_add(size=size, location=location)
    obj = bpy.context.active_object
    obj.name = name
    return obj


def empty(name, location):
    obj = bpy.data.objects.new(name, None)
    obj.location = location
    bpy.context.scene.collection.objects.link(obj)
    return obj


def data_object(name, data):
    obj = bpy.data.objects.new(name, data)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def tip(bar):
    return [int(i) for i in np.flatnonzero(vertices(bar)[:, 0] > 4.0 - 1e-9)]


def node_group(name, build=None):
    """A Geometry Nodes group with a geometry input and output; `build(group, input, output)`
    adds nodes between them (default: the input passed through)."""
    group = bpy.data.node_groups.new(name, 'GeometryNodeTree')
    group.interface.new_socket("Geometry", in_out='INPUT', socket_type='NodeSocketGeometry')
    group.interface.new_socket("Geometry", in_out='OUTPUT', socket_type='NodeSocketGeometry')
    into, out = group.nodes.new('NodeGroupInput'), group.nodes.new('NodeGroupOutput')
    if build is None:
        group.links.new(into.outputs[0], out.inputs[0])
    else:
        build(group, into, out)
    return group


def set_hook(bar, modifier):
    modifier.object = empty("Hook", (0.0, 0.0, 0.2))     # moves the tip 0.2 up
    modifier.vertex_indices_set(tip(bar))


def set_multires(bar, modifier):
    make_active(bar)
    bpy.ops.object.multires_subdivide(modifier=modifier.name, mode='CATMULL_CLARK')


def set_warp(bar, modifier):
    modifier.object_from = empty("From", (2.0, 0.5, 0.5))
    modifier.object_to = empty("To", (2.0, 0.5, 0.8))


def set_boolean(bar, modifier):
    cutter = cube("Cutter", (2.0, 0.5, 1.0))              # a notch in the top of the bar
    cutter.hide_set(True)
    modifier.object = cutter


def set_armature(bar, modifier):
    armature = bpy.data.armatures.new("Rig")
    modifier.object = data_object("Rig", armature)


def set_curve(bar, modifier):
    curve = bpy.data.curves.new("Path", 'CURVE')
    spline = curve.splines.new('POLY')
    spline.points.add(1)
    spline.points[1].co = (4.0, 0.0, 0.5, 1.0)
    modifier.object = data_object("Path", curve)


def set_lattice(bar, modifier):
    lattice = data_object("Lattice", bpy.data.lattices.new("Lattice"))
    lattice.location, lattice.scale = (2.0, 0.5, 0.5), (5.0, 2.0, 2.0)
    modifier.object = lattice


def target_cube(bar, modifier, attribute="target"):
    setattr(modifier, attribute, cube("Target", (2.0, 0.5, 0.5), size=3.0))


SETUP = {
    'HOOK': set_hook,
    'MULTIRES': set_multires,
    'WARP': set_warp,
    'BOOLEAN': set_boolean,
    'ARMATURE': set_armature,
    'CURVE': set_curve,
    'LATTICE': set_lattice,
    'MESH_DEFORM': lambda bar, m: target_cube(bar, m, "object"),      # not bound: no effect
    'SURFACE_DEFORM': target_cube,                                      # not bound: no effect
    'SHRINKWRAP': target_cube,
    'DATA_TRANSFER': lambda bar, m: target_cube(bar, m, "object"),
    'VERTEX_WEIGHT_PROXIMITY': target_cube,
    'PARTICLE_INSTANCE': lambda bar, m: target_cube(bar, m, "object"),
    'LAPLACIANDEFORM': lambda bar, m: setattr(m, "vertex_group", "Pin"),
    'NODES': lambda bar, m: setattr(m, "node_group", node_group("Pass")),
}


def prepare_timed():
    """(result or the one line it refused with, seconds)."""
    start = time.monotonic()
    try:
        result = bpy.ops.rs_elastic.prepare()
    except RuntimeError as exc:
        lines = [line.removeprefix("Error: ") for line in str(exc).strip().splitlines()]
        assert len(lines) == 1, lines
        result = lines[0]
    return result, time.monotonic() - start


@pytest.mark.parametrize("kind", MODIFIER_TYPES)
def test_prepare_with_every_modifier_type(ext, kind):
    bar = small_bar()
    bar.rs_elastic.mesher_time_limit = TIME_LIMIT
    modifier = bar.modifiers.new(kind.replace("_", " ").title().replace(" ", "_"), kind)
    if modifier is None:           # Blender refuses it on a mesh (Grease Pencil, volumes)
        assert kind in NOT_FOR_MESHES or kind.startswith("GREASE_PENCIL"), kind
        return
    SETUP.get(kind, lambda bar, modifier: None)(bar, modifier)
    make_active(bar)
    bpy.context.view_layer.update()
    draw_all()                                       # the panels read it (staleness, estimate)
    before = user_fingerprint()
    result, seconds = prepare_timed()
    print(f"{kind}: {result} in {seconds:.1f} s")
    assert seconds < TIME_BOUND, (kind, seconds)
    outcome = expected(kind)
    if result == {'FINISHED'}:
        assert outcome in (WORKS, SLOW, UNKNOWN), f"{kind} was to be refused: {outcome}"
        assert ext.bridge.staleness.stale_reason(bar, cached=True) is None
        assert bar.rs_elastic.tet_count > 0
    else:
        assert user_fingerprint() == before          # a refusal changes nothing
        assert not bar.rs_elastic.is_prepared
        assert outcome != WORKS, f"{kind} was to prepare: {result}"
        if outcome == SLOW:
            assert result.startswith("'Bar': fTetWild did not finish within its Time Limit of "
                                     f"{TIME_LIMIT:g} s"), result
        elif outcome != UNKNOWN:
            assert result == outcome
    draw_all()


# --- Geometry Nodes: deforming, generating, instancing, and its inputs ---------------------------

def lift(group, into, out):
    """Set Position: every point 0.1 up (a deformer)."""
    move = group.nodes.new('GeometryNodeSetPosition')
    move.inputs["Offset"].default_value = (0.0, 0.0, 0.1)
    group.links.new(into.outputs[0], move.inputs["Geometry"])
    group.links.new(move.outputs[0], out.inputs[0])


def subdivide(group, into, out):
    """Subdivide Mesh, one level (generates 4x the faces)."""
    node = group.nodes.new('GeometryNodeSubdivideMesh')
    group.links.new(into.outputs[0], node.inputs["Mesh"])
    group.links.new(node.outputs[0], out.inputs[0])


def instancer(source_object=None):
    """The body joined with instances on its points: of its own geometry (source None), or of
    another object's."""
    def build(group, into, out):
        points = group.nodes.new('GeometryNodeMeshToPoints')
        instance = group.nodes.new('GeometryNodeInstanceOnPoints')
        join = group.nodes.new('GeometryNodeJoinGeometry')
        group.links.new(into.outputs[0], points.inputs[0])
        group.links.new(points.outputs[0], instance.inputs["Points"])
        if source_object is None:
            group.links.new(into.outputs[0], instance.inputs["Instance"])
        else:
            info = group.nodes.new('GeometryNodeObjectInfo')
            info.inputs["Object"].default_value = source_object
            group.links.new(info.outputs["Geometry"], instance.inputs["Instance"])
        group.links.new(instance.outputs[0], join.inputs[0])
        group.links.new(into.outputs[0], join.inputs[0])
        group.links.new(join.outputs[0], out.inputs[0])
    return build


def geometry_nodes(bar, build=None):
    modifier = bar.modifiers.new("GeometryNodes", 'NODES')
    modifier.node_group = node_group("Nodes", build)
    make_active(bar)
    bpy.context.view_layer.update()
    return modifier


def evaluated_surface(ext, bar):
    return ext.bridge.bodies.rest_surface(bar, bpy.context.evaluated_depsgraph_get())


@pytest.mark.parametrize("build, changes", [(None, "nothing"), (lift, "moves"),
                                            (subdivide, "subdivides")],
                         ids=["pass-through", "deforming", "generating"])
def test_geometry_nodes_bodies_prepare_on_what_they_make(ext, build, changes):
    """Before: any Geometry Nodes modifier raised `TypeError: bpy_struct.keys()` in Prepare.
    The tets are made of the evaluated surface: lifted 0.1 by Set Position, 4x the faces by
    Subdivide Mesh."""
    bar = small_bar()
    geometry_nodes(bar, build)
    V, F = evaluated_surface(ext, bar)
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert ext.bridge.staleness.stale_reason(bar) is None
    rest = vertices(bar)
    assert len(F) == {"nothing": 48, "moves": 48, "subdivides": 4 * 48}[changes]
    lifted = 0.1 if changes == "moves" else 0.0
    assert V[:, 2].min() == pytest.approx(rest[:, 2].min() + lifted, abs=1e-6)


def test_geometry_nodes_instancing_the_body_is_refused(ext):
    bar = small_bar()
    geometry_nodes(bar, instancer())
    assert refusal(bpy.ops.rs_elastic.prepare) == (
        "'Bar' makes instances of its own mesh (Geometry Nodes 'GeometryNodes'), which would "
        "repeat the baked motion as an Array does: remove those instances first")


def test_geometry_nodes_instancing_another_object_prepares_the_body_alone(ext):
    """A scatter of another object on the body's points rides along; the body is its own mesh."""
    cone = cube("Stud", (10.0, 0.0, 0.0), size=0.1)
    bar = small_bar()
    geometry_nodes(bar, instancer(cone))
    V, F = evaluated_surface(ext, bar)
    assert len(F) == 48
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}


def set_input(modifier, identifier, value):
    """A Geometry Nodes modifier's input value: an ID property up to Blender 4.x, an RNA
    property of `modifier.properties.inputs` from 5.0 on."""
    if hasattr(modifier, "properties"):
        getattr(modifier.properties.inputs, identifier).value = value
    else:
        modifier[identifier] = value
    modifier.id_data.update_tag()


@pytest.mark.parametrize("kind, value", [('NodeSocketFloat', 0.25),
                                         ('NodeSocketVector', (0.0, 0.0, 0.3))],
                         ids=["float", "vector"])
def test_a_changed_geometry_nodes_input_makes_the_body_stale(ext, kind, value):
    """The input drives a Set Position offset; changing it after Prepare is a stale body, said in
    one line by the panel's check and by every operator (before: the check raised TypeError;
    on Blender 4.x a vector input's change was not seen, its repr has no values)."""
    def build(group, into, out):
        lift(group, into, out)
        socket = group.interface.new_socket("Offset", in_out='INPUT', socket_type=kind)
        move = group.nodes["Set Position"]
        if kind == 'NodeSocketFloat':
            combine = group.nodes.new('ShaderNodeCombineXYZ')
            group.links.new(into.outputs[socket.identifier], combine.inputs["Z"])
            group.links.new(combine.outputs[0], move.inputs["Offset"])
        else:
            group.links.new(into.outputs[socket.identifier], move.inputs["Offset"])

    bar = small_bar(use_scene_range=False, frame_start=1, frame_end=4)
    modifier = geometry_nodes(bar, build)
    identifier = modifier.node_group.interface.items_tree["Offset"].identifier
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    staleness = ext.bridge.staleness
    assert staleness.stale_reason(bar, cached=True) is None
    set_input(modifier, identifier, value)
    bpy.context.view_layer.update()
    stale = "'Bar': the modifiers changed since Prepare Body: prepare again"
    assert f"'Bar': {staleness.stale_reason(bar, cached=True)}" == stale
    draw_all()
    for operator in (bpy.ops.rs_elastic.simulate, bpy.ops.rs_elastic.solve_spacetime):
        assert refusal(operator) == stale
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert staleness.stale_reason(bar) is None


def test_geometry_nodes_added_after_prepare_is_a_stale_body(ext):
    """Before: a pass-through Geometry Nodes modifier added after Prepare made Simulate, Solve
    and the panel's staleness check raise TypeError."""
    bar = small_bar(use_scene_range=False, frame_start=1, frame_end=4)
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    geometry_nodes(bar)
    stale = "'Bar': the modifiers changed since Prepare Body: prepare again"
    assert f"'Bar': {ext.bridge.staleness.stale_reason(bar, cached=True)}" == stale
    draw_all()
    for operator in (bpy.ops.rs_elastic.simulate, bpy.ops.rs_elastic.solve_spacetime):
        assert refusal(operator) == stale


def test_a_layout_change_or_a_reopen_is_not_a_change(ext, tmp_path):
    """Moving nodes leaves the body prepared, and so does a save and reopen (Blender 4.x keeps
    the inputs as ID properties, whose booleans come back as integers)."""
    def build(group, into, out):
        lift(group, into, out)
        group.interface.new_socket("Offset", in_out='INPUT', socket_type='NodeSocketVector')

    bar = small_bar()
    modifier = geometry_nodes(bar, build)
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    modifier.node_group.nodes["Group Input"].location.x -= 300.0
    bar.update_tag()
    bpy.context.view_layer.update()
    assert ext.bridge.staleness.stale_reason(bar) is None
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "nodes.blend"))
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "nodes.blend"))
    assert ext.bridge.staleness.stale_reason(bpy.data.objects["Bar"]) is None


# --- the mesher's time limit and the estimate ----------------------------------------------------

def test_a_default_solidify_on_a_closed_bar_stops_at_the_time_limit(ext):
    """Before: fTetWild ran for its full 600 s (or 191 s here) on this thin hollow shell before a
    one-line refusal. Now the object's Time Limit stops it, and the line says what to do. The
    shell's estimate is at the top of the thinness range (about 10 s): under a 5 s limit it is
    refused before fTetWild starts, so the limit here is just above the estimate."""
    bar = small_bar()
    seconds = ext.solver.proxy.tetwild_seconds(96, ext.solver.proxy.THINNESS_RANGE[1])
    limit = float(int(seconds) + 2)
    bar.rs_elastic.mesher_time_limit = limit
    bar.modifiers.new("Solidify", 'SOLIDIFY')
    start = time.monotonic()
    message = refusal(bpy.ops.rs_elastic.prepare)
    assert time.monotonic() - start < limit + 20.0
    assert message == (f"'Bar': fTetWild did not finish within its Time Limit of {limit:g} s "
                       f"(estimated {seconds:.0f} s for 96 triangles): try a coarser Edge "
                       "Length, fewer Proxy Triangles, a larger Envelope, or a higher Time Limit")


def panel_estimate():
    """The Tet Mesh panel's estimate sentence (the same in each editor that shows the panel).
    The panel wraps it into short labels (panels/body.py draw_lines, breaking at spaces and after
    ': '); it ends with the time limit's ')'."""
    labels = [text for kind, text in draw_all() if kind == "label"]
    sentences = set()
    for start in (i for i, text in enumerate(labels) if text.startswith("fTetWild meshes")):
        parts = [labels[start]]
        while not parts[-1].endswith(")") and start + len(parts) < len(labels):
            parts.append(labels[start + len(parts)])
        sentences.add(" ".join(parts))
    assert len(sentences) == 1, sentences
    return sentences.pop()


def test_the_estimate_counts_what_the_modifiers_make(ext):
    """Subdivision level 3 makes 64x the bar's faces: the panel's estimate names them and their
    proxy, with the time limit (before: it counted the base mesh's 48 triangles)."""
    bar = small_bar()
    bar.modifiers.new("Subdivision", 'SUBSURF').levels = 3
    bpy.context.view_layer.update()
    triangles, meshed = ext.bridge.estimates.mesh_estimate(bar, bar.rs_elastic)
    assert triangles == 64 * 48 and meshed == min(triangles, ext.solver.proxy.MIN_BUDGET)
    seconds = ext.solver.proxy.tetwild_seconds(meshed, estimated_thinness(ext, bar))
    assert panel_estimate() == (f"fTetWild meshes a {meshed:,}-triangle proxy of {triangles:,}: "
                                f"roughly {seconds:.0f} s (limit 120 s)")
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}


def estimated_thinness(ext, obj):
    """The panel's thinness (from polygon areas and centres), checked against the solver's of the
    evaluated surface's triangles (same divergence theorem, another path)."""
    thinness = ext.bridge.estimates.surface_estimate(obj, obj.rs_elastic)[3]
    V, F = evaluated_surface(ext, obj)
    assert thinness == pytest.approx(
        ext.solver.proxy.surface_thinness(V, F, obj.rs_elastic.edge_length), rel=1e-3)
    return thinness


def open_sphere(segments=128, rings=64):
    """A UV sphere with one face deleted: dense, and not a closed manifold."""
    bpy.ops.mesh.primitive_uv_sphere_add(segments=segments, ring_count=rings, radius=1.0)
    sphere = bpy.context.active_object
    bpy.ops.object.mode_set(mode='EDIT')
    bpy.ops.mesh.select_all(action='DESELECT')
    bpy.ops.object.mode_set(mode='OBJECT')
    sphere.data.polygons[len(sphere.data.polygons) // 2].select = True
    bpy.ops.object.mode_set(mode='EDIT')
    bpy.ops.mesh.delete(type='ONLY_FACE')
    bpy.ops.object.mode_set(mode='OBJECT')
    sphere.rs_elastic.num_modes = 6
    make_active(sphere)
    return sphere


def test_a_dense_open_surface_is_refused_at_once_with_its_estimate(ext):
    """Not a closed manifold, so no proxy: fTetWild would mesh all of it. Its estimate is over
    the limit, so Prepare refuses before fTetWild starts, and the panel says so first."""
    sphere = open_sphere()
    sphere.rs_elastic.mesher_time_limit = 5.0
    triangles = sum(len(p.vertices) - 2 for p in sphere.data.polygons)
    seconds = ext.solver.proxy.tetwild_seconds(triangles, estimated_thinness(ext, sphere))
    assert seconds > 5.0
    assert ext.bridge.estimates.mesh_estimate(sphere, sphere.rs_elastic) == (triangles, triangles)
    assert panel_estimate() == (f"fTetWild meshes all {triangles:,} triangles (not a closed "
                                f"manifold, so no proxy): roughly {seconds:.0f} s (limit 5 s)")
    drawn = draw_all()                                  # the line, wrapped after its ': '
    assert ("label", "Over the Time Limit:") in drawn
    assert ("label", "a new tet mesh is refused") in drawn
    start = time.monotonic()
    message = refusal(bpy.ops.rs_elastic.prepare)
    assert time.monotonic() - start < 10.0
    assert message == (f"'Sphere' is not a closed manifold, so fTetWild would mesh all "
                       f"{triangles:,} of its triangles, roughly {seconds:.0f} s, over its Time "
                       "Limit of 5 s: close the surface so that a simplified proxy can stand "
                       "in for it, or raise the Time Limit")
    assert ext.bridge.stage_cache.stats["tetrahedralize"] == 0


def test_ocean_displacing_the_body_is_a_deformer(ext):
    """The Ocean modifier's Displace geometry deforms the mesh: the body prepares on it (its
    default Generate geometry replaces the mesh and is refused: see the sweep)."""
    bar = small_bar()
    ocean = bar.modifiers.new("Ocean", 'OCEAN')
    ocean.geometry_mode = 'DISPLACE'
    bpy.context.view_layer.update()
    V, F = evaluated_surface(ext, bar)
    assert len(F) == 48 and not np.allclose(V, vertices(bar))
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
