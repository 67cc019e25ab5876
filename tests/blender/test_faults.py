"""The fault suite (issue 10): every bad input, command-line misuse and user-data case is a row.

Each refusal row asserts the exact one-line message and an unchanged `user_fingerprint` (mesh,
the user's shape keys and their keyframes, settings, every object). Each ownership row runs the
real operators around the user's data and asserts the same fingerprint afterwards.
"""
import bpy
import numpy as np
import pytest

from blender_helpers import link_mesh, make_active, make_bar, user_fingerprint, vertices


# --- helpers ----------------------------------------------------------------------------------------

def refusal(operator):
    """The one error line the operator reports; it must refuse (raise) and change nothing."""
    before = user_fingerprint()
    with pytest.raises(RuntimeError) as info:
        operator()
    assert user_fingerprint() == before
    lines = [line.removeprefix("Error: ") for line in str(info.value).strip().splitlines()]
    assert len(lines) == 1, lines
    return lines[0]


def small_bar(**settings):
    """A 4×1×1 bar pinned at x = 0, coarse enough to prepare in seconds."""
    obj = make_bar()
    obj.rs_elastic.edge_length, obj.rs_elastic.num_modes = 0.15, 6
    for name, value in settings.items():
        setattr(obj.rs_elastic, name, value)
    return obj


def prepared_bar(frames=(1, 4)):
    obj = small_bar(use_scene_range=False, frame_start=frames[0], frame_end=frames[1])
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    return obj


def cube(name="Cube", offset=(0.0, 0.0, 0.0)):
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0, 0, 0))
    obj = bpy.context.active_object
    obj.name = name
    co = vertices(obj) + np.asarray(offset)
    obj.data.vertices.foreach_set("co", co.ravel())
    obj.data.update()
    obj.rs_elastic.edge_length, obj.rs_elastic.num_modes = 0.1, 6
    return obj


def key_names(obj):
    keys = obj.data.shape_keys
    return [] if keys is None else [k.name for k in keys.key_blocks]


def add_user_key(obj, name, offset=0.0, keyed_frames=()):
    """A shape key of the user's: its data moved by `offset`, its value keyed on some frames."""
    block = obj.shape_key_add(name=name, from_mix=False)
    if offset:
        block.data.foreach_set("co", (vertices(obj) + offset).astype(np.float32).ravel())
    for frame in keyed_frames:
        block.value = 0.3
        block.keyframe_insert("value", frame=frame)
    return block


# --- bad input: the operators refuse with one message and change nothing -----------------------------

LINKED = ("'Bar' shares its mesh 'Cube' with 1 other object(s): make it single-user first "
          "(Object > Relations > Make Single User > Object & Data)")


def no_active_object():
    bpy.context.view_layer.objects.active = None


def a_camera():
    bpy.ops.object.camera_add()


def an_empty_mesh():
    link_mesh("Empty", [], [])


def a_flat_mesh():
    bpy.ops.mesh.primitive_grid_add()


def bar_with(**settings):
    return lambda: small_bar(**settings)


def linked_duplicate():
    obj = small_bar()
    twin = obj.copy()                 # shares obj.data, as Alt+D does
    bpy.context.scene.collection.objects.link(twin)
    make_active(obj)


def mirrored_bar():
    small_bar().modifiers.new("Mirror", 'MIRROR')


def arrayed_bar():
    small_bar().modifiers.new("Row", 'ARRAY')


def bar_mirrored_in_renders():
    small_bar().modifiers.new("Mirror", 'MIRROR').show_viewport = False


def bar_missing_pin_group():
    small_bar().rs_elastic.pin_group = "Nope"


def bar_all_pinned():
    obj = small_bar()
    obj.vertex_groups["Pin"].add(list(range(len(obj.data.vertices))), 1.0, 'REPLACE')


PREPARE, TETRAHEDRALIZE = "prepare", "tetrahedralize"
FLAT = ("'Grid': the surface is flat (it has no thickness), so it encloses no volume; "
        "give it thickness (e.g. a Solidify modifier) first")

