"""The parent panel: which body the settings below belong to."""
import bpy

from ..bridge import mesh_cache, staleness


class RSElasticPanel:
    bl_space_type = 'VIEW_3D'
    bl_region_type = 'UI'
    bl_category = "RS Elastic"

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        return obj is not None and obj.type == 'MESH'


def draw_frame_range(layout, settings):
    """The frame-range settings shared by space-time solves and simulations."""
    layout.prop(settings, "use_scene_range")
    if not settings.use_scene_range:
        row = layout.row(align=True)
        row.prop(settings, "frame_start")
        row.prop(settings, "frame_end")


def frame_count(scene, settings):
    """Frames in the range a solve or simulation bakes."""
    if settings.use_scene_range:
        return scene.frame_end - scene.frame_start + 1
    return settings.frame_end - settings.frame_start + 1


def draw_bake_buttons(layout, obj=None, frames=0):
    """Bake To, a Mesh Cache suggestion when a shape-key bake of ``frames`` would be large,
    and Keep Bake as Take / Clear Bake."""
    if obj is not None:
        settings = obj.rs_elastic
        layout.prop(settings, "bake_to")
        size = mesh_cache.shape_key_bytes(frames, len(obj.data.vertices))
        if settings.bake_to == 'KEYS' and size > mesh_cache.SUGGEST_BYTES:
            layout.label(text=f"Shape keys would add {size / 2 ** 20:.0f} MB to the .blend: "
                              "Mesh Cache keeps them on disk", icon='INFO')
    row = layout.row(align=True)
    row.operator("rs_elastic.keep_take", icon='PINNED')
    row.operator("rs_elastic.clear_bake", icon='TRASH')


class RS_ELASTIC_PT_body(RSElasticPanel, bpy.types.Panel):
    bl_label = "RS Elastic"

    @classmethod
    def poll(cls, context):
        return True

    def draw(self, context):
        obj = context.active_object
        if obj is None or obj.type != 'MESH':
            self.layout.label(text="Select a mesh object", icon='INFO')
            return
        settings = obj.rs_elastic
        row = self.layout.row()
        row.label(text=obj.name, icon='MESH_DATA')
        stale = staleness.stale_reason(obj, cached=True)   # cached: cheap enough for every redraw
        if stale:
            row.label(text="Stale", icon='ERROR')
            self.layout.label(text=stale[0].upper() + stale[1:])
        elif settings.is_prepared:
            row.label(text="Prepared", icon='CHECKMARK')
        elif settings.tets_key:
            row.label(text="Tetrahedralized", icon='MESH_ICOSPHERE')
        else:
            row.label(text="Not prepared", icon='DOT')
        self.layout.operator("rs_elastic.write_farm_job_type", icon='NETWORK_DRIVE')


CLASSES = (RS_ELASTIC_PT_body,)
