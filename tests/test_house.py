"""The house rules that keep the library honest: what it imports, import cycles, cache keys that know the code."""

from __future__ import annotations

import ast
import re
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
    code = ("import sys, sync4d.run.pipeline; from sync4d.plugins import load_all; load_all(); "
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


# ---------------------------------------------------------------------------------------------- the map


def house_map() -> dict[str, int]:
    """The layer of every top-level module and package of ``sync4d``, from docs/DEVELOPING.md's map."""
    import re

    text = (ROOT / "docs" / "DEVELOPING.md").read_text()
    table = text.split("<!-- house:map -->")[1].split("<!-- /house:map -->")[0]
    layers: dict[str, int] = {}
    for row in table.splitlines():
        cells = [c.strip() for c in row.strip().strip("|").split("|")]
        if len(cells) < 2 or not re.match(r"^\d", cells[0]):
            continue
        for name in re.findall(r"`([\w.]+)`", cells[1]):
            layers[name] = int(cells[0].split()[0])
    return layers


def top_level_name(module: str) -> str:
    """``sync4d.sim.mpm_warp.solver`` -> ``sim``; ``sync4d.geometry`` -> ``geometry``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def test_every_top_level_module_and_package_is_on_the_map():
    on_disk = {p.stem for p in LIBRARY.glob("*.py") if p.stem != "__init__"} | {
        p.name for p in LIBRARY.iterdir() if p.is_dir() and (p / "__init__.py").is_file()}
    mapped = set(house_map())
    assert not on_disk - mapped, f"not on the map in docs/DEVELOPING.md: {sorted(on_disk - mapped)}"
    assert not mapped - on_disk, f"on the map but not in sync4d/: {sorted(mapped - on_disk)}"


def library_edges(*, top_level_only: bool) -> set[tuple[str, str, str]]:
    """(importing module, imported module, the import) for every import between library modules."""
    modules = {module_name(p): p for p in LIBRARY.rglob("*.py")}
    edges = set()
    for name, path in modules.items():
        for imported in imports(path, top_level_only=top_level_only):
            if imported in modules and imported != name:
                edges.add((name, imported, imported))
    return edges


def test_no_import_points_to_a_higher_layer():
    layer = house_map()
    upward = sorted(f"{a} (layer {layer[top_level_name(a)]}) imports {b} (layer {layer[top_level_name(b)]})"
                    for a, b, _ in library_edges(top_level_only=False)
                    if top_level_name(a) and top_level_name(b)  # the package root (sync4d/__init__) is no layer
                    and layer[top_level_name(b)] > layer[top_level_name(a)])
    assert not upward, upward


def test_no_import_cycle_between_packages():
    """Counting lazy (function-level) imports too: a package never reaches back to itself."""
    graph: dict[str, set[str]] = {}
    for a, b, _ in library_edges(top_level_only=False):
        pa, pb = top_level_name(a), top_level_name(b)
        if pa != pb and pa and pb:
            graph.setdefault(pa, set()).add(pb)

    def reaches(start: str, goal: str, seen: set[str]) -> bool:
        for nxt in graph.get(start, ()):
            if nxt == goal or (nxt not in seen and reaches(nxt, goal, seen | {nxt})):
                return True
        return False

    circles = sorted(p for p in graph if reaches(p, p, {p}))
    assert not circles, f"packages on an import circle: {circles}"


def private_uses(path: Path) -> list[str]:
    """``from m import _name`` and ``m._name`` of a project module in one file."""
    tree = ast.parse(path.read_text())
    mine = ("sync4d", "sync4d_tools", "benchmarks")
    aliases: set[str] = set()
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] in mine:
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__"):
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno} from {node.module} import {alias.name}")
                aliases.add(alias.asname or alias.name)
        elif isinstance(node, ast.Import):
            aliases |= {a.asname or a.name.split(".")[0] for a in node.names if a.name.split(".")[0] in mine}
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")
                and isinstance(node.value, ast.Name) and node.value.id in aliases):
            found.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.value.id}.{node.attr}")
    return found


def test_no_private_name_is_used_across_modules():
    """A private function or class stays in its module; what another module needs is public."""
    found = [hit for folder in ("sync4d", "sync4d_tools", "benchmarks")
             for path in (ROOT / folder).rglob("*.py") for hit in private_uses(path)]
    assert not found, found


def long_functions(path: Path, limit: int) -> list[str]:
    tree = ast.parse(path.read_text())
    return [f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({node.end_lineno - node.lineno + 1} lines)"
            for node in ast.walk(tree) if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
            and node.end_lineno is not None and node.end_lineno - node.lineno + 1 >= limit]


def test_every_function_is_under_80_lines():
    found = [hit for path in LIBRARY.rglob("*.py") for hit in long_functions(path, 80)]
    assert not found, found


def test_only_the_plan_reads_the_raw_config():
    """``cfg`` names the raw Hydra config; attribute reads of it happen only where the run plan is built."""
    reads = [f"{path.relative_to(LIBRARY.parent)}:{n}" for path in sorted(LIBRARY.rglob("*.py"))
             for n, line in enumerate(path.read_text().splitlines(), 1)
             if re.search(r"\bcfg\.", line) and path.relative_to(LIBRARY).as_posix() != "run/plan.py"]
    assert not reads, reads


# ---------------------------------------------------------------------------------------------- capabilities

#: Files being rewritten whose probes go with the rewrite (none left). Paths under sync4d/, a folder ends in /.
PROBES_PENDING: tuple[str, ...] = ()
#: The registry checks that what it registers has a ``Config``: the one requirement it enforces by name; the
#: thread count asks the platform (not a component) whether it can tell the usable cores.
PROBES_ALLOWED = {("registry.py", "Config"), ("sim/mpm_warp/budget.py", "sched_getaffinity")}


def capability_probes(path: Path) -> list[tuple[str, int, str]]:
    """Probes in one file, as (path, line, the name asked for): every ``hasattr``, every ``getattr`` with a
    default, and ``getattr`` of a literal name (``getattr(config, field.name)`` over a dataclass's fields is
    reading, not probing)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and len(node.args) >= 2):
            continue
        name = node.args[1].value if isinstance(node.args[1], ast.Constant) else ast.unparse(node.args[1])
        if node.func.id == "hasattr" or (node.func.id == "getattr" and (
                len(node.args) == 3 or isinstance(node.args[1], ast.Constant))):
            found.append((path.relative_to(LIBRARY).as_posix(), node.lineno, str(name)))
    return found


def test_capabilities_are_declared_not_probed():
    """An optional capability is a Protocol in sync4d/interfaces.py checked with ``isinstance``; asking an object
    whether it has an attribute of some name (``hasattr``, ``getattr`` with a default) is not how the library
    finds out what a component can do. A value's kind is asked with ``isinstance`` too."""
    probes = [f"{file}:{line} {kind}" for path in sorted(LIBRARY.rglob("*.py"))
              for file, line, kind in capability_probes(path)
              if not file.startswith(PROBES_PENDING) and (file, kind) not in PROBES_ALLOWED]
    assert not probes, f"probes of a capability by name (declare a Protocol in sync4d/interfaces.py): {probes}"


def test_the_pending_probes_are_listed():
    """What the rewrite of the files in PROBES_PENDING still has to replace (printed with ``pytest -s``)."""
    pending = [f"{file}:{line} {kind}" for path in sorted(LIBRARY.rglob("*.py"))
               for file, line, kind in capability_probes(path) if file.startswith(PROBES_PENDING)]
    print("probes left in files being rewritten:", *pending, sep="\n  ")
