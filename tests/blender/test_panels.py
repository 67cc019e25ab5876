"""Panels draw without error and show what the issue promises (background mode never draws them,
so they are drawn here into a recording layout that checks every property it is given)."""
import math

import bpy

from blender_helpers import make_bar


class RecordingLayout:
    """Stands in for bpy.types.UILayout: records labels, checks properties exist."""

    def __init__(self, log):
        self.log = log
        self.use_property_split = False
        self.active = True

    def _child(self, *args, **kwargs):
        return type(self)(self.log)

    row = column = box = split = _child

    def label(self, text="", icon='NONE'):
        self.log.append(("label", text))

    def prop(self, data, name, **kwargs):
        assert name in data.bl_rna.properties, f"{type(data).__name__} has no property {name}"
        self.log.append(("prop", name))

    def prop_search(self, data, name, search_data, search_name, **kwargs):
        assert name in data.bl_rna.properties
        assert search_name in search_data.bl_rna.properties
        self.log.append(("prop", name))

    def operator(self, idname, **kwargs):
        module, name = idname.split(".")
        assert hasattr(getattr(bpy.ops, module), name), idname
        self.log.append(("operator", idname))

    def menu(self, idname, **kwargs):
        assert hasattr(bpy.types, idname), idname
        self.log.append(("menu", idname))

    def panel(self, idname, default_closed=False):
        """(header, body) of a sub-panel (UILayout.panel): the body is recorded too."""
        assert "panel" in bpy.types.UILayout.bl_rna.functions   # this Blender has sub-panels
        assert isinstance(idname, str) and idname and isinstance(default_closed, bool)
        return type(self)(self.log), type(self)(self.log)

    def template_list(self, list_type, list_id, data, name, active_data, active_name, **kwargs):
        assert hasattr(bpy.types, list_type)
        assert name in data.bl_rna.properties and active_name in active_data.bl_rna.properties
        self.log.append(("list", name))


def draw_all():
    return [item for log in draw_each().values() for item in log]


def fitted_table(shown):
    """What the Take panel shows of a fitted material, read back from the labels it recorded
    (``draw_each()["RS_ELASTIC_PT_take"]``): ({'Frames': .., 'Residual': .., 'Worst frame':
    ..}, [(mode number, (prepared, fitted) Hz, (prepared, fitted) 1/s), ...])."""
    labels = [text for kind, text in shown if kind == "label"]
    start = labels.index("Frames")
    facts = dict(zip(labels[start:start + 6:2], labels[start + 1:start + 6:2]))
    cells = labels[labels.index("Damping, 1/s") + 1:]

    def pair(cell):                                     # 'a → b'
        return tuple(float(x) for x in cell.split(" → "))
    rows = [(number, pair(hz), pair(damping))
            for number, hz, damping in zip(cells[::3], cells[1::3], cells[2::3])]
    return facts, rows


def draw_each(layout=RecordingLayout):
    """{panel class name: what it recorded} of every registered RS Elastic panel whose poll
    passes (an import of the source tree under another package name leaves unregistered
    copies of the classes behind)."""
    logs = {}
    for cls in bpy.types.Panel.__subclasses__():
        if not (cls.__name__.startswith("RS_ELASTIC_PT") and cls.is_registered
                and cls.poll(bpy.context)):
            continue
        log = logs[cls.__name__] = []
        panel = type("Fake", (), {"layout": layout(log)})()
        if hasattr(cls, "draw_header"):
            cls.draw_header(panel, bpy.context)
        cls.draw(panel, bpy.context)
    return logs


def test_panels_show_counts_frequencies_and_mnf(ext):
    obj = make_bar()
    obj.rs_elastic.edge_length = 0.1
    obj.rs_elastic.num_modes = 3
    before = draw_all()
    assert ("operator", "rs_elastic.prepare") in before
    assert ("operator", "rs_elastic.tetrahedralize") in before
    assert ("label", "Not prepared") in before
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    after = draw_all()
    s = obj.rs_elastic
    assert ("label", f"{s.tet_node_count:,} nodes, {s.tet_count:,} tets") in after
    assert ("label", f"MNF {s.mnf:.4g} rad/s") in after
    assert ("list", "mode_results") in after
    assert ("prop", "show_tets") in after and ("prop", "preview_amplitude") in after
    # The Rayleigh damping shown as a damping ratio at the first mode: alpha/(2 w1) + beta w1/2.
    w1 = 2.0 * math.pi * s.frequencies[0]
    zeta = s.damping_mass / (2.0 * w1) + s.damping_stiffness * w1 / 2.0
    assert ("label", f"Damping ratio at mode 1: {100.0 * zeta:.3g} %") in after
    assert ("prop", "integrator") in after and ("prop", "substeps") in after


def test_panel_without_a_mesh_says_so(ext):
    bpy.ops.object.camera_add()
    assert ("label", "Select a mesh object") in draw_all()


