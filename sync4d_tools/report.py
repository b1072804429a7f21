"""``python -m sync4d_tools.report <multirun folder> [--out DIR]``: a sweep's runs as a table and charts.

Walks the folder for run sub-folders (each holds ``metrics.json`` with ``status`` ok or failed, and
Hydra's ``.hydra/overrides.yaml``; a job folder with overrides but no ``metrics.json`` is reported as
``missing``: it crashed hard or is still running) and writes into ``--out`` (default: the folder):

* ``report.csv`` and ``report.md``: one row per run (overrides, status, error, the main metrics);
  ``report.md`` also lists failed runs with their reason and embeds the charts;
* ``speed_accuracy.png``: seconds per frame against pose error (or displacement error when a run has
  no pose ground truth), one labelled point per run, the Pareto front drawn;
* ``stability_map.png`` (when the sweep varies ``sim.E`` and the substep size or ``sim.nu``): each
  configuration coloured by outcome (stable / guarded by automatic sub-stepping / diverged or rejected
  with a clear error / failed otherwise), with the CFL bound dt_max = cfl_safety dx / c drawn, one
  panel per value of any other swept key (e.g. ``sim.auto_substep``);
* ``ablation_<key>.png``: the main metric per value of each swept key (mean over the other keys).

Everything but :func:`main` and the ``plot_*`` functions is a small pure function (tested in
``tests/test_report.py``).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import yaml

METRIC_COLUMNS: tuple[str, ...] = (
    "pose_error_pct",
    "displacement_error_pct",
    "drift_pct",
    "rigidity_residual_pct",
    "det_f_deviation",
    "jitter_ratio",
    "seconds_per_frame",
    "peak_memory_mb",
)
COLUMNS: tuple[str, ...] = ("run", "overrides", "status", "outcome", "error", *METRIC_COLUMNS)
# Override keys that name how a sweep was launched, not what it varies.
LAUNCH_KEYS: tuple[str, ...] = ("experiment", "debug", "resume", "hydra", "hydra.launcher")
SIMULATION_ERRORS: tuple[str, ...] = ("SimulationDiverged", "SimulationUnstable")
OUTCOME_COLORS: dict[str, str] = {
    "stable": "#2ca02c",     # ran with the configured substeps
    "guarded": "#ff7f0e",    # ran; automatic sub-stepping raised the substeps
    "diverged": "#d62728",   # stopped with a clear simulator error (SimulationDiverged/SimulationUnstable)
    "rejected": "#9467bd",   # stopped with a clear ConfigError (out-of-range value)
    "failed": "#7f7f7f",     # any other failure: a bug to fix
    "missing": "#000000",    # no metrics.json: crashed hard or still running
}


# ----------------------------------------------------------------------------------------------- runs
@dataclass
class RunRecord:
    """One job of a sweep as read from its folder.

    Attributes:
        name: the run folder relative to the sweep folder (``.`` for the folder itself).
        overrides: command-line overrides ``{key: value}`` (values as typed on the command line).
        status: ``ok`` | ``failed`` | ``missing`` (no ``metrics.json``).
        error: the one-line reason of a failure, else ``""``.
        metrics: the contents of ``metrics.json`` (empty when missing).
        config: the composed config ``.hydra/config.yaml`` (empty when absent).
    """

    name: str
    overrides: dict[str, str]
    status: str
    error: str = ""
    metrics: dict[str, Any] = field(default_factory=dict)
    config: dict[str, Any] = field(default_factory=dict)


OUTCOME_LEGEND = {
    "stable": "stable",
    "guarded": "guarded (automatic sub-stepping)",
    "diverged": "stopped with a clear error (CFL guard / divergence check)",
    "rejected": "config refused (ConfigError)",
}


def parse_overrides(items: Iterable[str]) -> dict[str, str]:
    """``["sim.E=1e4", "+foo=1"]`` -> ``{"sim.E": "1e4", "foo": "1"}`` (Hydra's ``+``/``~``/``++`` dropped)."""
    out: dict[str, str] = {}
    for item in items:
        key, _, value = str(item).partition("=")
        out[key.lstrip("+~")] = value
    return out


def find_run_dirs(root: Path) -> list[Path]:
    """Folders under ``root`` (itself included) holding ``metrics.json`` or ``.hydra/overrides.yaml``, sorted."""
    root = Path(root)
    found = {p.parent for p in root.rglob("metrics.json") if ".hydra" not in p.parts}
    found |= {p.parent.parent for p in root.rglob(".hydra/overrides.yaml")}
    return sorted(found)


def _read_yaml(path: Path) -> Any:
    return yaml.safe_load(path.read_text()) if path.is_file() else None


def load_run(run_dir: Path, root: Path) -> RunRecord:
    """Read one run folder: ``metrics.json``, ``.hydra/overrides.yaml`` and ``.hydra/config.yaml``."""
    run_dir = Path(run_dir)
    name = str(run_dir.relative_to(root)) if run_dir != Path(root) else "."
    metrics_path = run_dir / "metrics.json"
    metrics: dict[str, Any] = json.loads(metrics_path.read_text()) if metrics_path.is_file() else {}
    listed = _read_yaml(run_dir / ".hydra" / "overrides.yaml")
    overrides = parse_overrides(listed) if listed else {str(k): str(v) for k, v in (metrics.get("overrides") or {}).items()}
    config = _read_yaml(run_dir / ".hydra" / "config.yaml") or {}
    if not metrics:
        status, error = "missing", "no metrics.json: the job crashed without a recorded error or is still running"
    else:
        status, error = str(metrics.get("status", "ok")), str(metrics.get("error") or "")
    return RunRecord(name=name, overrides=overrides, status=status, error=error, metrics=metrics, config=config)


def load_runs(root: Path) -> list[RunRecord]:
    """Every run under a sweep folder, sorted by folder name."""
    root = Path(root)
    return [load_run(d, root) for d in find_run_dirs(root)]


def sweep_overrides(overrides: dict[str, str]) -> dict[str, str]:
    """The overrides that describe the configuration (launch keys such as ``debug``/``hydra.*`` dropped)."""
    return {k: v for k, v in overrides.items() if k not in LAUNCH_KEYS and not k.startswith("hydra.")}


def swept_keys(runs: Sequence[RunRecord]) -> list[str]:
    """Override keys taking more than one value across the runs, in first-seen order."""
    values: dict[str, set[str]] = {}
    for run in runs:
        for key, value in sweep_overrides(run.overrides).items():
            values.setdefault(key, set()).add(value)
    missing = {k for k in values if any(k not in sweep_overrides(r.overrides) for r in runs)}
    return [k for k, v in values.items() if len(v) > 1 or k in missing]


def label_of(run: RunRecord, keys: Sequence[str] | None = None) -> str:
    """``k=v,k=v`` of a run's overrides (only ``keys`` when given; ``run name`` when there are none)."""
    items = sweep_overrides(run.overrides)
    if keys is not None:
        items = {k: items[k] for k in keys if k in items}
    return ",".join(f"{k}={v}" for k, v in items.items()) or run.name


# -------------------------------------------------------------------------------------------- numbers
def as_float(value: Any) -> float | None:
    """A finite float, or None (for None, non-numbers, NaN and inf)."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if math.isfinite(number) else None


def main_metric(runs: Sequence[RunRecord]) -> str:
    """``pose_error_pct`` when every successful run has it (self-transfer), else ``displacement_error_pct``."""
    ok = [r for r in runs if r.status == "ok"]
    if ok and all(as_float(r.metrics.get("pose_error_pct")) is not None for r in ok):
        return "pose_error_pct"
    return "displacement_error_pct"


def pareto_front(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point dominates, both coordinates minimised, sorted by x then y.

    A point is dominated when another is <= in both coordinates and < in at least one. Duplicates of
    a front point are all kept.
    """
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front: list[int] = []
    best_y = math.inf
    for i in order:
        x, y = points[i]
        if y < best_y:
            front.append(i)
            best_y = y
        elif front and (x, y) == tuple(points[front[-1]]):
            front.append(i)
    return front


def effective_value(config: dict[str, Any], group: str, key: str, default: Any = None) -> Any:
    """``config[group][key]`` with the ``shrink.<group>.<key>`` of ``debug=smoke`` applied (shrink wins)."""
    shrink = (config.get("shrink") or {}).get(group) or {}
    if key in shrink:
        return shrink[key]
    return (config.get(group) or {}).get(key, default)


def configured_substeps(run: RunRecord) -> int | None:
    """The run's ``sim.substeps`` as configured (the minimum the simulator may raise), or None."""
    value = effective_value(run.config, "sim", "substeps")
    if value is None:
        value = run.overrides.get("sim.substeps")
    number = as_float(value)
    return None if number is None else int(number)


def used_substeps(run: RunRecord) -> int | None:
    """The most substeps any frame used (``frame_stats[*]['time/substeps']``), or None if not recorded."""
    counts = [c for s in run.metrics.get("frame_stats") or [] if (c := as_float(s.get("time/substeps"))) is not None]
    return int(max(counts)) if counts else None


def outcome_of(run: RunRecord) -> str:
    """``stable`` | ``guarded`` (auto sub-stepping raised the substeps) | ``diverged`` (failed with a
    clear simulator error) | ``rejected`` (failed with a ConfigError) | ``failed`` (any other failure)
    | ``missing`` (no metrics.json). See :data:`OUTCOME_COLORS`."""
    if run.status == "missing":
        return "missing"
    if run.status != "ok":
        if any(name in run.error for name in SIMULATION_ERRORS):
            return "diverged"
        return "rejected" if "ConfigError" in run.error else "failed"
    used, configured = used_substeps(run), configured_substeps(run)
    if used is not None and configured is not None and used > configured:
        return "guarded"
    return "stable"


def table_rows(runs: Sequence[RunRecord]) -> list[dict[str, Any]]:
    """One row per run with :data:`COLUMNS` (metrics None when absent or not finite)."""
    rows = []
    for run in runs:
        row: dict[str, Any] = {
            "run": run.name,
            "overrides": label_of(run),
            "status": run.status,
            "outcome": outcome_of(run),
            "error": run.error,
        }
        row.update({key: as_float(run.metrics.get(key)) for key in METRIC_COLUMNS})
        rows.append(row)
    return rows


# ----------------------------------------------------------------------------------- stability physics
def grid_cell_size(extent: float, n_grid: int, padding: float, wall: int = 3) -> float:
    """Cell size dx [m] of ``sync4d.sim.physics.fit_grid``: the padded longest extent
    ``extent (1 + 2 padding)`` [m] spans the wall-free interior ``n_grid - 2 wall - 2`` cells."""
    return extent * (1.0 + 2.0 * padding) / (n_grid - 2 * wall - 2)


def object_extent(run_dir: Path) -> float | None:
    """Longest bounding-box extent [m] of the target at frame 0 (``trajectory.npz`` or ``frames/000000.ply``)."""
    import numpy as np

    trajectory = run_dir / "trajectory.npz"
    if trajectory.is_file():
        with np.load(trajectory) as data:
            x0 = data["x"][0]
    elif (run_dir / "frames" / "000000.ply").is_file():
        from sync4d.io.ply import read_gaussians_ply

        x0 = read_gaussians_ply(run_dir / "frames" / "000000.ply").means
    else:
        return None
    return float((x0.max(0) - x0.min(0)).max())


def run_cell_size(run: RunRecord, extent: float | None) -> float | None:
    """The run's dx [m]: recorded in ``metrics.json`` (``dx``) if present, else estimated from the grid."""
    recorded = as_float(run.metrics.get("dx"))
    if recorded is not None:
        return recorded
    n_grid = as_float(effective_value(run.config, "sim", "n_grid"))
    if extent is None or n_grid is None:
        return None
    padding = as_float(effective_value(run.config, "sim", "grid_padding", 0.25)) or 0.0
    wall = int(as_float(effective_value(run.config, "sim", "wall_cells", 3)) or 3)
    return grid_cell_size(extent, int(n_grid), padding, wall)


def substep_size(run: RunRecord) -> float | None:
    """The configured substep dt = sim.frame_time / sim.substeps [s], or None."""
    frame_time = as_float(effective_value(run.config, "sim", "frame_time"))
    substeps = configured_substeps(run)
    return None if frame_time is None or not substeps else frame_time / substeps


def stability_axes(keys: Sequence[str]) -> tuple[str, str] | None:
    """(x, y) of the stability map: ``("E", "dt")`` when E and the substep size vary, ``("E", "nu")``
    when E and nu vary, else None."""
    if "sim.E" not in keys:
        return None
    if "sim.substeps" in keys or "sim.frame_time" in keys:
        return ("E", "dt")
    if "sim.nu" in keys:
        return ("E", "nu")
    return None


def stability_point(run: RunRecord, y_axis: str) -> tuple[float, float] | None:
    """(E [Pa], dt [s] or nu) of a run from its composed config (overrides as a fallback)."""
    E = as_float(effective_value(run.config, "sim", "E", run.overrides.get("sim.E")))
    y = substep_size(run) if y_axis == "dt" else as_float(effective_value(run.config, "sim", "nu", run.overrides.get("sim.nu")))
    return None if E is None or y is None else (E, y)


# ------------------------------------------------------------------------------------------- writing
def _fmt(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value).replace("|", "\\|").replace("\n", " ")


def write_csv(rows: Sequence[dict[str, Any]], path: Path) -> None:
    """``report.csv``: :data:`COLUMNS`, one row per run (empty cells for missing values)."""
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(COLUMNS))
        writer.writeheader()
        for row in rows:
            writer.writerow({k: "" if row.get(k) is None else row[k] for k in COLUMNS})


