"""Wall time of what the README quotes: the default run (fresh, then from the stage cache) and the test lanes.

Each command runs once, in this checkout, with the project's environment; the machine's load average at
the start of each is recorded beside it (this machine is shared: compare figures from one run only).

Usage:
    python benchmarks/runs.py [--only default_run,test_fast,test_slow] [--json benchmarks/results/runs.json]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
PY = sys.executable


def commands(scratch: Path) -> dict[str, tuple[str, list[str]]]:
    """Name -> (what it is, argv). The default run writes into ``scratch`` and uses a fresh stage cache."""
    run = [PY, "train.py", f"cache_dir={scratch / 'cache'}"]
    return {
        "default_run": ("python train.py (default scene, empty stage cache)", [*run, f"hydra.run.dir={scratch / 'a'}"]),
        "default_run_cached": ("python train.py again (reconstruction and matching from the cache)",
                               [*run, f"hydra.run.dir={scratch / 'b'}"]),
        "test_fast": ("make test's pytest lane (-m 'not slow')", [PY, "-m", "pytest", "-q", "-m", "not slow", "-p",
                                                                   "no:cacheprovider"]),
        "test_slow": ("make test-slow's pytest lane (-m slow)", [PY, "-m", "pytest", "-q", "-m", "slow", "-p",
                                                                  "no:cacheprovider"]),
    }


def pytest_counts(output: str) -> dict[str, int]:
    """``{'passed': n, 'failed': n, 'skipped': n}`` from pytest's closing line."""
    tail = output.strip().splitlines()[-1] if output.strip() else ""
    return {word: int(n) for n, word in re.findall(r"(\d+) (passed|failed|skipped|errors?)", tail)}


def time_command(argv: list[str]) -> dict:
    load = os.getloadavg()[0]
    started = time.perf_counter()
    proc = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, check=False)
    row: dict[str, Any] = {"seconds": round(time.perf_counter() - started, 1), "exit_code": proc.returncode,
           "load_average_at_start": round(load, 2)}
    if "pytest" in argv:
        row["counts"] = pytest_counts(proc.stdout)
    return row


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--only", default="", help="comma-separated names (default: all)")
    parser.add_argument("--json", type=Path, default=ROOT / "benchmarks" / "results" / "runs.json")
    args = parser.parse_args(argv)
    results = json.loads(args.json.read_text()) if args.json.is_file() else {}
    with tempfile.TemporaryDirectory() as tmp:
        table = commands(Path(tmp))
        names = [n for n in args.only.split(",") if n] or list(table)
        for name in names:
            what, cmd = table[name]
            row = {"what": what, **time_command(cmd)}
            results[name] = row
            print(f"{name:20s} {row['seconds']:8.1f} s  exit {row['exit_code']}  load {row['load_average_at_start']:5.2f}"
                  f"  {row.get('counts', '')}", flush=True)
    results["_machine"] = {"cpus": os.cpu_count(), "measured": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(results, indent=2) + "\n")
    return results


if __name__ == "__main__":
    main()
