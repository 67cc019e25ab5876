"""The parent panel: which body the settings below belong to."""
import textwrap

import bpy

from ..bridge import jobs, scene, staleness

WRAP = 34      # characters: about 215 px of the UI font at the default sidebar width


def body_object(context):
    """The body the panels show: the active mesh, or the mesh whose handle the active Empty is."""
    obj = scene.acted_on(context)
    return obj if obj is not None and obj.type == 'MESH' else None


def draw_lines(layout, text, icon='NONE'):
    """A sentence as short lines (a line per clause, broken after ': ', each wrapped at
    WRAP characters), so it fits the sidebar's default width; the lines after the first are
    indented under the icon."""
    lines = [line for clause in text.replace(": ", ":\n").split("\n")
             for line in textwrap.wrap(clause, WRAP)]
    col = layout.column(align=True)
    for i, line in enumerate(lines):
        col.label(text=line, icon=icon if i == 0 else ('BLANK1' if icon != 'NONE' else 'NONE'))


def draw_progress(layout, obj, idname):
    """While operator `idname` (e.g. "rs_elastic.prepare") runs on `obj` as a modal job: its
    progress as a bar (Blender 4.0 on) or a line, its note, and whether Esc cancels it. A message
    too long for the bar goes under it, wrapped. True if drawn."""
    job = jobs.running_job(obj)
    if job is None or job.idname != idname:
        return False
    percent = f"{100 * job.fraction:.0f} %"
    text = f"{job.message} ({percent})"
    below = None
    if len(text) > WRAP:            # the bar would cut it: the percentage in it, the words under
        text, below = percent, job.message
    if hasattr(layout, "progress"):
        layout.progress(factor=job.fraction, type='BAR', text=text)
    else:
        layout.label(text=text, icon='TIME')
    if below:
        draw_lines(layout, below)
    if job.note:
        draw_lines(layout, job.note, icon='INFO')
    layout.label(text="Esc cancels" if not job.is_cancelled() else "Cancelling", icon='CANCEL')
    return True


def drawn_body(layout, context):
    """The body a panel draws into `layout`; with a handle's Empty active, the layout's buttons
    act on the body (the operators read the active object)."""
    obj = body_object(context)
    if obj is not None and obj is not context.active_object:
        layout.context_pointer_set("active_object", obj)
        layout.context_pointer_set("object", obj)
    return obj


def body_status(layout, obj):
    """The body's name and whether it is prepared, stale (and why) or tetrahedralized."""
    settings = obj.rs_elastic
    row = layout.row()
    row.label(text=obj.name, icon='MESH_DATA')
    stale = staleness.stale_reason(obj, cached=True)   # cached: cheap enough for every redraw
    if stale:
        row.label(text="Stale", icon='ERROR')
        draw_lines(layout, stale[0].upper() + stale[1:])
    elif settings.is_prepared:
        row.label(text="Prepared", icon='CHECKMARK')
    elif settings.tets_key:
        row.label(text="Tetrahedralized", icon='MESH_ICOSPHERE')
    else:
        row.label(text="Not prepared", icon='DOT')


class RSElasticPanel:
    bl_space_type = 'VIEW_3D'
    bl_region_type = 'UI'
    bl_category = "RS Elastic"

    @classmethod
    def poll(cls, context):
        return body_object(context) is not None


class RS_ELASTIC_PT_body(RSElasticPanel, bpy.types.Panel):
    bl_label = "RS Elastic"

    @classmethod
    def poll(cls, context):
        return True

    def draw(self, context):
        obj = drawn_body(self.layout, context)
        if obj is None:
            self.layout.label(text="Select a mesh object", icon='INFO')
            return
        body_status(self.layout, obj)
        if obj is not context.active_object:
            self.layout.label(text=f"Handle of {obj.name}", icon='EMPTY_AXIS')
        self.layout.operator("rs_elastic.write_farm_job_type", icon='NETWORK_DRIVE')


CLASSES = (RS_ELASTIC_PT_body,)
