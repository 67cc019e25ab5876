"""Make the Follow Rig group of a rigged body from the bones selected in its armature."""
import bpy

from ..bridge import armature, scene, writes
from ..bridge.scene import InputError

GROUP = "Follow Rig"


class RS_ELASTIC_OT_follow_bones(bpy.types.Operator):
    """Set Follow Rig to the vertices the selected bones move: each vertex gets the sum of its
    weights for those bones (at most 1), so what they carry follows the rig and the rest is
    free flesh"""
    bl_idname = "rs_elastic.follow_bones"
    bl_label = "Follow Selected Bones"
    bl_options = {'REGISTER', 'UNDO'}

    def execute(self, context):
        obj = scene.active_mesh_or_report(self, context)
        if obj is None:
            return {'CANCELLED'}
        try:        # weights are painted in Weight Paint mode; Edit Mode keeps its own copy
            writes.require_object_mode(obj, "set Follow Rig", allowed=('OBJECT', 'WEIGHT_PAINT'))
        except InputError as exc:
            self.report({'ERROR'}, str(exc))
            return {'CANCELLED'}
        if not armature.is_rigged(obj):
            self.report({'ERROR'}, f"'{obj.name}' has no Armature modifier with an armature")
            return {'CANCELLED'}
        rig = armature.armature_modifier(obj).object
        selected = set(armature.selected_bones(rig))
        bones = [name for name in armature.deform_bones(obj) if name in selected]
        if not bones:
            self.report({'ERROR'}, f"Select the bones to follow in '{rig.name}' (Pose Mode) "
                                   "first; only deform bones with a vertex group count")
            return {'CANCELLED'}
        weights = armature.bone_group_weights(obj, bones)
        group = obj.vertex_groups.get(GROUP) or obj.vertex_groups.new(name=GROUP)
        group.remove(list(range(len(obj.data.vertices))))
        for value in sorted(set(weights[weights > 0.0].round(6))):
            group.add([int(i) for i in (weights.round(6) == value).nonzero()[0]], float(value),
                      'REPLACE')
        obj.rs_elastic.pin_group = group.name
        self.report({'INFO'}, f"'{group.name}' follows {', '.join(bones)} "
                              f"({int((weights > 0).sum())} vertices); Prepare to use it")
        return {'FINISHED'}


CLASSES = (RS_ELASTIC_OT_follow_bones,)
