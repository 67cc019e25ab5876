"""One operator per user action; see each module."""
from . import apply_material_preset, prepare, tetrahedralize

MODULES = (tetrahedralize, prepare, apply_material_preset)
CLASSES = tuple(cls for module in MODULES for cls in module.CLASSES)
