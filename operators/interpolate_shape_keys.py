"""In-between poses of two shape keys through rotation-strain coordinates."""
import bpy
import numpy as np

from ..bridge import bake, interpolation, scene
from ..bridge.scene import InputError


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
        obj = scene.acted_on(context)
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
        obj = scene.require_mesh_object(scene.acted_on(context))
        bake.require_writable(obj, "write shape keys")
        if self.output == 'ANIMATION':
            if self.frame_end <= self.frame_start:
                raise InputError(f"The frame range {self.frame_start}–{self.frame_end} is empty")
            bake.require_target(obj)
            frames = list(range(self.frame_start, self.frame_end + 1))
            ts = np.linspace(0.0, 1.0, len(frames))
        else:
            ts = np.arange(1, self.count + 1) / (self.count + 1)
        poses, inverted = interpolation.in_betweens(obj, self.key_from, self.key_to, ts)
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