REFUSALS = [
    ("no active object", no_active_object, PREPARE, "No active object: select a mesh object"),
    ("no active object", no_active_object, TETRAHEDRALIZE, "No active object: select a mesh object"),
    ("not a mesh", a_camera, PREPARE, "'Camera' is a camera, not a mesh"),
    ("not a mesh", a_camera, TETRAHEDRALIZE, "'Camera' is a camera, not a mesh"),
    ("empty mesh", an_empty_mesh, PREPARE, "'Empty' has an empty mesh (no faces)"),
    ("empty mesh", an_empty_mesh, TETRAHEDRALIZE, "'Empty' has an empty mesh (no faces)"),
    ("flat mesh", a_flat_mesh, PREPARE, FLAT),
    ("flat mesh", a_flat_mesh, TETRAHEDRALIZE, FLAT),
    ("poisson 0.5", bar_with(poisson_ratio=0.5), PREPARE,
     "Poisson's ratio must lie strictly between -1 and 0.5 (got 0.5)"),
    ("poisson 0.7", bar_with(poisson_ratio=0.7), PREPARE,
     "Poisson's ratio must lie strictly between -1 and 0.5 (got 0.7)"),
    ("poisson -1", bar_with(poisson_ratio=-1.0), PREPARE,
     "Poisson's ratio must lie strictly between -1 and 0.5 (got -1)"),
    ("poisson nan", bar_with(poisson_ratio=float("nan")), PREPARE,
     "'Bar': Poisson's Ratio is nan; it must be a finite number"),
    ("density inf", bar_with(density=float("inf")), PREPARE,
     "'Bar': Density is inf; it must be a finite number"),
    ("density inf", bar_with(density=float("inf")), TETRAHEDRALIZE,
     "'Bar': Density is inf; it must be a finite number"),
    ("density 0", bar_with(density=0.0), PREPARE,
     "Density must be above 0 and at most 1e+06 kg/m³, got 0 kg/m³"),
    ("density negative", bar_with(density=-5.0), PREPARE,
     "Density must be above 0 and at most 1e+06 kg/m³, got -5 kg/m³"),
    ("density absurd", bar_with(density=1e9), PREPARE,
     "Density must be above 0 and at most 1e+06 kg/m³, got 1e+09 kg/m³"),
    ("young 0", bar_with(youngs_modulus=0.0), PREPARE,
     "Young's modulus must be above 0 and at most 1e+13 Pa, got 0 Pa"),
    ("young negative", bar_with(youngs_modulus=-1e6), PREPARE,
     "Young's modulus must be above 0 and at most 1e+13 Pa, got -1e+06 Pa"),
    ("young inf", bar_with(youngs_modulus=float("inf")), PREPARE,
     "'Bar': Young's Modulus is inf; it must be a finite number"),
    ("damping nan", bar_with(damping_mass=float("nan")), PREPARE,
     "'Bar': Mass Damping is nan; it must be a finite number"),
    ("not prepared", bar_with(), "simulate",
     "'Bar' is not prepared for its current mesh: run Prepare Body"),
    ("not prepared", bar_with(), "solve_spacetime",
     "'Bar' is not prepared for its current mesh: run Prepare Body"),
    ("no bake", bar_with(), "keep_take", "'Bar' has no bake to keep"),
    ("missing pin group", bar_missing_pin_group, PREPARE,
     "Pin group 'Nope' does not exist on 'Bar'"),
    ("every vertex pinned", bar_all_pinned, PREPARE,
     "Every vertex of 'Bar' is in pin group 'Pin': nothing is left free to move"),
    ("linked duplicate", linked_duplicate, PREPARE, LINKED),
    ("linked duplicate", linked_duplicate, TETRAHEDRALIZE, LINKED),
    ("linked duplicate", linked_duplicate, "clear_bake", LINKED),
    ("linked duplicate", linked_duplicate, "keep_take", LINKED),
    ("mirror modifier", mirrored_bar, PREPARE,
     "'Bar' has a Mirror modifier ('Mirror'), which would copy the baked motion: apply the "
     "Mirror modifier first"),
    ("mirror modifier", mirrored_bar, TETRAHEDRALIZE,
     "'Bar' has a Mirror modifier ('Mirror'), which would copy the baked motion: apply the "
     "Mirror modifier first"),
    ("mirror in renders only", bar_mirrored_in_renders, PREPARE,
     "'Bar' has a Mirror modifier ('Mirror'), which would copy the baked motion: apply the "
     "Mirror modifier first"),
    ("array modifier", arrayed_bar, PREPARE,
     "'Bar' has a Array modifier ('Row'), which would copy the baked motion: apply the "
     "Array modifier first"),
]


