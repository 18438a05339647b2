"""The layering rules of docs/architecture.md, checked on every module's imports (those inside functions too)."""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "moisst_ns"
MAX_LINES = 500


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict:
    return {module_name(p): p for p in PACKAGE.rglob("*.py")}


def imports_of(path: Path, known: set) -> set:
    """moisst_ns modules imported by ``path`` anywhere in the file (``from a import b`` counts ``a.b`` if a module)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("moisst_ns")}
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("moisst_ns"):
            out.add(node.module)
            out |= {f"{node.module}.{a.name}" for a in node.names if f"{node.module}.{a.name}" in known}
    return {m for m in out if m in known}


def graph() -> dict:
    mods = modules()
    return {name: imports_of(path, set(mods)) - {name} for name, path in mods.items()}


def test_no_import_cycle():
    edges = graph()
    state, stack = {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(edges[node]):
            if nxt == "moisst_ns" or node == "moisst_ns":
                continue  # the package __init__ (which imports nothing) is loaded with any submodule
            if state.get(nxt) == "open":
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(nxt):] + [nxt]))
            if nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = "done"

    for node in sorted(edges):
        if node not in state:
            visit(node)


def test_nothing_below_cli_imports_cli():
    offenders = {m: sorted(i for i in deps if i.startswith("moisst_ns.cli")) for m, deps in graph().items() if not m.startswith("moisst_ns.cli")}
    assert {m: d for m, d in offenders.items() if d} == {}


def test_every_console_script_lives_in_cli():
    scripts = tomllib.loads((PACKAGE.parent / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts and all(target.startswith("moisst_ns.cli.") for target in scripts.values()), scripts
    for target in scripts.values():
        module, _, func = target.partition(":")
        assert func == "main" and module in modules(), target


def test_no_exit_outside_cli():
    offenders = []
    for name, path in modules().items():
        if name.startswith("moisst_ns.cli"):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Name) and node.id == "SystemExit":
                offenders.append(f"{name}:{node.lineno}")
            if isinstance(node, ast.Attribute) and node.attr == "exit" and getattr(node.value, "id", None) == "sys":
                offenders.append(f"{name}:{node.lineno}")
    assert offenders == []


def test_file_sizes():
    sizes = {str(p.relative_to(PACKAGE)): len(p.read_text().splitlines()) for p in PACKAGE.rglob("*.py")}
    assert {f: n for f, n in sizes.items() if n > MAX_LINES} == {}
