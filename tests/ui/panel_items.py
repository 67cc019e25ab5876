"""What a panel draws besides labels: its properties (with the text each is shown with) and its
operators, drawn by the panel's own draw code in the running Blender with the real context into
a layout that records them; a UI list's rows are drawn by the list's own draw_item."""

RECORDER = '''
class _Items:
    def __init__(self, log):
        self.log, self.use_property_split, self.use_property_decorate = log, False, True
        self.active = self.enabled = True
        self.operator_context = 'INVOKE_DEFAULT'
    def _child(self, *args, **kwargs):
        return _Items(self.log)
    row = column = box = split = grid_flow = _child
    def label(self, text="", **kwargs):
        self.log.append(["label", text, text])
    def prop(self, data, name, text=None, **kwargs):
        shown = data.bl_rna.properties[name].name if text is None else text
        self.log.append(["prop", name, shown])
    def prop_search(self, data, name, search_data, search_name, text=None, **kwargs):
        self.prop(data, name, text=text)
    def operator(self, idname, text=None, **kwargs):
        self.log.append(["operator", idname, text])
    def menu(self, idname, **kwargs):
        self.log.append(["menu", idname, None])
    def template_list(self, list_type, list_id, data, name, active_data, active_name, **kwargs):
        drawer = getattr(bpy.types, list_type)
        for index, item in enumerate(getattr(data, name)):
            drawer.draw_item(drawer, bpy.context, _Items(self.log), data, item, 0, active_data,
                             active_name, index)
    def _skip(self, *args, **kwargs):
        return None
    def progress(self, factor=0.0, type='BAR', text=""):
        self.log.append(["progress", text, factor])
    separator = context_pointer_set = _skip


def panel_items(idnames):
    """{panel: [[kind, property or operator or label, the text it is shown with], ...]}."""
    out = {}
    for idname in idnames:
        cls = getattr(bpy.types, idname)
        log = []
        if cls.poll(bpy.context):
            cls.draw(type("Drawn", (), {"layout": _Items(log)})(), bpy.context)
        out[idname] = log
    return out
'''


def panel_items(gui, idnames):
    return gui.run(f"{RECORDER}\nresult = panel_items({sorted(idnames)!r})")
