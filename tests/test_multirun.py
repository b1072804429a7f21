"""A tiny recorded sweep end to end: ``train.py -m experiment=ablate_bones debug=smoke`` then the report.

Three jobs: recon.bones=2 and 3 succeed; recon.bones=0 is a bad config that must not stop the sweep
and must appear in the table as failed with its reason.
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def bones_of(run_name: str) -> str:
    """``logger=none,recon.bones=2`` (Hydra's override_dirname) -> ``recon.bones=2``."""
    return next(part for part in run_name.split(",") if part.startswith("recon.bones="))


@pytest.mark.slow
def test_ablate_bones_sweep_and_report(tmp_path: Path) -> None:
    sweep = tmp_path / "sweep"
    env = {**os.environ, "WARP_CACHE_PATH": os.environ.get("WARP_CACHE_PATH", str(ROOT / ".warp_cache"))}
    env.pop("HYDRA_FULL_ERROR", None)  # a failing job must be recorded, not re-raised
    command = [
        sys.executable, "train.py", "-m", "experiment=ablate_bones", "debug=smoke", "logger=none",
        "recon.bones=2,3,0", f"hydra.sweep.dir={sweep}",
    ]
    done = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]

    metrics = {bones_of(p.parent.name): json.loads(p.read_text()) for p in sweep.glob("*/metrics.json")}
    assert set(metrics) == {"recon.bones=2", "recon.bones=3", "recon.bones=0"}, sorted(metrics)
    for name in ("recon.bones=2", "recon.bones=3"):
        assert metrics[name]["status"] == "ok", metrics[name].get("error")
    # ablate_bones is a self-transfer: each job has a pose error, and the bone count moves it
    assert metrics["recon.bones=2"]["pose_error_pct"] != metrics["recon.bones=3"]["pose_error_pct"]
    assert len(list(sweep.glob("*/.hydra/overrides.yaml"))) == 3
    assert metrics["recon.bones=0"]["status"] == "failed"
    assert "ConfigError" in metrics["recon.bones=0"]["error"]

    report = subprocess.run([sys.executable, "-m", "sync4d_tools.report", str(sweep), "--out", str(tmp_path / "report")],
                            cwd=ROOT, env=env, capture_output=True, text=True, timeout=300, check=False)
    assert report.returncode == 0, report.stderr[-3000:]
    out = tmp_path / "report"
    with open(out / "report.csv") as handle:
        rows = {bones_of(row["run"]): row for row in csv.DictReader(handle)}
    assert set(rows) == set(metrics)
    assert rows["recon.bones=0"]["status"] == "failed" and "ConfigError" in rows["recon.bones=0"]["error"]
    for name in ("recon.bones=2", "recon.bones=3"):  # the report carries each job's own numbers
        for key in ("pose_error_pct", "seconds_per_frame"):
            assert float(rows[name][key]) == pytest.approx(metrics[name][key], rel=1e-6), (name, key)
    text = (out / "report.md").read_text()
    assert "recon.bones=0" in text.split("## Failed runs")[1]
    for chart in ("speed_accuracy.png", "ablation_recon_bones.png"):
        assert (out / chart).stat().st_size > 1000, chart
