"""Helpers for tests that run ``train.py`` end to end: start runs, compare their frames and metrics."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
TIMEOUT_S = 600
#: metrics.json keys that are timings or memory (differ between identical runs) or record the command.
VOLATILE_KEYS = frozenset({"wall_seconds", "seconds_per_frame", "peak_memory_mb", "overrides"})
VOLATILE_FRAME_KEYS = frozenset({"seconds", "time/frame_s"})


def train_command(run_dir: Path, *overrides: str) -> list[str]:
    """``python train.py debug=smoke <overrides> hydra.run.dir=<run_dir>``."""
    return [sys.executable, str(ROOT / "train.py"), "debug=smoke", *overrides, f"hydra.run.dir={run_dir}"]


def train_env() -> dict[str, str]:
    env = {**os.environ, "WARP_CACHE_PATH": str(ROOT / ".warp_cache")}
    env.pop("HYDRA_FULL_ERROR", None)
    return env


def run_train(run_dir: Path, *overrides: str) -> subprocess.CompletedProcess:
    """Run ``train.py`` to completion; returns the process (stdout/stderr captured as text)."""
    return subprocess.run(train_command(run_dir, *overrides), cwd=ROOT, env=train_env(), capture_output=True,
                          text=True, timeout=TIMEOUT_S, check=False)


def start_train(run_dir: Path, *overrides: str, log: Path) -> subprocess.Popen:
    """Start ``train.py`` in the background (its own process group), output to ``log``."""
    with log.open("w") as out:
        return subprocess.Popen(train_command(run_dir, *overrides), cwd=ROOT, env=train_env(), stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True)


def stable_metrics(run_dir: Path) -> dict[str, Any]:
    """``metrics.json`` without timings, memory and the command line."""
    metrics = json.loads((run_dir / "metrics.json").read_text())

    def strip(row: dict[str, Any]) -> dict[str, Any]:
        return {k: v for k, v in row.items() if k not in VOLATILE_FRAME_KEYS}

    out = {k: v for k, v in metrics.items() if k not in VOLATILE_KEYS}
    out["per_frame"] = [strip(r) for r in metrics["per_frame"]]
    out["frame_stats"] = [strip(r) for r in metrics["frame_stats"]]
    return out


def frame_bytes(run_dir: Path) -> dict[str, bytes]:
    """The run's ``frames/*.ply`` files by name."""
    return {p.name: p.read_bytes() for p in sorted((run_dir / "frames").glob("*.ply"))}


def assert_same_run(a: Path, b: Path) -> None:
    """Identical frame files (byte for byte) and identical metrics (timings aside)."""
    frames_a, frames_b = frame_bytes(a), frame_bytes(b)
    assert list(frames_a) == list(frames_b), f"frame files differ: {list(frames_a)} vs {list(frames_b)}"
    differ = [name for name in frames_a if frames_a[name] != frames_b[name]]
    assert not differ, f"frames differ between {a} and {b}: {differ}"
    metrics_a, metrics_b = stable_metrics(a), stable_metrics(b)
    keys = [k for k in metrics_a.keys() | metrics_b.keys() if metrics_a.get(k) != metrics_b.get(k)]
    assert not keys, f"metrics differ in {sorted(keys)}: {[(metrics_a.get(k), metrics_b.get(k)) for k in keys]}"


def train_in_process(run_dir: Path, *overrides: str) -> tuple[int, str]:
    """What ``python train.py debug=smoke <overrides> hydra.run.dir=<run_dir>`` would do, in this process.

    The same command-line checks, composition and :func:`sync4d.run.pipeline.run_guarded`, without paying
    for a new interpreter (torch, Warp, Hydra: seconds per launch). Returns (exit code, stderr text);
    log records go elsewhere, as under Hydra they go to the run's log.
    """
    import contextlib
    import io
    import logging

    from hydra import compose, initialize_config_dir
    from omegaconf import open_dict

    from sync4d.cli import check_command_line
    from sync4d.run.pipeline import run_guarded

    argv = ["debug=smoke", *overrides, f"hydra.run.dir={run_dir}"]
    err = io.StringIO()
    root = logging.getLogger()
    quiet = logging.NullHandler()
    root.addHandler(quiet)
    try:
        with contextlib.redirect_stderr(err):
            check_command_line(argv, ROOT / "conf")
            overrides = [a for a in argv if not a.startswith("hydra.")]
            with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
                cfg = compose(config_name="config", overrides=overrides)
            with open_dict(cfg):
                cfg.run_dir = str(run_dir)
                cfg.hydra = {"overrides": {"task": overrides}}  # what Hydra records of the command line
            run_guarded(cfg)
        return 0, err.getvalue()
    except SystemExit as stop:
        return int(stop.code or 0), err.getvalue()
    finally:
        root.removeHandler(quiet)
