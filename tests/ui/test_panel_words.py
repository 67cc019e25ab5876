"""The panels say only what is true of the bake in place, in the real window: a solve's words
go when a simulation replaces its bake or when the solve is undone (a real ctrl+z), and none
says a word twice."""
from panel_sources import PANELS
from panel_text import labels
from test_file_and_undo import press

SOLVED = """
import blender_helpers as h
with override():
    obj = h.make_bar(cuts=3)
obj.rs_elastic.edge_length = 0.1
obj.rs_elastic.num_modes = 3
bpy.context.scene.frame_start, bpy.context.scene.frame_end = 1, 8
with override():
    assert bpy.ops.rs_elastic.prepare() == {'FINISHED'}
    h.add_tip_handle(obj, {1: (4.0, 0.5, 0.5), 8: (4.0, 0.5, 1.0)})
    h.make_active(obj)
"""
# As from their buttons, with an undo step each (the second argument), run to their end here.
SOLVE = ("with override():\n"
         "    assert bpy.ops.rs_elastic.solve_spacetime('EXEC_DEFAULT', True) == {'FINISHED'}")
SIMULATE = ("with override():\n"
            "    assert bpy.ops.rs_elastic.simulate('EXEC_DEFAULT', True) == {'FINISHED'}")
SPACETIME = "RS_ELASTIC_PT_spacetime"


def _solve_words(said):
    return [line for line in said if line.startswith(("Solve ", "Objective"))]


def test_the_panels_drop_a_solves_words_when_its_bake_goes(gui):
    gui.run(SOLVED, timeout=300)
    gui.run(SOLVE, timeout=300)
    said = labels(gui, SPACETIME)
    assert _solve_words(said), said
    for line in said:
        words = line.replace("(", " ").replace(")", " ").split()
        assert not any(a == b for a, b in zip(words, words[1:])), line
        assert "converged (converged)" not in line, line

    gui.run(SIMULATE, timeout=300)             # the simulation's bake replaces the solve's
    said = labels(gui, SPACETIME)
    assert not _solve_words(said), f"after a simulation replaced the bake: {said}"

    gui.run(SOLVE, timeout=300)
    assert _solve_words(labels(gui, SPACETIME))
    press(gui, "ctrl+z")                       # undo the solve, as a hand does
    gui.screenshot("solve_undone")
    said = labels(gui, SPACETIME)
    assert not _solve_words(said), f"after the solve was undone: {said}"


def _baked_lines(gui):
    return {panel: [line for line in labels(gui, panel) if line.startswith("Baked frames")]
            for panel in PANELS}


def test_the_baked_frames_line_is_of_the_bake_in_place(gui):
    gui.run(SOLVED, timeout=300)
    gui.run(SOLVE, timeout=300)
    assert sum(_baked_lines(gui).values(), []) == ["Baked frames 1–8"], _baked_lines(gui)
    gui.run("bpy.context.scene.frame_end = 6")
    gui.run(SIMULATE, timeout=300)             # the simulation's bake replaces the solve's
    said = _baked_lines(gui)
    assert not said[SPACETIME], f"the solve's panel after a simulation replaced its bake: {said}"
    assert sum(said.values(), []) == ["Baked frames 1–6"], said
    gui.run("with override():\n    assert bpy.ops.rs_elastic.clear_bake() == {'FINISHED'}")
    assert not sum(_baked_lines(gui).values(), []), _baked_lines(gui)
