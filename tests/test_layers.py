"""The shape of the source tree, read from the source.

The import graph: every import (deferred ones inside functions too) goes down the layers the
README draws, and no two modules import each other, directly or round a circle. A new module
must be placed in :data:`LAYERS` before this passes.

Sizes a reader can take in: no module over 500 lines unless its docstring says why it must be
longer ("longer than 500 lines because ..."), no function over 60 lines (decorators left out)."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

# Bottom first. A module belongs to the first entry whose prefix names it or a package above
# it; a package's ``cli`` module is its part of the command line, the top layer.
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("messages", ("msgs",)),
    ("workcell", ("workcell",)),
    ("bus", ("bus",)),
    ("perception", ("perception",)),
    ("simulated world", ("sim",)),
    ("device backends", ("drivers",)),
    ("dataset", ("dataset",)),
    ("models", ("models",)),
    ("nodes", ("nodes",)),
    ("command line and reports", ("dtx", "report", "benchmarks", "*.cli")),
]
PACKAGES = (
    "msgs",
    "workcell",
    "bus",
    "nodes",
    "perception",
    "sim",
    "drivers",
    "dataset",
    "models",
    "dtx",
    "report",
    "benchmarks",
)
MAX_MODULE_LINES = 500
MAX_FUNCTION_LINES = 60


def _module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(path): path for package in PACKAGES for path in (REPO / package).rglob("*.py")}


def _imports(module: str, path: Path, known: set[str]) -> set[str]:
    """The project modules ``module`` imports anywhere in its file (a ``from package import
    name`` counts as the submodule when ``name`` is one)."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            targets = [f"{base}.{alias.name}" for alias in node.names] + [base]
        else:
            continue
        for target in targets:
            while target and target not in known:
                target = target.rpartition(".")[0]
            if target and target != module:
                found.add(target)
    return found


def _layer(module: str) -> int:
    if module.endswith(".cli"):
        return next(rank for rank, (_, prefixes) in enumerate(LAYERS) if "*.cli" in prefixes)
    for rank, (_, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            if module == prefix or module.startswith(prefix + "."):
                return rank
    raise AssertionError(f"{module} is in no layer: add it to LAYERS")


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    known = set(modules)
    return {module: _imports(module, path, known) for module, path in modules.items()}


def test_every_import_goes_down_the_layers() -> None:
    upward = [
        f"{module} ({LAYERS[_layer(module)][0]}) imports {target} ({LAYERS[_layer(target)][0]})"
        for module, targets in sorted(_graph().items())
        for target in sorted(targets)
        if _layer(target) > _layer(module)
    ]
    assert upward == []


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    circles.append(sorted(component))
    return circles


def test_no_module_imports_itself_round_a_circle() -> None:
    assert _circles(_graph()) == []


def test_the_checks_see_an_upward_import_and_a_circle() -> None:
    assert _layer("sim.world") > _layer("workcell.scene") and _layer("sim.cli") == len(LAYERS) - 1
    assert _circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    graph = _graph()
    assert "workcell.scene" in graph["nodes.collector"] and "msgs.codec" in graph["bus.pubsub"]


def test_no_module_is_over_500_lines_without_saying_why() -> None:
    long = []
    for path in _modules().values():
        text = path.read_text()
        docstring = ast.get_docstring(ast.parse(text)) or ""
        if len(text.splitlines()) > MAX_MODULE_LINES and "longer than 500 lines because" not in docstring:
            long.append(f"{path.relative_to(REPO)}: {len(text.splitlines())} lines")
    assert long == []


def test_no_function_is_over_60_lines() -> None:
    long = []
    for path in [*_modules().values(), *sorted((REPO / "tests").rglob("*.py"))]:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = node.end_lineno - node.lineno + 1  # type: ignore[operator]
                if lines > MAX_FUNCTION_LINES:
                    long.append(f"{path.relative_to(REPO)}:{node.lineno} {node.name}: {lines} lines")
    assert long == []
