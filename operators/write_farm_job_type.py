"""Write the Flamenco job type (rs-elastic-bake) into a Flamenco Manager's scripts folder."""
import bpy

from ..bridge import farm
from ..bridge.scene import InputError


class RS_ELASTIC_OT_write_farm_job_type(bpy.types.Operator):
    """Write the RS Elastic Bake job type for Flamenco into a Manager's scripts folder (or the
    folder of the flamenco-manager program, which gets a scripts folder)"""
    bl_idname = "rs_elastic.write_farm_job_type"
    bl_label = "Write Flamenco Job Type…"
    bl_options = {'REGISTER'}

    directory: bpy.props.StringProperty(name="Folder", subtype='DIR_PATH')

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {'RUNNING_MODAL'}

    def execute(self, context):
        try:
            path = farm.write_job_type(self.directory)
        except InputError as exc:
            self.report({'ERROR'}, str(exc))
            return {'CANCELLED'}
        self.report({'INFO'}, f"Wrote {path}: refresh the job types in the Flamenco panel")
        return {'FINISHED'}


CLASSES = (RS_ELASTIC_OT_write_farm_job_type,)
