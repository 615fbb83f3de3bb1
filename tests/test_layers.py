"""The package's layers (docs/layout.md): every import of a flexmbs module, at the top of a
module or inside a function, goes to the same layer or one listed before it; no modules import
each other in a circle; only flexmbs.core imports the compiled extension flexmbs._core."""
from __future__ import annotations

import ast
import pathlib

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "python" / "flexmbs"

#: The layers, lowest first: a module may import from its own layer and the ones before it.
LAYERS = [
    ("base", ["flexmbs.errors", "flexmbs.version", "flexmbs.files", "flexmbs.resources",
              "flexmbs.progress"]),
    ("model", ["flexmbs.model"]),
    ("responses", ["flexmbs.responses"]),
    ("core", ["flexmbs.core", "flexmbs._core"]),
    ("visual", ["flexmbs.visual"]),
    ("analysis", ["flexmbs.analysis"]),
    ("problem", ["flexmbs.output", "flexmbs.problem"]),
    ("optimizers", ["flexmbs.optimizers"]),
    ("batch", ["flexmbs.batch", "flexmbs.sweep"]),
    ("methods", ["flexmbs.methods", "flexmbs.optimize"]),
    ("paper", ["flexmbs.paper"]),
    ("command line", ["flexmbs.cli", "flexmbs.__main__"]),
]


def _module(path):
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _layer(module):
    """The index of the layer a module belongs to (None: the package's face, flexmbs)."""
    for k, (_, prefixes) in enumerate(LAYERS):
        if any(module == p or module.startswith(p + ".") for p in prefixes):
            return k
    return None


def _imports():
    """{module: [(imported module, line)]}: every import of a flexmbs module."""
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        me = _module(path)
        names = []
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module and \
                    node.module.split(".")[0] == "flexmbs":
                if node.module == "flexmbs":        # from flexmbs import _core / a submodule
                    names += [(f"flexmbs.{a.name}", node.lineno) for a in node.names]
                else:
                    names.append((node.module, node.lineno))
            elif isinstance(node, ast.Import):
                names += [(a.name, node.lineno) for a in node.names
                          if a.name.split(".")[0] == "flexmbs"]
        found[me] = names
    return found


def test_every_module_has_a_layer():
    """Each module of the package (but its face, flexmbs/__init__.py) is in a layer."""
    lost = [m for m in _imports() if m != "flexmbs" and _layer(m) is None]
    assert not lost, f"modules in no layer of tests/test_layers.py (and docs/layout.md): {lost}"


def test_no_import_goes_up():
    """No module imports one of a later layer, nor the package's face."""
    up = []
    for me, names in _imports().items():
        mine = _layer(me)
        if mine is None:
            continue
        for target, line in names:
            theirs = _layer(target)
            if theirs is None or theirs > mine:
                up.append(f"{me}:{line} imports {target} "
                          f"({LAYERS[mine][0]} -> {'the face' if theirs is None else LAYERS[theirs][0]})")
    assert not up, "imports that go up a layer:\n" + "\n".join(up)


def test_only_the_core_module_imports_the_extension():
    """flexmbs.core is the one owner of the compiled extension flexmbs._core."""
    owners = sorted({me for me, names in _imports().items()
                     for target, _ in names if target == "flexmbs._core"})
    assert owners == ["flexmbs.core"], owners


def test_no_circle_of_imports():
    """No modules import each other in a circle (imports inside functions count)."""
    modules = _imports()
    edges = {m: {t for t, _ in names if t in modules and t != m} for m, names in modules.items()
             if m != "flexmbs"}
    state, circle = {}, []

    def visit(m, path):
        state[m] = 1
        for t in sorted(edges.get(m, ())):
            if state.get(t) == 1:
                circle.append(path[path.index(t):] + [t])
            elif t not in state:
                visit(t, path + [t])
        state[m] = 2

    for m in sorted(edges):
        if m not in state:
            visit(m, [m])
    assert not circle, f"circles of imports: {circle}"
