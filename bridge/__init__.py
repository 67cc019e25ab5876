"""The thin Blender layer: reads the scene into arrays for `solver` and writes results back.

Everything here may import bpy; nothing in `solver` does.
"""
