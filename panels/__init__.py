"""Sidebar panels (3D Viewport > N > RS Elastic), one per operator group, and the body's physical
settings in the Properties editor's Physics tab (physics.py)."""
from . import (bake, body, interpolate, physics, prepare, preview, simulate, spacetime, take,
               tetrahedralize)

MODULES = (body, tetrahedralize, prepare, preview, interpolate, bake, spacetime, take, simulate,
           physics)
CLASSES = tuple(cls for module in MODULES for cls in module.CLASSES)
