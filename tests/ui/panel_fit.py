"""Whether every label a panel draws fits the width the sidebar gives it, measured in the running
Blender (the window's own layout cannot be read back, and a screenshot would need OCR).

A panel's own draw code runs with the real context into a layout that records its tree (rows,
columns, boxes) and its items. The tree is then given widths the way Blender's layout gives them
in the sidebar, and every text is measured with blf in the UI font at the UI scale (font id 0,
size: the widget style's points times the preferences' ui_scale):
- the panels' content width is the sidebar region's width less 2.65 widget units (the tab column
  and the panel borders); a column gives each child its full width; a row gives each item with
  text an even share (Blender sizes them all alike in a panel: `_natural`), an icon alone one
  unit, and a list's row each item its natural width (text, icon, margins) scaled to fill it;
- a split gives its first child `factor` of its width and the others even shares of the rest
  (Blender's split);
- with use_property_split a property's label gets 0.4 of its width less the decorator's unit
  (Blender's UI_ITEM_PROP_SEP_DIVIDE), the value 0.6; a checkbox's text sits after its box in
  the value part, an expanded enum's items share the value part;
- a text needs its icon's unit and 0.3 unit of margin each side (0.15 unit in the split's label
  column, right-aligned against the value; 0.15 each side in an expanded enum's buttons); a
  number field without the split holds 'Name: value' (seven digits assumed); a text, search or
  object field without the split puts 'Name:' before it in a slot of 8/3 units whatever the
  width (55.5 px here: the window showed 'Empty:' and 'Group:' whole, 'Take So…' cut).
The constants were read off Blender 4.3's sidebar at its default width (291 px at ui_scale 1.04):
with them, 'Poisson's Ratio' (82 px) fits and 'Proxy Triangles' (83 px) does not, as the window
shows ('Proxy Triangl…'). Deterministic: no pixels are compared, only font metrics and widths.
"""

