"""Sidebar panels (3D Viewport > N > RS Elastic), one per operator group."""
from . import bake, body, interpolate, prepare, preview, simulate, spacetime, take, tetrahedralize

MODULES = (body, tetrahedralize, prepare, preview, interpolate, bake, spacetime, take, simulate)
CLASSES = tuple(cls for module in MODULES for cls in module.CLASSES)
