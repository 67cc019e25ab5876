"""`make demo`: build scenes from nothing with the installed extension, save them and render.

1. The showcase (demo.blend, demo.png, a contact sheet of frames):
   - a rubber bar pinned at one end whose tip is pulled through two keyed Empties and released,
     solved by space-time editing with material optimisation and baked;
   - a jelly antenna pinned at its foot, simulated under gravity;
   - a free jelly cube dropped onto a floor (a plane with a Collision modifier), simulated;
   - a keyed prop (a rubber rod carried sideways and stopped), simulated: its secondary motion
     swings its top into a wall (another Collision plane), which stops it.
2. Modes (modes.blend, modes.png): a pinned bar and a free Suzanne at rest, along their first
   mode by the linear preview (which stretches and inflates) and by the RS preview at the same
   amplitude (which bends and keeps its volume).
3. A rigged creature (rig.blend, rig.png): the same keyed creature (tools/creature.py: it hops
   and flicks an ear) twice, on the left with its rig alone, on the right with its belly and
   ears simulated on the rig as free flesh.
4. The material recovered from an animation (fit.blend, fit.png): a bar whose stiffness falls
   threefold from root to tip (painted) is carried up and let ring, simulated, as the reference;
   a second, uniform bar takes that motion (Take from Animation), fits its material to frames
   10-60 (Fit Material) and plays on from there (Continue); the sheet shows frames after the
   fit, the reference above the continuation.
"""
import argparse
import os
import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import blender_session  # noqa: E402
import creature  # noqa: E402

SHEET_FRAMES = (1, 14, 22, 30, 44, 72)
FIT_RANGE, FIT_END = (10, 60), 108      # the fitted frames, the continuation's last frame
FIT_SHEET_FRAMES = (64, 72, 80, 88, 96, 104)
RIG_FRAMES = (1, 7, 10, 13, 16, 20)
TILE = (640, 360)
ROW_GAP = 3.4   # metres between the rows of the modes picture


def parse_args():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--output", default="demo_output")
    parser.add_argument("--zip", default=os.environ.get("RS_ELASTIC_ZIP"))
    return parser.parse_args()


# --- scene building ---------------------------------------------------------------------------

def make_box(bpy, np, name, size, cuts, pin_axis=0, location=(0.0, 0.0, 0.0)):
    """A box of `size` starting at the origin along +`pin_axis`, pinned at that end ('Pin')."""
    bpy.ops.mesh.primitive_cube_add(size=1.0)
    obj = bpy.context.active_object
    obj.name = name
    bpy.ops.object.mode_set(mode='EDIT')
    bpy.ops.mesh.subdivide(number_cuts=cuts)
    bpy.ops.object.mode_set(mode='OBJECT')
    co = np.empty(len(obj.data.vertices) * 3)
    obj.data.vertices.foreach_get("co", co)
    shift = np.full(3, 0.0)
    if pin_axis is not None:
        shift[pin_axis] = 0.5
    co = (co.reshape(-1, 3) + shift) * np.array(size)
    obj.data.vertices.foreach_set("co", co.ravel())
    obj.data.update()
    if pin_axis is not None:
        pin = obj.vertex_groups.new(name="Pin")
        pin.add([int(i) for i in np.flatnonzero(co[:, pin_axis] < 1e-6)], 1.0, 'REPLACE')
        obj.rs_elastic.pin_group = "Pin"
    obj.location = location
    bpy.ops.object.shade_smooth()
    return obj


def prepare(bpy, obj, preset, edge_length, num_modes=12):
    """Prepare `obj` with a material preset (None: keep the material already set)."""
    bpy.context.view_layer.objects.active = obj
    if preset is not None:
        bpy.ops.rs_elastic.apply_material_preset(preset=preset)
    obj.rs_elastic.edge_length = edge_length
    obj.rs_elastic.num_modes = num_modes
    if bpy.ops.rs_elastic.prepare() != {'FINISHED'}:
        sys.exit(f"demo: preparing {obj.name} failed")
    s = obj.rs_elastic
    print(f"demo: {obj.name}: {s.tet_count} tets, modes {s.frequencies[0]:.2f} … "
          f"{s.frequencies[-1]:.2f} Hz, reduced basis {s.reduced_basis_count}, "
          f"cubature {s.cubature_count} tets")


