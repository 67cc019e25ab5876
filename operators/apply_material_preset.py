"""Set the active body's material from a named preset."""
import bpy

from ..bridge import scene
from ..bridge.presets import MATERIAL_PRESETS
from ..bridge.scene import InputError


class RS_ELASTIC_OT_apply_material_preset(bpy.types.Operator):
    """Set Young's modulus, Poisson's ratio and density from a preset"""
    bl_idname = "rs_elastic.apply_material_preset"
    bl_label = "Material Preset"
    bl_options = {'REGISTER', 'UNDO'}

    preset: bpy.props.EnumProperty(
        name="Preset",
        items=[(key, label, f"E = {E:.3g} Pa, ν = {nu}, ρ = {rho:g} kg/m³")
               for key, (label, E, nu, rho) in MATERIAL_PRESETS.items()])

    @classmethod
    def poll(cls, context):
        obj = scene.acted_on(context)
        return obj is not None and obj.type == 'MESH'

    def execute(self, context):
        obj = scene.acted_on(context)
        try:
            scene.require_local(obj)
        except InputError as exc:       # a linked body's settings are not this file's to set
            self.report({'ERROR'}, str(exc))
            return {'CANCELLED'}
        _, E, nu, rho = MATERIAL_PRESETS[self.preset]
        settings = obj.rs_elastic
        settings.youngs_modulus, settings.poisson_ratio, settings.density = E, nu, rho
        return {'FINISHED'}


CLASSES = (RS_ELASTIC_OT_apply_material_preset,)