def test_a_rigged_body_shows_follow_rig_and_the_tet_estimate(ext):
    import numpy as np
    import creature
    obj, rig = creature.build(bpy, np)
    bpy.context.view_layer.objects.active = obj
    log = draw_all()
    assert ("operator", "rs_elastic.follow_bones") in log
    labels = [text for kind, text in log if kind == "label"]
    assert any("Rigged by 'Critter Rig'" in text for text in labels)
    triangles = sum(len(p.vertices) - 2 for p in obj.data.polygons)
    assert any(f"fTetWild meshes {triangles:,} triangles" in text for text in labels), labels


def test_the_space_time_panel_shows_the_objective_before_and_after_and_every_step(ext):
    """After a solve: one line with the first and last objective, a sub-panel headed by the
    number of steps, and in it every recorded value (the solve's own history)."""
    from blender_helpers import add_tip_handle, make_active
    obj = make_bar(cuts=3)
    obj.rs_elastic.edge_length, obj.rs_elastic.num_modes = 0.1, 3
    bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 8
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    add_tip_handle(obj, {1: (4.0, 0.5, 0.5), 8: (4.0, 0.5, 1.0)})
    make_active(obj)
    assert bpy.ops.rs_elastic.solve_spacetime() == {'FINISHED'}
    history = [item.value for item in obj.rs_elastic.solve_history]
    assert len(history) >= 2 and history[-1] < history[0]
    labels = [text for kind, text in draw_all() if kind == "label"]
    drawn = labels.count(f"Objective {history[0]:.3g} to {history[-1]:.3g}")
    assert drawn >= 1                                   # the sidebar's and the Physics tab's
    assert labels.count(f"{len(history) - 1} Steps") == drawn
    steps = [text for text in labels if text[:3].strip().isdigit() and "   " in text]
    assert steps == [f"{i:3d}   {value:.6g}" for i, value in enumerate(history)] * drawn


class OwnerRecordingLayout(RecordingLayout):
    """Also records whose data each property edits, ("owner", name, ID name), and the context
    pointers the layout's buttons get, ("context", name, ID name)."""

    def prop(self, data, name, **kwargs):
        super().prop(data, name, **kwargs)
        self.log.append(("owner", name, data.id_data.name))

    def context_pointer_set(self, name, data):
        self.log.append(("context", name, data.name))


def test_with_a_handle_active_every_panel_shows_and_acts_on_its_body(ext):
    """Selecting a handle's Empty keeps the sidebar on its body: no panel edits the Empty's own
    (unused) settings, and every panel with buttons points them at the body (the operators
    read the active object)."""
    from blender_helpers import add_tip_handle, make_active
    obj = make_bar(cuts=3)
    obj.rs_elastic.edge_length, obj.rs_elastic.num_modes = 0.1, 3
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    empty, _ = add_tip_handle(obj, {1: (4.0, 0.5, 0.5)})
    make_active(empty)
    logs = draw_each(OwnerRecordingLayout)
    assert "RS_ELASTIC_PT_take" in logs and "RS_ELASTIC_PT_spacetime" in logs, sorted(logs)
    for panel, log in logs.items():
        owners = {item[2] for item in log if item[0] == "owner"}
        assert empty.name not in owners, (panel, sorted(owners))
        if any(item[0] == "operator" for item in log):
            assert ("context", "active_object", obj.name) in log, (panel, log)


def test_each_long_operator_draws_its_progress_in_the_panel_of_its_button(ext):
    """While a long operator runs on the body as a modal job, the panel holding its button
    draws its progress (here as a line: the recording layout has no bar) and Esc's hint, and no
    other panel does."""
    from blender_helpers import add_tip_handle, make_active
    obj = make_bar(cuts=3)
    obj.rs_elastic.edge_length, obj.rs_elastic.num_modes = 0.1, 3
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    add_tip_handle(obj, {1: (4.0, 0.5, 0.5)})
    make_active(obj)
    jobs = ext.bridge.jobs
    long_operators = sorted(cls.bl_idname for cls in ext.operators.CLASSES
                            if issubclass(cls, jobs.JobOperator))
    assert {"rs_elastic.prepare", "rs_elastic.tetrahedralize", "rs_elastic.simulate",
            "rs_elastic.fit_material"} <= set(long_operators), long_operators
    try:
        for idname in long_operators:
            job = jobs.Job(lambda job: None, idname, obj.name)
            job.fraction, job.message = 0.4, "Working"
            jobs.RUNNING[obj.name] = job
            logs = draw_each()
            buttons = sorted(p for p, log in logs.items() if ("operator", idname) in log)
            bars = sorted(p for p, log in logs.items() if ("label", "Working (40 %)") in log)
            hints = sorted(p for p, log in logs.items() if ("label", "Esc cancels") in log)
            assert buttons and bars == buttons and hints == buttons, (idname, buttons, bars)
    finally:
        jobs.RUNNING.pop(obj.name, None)