def add_collider(bpy, name, location, rotation, scale, damping, friction):
    """A plane with a Collision modifier (its normal is the side bodies stay on)."""
    bpy.ops.mesh.primitive_plane_add(size=2.0, location=location, rotation=rotation)
    plane = bpy.context.active_object
    plane.name = name
    plane.scale = scale
    plane.modifiers.new("Collision", 'COLLISION')
    plane.collision.damping = damping
    plane.collision.cloth_friction = friction
    plane.color = (0.55, 0.55, 0.58, 1.0)
    return plane


def add_label(bpy, text, location, size=0.45, name=None):
    curve = bpy.data.curves.new(name or text, 'FONT')
    curve.body = text
    curve.size = size
    curve.align_x = 'CENTER'
    label = bpy.data.objects.new(name or text, curve)
    label.location = location
    label.rotation_euler = (1.5708, 0.0, 0.0)
    bpy.context.scene.collection.objects.link(label)
    return label


def stage(bpy, camera_location, lens, resolution):
    scene = bpy.context.scene
    bpy.ops.object.camera_add(location=camera_location, rotation=(1.5708, 0.0, 0.0))
    scene.camera = bpy.context.active_object
    scene.camera.data.lens = lens
    scene.render.engine = 'BLENDER_WORKBENCH'
    scene.display.shading.light = 'STUDIO'
    scene.display.shading.color_type = 'OBJECT'
    scene.display.shading.show_cavity = True
    scene.render.resolution_x, scene.render.resolution_y = resolution
    if scene.world is None:
        scene.world = bpy.data.worlds.new("Demo")


# --- the showcase -------------------------------------------------------------------------------

