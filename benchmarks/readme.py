"""Rewrite the README's generated blocks from the benchmarks' JSON (no timing is typed by hand).

A block is ``<!-- bench:NAME -->`` ... ``<!-- /bench:NAME -->``; NAME picks a renderer below, which reads
``benchmarks/results/*.json``. Usage: ``python benchmarks/readme.py [--check]`` (``--check`` exits 1 when
the README is not what the JSON says).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"


def _load(name: str) -> dict:
    path = RESULTS / f"{name}.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def _minutes(seconds: float) -> str:
    if seconds < 60:
        return f"{seconds:.1f} s"
    total = int(round(seconds))
    return f"{total // 60} min {total % 60} s"


def render_runs() -> str:
    runs = _load("runs")
    if not runs:
        return "*(no measurement yet: run `python benchmarks/runs.py`)*"
    lines = ["| what | wall time | result | load average at start |", "|---|---|---|---|"]
    for name, row in runs.items():
        if name.startswith("_"):
            continue
        counts = ", ".join(f"{n} {k}" for k, n in row.get("counts", {}).items()) or f"exit {row['exit_code']}"
        lines.append(f"| {row['what']} | {_minutes(row['seconds'])} | {counts} | {row['load_average_at_start']} |")
    machine = runs.get("_machine", {})
    lines.append(f"\n*Measured {machine.get('measured', '?')} on {machine.get('cpus', '?')} cores by "
                 "`python benchmarks/runs.py` (benchmarks/results/runs.json).*")
    return "\n".join(lines)


RENDERERS = {"runs": render_runs}


def rewrite(text: str) -> str:
    def block(match: re.Match) -> str:
        name = match.group(1)
        body = RENDERERS[name]() if name in RENDERERS else match.group(2)
        return f"<!-- bench:{name} -->\n{body}\n<!-- /bench:{name} -->"

    return re.sub(r"<!-- bench:(\w+) -->\n(.*?)\n?<!-- /bench:\1 -->", block, text, flags=re.S)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--check", action="store_true")
    args = parser.parse_args(argv)
    readme = ROOT / "README.md"
    before = readme.read_text()
    after = rewrite(before)
    if args.check:
        return int(before != after)
    readme.write_text(after)
    return 0


if __name__ == "__main__":
    sys.exit(main())
