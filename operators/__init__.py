"""One operator per user action; see each module."""
from . import (add_handle, apply_material_preset, clear_bake, continue_motion, fit_material,
               follow_bones, interpolate_shape_keys, keep_take, prepare, simulate,
               solve_spacetime, take_from_animation, tetrahedralize, write_farm_job_type)

MODULES = (tetrahedralize, prepare, apply_material_preset, interpolate_shape_keys, add_handle,
           solve_spacetime, simulate, clear_bake, keep_take, take_from_animation, fit_material,
           continue_motion, follow_bones, write_farm_job_type)
CLASSES = tuple(cls for module in MODULES for cls in module.CLASSES)