def showcase(bpy, np, output):
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(output / "demo.blend"))   # caches go next to it
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 90
    scene.render.fps = 24

    # 1. Space-time: the tip is pulled up and over by two keyed Empties, then let go.
    bar = make_box(bpy, np, "Edited Bar", (4.0, 0.5, 0.5), 9, location=(-6.5, 0.0, 0.0))
    bar.color = (0.85, 0.35, 0.2, 1.0)
    prepare(bpy, bar, 'RUBBER', 0.04)
    tip = bar.vertex_groups.new(name="Tip")
    co = np.empty(len(bar.data.vertices) * 3)
    bar.data.vertices.foreach_get("co", co)
    tip.add([int(i) for i in np.flatnonzero(co.reshape(-1, 3)[:, 0] > 4.0 - 1e-6)], 1.0, 'REPLACE')
    bpy.ops.rs_elastic.add_handle(vertex_group="Tip")
    empty = bar.rs_elastic.handles[0].empty
    # Rest tip: (-2.5, 0, 0.25). Frame 14: bent up about 45°; frame 30: about 90°, then let go.
    for frame, location in ((14, (-3.2, 0.0, 2.2)), (30, (-4.4, 0.0, 3.0))):
        empty.location = location
        empty.keyframe_insert("location", frame=frame)
    bar.rs_elastic.optimize_material = True
    bar.rs_elastic.iterations = 40    # material rounds: this edit converges in about 25
    if bpy.ops.rs_elastic.solve_spacetime() != {'FINISHED'}:
        sys.exit("demo: the space-time solve failed")
    print(f"demo: {bar.name}: handle residual {bar.rs_elastic.handles[0].residual:.2g} m, "
          f"{len(bar.rs_elastic.solve_history)} objective values, last "
          f"{bar.rs_elastic.solve_history[-1].value:.4g}")

    # A floor strip under the stage and a wall the keyed prop's top swings into.
    # (The space-time bar ignores colliders, so the floor starts right of it.)
    add_collider(bpy, "Floor", (2.5, 0.0, -1.1), (0.0, 0.0, 0.0), (4.5, 1.2, 1.0),
                 damping=0.6, friction=30.0)
    add_collider(bpy, "Wall", (5.9, 0.0, 0.6), (0.0, -1.5708, 0.0), (1.7, 1.0, 1.0),
                 damping=0.6, friction=30.0)

    # 2. Simulation: a jelly antenna, pinned at its foot, sags and wobbles under gravity.
    antenna = make_box(bpy, np, "Rubber Antenna", (0.4, 0.4, 2.5), 7, pin_axis=2,
                       location=(-1.0, 0.0, -1.0))
    antenna.rotation_euler = (0.0, 0.5, 0.0)        # leaning, so gravity bends it
    antenna.color = (0.35, 0.75, 0.35, 1.0)
    bpy.context.view_layer.objects.active = antenna
    bpy.ops.rs_elastic.apply_material_preset(preset='RUBBER')
    antenna.rs_elastic.youngs_modulus = 4e6          # stiff rubber: sags and wobbles, stands
    antenna.rs_elastic.use_collisions = False        # its leaning foot is pinned in the floor
    prepare(bpy, antenna, None, 0.05, num_modes=10)
    antenna.rs_elastic.material_model = 'STVK'
    if bpy.ops.rs_elastic.simulate() != {'FINISHED'}:
        sys.exit("demo: simulating the antenna failed")

    # 3. A free jelly cube dropped onto the floor: it lands, squashes, bounces and settles.
    jelly = make_box(bpy, np, "Jelly Drop", (0.8, 0.8, 0.8), 5, pin_axis=None,
                     location=(1.4, 0.0, 1.9))
    jelly.rotation_euler = (0.3, 0.4, 0.0)           # lands on a corner, then tips over
    jelly.color = (0.9, 0.75, 0.2, 1.0)
    bpy.context.view_layer.objects.active = jelly
    bpy.ops.rs_elastic.apply_material_preset(preset='RUBBER')
    jelly.rs_elastic.youngs_modulus = 3e5
    jelly.rs_elastic.damping_mass = 0.5
    prepare(bpy, jelly, None, 0.08, num_modes=12)
    if bpy.ops.rs_elastic.simulate() != {'FINISHED'}:
        sys.exit("demo: simulating the jelly drop failed")

    # 4. Secondary motion: a rod carried sideways from frame 1 to 12, then held: its top
    #    swings on into the wall and stops there.
    prop = make_box(bpy, np, "Keyed Prop", (0.3, 0.3, 2.4), 7, pin_axis=2,
                    location=(3.0, 0.0, -1.0))
    prop.color = (0.3, 0.55, 0.85, 1.0)
    bpy.context.view_layer.objects.active = prop
    bpy.ops.rs_elastic.apply_material_preset(preset='RUBBER')
    prop.rs_elastic.youngs_modulus = 6e6
    prop.rs_elastic.damping_mass = 1.0
    prepare(bpy, prop, None, 0.05, num_modes=10)
    prop.keyframe_insert("location", frame=1)
    prop.location.x = 5.5
    prop.keyframe_insert("location", frame=12)
    bpy.context.view_layer.objects.active = prop
    if bpy.ops.rs_elastic.simulate() != {'FINISHED'}:
        sys.exit("demo: simulating the prop failed")

    for text, x in (("space-time edit", -4.5), ("gravity", -0.6), ("dropped on a floor", 1.4),
                    ("keyed prop, wall", 4.3)):
        add_label(bpy, text, (x, 0.0, -1.7), 0.35)
    frame_label = add_label(bpy, "frame", (-6.8, 0.0, 3.8), 0.45, name="Frame Label")
    stage(bpy, (-0.7, -15.0, 0.6), 33, TILE)
    scene.frame_set(1)
    bpy.ops.wm.save_mainfile()
    contact_sheet(bpy, np, frame_label, output / "demo.png")


def contact_sheet(bpy, np, frame_label, path, frames=SHEET_FRAMES):
    """Render six frames and tile them 3 × 2 into one picture."""
    scene = bpy.context.scene
    tiles = []
    for frame in frames:
        scene.frame_set(frame)
        frame_label.data.body = f"frame {frame}"
        scene.render.filepath = str(path.with_name(f".tile_{frame}.png"))
        bpy.ops.render.render(write_still=True)
        image = bpy.data.images.load(scene.render.filepath)
        pixels = np.empty(image.size[0] * image.size[1] * 4, dtype=np.float32)
        image.pixels.foreach_get(pixels)
        tiles.append(pixels.reshape(image.size[1], image.size[0], 4))
        bpy.data.images.remove(image)
        os.remove(scene.render.filepath)
    rows = [np.concatenate(tiles[i:i + 3], axis=1) for i in (3, 0)]   # images are bottom-up
    sheet = np.concatenate(rows, axis=0)
    image = bpy.data.images.new("Contact Sheet", sheet.shape[1], sheet.shape[0], alpha=True)
    image.pixels.foreach_set(sheet.ravel())
    image.filepath_raw = str(path)
    image.file_format = 'PNG'
    image.save()
    bpy.data.images.remove(image)
    print(f"demo: wrote {path}")


# --- linear against RS ----------------------------------------------------------------------------