@pytest.mark.parametrize("setup, operator, message",
                         [pytest.param(*row[1:], id=f"{row[0]}-{row[2]}") for row in REFUSALS])
def test_refused(setup, operator, message):
    setup()
    assert refusal(getattr(bpy.ops.rs_elastic, operator)) == message


def test_more_modes_than_the_body_has():
    small_bar(edge_length=0.2, num_modes=100000)
    message = refusal(bpy.ops.rs_elastic.prepare)
    assert message.startswith("'Bar': ") and "100000" in message and "modes" in message


# --- bad input to a prepared body: simulate and solve refuse -----------------------------------------

def absurd_gravity(obj):
    bpy.context.scene.gravity = (0.0, 0.0, -1e30)


def infinite_gravity(obj):
    bpy.context.scene.gravity = (0.0, float("inf"), 0.0)


def two_frames(obj):
    obj.rs_elastic.frame_start, obj.rs_elastic.frame_end = 5, 6


def too_many_frames(obj):
    obj.rs_elastic.frame_start, obj.rs_elastic.frame_end = 1, 20000


def linked_after_prepare(obj):
    bpy.context.scene.collection.objects.link(obj.copy())


def mirror_after_prepare(obj):
    obj.modifiers.new("Mirror", 'MIRROR')


def deleted_handle_empty(obj):
    assert bpy.ops.rs_elastic.add_handle(vertex_group="Pin") == {'FINISHED'}
    bpy.data.objects.remove(obj.rs_elastic.handles[0].empty)
    bpy.context.view_layer.objects.active = obj


def infinite_handle_weight(obj):
    assert bpy.ops.rs_elastic.add_handle(vertex_group="Pin") == {'FINISHED'}
    obj.rs_elastic.handles[0].weight = float("inf")
    make_active(obj)


GRAVITY = "The scene's gravity is {} m/s²; it must be finite and at most 1000 m/s²"

PREPARED_REFUSALS = [
    ("absurd gravity", absurd_gravity, "simulate", GRAVITY.format("1e+30")),
    ("infinite gravity", infinite_gravity, "simulate", GRAVITY.format("3.4e+38")),
    ("no frames", two_frames, "simulate", "The frame range 5–6 has fewer than 3 frames"),
    ("no frames", two_frames, "solve_spacetime", "The frame range 5–6 has fewer than 3 frames"),
    ("too many frames", too_many_frames, "simulate",
     "The frame range 1–20000 has more than 10000 frames"),
    ("linked duplicate", linked_after_prepare, "simulate", LINKED),
    ("mirror modifier", mirror_after_prepare, "simulate",
     "'Bar' has a Mirror modifier ('Mirror'), which would copy the baked motion: apply the "
     "Mirror modifier first"),
    ("mirror modifier", mirror_after_prepare, "solve_spacetime",
     "'Bar' has a Mirror modifier ('Mirror'), which would copy the baked motion: apply the "
     "Mirror modifier first"),
    ("handle empty deleted", deleted_handle_empty, "solve_spacetime",
     "Nothing to solve for on 'Bar': key a handle's Empty, key a shape key to 1 on a frame, or "
     "edit a take (Handle 1: its Empty was deleted; the handle is ignored)"),
    ("handle weight inf", infinite_handle_weight, "solve_spacetime",
     "'Bar': Weight is inf; it must be a finite number"),
]


@pytest.mark.parametrize("change, operator, message",
                         [pytest.param(*row[1:], id=f"{row[0]}-{row[2]}")
                          for row in PREPARED_REFUSALS])
def test_prepared_body_refused(change, operator, message):
    obj = prepared_bar()
    change(obj)
    assert refusal(getattr(bpy.ops.rs_elastic, operator)) == message
    assert key_names(obj) == []


# --- a motion that blows up is never baked ------------------------------------------------------------

