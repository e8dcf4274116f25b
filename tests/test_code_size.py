"""Sizes a reader can take in: no module over 500 lines unless its docstring says why it must be
longer ("longer than 500 lines because ..."), no function over 60 lines (decorators left out)."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PACKAGES = (
    "msgs",
    "workcell",
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


def _sources(*folders: str) -> list[Path]:
    return sorted(path for folder in folders for path in (REPO / folder).rglob("*.py"))


def test_no_module_is_over_500_lines_without_saying_why() -> None:
    long = []
    for path in _sources(*PACKAGES):
        text = path.read_text()
        docstring = ast.get_docstring(ast.parse(text)) or ""
        if len(text.splitlines()) > MAX_MODULE_LINES and "longer than 500 lines because" not in docstring:
            long.append(f"{path.relative_to(REPO)}: {len(text.splitlines())} lines")
    assert long == []


def test_no_function_is_over_60_lines() -> None:
    long = []
    for path in _sources(*PACKAGES, "tests"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = node.end_lineno - node.lineno + 1  # type: ignore[operator]
                if lines > MAX_FUNCTION_LINES:
                    long.append(f"{path.relative_to(REPO)}:{node.lineno} {node.name}: {lines} lines")
    assert long == []
