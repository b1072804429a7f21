"""The house rules that keep the library honest: what it imports, import cycles, cache keys that know the code."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
LIBRARY = ROOT / "sync4d"
TOOLS = ("sync4d_tools", "benchmarks")
#: The thin ``python -m sync4d.evaluate`` entry point is the one place the library names the tools.
ENTRY_POINTS = {LIBRARY / "evaluate" / "__main__.py"}


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path, *, top_level_only: bool) -> list[str]:
    """Absolute module names a file imports (all of them, or only those run when the module loads)."""
    tree = ast.parse(path.read_text())
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    out = []
    for node in nodes:
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            out += [node.module, *(f"{node.module}.{a.name}" for a in node.names)]
    return out


def test_library_never_imports_tools():
    offenders = [
        f"{p.relative_to(ROOT)} imports {name}"
        for p in LIBRARY.rglob("*.py") if p not in ENTRY_POINTS
        for name in imports(p, top_level_only=False) if name.split(".")[0] in TOOLS
    ]
    assert not offenders, offenders


def test_importing_the_pipeline_loads_no_tool():
    code = ("import sys, sync4d.pipeline; from sync4d.plugins import load_all; load_all(); "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('sync4d_tools', 'benchmarks')))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_no_import_cycle_in_the_library():
    """Module-level imports between library modules form no cycle (function-level imports are lazy)."""
    modules = {module_name(p): p for p in LIBRARY.rglob("*.py")}
    graph = {name: {m for m in imports(path, top_level_only=True) if m in modules and m != name}
             for name, path in modules.items()}
    # a package's __init__ importing its own submodules is not a cycle of design
    for name in graph:
        graph[name] = {m for m in graph[name] if not (name.startswith(m + ".") and modules[m].name == "__init__.py")}
    state: dict[str, int] = {}
    cycle: list[str] = []

    def visit(node: str, stack: list[str]) -> bool:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycle.extend([*stack[stack.index(nxt):], nxt] if nxt in stack else [node, nxt])
                return True
            if nxt not in state and visit(nxt, [*stack, nxt]):
                return True
        state[node] = 2
        return False

    for start in sorted(graph):
        if start not in state and visit(start, [start]):
            break
    assert not cycle, " -> ".join(cycle)


def test_cache_key_follows_the_code(monkeypatch: pytest.MonkeyPatch):
    """Editing any module a stage imports (here one the reconstruction imports indirectly) changes the key."""
    from sync4d import cache
    from sync4d.recon import skinning_fit

    before = cache.code_hash(skinning_fit.SkinningFit)
    closure = cache._import_closure("sync4d.recon.skinning_fit")
    assert "sync4d.types" in closure and "sync4d.recon.skinning_fit" in closure
    original = cache._source

    def edited(name: str) -> bytes:
        return original(name) + (b"# edited\n" if name == "sync4d.types" else b"")

    monkeypatch.setattr(cache, "_source", edited)
    assert cache.code_hash(skinning_fit.SkinningFit) != before


def test_readme_numbers_come_from_the_benchmarks_json():
    """The README's generated blocks are what ``benchmarks/readme.py`` makes of benchmarks/results/*.json."""
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "readme.py"), "--check"], cwd=ROOT,
                         capture_output=True, text=True, timeout=60, check=False)
    assert out.returncode == 0, "README.md differs from benchmarks/results: run python benchmarks/readme.py"
