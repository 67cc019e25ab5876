"""What a space-time solve and a simulation share: the frame range, the damping, and the bake
they write (Bake To, Keep Bake as Take, Clear Bake), drawn once."""
import bpy

from ..bridge import bake, estimates, mesh_cache
from .body import RSElasticPanel, drawn_body


def frame_count(scene, settings):
    """Frames in the range a solve or simulation bakes."""
    if settings.use_scene_range:
        return scene.frame_end - scene.frame_start + 1
    return settings.frame_end - settings.frame_start + 1


def damping_label(settings, frequency_hz):
    """The Rayleigh damping as a damping ratio at the first mode (frequency in Hz)."""
    zeta = estimates.first_mode_damping_ratio(settings, frequency_hz)
    return f"Damping ratio at mode 1: {100.0 * zeta:.3g} %"


class RS_ELASTIC_PT_bake(RSElasticPanel, bpy.types.Panel):
    bl_label = "Frames, Damping and Bake"
    bl_parent_id = "RS_ELASTIC_PT_body"

    def draw(self, context):
        obj = drawn_body(self.layout, context)
        settings = obj.rs_elastic
        layout = self.layout
        layout.prop(settings, "use_scene_range")
        if not settings.use_scene_range:
            row = layout.row(align=True)
            row.prop(settings, "frame_start")
            row.prop(settings, "frame_end")
        col = layout.column(align=True)
        col.use_property_split = True
        col.prop(settings, "damping_mass", text="Damping Mass")
        col.prop(settings, "damping_stiffness", text="Stiffness")
        frequencies = settings.frequencies
        if frequencies and frequencies[0] > 0.0:
            layout.label(text=damping_label(settings, frequencies[0]))
        split = layout.column()
        split.use_property_split = True
        split.prop(settings, "bake_to")
        size = mesh_cache.shape_key_bytes(frame_count(context.scene, settings),
                                          len(obj.data.vertices))
        if settings.bake_to == 'KEYS' and size > mesh_cache.SUGGEST_BYTES:
            col = layout.column(align=True)
            col.label(text=f"Shape keys would add {size / 2 ** 20:.0f} MB", icon='INFO')
            col.label(text="to the .blend: Mesh Cache keeps", icon='BLANK1')
            col.label(text="them on disk", icon='BLANK1')
        frames = bake.bake_frames(obj)    # whichever made it: a solve or a simulation
        if frames:
            layout.label(text=f"Baked frames {frames[0]}–{frames[-1]}", icon='SHAPEKEY_DATA')
        col = layout.column(align=True)         # side by side, half the width cut the first
        col.operator("rs_elastic.keep_take", icon='PINNED')
        col.operator("rs_elastic.clear_bake", icon='TRASH')


CLASSES = (RS_ELASTIC_PT_bake,)
