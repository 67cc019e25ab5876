"""The layers hold: the solver never reaches Blender or the bridge, panels and operators reach the
solver only through the bridge, and the package has no import circle.

Read from the source with `ast` (nothing is imported), so the check holds even in an environment
that has bpy installed, as the solver tests' own does.
"""
import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
LAYERS = ("solver", "bridge", "operators", "panels")
BLENDER_MODULES = {"bpy", "mathutils", "bpy_extras", "bmesh", "gpu", "gpu_extras", "blf",
                   "addon_utils", "bl_math"}


def _modules():
    """{dotted name inside the package: path} of every module of the layers."""
    found = {}
    for layer in LAYERS:
        for path in sorted((ROOT / layer).glob("*.py")):
            name = layer if path.stem == "__init__" else f"{layer}.{path.stem}"
            found[name] = path
    return found


def _imports(name, path):
    """(absolute top-level names, package-internal modules) that the module imports."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = name if path.stem == "__init__" else name.rpartition(".")[0]
    external, internal = set(), set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            external.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                external.add(node.module.split(".")[0])
                continue
            base = package.split(".") if package else []
            base = base[:len(base) - (node.level - 1)] if node.level > 1 else base
            target = ".".join(base + ([node.module] if node.module else []))
            internal.add(target)
            internal.update(f"{target}.{alias.name}" for alias in node.names)
    return external, internal


MODULES = _modules()
IMPORTS = {name: _imports(name, path) for name, path in MODULES.items()}


def _layer(module):
    return module.split(".")[0]


@pytest.mark.parametrize("name", sorted(n for n in MODULES if _layer(n) == "solver"))
def test_the_solver_never_imports_blender_or_the_bridge(name):
    external, internal = IMPORTS[name]
    assert not external & BLENDER_MODULES, f"{name} imports {external & BLENDER_MODULES}"
    reached = {_layer(m) for m in internal if m in MODULES or _layer(m) in LAYERS}
    assert reached <= {"solver"}, f"{name} reaches {reached - {'solver'}}"


@pytest.mark.parametrize("name", sorted(n for n in MODULES if _layer(n) in ("panels", "operators")))
def test_panels_and_operators_reach_the_solver_only_through_the_bridge(name):
    _, internal = IMPORTS[name]
    assert not {m for m in internal if _layer(m) == "solver"}, f"{name} imports the solver"


def test_the_bridge_never_imports_panels_or_operators():
    offenders = {name: sorted(m for m in IMPORTS[name][1] if _layer(m) in ("panels", "operators"))
                 for name in MODULES if _layer(name) == "bridge"}
    assert not {k: v for k, v in offenders.items() if v}


def _edges():
    return {name: {m for m in IMPORTS[name][1] if m in MODULES and m != name} for name in MODULES}


def test_no_import_circle():
    edges, state, circles = _edges(), {}, []

    def visit(node, path):
        state[node] = "open"
        for target in sorted(edges[node]):
            if state.get(target) == "open":
                circles.append(path[path.index(target):] + [target])
            elif target not in state:
                visit(target, path + [target])
        state[node] = "done"

    for name in sorted(edges):
        if name not in state:
            visit(name, [name])
    assert not circles, f"import circles: {circles}"


def test_the_guard_sees_a_forbidden_import(tmp_path):
    """The reader itself can fail: a planted `import bpy` and a planted circle are found."""
    planted = tmp_path / "planted.py"
    planted.write_text("import bpy\nfrom ..bridge import scene\nfrom . import planted\n")
    external, internal = _imports("solver.planted", planted)
    assert "bpy" in external and "bridge.scene" in internal and "solver.planted" in internal