@pytest.mark.parametrize("bad, message", [
    (np.nan, "The motion of 'Bar' blew up (non-finite positions); nothing was baked"),
    (1e6, "The motion of 'Bar' blew up (2.36e+05 times its size at rest); check gravity, "
          "material and damping. Nothing was baked"),
])
def test_blown_up_simulation_is_not_baked(ext, monkeypatch, bad, message):
    obj = prepared_bar()
    run = ext.solver.dynamics.Simulation.run

    def blow_up(self, steps, **kwargs):
        trajectory = run(self, steps, **kwargs)
        original = trajectory.body_displacements

        def displacements(rows):          # the last frame's first vertex flies off
            d = original(rows)
            d[-1, 0, 0] += bad
            return d
        trajectory.body_displacements = displacements
        return trajectory

    monkeypatch.setattr(ext.solver.dynamics.Simulation, "run", blow_up)
    assert refusal(bpy.ops.rs_elastic.simulate) == message
    assert key_names(obj) == []


def test_blown_up_solve_is_not_baked(ext, monkeypatch):
    obj = prepared_bar()
    tip = obj.vertex_groups.new(name="Tip")
    tip.add([v.index for v in obj.data.vertices if v.co.x > 3.99], 1.0, 'REPLACE')
    assert bpy.ops.rs_elastic.add_handle(vertex_group="Tip") == {'FINISHED'}
    empty = obj.rs_elastic.handles[0].empty
    empty.location.z += 0.5
    empty.keyframe_insert("location", frame=3)
    bpy.context.view_layer.objects.active = obj
    solve = ext.solver.spacetime.solve

    def blow_up(*args, **kwargs):
        result = solve(*args, **kwargs)
        result.Z[-1] = np.nan            # inputs = Z Sᵀ: the last frame is lost
        return result

    monkeypatch.setattr(ext.solver.spacetime, "solve", blow_up)
    assert refusal(bpy.ops.rs_elastic.solve_spacetime) == (
        "The motion of 'Bar' blew up (non-finite positions); nothing was baked")
    assert key_names(obj) == []


# --- the user's data: operators never touch what they did not make ------------------------------------

def bake_then_clear(obj):
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    assert bpy.ops.rs_elastic.clear_bake() == {'FINISHED'}


def bake_keep_bake_clear(obj):
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    assert bpy.ops.rs_elastic.keep_take() == {'FINISHED'}
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    assert bpy.ops.rs_elastic.clear_bake() == {'FINISHED'}


def preview_on_off(obj):
    obj.rs_elastic.preview_enabled = True
    assert "RS Elastic Preview" in key_names(obj)
    obj.rs_elastic.preview_enabled = False


@pytest.mark.parametrize("user_keys", [["Rest"], ["Rest", "RS Bake notes"],
                                       ["Basis", "RS Take notes", "RS Elastic Preview notes"]],
                         ids=["first key Rest", "key RS Bake notes", "keys named like ours"])
@pytest.mark.parametrize("actions", [bake_then_clear, bake_keep_bake_clear, preview_on_off],
                         ids=["bake+clear", "bake+take+bake+clear", "preview"])
def test_user_keys_survive(user_keys, actions):
    obj = prepared_bar()
    add_user_key(obj, user_keys[0])
    for i, name in enumerate(user_keys[1:], start=1):
        add_user_key(obj, name, offset=0.01 * i, keyed_frames=(1, 3))
    before, names = user_fingerprint(), key_names(obj)
    actions(obj)
    remaining = [n for n in key_names(obj) if not n.startswith("RS Take 0")]
    assert remaining == names
    assert obj.data.shape_keys.reference_key.name == user_keys[0]
    assert user_fingerprint() == before


def test_the_basis_we_made_goes_with_the_bake():
    obj = prepared_bar()
    before = user_fingerprint()
    bake_then_clear(obj)
    assert obj.data.shape_keys is None
    assert user_fingerprint() == before


def test_linked_duplicates_keep_each_others_bake():
    """A duplicate made single-user (the fix the refusal names) bakes on its own keys."""
    obj = prepared_bar()
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    twin = obj.copy()
    bpy.context.scene.collection.objects.link(twin)
    baked = key_names(obj)
    assert refusal(bpy.ops.rs_elastic.clear_bake) == LINKED.replace("Cube", obj.data.name)
    twin.data = obj.data.copy()       # Make Single User > Object & Data
    assert bpy.ops.rs_elastic.clear_bake() == {'FINISHED'}
    assert key_names(twin) == baked and key_names(obj) == []


