"""In-between poses of two shape keys through rotation-strain coordinates."""
import bpy
import numpy as np

from ..bridge import bake, rs_tools, scene, staleness
from ..bridge.scene import InputError
from ..solver import rs


def key_positions(obj, name):
    keys = obj.data.shape_keys
    block = keys.key_blocks.get(name) if keys is not None else None
    if block is None:
        raise InputError(f"'{name}' is not a shape key of '{obj.name}'")
    co = np.empty(len(block.data) * 3)
    block.data.foreach_get("co", co)
    return co.reshape(-1, 3)


def interpolate_poses(tools, points_a, points_b, ts, pins_fixed):
    """Render-vertex poses at the blend weights `ts`, and how many tets the inputs invert.

    Both poses are carried to the tet nodes, turned into RS coordinates (B's rotation branch
    chosen nearest to A's, so each tet turns the short way), blended linearly and reconstructed.
    What the tets cannot express (sub-tet surface detail, the transfer's fit error) is carried
    along as a residual blended linearly, so t = 0 and t = 1 give back the keys exactly.
    """
    X, T = tools.nodes, tools.tets
    nodes_a = tools.pose_transfer.nodes_from_points(points_a)
    nodes_b = tools.pose_transfer.nodes_from_points(points_b)
    y_a, inverted_a = rs.pose_to_rs(X, T, nodes_a, neighbours=tools.neighbours)
    y_b, inverted_b = rs.pose_to_rs(X, T, nodes_b, reference=y_a[:, :3])
    recon = tools.reconstruction if pins_fixed else tools.free_reconstruction
    weights = recon.weights
    mean_a = weights @ (nodes_a - X) / weights.sum()
    mean_b = weights @ (nodes_b - X) / weights.sum()

    rest = tools.embedding @ X

    def surface(y, mean):
        # Displacements through the pinned embedding, so pinned vertices stay exactly at rest.
        return rest + tools.displacement_embedding @ recon.reconstruct(y, mean_displacement=mean)

    residual_a = points_a - surface(y_a, mean_a)
    residual_b = points_b - surface(y_b, mean_b)
    poses = [surface(rs.interpolate(y_a, y_b, t), (1 - t) * mean_a + t * mean_b)
             + (1 - t) * residual_a + t * residual_b for t in ts]
    return poses, int(np.count_nonzero(inverted_a | inverted_b))


class RS_ELASTIC_OT_interpolate_shape_keys(bpy.types.Operator):
    """Blend two shape keys through rotation-strain coordinates: rotations stay rotations"""
    bl_idname = "rs_elastic.interpolate_shape_keys"
    bl_label = "RS Interpolate Shape Keys"
    bl_options = {'REGISTER', 'UNDO'}

    key_from: bpy.props.StringProperty(name="From", description="Shape key at the start (may be the Basis)")
    key_to: bpy.props.StringProperty(name="To", description="Shape key at the end")
    output: bpy.props.EnumProperty(
        name="Output",
        items=[('KEYS', "Shape Keys", "A number of new in-between shape keys"),
               ('ANIMATION', "Animation", "A bake over a frame range: one key per frame, keyed so "
                                          "that scrubbing plays it")],
        default='KEYS')
    count: bpy.props.IntProperty(name="In-betweens", default=5, min=1, soft_max=100)
    frame_start: bpy.props.IntProperty(name="Start", default=1)
    frame_end: bpy.props.IntProperty(name="End", default=24)

    def invoke(self, context, event):
        scene_ = context.scene
        self.frame_start, self.frame_end = scene_.frame_start, scene_.frame_end
        return context.window_manager.invoke_props_dialog(self)

    def draw(self, context):
        obj = context.active_object
        layout = self.layout
        keys = obj.data.shape_keys if obj is not None and obj.type == 'MESH' else None
        if keys is None:
            layout.label(text="The object has no shape keys", icon='ERROR')
            return
        layout.prop_search(self, "key_from", keys, "key_blocks")
        layout.prop_search(self, "key_to", keys, "key_blocks")
        layout.prop(self, "output", expand=True)
        if self.output == 'KEYS':
            layout.prop(self, "count")
        else:
            row = layout.row(align=True)
            row.prop(self, "frame_start")
            row.prop(self, "frame_end")

    def execute(self, context):
        try:
            return self._run(context)
        except InputError as exc:
            self.report({'ERROR'}, str(exc))
            return {'CANCELLED'}

    def _run(self, context):
        obj = scene.require_mesh_object(context.active_object)
        staleness.require_current(obj)
        tools = rs_tools.for_object(obj)
        if tools is None:
            raise InputError(f"'{obj.name}' is not prepared for its current mesh: run Prepare Body")
        if self.key_from == self.key_to:
            raise InputError("Pick two different shape keys")
        points_a = key_positions(obj, self.key_from)
        points_b = key_positions(obj, self.key_to)
        if self.output == 'ANIMATION':
            if self.frame_end <= self.frame_start:
                raise InputError(f"The frame range {self.frame_start}–{self.frame_end} is empty")
            bake.require_target(obj)
            frames = list(range(self.frame_start, self.frame_end + 1))
            ts = np.linspace(0.0, 1.0, len(frames))
        else:
            ts = np.arange(1, self.count + 1) / (self.count + 1)
        pinned = tools.pinned_nodes
        rest = scene.base_vertices(obj)
        pin_rows = tools.displacement_embedding[:, pinned].getnnz(axis=1) > 0 if len(pinned) else None
        pins_fixed = pin_rows is not None and all(
            np.abs(p[pin_rows] - rest[pin_rows]).max(initial=0.0) < 1e-9 for p in (points_a, points_b))
        poses, inverted = interpolate_poses(tools, points_a, points_b, ts, pins_fixed)
        if self.output == 'ANIMATION':
            active = bake.write_bake(obj, frames, poses)
            what = f"baked frames {frames[0]}–{frames[-1]}"
            if active:
                self.report({'WARNING'}, f"Shape keys {', '.join(active)} are not at 0 and add "
                                         "on top of the bake")
        else:
            prefix = f"RS {self.key_from} → {self.key_to} "
            names = [f"{prefix}{i + 1:02d}" for i in range(len(poses))]
            bake.replace_key_set(obj, prefix, names, poses)
            what = f"{len(poses)} in-between keys"
        self.report({'WARNING'} if inverted else {'INFO'},
                    f"'{obj.name}': {what}" + (f"; {inverted} tets are inverted in the input "
                                               "poses" if inverted else ""))
        return {'FINISHED'}


CLASSES = (RS_ELASTIC_OT_interpolate_shape_keys,)
