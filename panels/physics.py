"""The Properties editor's Physics tab: a body's physical settings (material, pins, simulation
settings), where Blender users look for Soft Body and Cloth. The rows are the sidebar's own draw
functions; the animation tools (handles, space-time, Live, bakes) stay in the sidebar."""
import bpy

from .body import body_status, draw_lines
from .prepare import draw_material
from .simulate import draw_simulation_settings


class PhysicsTabPanel:
    bl_space_type = 'PROPERTIES'
    bl_region_type = 'WINDOW'
    bl_context = "physics"

    @classmethod
    def poll(cls, context):
        return context.object is not None and context.object.type == 'MESH'


class RS_ELASTIC_PT_physics(PhysicsTabPanel, bpy.types.Panel):
    bl_label = "RS Elastic"

    def draw(self, context):
        body_status(self.layout, context.object)
        draw_lines(self.layout, "Prepare, edit and bake: in the 3D Viewport's sidebar (N), "
                                "RS Elastic tab", 'INFO')


class RS_ELASTIC_PT_physics_material(PhysicsTabPanel, bpy.types.Panel):
    bl_label = "Material and Pins"
    bl_parent_id = "RS_ELASTIC_PT_physics"

    def draw(self, context):
        draw_material(self.layout, context.object)


class RS_ELASTIC_PT_physics_simulation(PhysicsTabPanel, bpy.types.Panel):
    bl_label = "Simulation"
    bl_parent_id = "RS_ELASTIC_PT_physics"

    def draw(self, context):
        draw_simulation_settings(self.layout, context, context.object)


CLASSES = (RS_ELASTIC_PT_physics, RS_ELASTIC_PT_physics_material, RS_ELASTIC_PT_physics_simulation)