def test_a_bake_from_before_tagging_is_cleared(ext):
    """An untagged bake (keys named RS Bake NNNN with the 0-1-0 step) is recognised and cleared;
    a user's key with a similar name is not, and the untagged Basis is kept."""
    obj = small_bar()
    obj.shape_key_add(name="Basis", from_mix=False)
    notes = add_user_key(obj, "RS Bake notes", keyed_frames=(2,))
    fake = add_user_key(obj, "RS Bake 0009")                # a user's key: no bake F-curve
    for frame in (1, 2, 3):
        name = f"RS Bake {frame:04d}"
        add_user_key(obj, name, offset=0.1 * frame)
        ext.bridge.animation.insert_keys(obj.data.shape_keys, f'key_blocks["{name}"].value',
                                         [(frame - 1, 0.0), (frame, 1.0), (frame + 1, 0.0)],
                                         'CONSTANT')
    assert "rs_elastic" not in obj.data.shape_keys
    assert ext.bridge.bake.bake_frames(obj) == [1, 2, 3]
    assert bpy.ops.rs_elastic.clear_bake() == {'FINISHED'}
    assert key_names(obj) == ["Basis", notes.name, fake.name]


@pytest.mark.parametrize("kind", ['SUBSURF', 'DISPLACE'])
def test_subdivision_and_deforming_modifiers_stay_supported(kind):
    obj = small_bar(use_scene_range=False, frame_start=1, frame_end=4)
    obj.modifiers.new(kind.title(), kind)
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert bpy.ops.rs_elastic.simulate() == {'FINISHED'}
    assert len(key_names(obj)) == 1 + 4


# --- settings at the ends of their declared range --------------------------------------------------------

def test_one_mode():
    small_bar(num_modes=1)
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert len(bpy.context.active_object.rs_elastic.frequencies) == 1


def first_frequency(obj):
    make_active(obj)
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    return obj.rs_elastic.frequencies[0]


def test_loose_vertex_is_left_out_of_the_tets():
    plain = first_frequency(cube("Plain"))
    loose = cube("Loose")
    loose.data.vertices.add(1)
    loose.data.vertices[-1].co = (10.0, 10.0, 10.0)
    loose.data.update()
    assert first_frequency(loose) == pytest.approx(plain, rel=0.05)


def test_coarsest_pinned_cube():
    """The declared largest edge length on a small pinned body (few tet nodes) prepares."""
    obj = cube()
    obj.rs_elastic.edge_length = 0.5
    group = obj.vertex_groups.new(name="Pin")
    group.add([v.index for v in obj.data.vertices if v.co.z < 0], 1.0, 'REPLACE')
    obj.rs_elastic.pin_group = "Pin"
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    assert obj.rs_elastic.frequencies[0] > 0.0


def test_far_from_the_origin():
    """Position does not matter to the mesher (it meshes in unit coordinates): a cube 10 km away
    prepares like one at the origin, without fTetWild blocking."""
    plain = first_frequency(cube("Plain"))
    assert first_frequency(cube("Far", offset=(1e4, 0.0, 0.0))) == pytest.approx(plain, rel=0.05)


def test_too_far_for_blenders_float32_coordinates():
    """At 1e7 m Blender's float32 vertex coordinates are 1 m apart: the unit cube collapses, and
    that is said at once (before: fTetWild blocked for 600 s)."""
    cube("Far", offset=(1e7, 0.0, 0.0))
    assert refusal(bpy.ops.rs_elastic.prepare) == (
        "'Far': the surface is flat (it has no thickness), so it encloses no volume; give it "
        "thickness (e.g. a Solidify modifier) first")


# --- the command line: bad arguments exit 2, failures exit 1, each with one line ---------------------

def saved_bar(tmp_path, **settings):
    obj = small_bar(**settings)
    blend = tmp_path / "shot.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    return obj, blend


