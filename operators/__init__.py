"""One operator per user action; see each module."""
from . import apply_material_preset, interpolate_shape_keys, prepare, tetrahedralize

MODULES = (tetrahedralize, prepare, apply_material_preset, interpolate_shape_keys)
CLASSES = tuple(cls for module in MODULES for cls in module.CLASSES)
