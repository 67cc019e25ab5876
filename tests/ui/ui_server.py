"""Runs inside the Blender under test (`blender --python ui_server.py`): the tests' command channel.

A persistent `bpy.app.timers` callback polls the folder RS_UI_CHANNEL for requests
(`req-<n>.json`, {"code": ...}), runs each on Blender's main thread in one namespace kept across
requests, and writes `res-<n>.json`: {"ok": true, "result": <the value the code left in `result`>}
or {"ok": false, "error": <the traceback>}. A request's exception goes back to the test, never to
Blender's log, so the log's tracebacks are Blender's own (a panel's draw error, say).

The namespace carries helpers for the tests' code: `view3d()` and `override()` (a window context
for operators called with 'INVOKE_DEFAULT'), `rects()` (where things are on the screen, in X
pixels), `to_screen()` (a point in the world projected into the viewport), `reports()` (the
window manager's report log, as the Info editor lists it) and `DRAWN` (which panels drew, in the
order they drew, recorded by a function appended to each RS Elastic panel).
"""
import contextlib
import json
import os
import traceback

import bpy

CHANNEL = os.environ["RS_UI_CHANNEL"]
NAMESPACE = {"__name__": "rs_ui", "bpy": bpy}

# Blender asks nothing on quit and shows no splash in front of the viewport.
bpy.context.preferences.view.use_save_prompt = False
bpy.context.preferences.view.show_splash = False


def _helper(function):
    NAMESPACE[function.__name__] = function
    return function


@_helper
def view3d():
    """(window, area, region) of the largest 3D viewport's main region."""
    window = bpy.context.window_manager.windows[0]
    areas = [a for a in window.screen.areas if a.type == 'VIEW_3D']
    area = max(areas, key=lambda a: a.width * a.height)
    region = next(r for r in area.regions if r.type == 'WINDOW')
    return window, area, region


@_helper
@contextlib.contextmanager
def override(region_type='WINDOW'):
    """A context with the 3D viewport's window, area and region (`region_type`: WINDOW or UI)."""
    window, area, _ = view3d()
    region = next(r for r in area.regions if r.type == region_type)
    with bpy.context.temp_override(window=window, screen=window.screen, area=area,
                                   region=region):
        yield


@_helper
def rects():
    """Rectangles in window pixels, origin at the window's top left (X's way; Blender's is the
    bottom left): {name: [x, y, width, height]} for the window, the 3D viewport area, its main
    region ('view') and its sidebar ('sidebar', while it is shown)."""
    window, area, region = view3d()

    def box(thing):
        return [thing.x, window.height - (thing.y + thing.height), thing.width, thing.height]

    out = {"window": [0, 0, window.width, window.height], "area": box(area), "view": box(region)}
    sidebar = next((r for r in area.regions if r.type == 'UI'), None)
    if sidebar is not None and sidebar.width > 1:
        out["sidebar"] = box(sidebar)
    return out


@_helper
def to_screen(point):
    """Window pixel (x, y) of a world-space point in the 3D viewport, or None if behind it."""
    from bpy_extras import view3d_utils
    window, area, region = view3d()
    xy = view3d_utils.location_3d_to_region_2d(region, area.spaces.active.region_3d, point)
    if xy is None:
        return None
    x, y, _, height = rects()["view"]
    return [x + xy.x, y + height - xy.y]


@_helper
def reports():
    """The report log, oldest first, as the Info editor shows it ('Info: ...', 'Warning: ...'):
    the viewport's area is turned into an Info editor for a moment and its reports copied."""
    window, area, _ = view3d()
    old_type = area.type
    clipboard = bpy.context.window_manager.clipboard
    try:
        area.type = 'INFO'
        region = next(r for r in area.regions if r.type == 'WINDOW')
        with bpy.context.temp_override(window=window, screen=window.screen, area=area,
                                       region=region):
            bpy.ops.info.select_all(action='SELECT')
            bpy.ops.info.report_copy()
        text = bpy.context.window_manager.clipboard
    finally:
        area.type = old_type
        bpy.context.window_manager.clipboard = clipboard
    return [line for line in text.splitlines() if line.strip()]


DRAWN = []                   # [(panel idname, active object's name), ...] as panels draw
NAMESPACE["DRAWN"] = DRAWN
SIDEBAR_DRAWS = [0]          # how often a 3D viewport's sidebar has drawn
NAMESPACE["SIDEBAR_DRAWS"] = SIDEBAR_DRAWS


def _count_sidebar_draw():
    SIDEBAR_DRAWS[0] += 1


bpy.types.SpaceView3D.draw_handler_add(_count_sidebar_draw, (), 'UI', 'POST_PIXEL')


def _record(panel_name):
    def record(self, context):
        obj = context.active_object
        DRAWN.append((panel_name, obj.name if obj is not None else None))
    record.__name__ = f"rs_ui_record_{panel_name}"
    return record


@_helper
def watch_panels():
    """Append a recorder to every registered RS Elastic panel (once): it runs after the panel's
    own draw, so a panel whose draw raised records nothing. Returns the panels' idnames."""
    names = sorted(name for name in dir(bpy.types) if name.startswith("RS_ELASTIC_PT_"))
    for name in names:
        panel = getattr(bpy.types, name)
        funcs = getattr(panel.draw, "_draw_funcs", [])
        if not any(getattr(f, "__name__", "") == f"rs_ui_record_{name}" for f in funcs):
            panel.append(_record(name))
    return names


def _answer(name):
    number = name[len("req-"):-len(".json")]
    path = os.path.join(CHANNEL, name)
    with open(path) as handle:
        request = json.load(handle)
    os.remove(path)
    NAMESPACE.pop("result", None)
    try:
        exec(compile(request["code"], f"<request {number}>", "exec"), NAMESPACE)
        answer = {"ok": True, "result": NAMESPACE.get("result")}
        text = json.dumps(answer, default=repr)
    except BaseException:       # everything goes back to the test, which raises it there
        text = json.dumps({"ok": False, "error": traceback.format_exc()})
    partial = os.path.join(CHANNEL, f"res-{number}.part")
    with open(partial, "w") as handle:
        handle.write(text)
    os.replace(partial, os.path.join(CHANNEL, f"res-{number}.json"))


def _poll():
    """One request per call, so Blender handles events and redraws between requests."""
    requests = sorted(n for n in os.listdir(CHANNEL) if n.startswith("req-") and n.endswith(".json"))
    if requests:
        _answer(requests[0])
        return 0.0
    return 0.02


bpy.app.timers.register(_poll, first_interval=0.1, persistent=True)
with open(os.path.join(CHANNEL, "ready"), "w") as ready:
    ready.write(bpy.app.version_string)