def row_copy(bpy, obj, label, row):
    """A copy `row` rows up, with its own mesh so each row's preview key is its own."""
    copy = obj.copy()
    copy.data = obj.data.copy()
    copy.name = f"{obj.name} ({label})"
    copy.location.z += row * ROW_GAP
    bpy.context.scene.collection.objects.link(copy)
    return copy


def modes_picture(bpy, np, output):
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(output / "modes.blend"))
    # Thinner in z than in y, so the first mode bends it up and down, towards no camera.
    bar = make_box(bpy, np, "Rubber Bar", (4.0, 0.6, 0.4), 9, location=(-4.5, 0.0, 0.0))
    bpy.ops.mesh.primitive_monkey_add(size=2.0, location=(3.0, 0.0, 0.0))
    suzanne = bpy.context.active_object
    suzanne.name = "Suzanne"
    bpy.ops.object.shade_smooth()
    # Large amplitudes: the bar's linear tip displacement is about 4× its thickness.
    for obj, edge, amplitude in ((bar, 0.03, 0.5), (suzanne, 0.05, 0.25)):
        prepare(bpy, obj, 'RUBBER', edge)
        obj.rs_elastic.preview_amplitude = amplitude
    for obj, color in ((bar, (0.85, 0.35, 0.2, 1.0)), (suzanne, (0.3, 0.55, 0.85, 1.0))):
        obj.color = color
        obj.rs_elastic.preview_mode = 1
        row_copy(bpy, obj, "rest", 2)
        linear = row_copy(bpy, obj, "linear", 1)
        for copy, method in ((linear, 'LINEAR'), (obj, 'RS')):
            bpy.context.view_layer.objects.active = copy
            copy.rs_elastic.preview_method = method
            copy.rs_elastic.preview_enabled = True
    for text, row in (("rest", 2), ("linear mode 1", 1), ("RS mode 1", 0)):
        add_label(bpy, text, (-8.2, 0.0, row * ROW_GAP + 0.9))
    for obj, x in ((bar, -2.5), (suzanne, 3.0)):
        add_label(bpy, f"{obj.name}: {obj.rs_elastic.frequencies[0]:.2f} Hz", (x, 0.0, -2.4), 0.35)
    stage(bpy, (0.0, -21.0, ROW_GAP), 32, (1280, 720))
    bpy.context.scene.render.filepath = str(output / "modes.png")
    bpy.ops.render.render(write_still=True)
    bpy.ops.wm.save_mainfile()
    print(f"demo: wrote {output / 'modes.png'}")


def rig_picture(bpy, np, output):
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(output / "rig.blend"))
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 36
    scene.render.fps = 24
    plain, _ = creature.build(bpy, np, "Rig Only", location=(-0.8, 0.0, 0.0))
    flesh, _ = creature.build(bpy, np, "Elastic Flesh", location=(0.8, 0.0, 0.0))
    plain.color, flesh.color = (0.6, 0.6, 0.65, 1.0), (0.9, 0.55, 0.3, 1.0)
    flesh.rs_elastic.pin_group = "Follow Rig"
    flesh.rs_elastic.youngs_modulus, flesh.rs_elastic.density = 2.0e5, 1000.0
    flesh.rs_elastic.damping_stiffness = 0.002
    prepare(bpy, flesh, None, 0.05, num_modes=12)
    if bpy.ops.rs_elastic.simulate() != {'FINISHED'}:
        sys.exit("demo: simulating the rigged creature failed")
    for text, x in (("rig only", -0.8), ("RS Elastic flesh", 0.8)):
        add_label(bpy, text, (x, 0.0, -0.85), 0.16)
    frame_label = add_label(bpy, "frame", (-1.5, 0.0, 1.45), 0.16, name="Frame Label")
    stage(bpy, (0.0, -6.0, 0.45), 35, TILE)
    scene.frame_set(1)
    bpy.ops.wm.save_mainfile()
    contact_sheet(bpy, np, frame_label, output / "rig.png", RIG_FRAMES)


