"""The package's layout: module-level imports between its modules form no cycle, and importing
a module starts no JAX backend.

A cycle makes import order matter and hides which stage depends on which (docs/architecture.md).
Imports inside functions are left out: they are reserved for expensive optional dependencies.
"""

import ast
import subprocess
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "evojax_motion"


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _with_parents(name: str, modules: set[str]) -> set[str]:
    """``name`` and the packages above it that import runs first (``a.b.c``: ``a.b``, ``a``)."""
    parts = name.split(".")
    return {".".join(parts[:i]) for i in range(1, len(parts) + 1)} & modules


def _top_level_imports(path: Path, modules: set[str]) -> set[str]:
    """The package's modules that ``path`` imports at module level (not inside a function),
    with the packages above them (their ``__init__`` runs first)."""
    found = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.If | ast.Try):  # e.g. TYPE_CHECKING blocks are not executed
            continue
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for alias in node.names:
                sub = f"{node.module}.{alias.name}"
                found.add(sub if sub in modules else node.module)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
    return {p for m in found if m in modules for p in _with_parents(m, modules)}


def import_graph() -> dict[str, set[str]]:
    files = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    modules = set(files)
    # A package's own __init__ is not an import of its modules (it runs before them, and a
    # module importing its package's __init__ back is only a cycle if the __init__ imports it).
    return {
        name: _top_level_imports(path, modules) - _with_parents(name, modules)
        for name, path in files.items()
    }


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of ``graph`` as a list of modules, or None (depth-first search)."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return [*path[path.index(nxt) :], nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        path.pop()
        state[node] = 2
        return None

    for start in sorted(graph):
        if start not in state and (cycle := visit(start)):
            return cycle
    return None


def test_find_cycle_finds_a_planted_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None


def test_package_has_no_import_cycle():
    graph = import_graph()
    assert "evojax_motion.settings" in graph and "evojax_motion.compiler.optimisation" in graph
    assert find_cycle(graph) is None, " -> ".join(find_cycle(graph) or [])


def test_settings_import_nothing_of_the_pipeline():
    """Every stage reads its settings from ``settings``; so ``settings`` depends on no stage:
    its modules import only ``errors`` and each other."""
    graph = import_graph()
    for name, imports in graph.items():
        if name.startswith("evojax_motion.settings"):
            others = {m for m in imports if not m.startswith("evojax_motion.settings")}
            assert others <= {"evojax_motion", "evojax_motion.errors"}, (name, others)


_IMPORT_EVERY_MODULE = """
import importlib, pkgutil
from jax._src import xla_bridge
import evojax_motion
for m in pkgutil.walk_packages(evojax_motion.__path__, "evojax_motion."):
    if not m.name.endswith("__main__"):
        importlib.import_module(m.name)
print("backends started:", xla_bridge.backends_are_initialized())
"""


def test_importing_a_module_starts_no_jax_backend():
    """No module makes an array or asks for a device at import: the command line chooses the
    platform (``--device``, `cli.online.use_device`) after its imports, which only works while
    no backend has started. A fresh process, as the command line's."""
    run = subprocess.run(
        [sys.executable, "-c", _IMPORT_EVERY_MODULE],
        capture_output=True, text=True, cwd=PACKAGE.parent, timeout=300,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert "backends started: False" in run.stdout