def markdown_table(rows: Sequence[dict[str, Any]], columns: Sequence[str]) -> str:
    """A GitHub markdown table of ``rows`` restricted to ``columns``."""
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(_fmt(row.get(c)) for c in columns) + " |" for row in rows]
    return "\n".join(lines)


def markdown_report(root: Path, rows: Sequence[dict[str, Any]], metric: str, front: Sequence[str],
                    charts: Sequence[str]) -> str:
    """The text of ``report.md``: summary, table, failed runs with reasons, Pareto front, charts."""
    failed = [r for r in rows if r["status"] != "ok"]
    counts = {o: sum(r["outcome"] == o for r in rows) for o in OUTCOME_COLORS}
    parts = [
        f"# Sweep report: `{root}`",
        "",
        f"{len(rows)} runs: " + ", ".join(f"{n} {o}" for o, n in counts.items() if n) + f". Main metric: `{metric}`.",
        "",
        markdown_table(rows, [c for c in COLUMNS if c != "error"]),
        "",
        "## Failed runs",
        "",
    ]
    parts += [f"- `{r['run']}` ({r['overrides']}): {r['error']}" for r in failed] or ["None."]
    parts += ["", "## Pareto front (seconds per frame vs " + metric + ")", ""]
    parts += [f"- {label}" for label in front] or ["No successful run with both numbers."]
    parts += ["", "## Charts", ""] + [f"![{Path(c).stem}]({c})" for c in charts]
    return "\n".join(parts) + "\n"


