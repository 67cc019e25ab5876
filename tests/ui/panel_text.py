"""What a panel says: its labels, drawn by its own draw code in the running Blender with the
real context, into a layout that records them (the window's own layout cannot be read back)."""

RECORDER = '''
class _Recording:
    def __init__(self, log):
        self.log, self.use_property_split, self.active, self.enabled = log, False, True, True
        self.operator_context = 'INVOKE_DEFAULT'
    def _child(self, *args, **kwargs):
        return _Recording(self.log)
    row = column = box = split = grid_flow = _child
    def label(self, text="", icon='NONE', **kwargs):
        self.log.append(text)
    def _skip(self, *args, **kwargs):
        return None
    prop = prop_search = operator = menu = template_list = separator = progress = _skip
    context_pointer_set = _skip
    def panel(self, idname, default_closed=False):
        """(header, body) of a sub-panel as first drawn: no body while closed."""
        return _Recording(self.log), None if default_closed else _Recording(self.log)


def panel_labels(idname):
    cls = getattr(bpy.types, idname)
    log = []
    if cls.poll(bpy.context):
        cls.draw(type("Drawn", (), {"layout": _Recording(log)})(), bpy.context)
    return log
'''


def labels(gui, idname):
    """The label texts panel `idname` shows for the active object now."""
    return gui.run(f"{RECORDER}\nresult = panel_labels({idname!r})")