MEASURER = r'''
import blf

def _unit():
    return 20.0 * bpy.context.preferences.system.ui_scale

def _text_width(text):
    style = bpy.context.preferences.ui_styles[0]
    blf.size(0, style.widget.points * bpy.context.preferences.system.ui_scale)
    return blf.dimensions(0, text)[0]


class _Node:
    """A recorded layout: its kind ('row', 'column' or 'split'), its split setting and its children
    (nodes, or items: (kind, texts, icon?))."""
    def __init__(self, kind, split=False):
        self.kind, self.children = kind, []
        self.use_property_split, self.use_property_decorate = split, True
        self.active = self.enabled = True
        self.alignment, self.scale_x, self.scale_y = 'EXPAND', 1.0, 1.0
        self.operator_context = 'INVOKE_DEFAULT'

    def _add(self, kind):
        child = _Node(kind, self.use_property_split)
        self.children.append(child)
        return child

    def row(self, **kwargs):
        return self._add('row')

    def column(self, **kwargs):
        return self._add('column')

    def split(self, factor=0.0, **kwargs):
        child = self._add('split')
        child.factor = factor
        return child

    box = column

    def _item(self, kind, texts, icon):
        self.children.append((kind, [t for t in texts if t], icon not in (None, 'NONE')))

    def label(self, text="", icon='NONE', **kwargs):
        self._item('label', [text], icon)

    def prop(self, data, name, text=None, icon='NONE', expand=False, toggle=False, **kwargs):
        rna = data.bl_rna.properties[name]
        text = rna.name if text is None else text
        if not text and not expand:
            self._item('icon', [], icon)
        elif rna.type == 'BOOLEAN' and toggle:
            self._item('button', [text], icon)
        elif rna.type == 'BOOLEAN':
            self._item('split_check' if self.use_property_split else 'check', [text], icon)
        elif rna.type == 'ENUM' and expand:
            self._item('split_expand' if self.use_property_split else 'expand',
                       [item.name for item in rna.enum_items], 'NONE')
        else:
            plain = 'number' if rna.type in ('INT', 'FLOAT') else 'field'
            self._item('split_label' if self.use_property_split else plain, [text], icon)

    def prop_search(self, data, name, search_data, search_name, text=None, icon='NONE', **kwargs):
        self.prop(data, name, text=text, icon=icon)

    def operator(self, idname, text=None, icon='NONE', **kwargs):
        module, name = idname.split(".")
        text = getattr(getattr(bpy.ops, module), name).get_rna_type().name if text is None else text
        self._item('button' if text else 'icon', [text], icon)

    def menu(self, idname, text=None, icon='NONE', **kwargs):
        text = getattr(bpy.types, idname).bl_label if text is None else text
        self._item('menu', [text], icon)

    def template_list(self, list_type, list_id, data, name, active_data, active_name, **kwargs):
        self.children.append(('list', (list_type, data, name, active_data, active_name), False))

    def separator(self, **kwargs):
        pass

    def context_pointer_set(self, name, data):
        pass

    def panel(self, idname, default_closed=False):
        """(header row, body column) of a sub-panel as first drawn: no body while closed."""
        return self._add('row'), None if default_closed else self._add('column')

    def progress(self, factor=0.0, type='BAR', text=""):
        self._item('progress', [text], 'NONE')


def _icon_only(child):
    if isinstance(child, _Node):
        return bool(child.children) and all(_icon_only(c) for c in child.children)
    return child[0] == 'icon'


def _natural(child, u, by_text=False):
    """The width an item or layout asks for in a row (a row sums its children, a column takes
    the widest). In a panel: 10 units for anything with text, whatever the text, and one unit
    for an icon alone; a panel lays out top to bottom, so Blender does not size a row's items
    by their text there (ui_layout_variable_size): two buttons in a row get half the width
    each (the window showed 'Keep Bake as Take' beside 'Clear Bake' cut to 'Keep Bake as …').
    A list's rows do size by text (``by_text``: text, icon, margins; the window showed a
    handle's name and its residual side by side, not in halves)."""
    if isinstance(child, _Node):
        sizes = [_natural(c, u, by_text) for c in child.children] or [0.0]
        return sum(sizes) if child.kind in ('row', 'split') else max(sizes)
    kind, texts, icon = child
    if kind == 'icon':
        return u
    if kind == 'list' or not by_text:
        return 10.0 * u
    widths = [_text_width(t) + 0.6 * u for t in texts] or [0.0]
    extra = (u if icon else 0.0) + (u if kind in ('check', 'menu') else 0.0)
    return (sum(widths) if kind == 'expand' else max(widths)) + extra


def _needs(kind, texts, icon, width, u):
    """[(text, its width, the width it has)] for one item given `width`."""
    pad = 0.6 * u + (u if icon else 0.0)
    if kind == 'split_label':
        return [(t, _text_width(t), 0.4 * (width - u) - 0.15 * u) for t in texts]
    if kind == 'split_check':
        return [(t, _text_width(t), 0.6 * (width - u) - u - 0.6 * u) for t in texts]
    if kind == 'split_expand':
        return [(t, _text_width(t), 0.6 * (width - u) / len(texts) - 0.3 * u) for t in texts]
    if kind == 'expand':
        return [(t, _text_width(t), width / len(texts) - 0.3 * u) for t in texts]
    if kind == 'check':
        return [(t, _text_width(t), width - u - 0.6 * u) for t in texts]
    if kind == 'number':       # 'Name: value' inside a full-width number field
        return [(t, _text_width(t + ": 0000000"), width - 0.6 * u) for t in texts]
    if kind == 'field':        # 'Name:' before its field, in a fixed slot of 8/3 units
        return [(t + ":", _text_width(t + ":"), 8.0 * u / 3.0 - 0.6 * u) for t in texts]
    if kind == 'menu':
        return [(t, _text_width(t), width - pad - u) for t in texts]
    return [(t, _text_width(t), width - pad) for t in texts]


def _list_rows(spec, width, u, out):
    list_type, data, name, active_data, active_name = spec
    drawer = getattr(bpy.types, list_type)
    for index, item in enumerate(getattr(data, name)):
        row = _Node('row')
        drawer.draw_item(drawer, bpy.context, row, data, item, 0, active_data, active_name, index)
        _fit(row, width - 0.5 * u, u, out, by_text=True)


def _fit(node, width, u, out, by_text=False):
    children = node.children
    if node.kind == 'row' and len(children) > 1:
        # Blender's row: each item its natural width (``_natural``), scaled to fill the row.
        natural = [_natural(c, u, by_text) for c in children]
        widths = [width * n / sum(natural) for n in natural]
    elif node.kind == 'split' and len(children) > 1:
        # Blender's split: the first item `factor` of the width (0: an even share), the
        # others an even share of the rest.
        first = width * (node.factor or 1.0 / len(children))
        widths = [first] + [(width - first) / (len(children) - 1)] * (len(children) - 1)
    else:
        widths = [width] * len(children)
    for child, w in zip(children, widths):
        if isinstance(child, _Node):
            _fit(child, w, u, out, by_text)
        elif child[0] == 'list':
            _list_rows(child[1], w - 1.2 * u, u, out)
        elif child[0] != 'icon':
            out.extend(_needs(child[0], child[1], child[2], w, u))


def sidebar_width():
    _, area, _ = view3d()
    return next(r for r in area.regions if r.type == 'UI').width


def cut_labels(idnames):
    """{panel: [[text, text px, px it has], ...]} of the texts that do not fit, for the active
    object now, at the sidebar's width; panels whose poll fails are left out."""
    u = _unit()
    content = sidebar_width() - 2.65 * u
    cut = {}
    for idname in idnames:
        cls = getattr(bpy.types, idname)
        if not cls.poll(bpy.context):
            continue
        root = _Node('column')
        cls.draw(type("Drawn", (), {"layout": root})(), bpy.context)
        out = []
        _fit(root, content, u, out)
        cut[idname] = [[t, round(need, 1), round(has, 1)] for t, need, has in out if need > has]
    return cut
'''


def cut_labels(gui, idnames):
    return gui.run(f"{MEASURER}\nresult = cut_labels({sorted(idnames)!r})")
