"""The package's imports go one way: no cycle, and each stage imports only the stages below it.

Read from the source with ``ast`` (nothing is imported), every import counts: at module level and
inside functions (a lazy import is still a dependency); only ``if TYPE_CHECKING:`` blocks are
left out, since they never run. docs/architecture.md, "Package layout", shows the same order.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "python" / "m360"

#: The stages from the bottom up; a module may import its own stage and those listed before it.
LAYERS: list[tuple[str, ...]] = [
    ("m360._core", "m360.errors", "m360._validate", "m360._compat", "m360._home", "m360._keywords"),
    ("m360.geometry",),
    ("m360.evaluation",),
    ("m360.estimators",),
    ("m360.stitching",),
    ("m360.io",),
    ("m360.pipeline",),
    ("m360.batch",),
    ("m360.video",),
    ("m360.cli",),
    ("m360",),  # the package's own __init__: the public API on top of everything
]


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}
#: The compiled core (its stub stands for it): a module too, with no m360 import of its own.
KNOWN = MODULES.keys() | {"m360._core"}
PACKAGES = {module_name(p) for p in PACKAGE.rglob("__init__.py")}


def _runtime_nodes(tree: ast.AST) -> Iterator[ast.AST]:
    """Every node, except the bodies of ``if TYPE_CHECKING:``."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            yield from (n for child in node.orelse for n in [child, *_runtime_nodes(child)])
            continue
        yield node
        yield from _runtime_nodes(node)


def imports_of(name: str) -> set[str]:
    """The m360 modules that module ``name`` imports."""
    path = MODULES[name]
    package = name if name in PACKAGES else name.rpartition(".")[0]
    found: set[str] = set()
    for node in _runtime_nodes(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.split(".")[0] == "m360")
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "m360":
                continue
            # ``from pkg import mod`` depends on the module; ``from mod import name`` on mod.
            subs = {f"{target}.{a.name}" for a in node.names} & KNOWN
            found.update(subs or {target})
    found.discard(name)
    return found & KNOWN


GRAPH = {name: imports_of(name) for name in MODULES}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def layer_of(name: str) -> int:
    for k, layer in reversed(list(enumerate(LAYERS))):
        if any(name == top or name.startswith(top + ".") for top in layer if top != "m360"):
            return k
    if name == "m360":
        return len(LAYERS) - 1
    raise AssertionError(f"{name} is in no layer of {__name__}.LAYERS: place it there")


def test_the_reader_sees_imports_including_lazy_ones_and_not_type_checking_ones() -> None:
    # The oracle for the graph itself: known edges of this package.
    assert "m360.geometry.plan_cache" in GRAPH["m360.geometry.layout"]  # a lazy import
    assert "m360.io.files" in GRAPH["m360.io.mesh"]
    assert "m360.stitching.depth" in GRAPH["m360.io.mesh"]
    assert "m360.estimators.onnx" in GRAPH["m360.estimators.registry"]
    assert "m360._core" in GRAPH["m360.geometry.layout"]
    tree = ast.parse(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import m360.cli\nimport m360.io\n"
    )
    seen = {a.name for n in _runtime_nodes(tree) if isinstance(n, ast.Import) for a in n.names}
    assert seen == {"m360.io"}


def test_cycle_finder_finds_a_cycle() -> None:
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle_inside_the_package() -> None:
    found = cycles(GRAPH)
    assert not found, "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


@pytest.mark.parametrize("name", sorted(MODULES))
def test_imports_only_go_down(name: str) -> None:
    mine = layer_of(name)
    upward = sorted(m for m in GRAPH[name] if layer_of(m) > mine)
    assert not upward, f"{name} (layer {mine}) imports from a higher stage: {upward}"


def test_every_stage_package_says_its_job_in_one_line() -> None:
    for name in sorted(PACKAGES - {"m360"}):
        doc = ast.get_docstring(ast.parse(MODULES[name].read_text(encoding="utf-8")))
        assert doc, f"{name} has no docstring"
        assert len(doc.splitlines()[0]) <= 100, f"{name}: the first line is the summary"
