"""Code run inside Blender that reads a body's state, for the GUI tests to compare before and
after an action: the Blender tests' fingerprints of the user's data and of the body, the
preparation's keys, whether it is stale, and the cache files it has."""

STATE = """
import os, sys
import blender_helpers as h
bridge = sys.modules["bl_ext.user_default.rs_elastic.bridge"]
obj = bpy.data.objects["Bar"]
s = obj.rs_elastic
cache = sorted(name for folder in bridge.stage_cache.cache_dirs() if os.path.isdir(folder)
               for name in os.listdir(folder) if name.startswith(obj.name + "."))
result = {"user": h.user_fingerprint(), "body": h.fingerprint(obj),
          "keys": [s.tets_key, s.prepared_key, s.reduced_key], "prepared": s.is_prepared,
          "stale": bridge.staleness.stale_reason(obj), "youngs": s.youngs_modulus, "cache": cache}
"""


def body_state(gui):
    return gui.run(STATE)
