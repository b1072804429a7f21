"""sync4d.report on synthetic sweep folders: table rows, Pareto front, outcomes, failures, charts."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from sync4d_tools import report as R


def make_run(root: Path, name: str, overrides: list[str], metrics: dict[str, Any] | None,
             sim: dict[str, Any] | None = None) -> Path:
    """A Hydra-like job folder: .hydra/overrides.yaml, .hydra/config.yaml and (optionally) metrics.json."""
    run = root / name
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    config = {"name": "t", "sim": {"type": "mpm_warp", "E": 1e4, "nu": 0.3, "density": 1000.0, "n_grid": 32,
                                    "grid_padding": 0.25, "wall_cells": 3, "frame_time": 0.04, "substeps": 20,
                                    "cfl_safety": 0.3, **(sim or {})}}
    (run / ".hydra" / "config.yaml").write_text(yaml.safe_dump(config))
    if metrics is not None:
        (run / "metrics.json").write_text(json.dumps(metrics))
    return run


def ok_metrics(pose: float | None, disp: float, seconds: float, substeps: list[float] | None = None) -> dict[str, Any]:
    return {
        "status": "ok", "pose_error_pct": pose, "displacement_error_pct": disp, "drift_pct": 0.1,
        "rigidity_residual_pct": 0.2, "det_f_deviation": 0.01, "jitter_ratio": 1.1, "seconds_per_frame": seconds,
        "peak_memory_mb": 500.0, "frame_stats": [{"time/frame_s": 0.0}] + [{"time/substeps": s} for s in substeps or [20.0]],
    }


def test_pareto_front_exact() -> None:
    points = [(1.0, 5.0), (2.0, 3.0), (3.0, 4.0), (4.0, 1.0), (5.0, 1.0), (2.5, 3.0), (0.5, 9.0), (2.0, 3.0)]
    # (3,4) dominated by (2,3); (5,1) by (4,1); (2.5,3) by (2,3); both copies of (2,3) are on the front.
    assert R.pareto_front(points) == [6, 0, 1, 7, 3]
    assert R.pareto_front([]) == []
    assert R.pareto_front([(1.0, 1.0)]) == [0]


def test_table_rows_outcomes_and_failures(tmp_path: Path) -> None:
    make_run(tmp_path, "sim.E=1e3", ["sim.E=1e3", "debug=smoke"], ok_metrics(None, 0.5, 2.0), {"E": 1e3})
    make_run(tmp_path, "sim.E=1e5", ["sim.E=1e5", "debug=smoke"], ok_metrics(None, 0.3, 3.0, [20.0, 45.0]), {"E": 1e5})
    make_run(tmp_path, "sim.E=1e7", ["sim.E=1e7", "debug=smoke"],
             {"status": "failed", "error": "SimulationUnstable: dt 2e-3 s breaks the CFL bound 4e-5 s; set sim.auto_substep=true",
              "overrides": {"sim.E": "1e7"}}, {"E": 1e7})
    make_run(tmp_path, "sim.E=1e9", ["sim.E=1e9", "debug=smoke"], {"status": "failed", "error": "RuntimeError: boom"}, {"E": 1e9})
    make_run(tmp_path, "sim.E=-1", ["sim.E=-1", "debug=smoke"], {"status": "failed", "error": "ConfigError: sim.E=-1: must be > 0"}, {"E": -1.0})
    make_run(tmp_path, "sim.E=1e2", ["sim.E=1e2", "debug=smoke"], None, {"E": 1e2})
    runs = R.load_runs(tmp_path)
    rows = {r["run"]: r for r in R.table_rows(runs)}
    assert set(rows) == {"sim.E=1e3", "sim.E=1e5", "sim.E=1e7", "sim.E=1e9", "sim.E=1e2", "sim.E=-1"}
    assert rows["sim.E=-1"]["outcome"] == "rejected"
    assert rows["sim.E=1e3"]["overrides"] == "sim.E=1e3"  # debug=smoke is a launch key, not a label
    assert rows["sim.E=1e3"]["status"] == "ok" and rows["sim.E=1e3"]["outcome"] == "stable"
    assert rows["sim.E=1e3"]["displacement_error_pct"] == 0.5 and rows["sim.E=1e3"]["pose_error_pct"] is None
    assert rows["sim.E=1e5"]["outcome"] == "guarded"  # 45 substeps used > 20 configured
    assert rows["sim.E=1e7"]["outcome"] == "diverged" and rows["sim.E=1e7"]["error"].startswith("SimulationUnstable")
    assert rows["sim.E=1e9"]["outcome"] == "failed"
    assert rows["sim.E=1e2"]["status"] == "missing"
    assert R.main_metric(runs) == "displacement_error_pct"
    assert R.swept_keys(runs) == ["sim.E"]

    result = R.make_report(tmp_path, tmp_path / "out")
    out = tmp_path / "out"
    with open(out / "report.csv") as handle:
        table = list(csv.DictReader(handle))
    assert [row["run"] for row in table] == sorted(rows)
    assert list(table[0]) == list(R.COLUMNS)
    text = (out / "report.md").read_text()
    assert "## Failed runs" in text
    failed_section = text.split("## Failed runs")[1].split("##")[0]
    assert "SimulationUnstable: dt 2e-3 s breaks the CFL bound" in failed_section
    assert "RuntimeError: boom" in failed_section and "no metrics.json" in failed_section
    assert "sim.E=1e3" not in failed_section
    assert result["front"] == ["sim.E=1e3", "sim.E=1e5"]
    assert result["charts"] == ["speed_accuracy.png", "ablation_sim_E.png"]
    for chart in result["charts"]:
        assert (out / chart).stat().st_size > 1000


def test_stability_map_and_ablation(tmp_path: Path) -> None:
    for E in ("1e3", "1e5"):
        for substeps in (2, 20):
            metrics = ok_metrics(1.0, 0.5, 1.0 + substeps / 10, [float(substeps)])
            if E == "1e5" and substeps == 2:
                metrics = {"status": "failed", "error": "SimulationUnstable: raise sim.substeps"}
            run = make_run(tmp_path, f"E={E},n={substeps}", [f"sim.E={E}", f"sim.substeps={substeps}"], metrics,
                           {"E": float(E), "substeps": substeps})
            if metrics["status"] == "ok":  # frame 0 of a 0.4 m object: dx = 0.025 m for the CFL curve
                np.savez(run / "trajectory.npz", x=np.array([[[0.0, 0.0, 0.0], [0.4, 0.1, 0.2]]] * 2))
    runs = R.load_runs(tmp_path)
    assert R.main_metric(runs) == "pose_error_pct"
    assert R.stability_axes(R.swept_keys(runs)) == ("E", "dt")
    assert runs[0].name == "E=1e3,n=2"
    assert R.stability_point(runs[0], "dt") == pytest.approx((1e3, 0.04 / 2))
    values = R.ablation_values(runs, "sim.substeps", "pose_error_pct")
    assert values == [("2", 1.0, 1), ("20", 1.0, 0)]
    assert R.object_extent(tmp_path / runs[0].name) == pytest.approx(0.4)
    assert R.run_cell_size(runs[0], 0.4) == pytest.approx(0.025)
    panels = R.stability_panels(runs, ["sim.E", "sim.substeps", "sim.auto_substep"])
    assert list(panels) == ["sim.auto_substep=-"] and len(panels["sim.auto_substep=-"]) == 4
    assert list(R.stability_panels(runs, ["sim.E", "sim.substeps"])) == [""]
    result = R.make_report(tmp_path)
    assert "stability_map.png" in result["charts"] and (tmp_path / "stability_map.png").is_file()
    assert {"ablation_sim_E.png", "ablation_sim_substeps.png"} <= set(result["charts"])


def test_grid_cell_size_and_effective_value() -> None:
    # 0.4 m object, padding 0.25, 32 nodes, walls of 3: 0.6 m over 24 interior cells.
    assert R.grid_cell_size(0.4, 32, 0.25, 3) == pytest.approx(0.025)
    config = {"sim": {"substeps": 20, "n_grid": 32}, "shrink": {"sim": {"substeps": 4}}}
    assert R.effective_value(config, "sim", "substeps") == 4
    assert R.effective_value(config, "sim", "n_grid") == 32
    assert R.parse_overrides(["+a.b=1", "c=x=y"]) == {"a.b": "1", "c": "x=y"}


def test_cli_empty_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert R.main([str(tmp_path)]) == 2
    assert "no run folders" in capsys.readouterr().err