CLI_ROWS = [
    ("unknown object", ["--object", "Nobody"], 2, "no object named 'Nobody' in {blend}"),
    ("not a mesh", ["--object", "Camera"], 2, "'Camera' is a camera, not a mesh"),
    ("frames abc", ["--object", "Bar", "--frames", "abc"], 2,
     "--frames must look like 1-120, got 'abc'"),
    ("frames empty", ["--object", "Bar", "--frames", ""], 2,
     "--frames must look like 1-120, got ''"),
    ("frames 5-1", ["--object", "Bar", "--frames", "5-1"], 2,
     "--frames 5-1 has fewer than 3 frames (start before end)"),
    ("frames too many", ["--object", "Bar", "--frames", "1-20000"], 2,
     "--frames 1-20000 is too long: at most 10000 frames, ending by frame 1048574"),
    ("output folder missing", ["--object", "Bar", "--output", "{tmp}/nowhere/out.blend"], 2,
     "--output: the folder {tmp}/nowhere does not exist"),
    ("output not .blend", ["--object", "Bar", "--output", "{tmp}/out.txt"], 2,
     "--output must be a .blend file, got '{tmp}/out.txt'"),
    ("output is a folder", ["--object", "Bar", "--output", "{tmp}/dir.blend"], 2,
     "--output: {tmp}/dir.blend is a folder"),
    ("no --object", [], 2, "the following arguments are required: --object"),
    ("unknown mode", ["--object", "Bar", "--mode", "dance"], 2,
     "argument --mode: invalid choice: 'dance' (choose from 'simulate', 'spacetime')"),
    ("nothing to solve", ["--object", "Bar"], 1,
     "Nothing to solve for on 'Bar': key a handle's Empty, key a shape key to 1 on a frame, "
     "or edit a take"),
    ("bad material", ["--object", "Bar", "--mode", "simulate"], 1,
     "'Bar': Density is inf; it must be a finite number", {"density": float("inf")}),
]


def test_command_line_on_a_file_never_saved(ext, capsys):
    obj = small_bar()
    before = user_fingerprint()
    assert ext.bridge.cli.main(["bake", "--object", "Bar"]) == 2
    assert capsys.readouterr().err.splitlines() == [
        "rs_elastic: error: the open file was never saved: pass --output FILE.blend"]
    assert not obj.rs_elastic.is_prepared and user_fingerprint() == before


def test_command_line_in_a_new_blender_process(tmp_path):
    """The same handler as `blender -b shot.blend -c rs_elastic …`: one line, exit 2."""
    from test_spacetime import run_cli
    _, blend = saved_bar(tmp_path)
    saved = blend.read_bytes()
    result = run_cli(blend, ["bake", "--object", "Bar", "--frames", "abc"])
    assert result.returncode == 2
    errors = [line for line in result.stderr.splitlines() if "rs_elastic" in line]
    assert errors == ["rs_elastic: error: --frames must look like 1-120, got 'abc'"]
    assert "Traceback" not in result.stderr + result.stdout
    assert blend.read_bytes() == saved


@pytest.mark.parametrize("argv, code, message, settings",
                         [pytest.param(*row[1:4], row[4] if len(row) > 4 else {}, id=row[0])
                          for row in CLI_ROWS])
def test_command_line(ext, tmp_path, capsys, argv, code, message, settings):
    obj, blend = saved_bar(tmp_path, **settings)
    bpy.ops.object.camera_add()
    (tmp_path / "dir.blend").mkdir()
    make_active(obj)
    saved = blend.read_bytes()
    before = user_fingerprint()
    argv = ["bake"] + [a.format(tmp=tmp_path) for a in argv]
    capsys.readouterr()
    assert ext.bridge.cli.main(argv) == code
    out, err = capsys.readouterr()
    # stderr is one line; stdout may only hold Blender's own echo of an operator's report.
    assert err.splitlines() == [f"rs_elastic: error: {message.format(blend=blend, tmp=tmp_path)}"]
    assert "Traceback" not in out and "rs_elastic:" not in out
    if code == 2:                                      # refused before any work
        assert not obj.rs_elastic.is_prepared and obj.rs_elastic.tet_count == 0
    assert blend.read_bytes() == saved                 # the open file is never overwritten
    assert not (tmp_path / "out.blend").exists() and not (tmp_path / "out.txt").exists()
    assert user_fingerprint() == before