def fit_picture(bpy, np, output):
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(output / "fit.blend"))
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, FIT_END
    scene.render.fps, scene.use_gravity = 24, False     # free ringing, no sag to fit
    reference = make_box(bpy, np, "Reference", (4.0, 0.5, 0.5), 5, location=(-2.0, 0.0, 0.9))
    reference.color = (0.3, 0.55, 0.85, 1.0)
    stiff = reference.vertex_groups.new(name="Stiff")
    co = np.empty(len(reference.data.vertices) * 3)
    reference.data.vertices.foreach_get("co", co)
    for index, x in enumerate(co.reshape(-1, 3)[:, 0]):
        stiff.add([index], float(1.0 - x / 4.0), 'REPLACE')
    settings = reference.rs_elastic
    settings.youngs_modulus, settings.density, settings.damping_mass = 1.2e7, 1000.0, 0.05
    settings.stiffness_group, settings.stiffness_ratio = "Stiff", 1.0 / 3.0
    prepare(bpy, reference, None, 0.1, num_modes=12)
    for frame, z in ((1, 0.9), (6, 1.4)):                 # carried up, then held
        reference.location.z = z
        reference.keyframe_insert("location", frame=frame)
    bpy.context.view_layer.objects.active = reference
    if bpy.ops.rs_elastic.simulate() != {'FINISHED'}:
        sys.exit("demo: simulating the reference failed")

    fitted = make_box(bpy, np, "Fitted", (4.0, 0.5, 0.5), 5, location=(-2.0, 0.0, -1.3))
    fitted.color = (0.85, 0.35, 0.2, 1.0)
    settings = fitted.rs_elastic
    settings.youngs_modulus, settings.density, settings.damping_mass = 8e6, 1000.0, 0.05
    prepare(bpy, fitted, None, 0.1, num_modes=12)
    settings.take_source = reference
    settings.fit_frame_start, settings.fit_frame_end = FIT_RANGE
    scene.frame_end = FIT_RANGE[1]                        # the take: frames 1-60
    for operator in ("take_from_animation", "fit_material"):
        if getattr(bpy.ops.rs_elastic, operator)() != {'FINISHED'}:
            sys.exit(f"demo: {operator} failed")
    scene.frame_end = FIT_END
    if bpy.ops.rs_elastic.continue_motion(frame_end=FIT_END) != {'FINISHED'}:
        sys.exit("demo: continuing the fitted bar failed")
    report_fit(bpy, np, reference, fitted)

    add_label(bpy, "reference: stiffness falls 3x to the tip", (0.0, 0.0, 0.3), 0.3)
    add_label(bpy, f"uniform bar, material fitted to frames {FIT_RANGE[0]}-{FIT_RANGE[1]}, "
                   "continued", (0.0, 0.0, -2.2), 0.3)
    frame_label = add_label(bpy, "frame", (-4.0, 0.0, 3.0), 0.35, name="Frame Label")
    stage(bpy, (0.0, -11.0, 0.4), 35, TILE)
    scene.frame_set(1)
    bpy.ops.wm.save_mainfile()
    contact_sheet(bpy, np, frame_label, output / "fit.png", FIT_SHEET_FRAMES)


def report_fit(bpy, np, reference, fitted):
    """Print the fitted frequencies and the continuation's RMS distance to the reference."""
    scene, misses = bpy.context.scene, []
    for frame in range(FIT_RANGE[1] + 1, FIT_END + 1):
        scene.frame_set(frame)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        shapes = []
        for obj in (reference, fitted):
            mesh = obj.evaluated_get(depsgraph).data
            co = np.empty(len(mesh.vertices) * 3)
            mesh.vertices.foreach_get("co", co)
            shapes.append(co.reshape(-1, 3))
        misses.append(np.sum((shapes[0] - shapes[1]) ** 2, axis=1))
    figures = fitted.get("rs_elastic_fitted_material")
    hz = np.sqrt(np.asarray(figures["eigenvalues"])[:2]) / (2.0 * np.pi)
    print(f"demo: Fitted: first frequencies {np.round(hz, 3)} Hz (fit residual "
          f"{figures['residual']:.3g} m); continued frames {FIT_RANGE[1] + 1}-{FIT_END} miss the "
          f"reference by {np.sqrt(np.mean(misses)):.3g} m RMS")


def main():
    args = parse_args()
    if not args.zip:
        sys.exit("demo: pass --zip or set RS_ELASTIC_ZIP (make demo does)")
    output = pathlib.Path(args.output).resolve()
    output.mkdir(parents=True, exist_ok=True)
    blender_session.start(args.zip)
    import bpy
    import numpy as np
    modes_picture(bpy, np, output)
    rig_picture(bpy, np, output)
    fit_picture(bpy, np, output)
    showcase(bpy, np, output)
    print(f"demo: wrote {output / 'demo.blend'}, {output / 'demo.png'}, {output / 'modes.png'}, "
          f"{output / 'rig.png'}, {output / 'fit.png'}")


if __name__ == "__main__":
    main()
