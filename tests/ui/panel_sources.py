"""The panels the extension defines, read from its source (panels/*.py), independently of what
Blender registered: what the GUI tests expect to see registered and drawn (the sidebar's, and
the Physics tab's)."""
import re

from blender_gui import PROJECT


def defined_panels(base):
    """{idname: DEFAULT_CLOSED?} of every `class RS_ELASTIC_PT_...(base, ...)` in panels/."""
    panels = {}
    for path in sorted((PROJECT / "panels").glob("*.py")):
        source = path.read_text()
        for match in re.finditer(r"^class (RS_ELASTIC_PT_\w+)\(" + base + ",", source, re.M):
            body = source[match.end():].split("\nclass ", 1)[0]
            panels[match.group(1)] = "'DEFAULT_CLOSED'" in body
    return panels


PANELS = defined_panels("RSElasticPanel")                # the 3D viewport's sidebar
PHYSICS_PANELS = defined_panels("PhysicsTabPanel")       # the Properties editor's Physics tab