# -------------------------------------------------------------------------------------------- charts
def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_speed_accuracy(runs: Sequence[RunRecord], metric: str, keys: Sequence[str], path: Path) -> list[str]:
    """Seconds per frame against ``metric``, one labelled point per successful run, Pareto front drawn.

    Returns:
        the labels of the front's runs (fastest first); nothing is written when no run has both numbers.
    """
    points, labels = [], []
    for run in runs:
        x, y = as_float(run.metrics.get("seconds_per_frame")), as_float(run.metrics.get(metric))
        if run.status == "ok" and x is not None and y is not None:
            points.append((x, y))
            labels.append(label_of(run, keys or None))
    if not points:
        return []
    front = pareto_front(points)
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 5))
    ax.scatter([p[0] for p in points], [p[1] for p in points], color="#1f77b4", zorder=3)
    for (x, y), label in zip(points, labels):
        ax.annotate(label, (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7)
    fx, fy = [points[i][0] for i in front], [points[i][1] for i in front]
    ax.step(fx, fy, where="post", color="#d62728", lw=1.5, label="Pareto front", zorder=2)
    ax.scatter(fx, fy, facecolors="none", edgecolors="#d62728", s=90, zorder=4)
    ax.set_xlabel("seconds per frame [s]")
    ax.set_ylabel(f"{metric} [% bbox diagonal]")
    ax.set_title("Speed against accuracy (lower-left is better)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return [labels[i] for i in front]


STABILITY_KEYS: tuple[str, ...] = ("sim.E", "sim.nu", "sim.substeps", "sim.frame_time")


def stability_panels(runs: Sequence[RunRecord], keys: Sequence[str]) -> dict[str, list[RunRecord]]:
    """Runs grouped by the swept keys that are not axes of the stability map (e.g. ``sim.auto_substep``),
    one panel each, so configurations differing only there do not overlap; ``{"": runs}`` when none."""
    others = [k for k in keys if k not in STABILITY_KEYS]
    panels: dict[str, list[RunRecord]] = {}
    for run in runs:
        values = sweep_overrides(run.overrides)
        panels.setdefault(",".join(f"{k}={values.get(k, '-')}" for k in others), []).append(run)
    return dict(sorted(panels.items()))


def _draw_cfl(ax: Any, runs: Sequence[RunRecord], root: Path, y_axis: str, E_range: tuple[float, float]) -> None:
    """The CFL bound dt_max = cfl_safety dx / c(E, nu, rho) of the first run whose cell size is known:
    a line dt_max(E) on an (E, dt) map, the contour dt = dt_max(E, nu) on an (E, nu) map."""
    import numpy as np

    from sync4d.sim.physics import cfl_dt

    run = dx = None
    for candidate in runs:
        dx = run_cell_size(candidate, object_extent(root / candidate.name))
        if dx is not None:
            run = candidate
            break
    if run is None or dx is None:
        return
    nu = as_float(effective_value(run.config, "sim", "nu", 0.3)) or 0.3
    rho = as_float(effective_value(run.config, "sim", "density", 1000.0)) or 1000.0
    safety = as_float(effective_value(run.config, "sim", "cfl_safety", 0.3)) or 0.3
    E_line = np.logspace(math.log10(E_range[0]) - 0.3, math.log10(E_range[1]) + 0.3, 200)
    if y_axis == "dt":
        bound = [cfl_dt(dx, float(E), nu, rho, safety=safety) for E in E_line]
        ax.plot(E_line, bound, "k--", label=f"CFL bound {safety:g} dx/c (dx={dx * 1e3:.2f} mm, nu={nu:g})")
        return
    dt = substep_size(run)
    if dt is None:
        return
    nu_grid = np.linspace(0.0, 0.49, 120)
    ratio = np.array([[dt / cfl_dt(dx, float(E), float(n), rho, safety=safety) for E in E_line] for n in nu_grid])
    ax.contour(E_line, nu_grid, ratio, levels=[1.0], colors="k", linestyles="--")
    ax.plot([], [], "k--", label=f"CFL bound at dt={dt:.2e} s (dx={dx * 1e3:.2f} mm)")


def plot_stability_map(runs: Sequence[RunRecord], root: Path, y_axis: str, keys: Sequence[str], path: Path) -> bool:
    """Outcome per (E, substep size) or (E, nu), one panel per value of the other swept keys, with the
    CFL bound drawn. Returns False when no run has both coordinates."""
    placed = [(run, p) for run in runs if (p := stability_point(run, y_axis)) is not None]
    if not placed:
        return False
    E_range = (min(p[0] for _, p in placed), max(p[0] for _, p in placed))
    panels = stability_panels([run for run, _ in placed], keys)
    where = {id(run): p for run, p in placed}
    plt = _pyplot()
    fig, axes = plt.subplots(1, len(panels), figsize=(6.5 * len(panels), 5), squeeze=False, sharey=True)
    for ax, (title, members) in zip(axes[0], panels.items()):
        for outcome, color in OUTCOME_COLORS.items():
            pts = [where[id(run)] for run in members if outcome_of(run) == outcome]
            if pts:
                ax.scatter([p[0] for p in pts], [p[1] for p in pts], s=160, marker="s", color=color,
                           label=OUTCOME_LEGEND.get(outcome, outcome), edgecolors="k", zorder=3)
        _draw_cfl(ax, members, root, y_axis, E_range)
        ax.set_xscale("log")
        if y_axis == "dt":
            ax.set_yscale("log")
        ax.set_xlabel("Young's modulus E [Pa]")
        ax.set_title(title or "Stability: outcome per configuration")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    axes[0][0].set_ylabel("substep size dt = frame_time / substeps [s]" if y_axis == "dt" else "Poisson's ratio nu")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def ablation_values(runs: Sequence[RunRecord], key: str, metric: str) -> list[tuple[str, float | None, int]]:
    """Per value of ``key``: (value, mean ``metric`` over its successful runs or None, number of failures).

    Values sort numerically when they all are numbers, else as text; runs without the key count as ``-``.
    """
    groups: dict[str, list[RunRecord]] = {}
    for run in runs:
        groups.setdefault(sweep_overrides(run.overrides).get(key, "-"), []).append(run)
    numeric = all(as_float(v) is not None for v in groups)
    out = []
    for value in sorted(groups, key=lambda v: (as_float(v), v) if numeric else (0.0, v)):
        metrics = [m for r in groups[value] if r.status == "ok" and (m := as_float(r.metrics.get(metric))) is not None]
        failures = sum(r.status != "ok" for r in groups[value])
        out.append((value, sum(metrics) / len(metrics) if metrics else None, failures))
    return out


def plot_ablation(runs: Sequence[RunRecord], key: str, metric: str, path: Path) -> None:
    """Bars of the mean ``metric`` per value of ``key``; values whose runs all failed are marked."""
    values = ablation_values(runs, key, metric)
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(max(4.0, 0.9 * len(values) + 2), 4))
    heights = [v if v is not None else 0.0 for _, v, _ in values]
    bars = ax.bar(range(len(values)), heights, color="#1f77b4")
    for bar, (_, mean, failures) in zip(bars, values):
        text = "all failed" if mean is None else f"{mean:.3g}" + (f" ({failures} failed)" if failures else "")
        ax.annotate(text, (bar.get_x() + bar.get_width() / 2, bar.get_height()), ha="center", va="bottom", fontsize=8)
    ax.set_xticks(range(len(values)), [v for v, _, _ in values], rotation=30 if len(values) > 5 else 0)
    ax.set_xlabel(key)
    ax.set_ylabel(f"{metric} [% bbox diagonal]")
    ax.set_title(f"Ablation: {key}")
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def safe_name(key: str) -> str:
    """A file-name-safe version of an override key (``sim.E`` -> ``sim_E``)."""
    return "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in key)


# ---------------------------------------------------------------------------------------------- main
def make_report(root: Path, out: Path | None = None) -> dict[str, Any]:
    """Collect the runs under ``root`` and write report.md, report.csv and the charts into ``out``.

    Returns:
        ``{"rows": [...], "metric": str, "charts": [file names], "front": [labels]}``.

    Raises:
        FileNotFoundError: no run folder under ``root``.
    """
    root = Path(root)
    out = Path(out) if out is not None else root
    runs = load_runs(root)
    if not runs:
        raise FileNotFoundError(f"{root}: no run folders (metrics.json or .hydra/overrides.yaml) found")
    out.mkdir(parents=True, exist_ok=True)
    rows = table_rows(runs)
    metric = main_metric(runs)
    keys = swept_keys(runs)
    charts: list[str] = []
    front = plot_speed_accuracy(runs, metric, keys, out / "speed_accuracy.png")
    if front:
        charts.append("speed_accuracy.png")
    axes = stability_axes(keys)
    if axes is not None and plot_stability_map(runs, root, axes[1], keys, out / "stability_map.png"):
        charts.append("stability_map.png")
    for key in keys:
        name = f"ablation_{safe_name(key)}.png"
        plot_ablation(runs, key, metric, out / name)
        charts.append(name)
    write_csv(rows, out / "report.csv")
    (out / "report.md").write_text(markdown_report(root, rows, metric, front, charts))
    return {"rows": rows, "metric": metric, "charts": charts, "front": front}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sync4d_tools.report", description=__doc__.split("\n")[0])
    parser.add_argument("folder", type=Path, help="a multirun folder (hydra.sweep.dir)")
    parser.add_argument("--out", type=Path, default=None, help="where to write the report (default: the folder)")
    args = parser.parse_args(argv)
    try:
        result = make_report(args.folder, args.out)
    except FileNotFoundError as err:
        print(f"sync4d_tools.report: {err}", file=sys.stderr)
        return 2
    out = args.out or args.folder
    print(f"{len(result['rows'])} runs -> {out / 'report.md'}, {out / 'report.csv'}, charts: {', '.join(result['charts']) or 'none'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
