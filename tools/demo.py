"""`make demo`: build a scene from nothing, prepare it with the installed extension, save it and
render a picture.

Scene: a rubber bar pinned at one end and a free rubber Suzanne, each shown in three rows: at rest,
displaced along its first mode by the linear preview (which stretches and inflates), and by the
RS preview at the same amplitude (which bends and keeps its volume).
Writes <output>/demo.blend and <output>/demo.png.
"""
import argparse
import os
import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import blender_session  # noqa: E402

ROW_GAP = 3.4   # metres between the rows


def parse_args():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--output", default="demo_output")
    parser.add_argument("--zip", default=os.environ.get("RS_ELASTIC_ZIP"))
    return parser.parse_args()


def make_bar(bpy, np):
    """A 4 m × 0.5 m × 0.5 m rubber bar along +x, pinned at x = 0 through the 'Pin' group."""
    bpy.ops.mesh.primitive_cube_add(size=1.0)
    bar = bpy.context.active_object
    bar.name = "Rubber Bar"
    bpy.ops.object.mode_set(mode='EDIT')
    bpy.ops.mesh.subdivide(number_cuts=9)
    bpy.ops.object.mode_set(mode='OBJECT')
    co = np.empty(len(bar.data.vertices) * 3)
    bar.data.vertices.foreach_get("co", co)
    co = (co.reshape(-1, 3) + (0.5, 0.0, 0.0)) * (4.0, 0.5, 0.5)
    bar.data.vertices.foreach_set("co", co.ravel())
    bar.data.update()
    pin = bar.vertex_groups.new(name="Pin")
    pin.add([int(i) for i in np.flatnonzero(co[:, 0] < 1e-6)], 1.0, 'REPLACE')
    bar.rs_elastic.pin_group = "Pin"
    bar.location = (-4.5, 0.0, 0.0)
    return bar


def make_suzanne(bpy):
    bpy.ops.mesh.primitive_monkey_add(size=2.0, location=(3.0, 0.0, 0.0))
    suzanne = bpy.context.active_object
    suzanne.name = "Suzanne"
    bpy.ops.object.shade_smooth()
    return suzanne


def prepare(bpy, obj, edge_length, amplitude):
    bpy.context.view_layer.objects.active = obj
    bpy.ops.rs_elastic.apply_material_preset(preset='RUBBER')
    obj.rs_elastic.edge_length = edge_length
    obj.rs_elastic.num_modes = 12
    if bpy.ops.rs_elastic.prepare() != {'FINISHED'}:
        sys.exit(f"demo: preparing {obj.name} failed")
    obj.rs_elastic.preview_amplitude = amplitude
    f = obj.rs_elastic.frequencies
    print(f"demo: {obj.name}: {obj.rs_elastic.tet_count} tets, modes {f[0]:.2f} … {f[-1]:.2f} Hz")


def row_copy(bpy, obj, label, row):
    """A copy `row` rows up, with its own mesh so each row's preview key is its own."""
    copy = obj.copy()
    copy.data = obj.data.copy()
    copy.name = f"{obj.name} ({label})"
    copy.location.z += row * ROW_GAP
    bpy.context.scene.collection.objects.link(copy)
    return copy


def add_label(bpy, text, location, size=0.45):
    curve = bpy.data.curves.new(text, 'FONT')
    curve.body = text
    curve.size = size
    curve.align_x = 'CENTER'
    label = bpy.data.objects.new(text, curve)
    label.location = location
    label.rotation_euler = (1.5708, 0.0, 0.0)
    bpy.context.scene.collection.objects.link(label)
    return label


def stage(bpy, output):
    scene = bpy.context.scene
    bpy.ops.object.camera_add(location=(0.0, -21.0, ROW_GAP), rotation=(1.5708, 0.0, 0.0))
    scene.camera = bpy.context.active_object
    scene.camera.data.lens = 32
    scene.render.engine = 'BLENDER_WORKBENCH'
    scene.display.shading.light = 'STUDIO'
    scene.display.shading.color_type = 'OBJECT'
    scene.display.shading.show_cavity = True
    scene.render.resolution_x, scene.render.resolution_y = 1280, 720
    scene.render.film_transparent = False
    world = bpy.data.worlds.new("Demo") if scene.world is None else scene.world
    scene.world = world
    scene.render.filepath = str(output / "demo.png")


def main():
    args = parse_args()
    if not args.zip:
        sys.exit("demo: pass --zip or set RS_ELASTIC_ZIP (make demo does)")
    output = pathlib.Path(args.output).resolve()
    output.mkdir(parents=True, exist_ok=True)
    blender_session.start(args.zip)
    import bpy
    import numpy as np

    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(output / "demo.blend"))  # cache goes next to it
    bar = make_bar(bpy, np)
    suzanne = make_suzanne(bpy)
    # Large amplitudes: the bar's linear tip displacement is about 4× its thickness.
    prepare(bpy, bar, edge_length=0.03, amplitude=0.5)
    prepare(bpy, suzanne, edge_length=0.05, amplitude=0.25)

    for obj, color in ((bar, (0.85, 0.35, 0.2, 1.0)), (suzanne, (0.3, 0.55, 0.85, 1.0))):
        obj.color = color
        obj.rs_elastic.preview_mode = 1
        rest = row_copy(bpy, obj, "rest", 2)
        linear = row_copy(bpy, obj, "linear", 1)
        for copy, method in ((linear, 'LINEAR'), (obj, 'RS')):
            bpy.context.view_layer.objects.active = copy
            copy.rs_elastic.preview_method = method
            copy.rs_elastic.preview_enabled = True
    for text, row in (("rest", 2), ("linear mode 1", 1), ("RS mode 1", 0)):
        add_label(bpy, text, (-8.2, 0.0, row * ROW_GAP + 0.9))
    for obj, x in ((bar, -2.5), (suzanne, 3.0)):
        add_label(bpy, f"{obj.name}: {obj.rs_elastic.frequencies[0]:.2f} Hz", (x, 0.0, -2.4), 0.35)
    stage(bpy, output)
    bpy.ops.render.render(write_still=True)
    bpy.ops.wm.save_mainfile()
    print(f"demo: wrote {output / 'demo.blend'} and {output / 'demo.png'}")


if __name__ == "__main__":
    main()
