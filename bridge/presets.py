"""Named materials: (Young's modulus in Pa, Poisson's ratio, density in kg/m³).

Soft values are what animators want to see move; they are in the range of the real materials.
"""

MATERIAL_PRESETS = {
    "JELLY": ("Jelly", 1.0e4, 0.45, 1050.0),
    "RUBBER": ("Rubber", 1.0e6, 0.45, 1100.0),
    "SILICONE": ("Silicone", 3.0e5, 0.48, 1100.0),
    "FOAM": ("Foam", 5.0e4, 0.2, 100.0),
    "WOOD": ("Wood", 1.0e10, 0.3, 600.0),
    "STEEL": ("Steel", 2.0e11, 0.3, 7850.0),
}
