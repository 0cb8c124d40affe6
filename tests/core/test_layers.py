"""The package's layers (docs/architecture.md): each package imports only the layers below it, the module graph has
no cycle, the core loads no command, and the command runs as a module.

The imports are read from the source (every ``import`` statement, those inside functions included), so a rule
broken by an import that only runs on some path is found too. The layers are about what runs: imports under
``if TYPE_CHECKING:`` (for the type checker only) are left out there. The graph has no cycle even with them: a
reader following the types must not go round in circles either.
"""

from __future__ import annotations

import ast
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

import asyncdonkey

PACKAGE = Path(asyncdonkey.__file__).parent

#: the layers, bottom first: what each may import at run time besides itself and the layers named
FOUNDATION = {"errors", "ratelimit", "extras", "options", "memory", "contracts", "latest", "clock"}
MAY_IMPORT: dict[str, set[str]] = {
    **{name: FOUNDATION for name in FOUNDATION},
    "safety": FOUNDATION,
    "core": FOUNDATION | {"safety"},
    "loop": FOUNDATION | {"safety", "core"},
    "poller": FOUNDATION,
    "periodic": FOUNDATION,
    "pilot_export": FOUNDATION,
    "hw": FOUNDATION,
    "parts": FOUNDATION | {"safety", "core", "poller", "periodic", "hw", "pilot_export"},
    "testing": FOUNDATION | {"hw", "loop"},
}
#: the public faces, which re-export from every layer
FACES = {"__init__", "commands", "__main__"}


def _module_name(path: Path) -> tuple[str, bool]:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    is_package = parts[-1] == "__init__"
    return ".".join(parts[:-1] if is_package else parts), is_package


def _runtime_imports(path: Path, for_types: bool = False) -> list[tuple[str, int]]:
    """Every ``asyncdonkey`` module ``path`` imports at run time (``for_types``: and for the type checker), with
    the line; ``from pkg import name`` gives ``pkg.name`` when that is a module."""
    name, is_package = _module_name(path)
    here = name if is_package else name.rsplit(".", 1)[0]
    found: list[tuple[str, int]] = []

    def target_of(node: ast.ImportFrom) -> str:
        if not node.level:
            return node.module or ""
        base = here.split(".")[: len(here.split(".")) - node.level + 1]
        return ".".join(base + ([node.module] if node.module else []))

    def is_module(dotted: str) -> bool:
        rel = Path(*dotted.split("."))
        return (PACKAGE.parent / rel).with_suffix(".py").exists() or (PACKAGE.parent / rel).is_dir()

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            if not for_types and isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                for other in child.orelse:
                    visit(other)
                continue
            if isinstance(child, ast.ImportFrom):
                target = target_of(child)
                for alias in child.names:
                    full = f"{target}.{alias.name}"
                    found.append((full if is_module(full) else target, child.lineno))
            elif isinstance(child, ast.Import):
                found.extend((alias.name, child.lineno) for alias in child.names)
            visit(child)

    visit(ast.parse(path.read_text(), str(path)))
    return [(module, line) for module, line in found if module.split(".")[0] == "asyncdonkey"]


def _layer(module: str) -> str:
    """``asyncdonkey.core.drive`` → ``core``; ``asyncdonkey`` itself → ``__init__``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


SOURCES = sorted(PACKAGE.rglob("*.py"))


def test_at_most_15_modules_sit_directly_in_the_package() -> None:
    top = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert len(top) <= 15, top


def test_each_layer_imports_only_the_layers_below_it() -> None:
    broken = []
    for path in SOURCES:
        name, _ = _module_name(path)
        layer = _layer(name)
        if layer in FACES:
            continue
        allowed = MAY_IMPORT[layer] | {layer}
        for module, line in _runtime_imports(path):
            if _layer(module) not in allowed:
                broken.append(f"{path.relative_to(PACKAGE)}:{line} ({layer}) imports {module}")
    assert broken == []


def test_nothing_imports_the_drive_class_but_the_vehicle_and_the_commands() -> None:
    """The safety package is typed against small Protocols (``core.runtypes``), never against ``Drive``."""
    importers = set()
    for path in SOURCES:
        name, _ = _module_name(path)
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and any(a.name == "Drive" for a in node.names):
                importers.add(name)
    assert {m for m in importers if _layer(m) not in {"loop", "commands"}} == set()


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """A cycle of ``graph`` (module -> the modules it imports), as the path round it, or ``None``."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def walk(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return [*stack[stack.index(nxt) :], nxt]
            if nxt in graph and nxt not in state and (cycle := walk(nxt)) is not None:
                return cycle
        stack.pop()
        state[node] = 2
        return None

    for module in sorted(graph):
        if module not in state and (cycle := walk(module)) is not None:
            return cycle
    return None


def test_the_module_level_imports_have_no_cycle() -> None:
    graph: dict[str, set[str]] = {}
    for path in SOURCES:
        name, _ = _module_name(path)
        tree = ast.parse(path.read_text())
        top_lines = {n.lineno for n in tree.body if isinstance(n, ast.Import | ast.ImportFrom)}
        graph[name] = {m for m, line in _runtime_imports(path) if line in top_lines and m != name}
    assert _cycle(graph) is None, " -> ".join(_cycle(graph) or [])


def test_no_import_closes_a_cycle_not_even_one_for_the_type_checker() -> None:
    """Every import counts here (inside functions, under ``TYPE_CHECKING``): the views a module reads of another
    are Protocols declared below both (``core/runtypes.py``, ``safety/activity.py``) or beside their one user."""
    graph: dict[str, set[str]] = {}
    for path in SOURCES:
        name, _ = _module_name(path)
        graph[name] = {m for m, _ in _runtime_imports(path, for_types=True) if m != name}
    assert _cycle(graph) is None, " -> ".join(_cycle(graph) or [])


@pytest.mark.subprocess
def test_the_core_does_not_load_the_commands() -> None:
    code = "import sys, asyncdonkey; print(sorted(m for m in sys.modules if m.startswith('asyncdonkey.commands')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.subprocess
def test_the_command_runs_as_a_module() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "asyncdonkey.commands", "--version"], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().endswith(importlib.import_module("asyncdonkey").__version__)
