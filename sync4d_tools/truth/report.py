"""Tables and charts of ``transfer_gt`` and ``transfer_paper`` results (Markdown, PNG)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

CURVE = ("5", "10", "20", "30")
COLUMNS = (
    ("pose %", "pose_error_pct"), ("pose max %", "pose_error_max_pct"), ("follow deg", "follow_rotation_deg"),
    ("follow %", "follow_translation_pct"), ("torn % at 5/10/20/30", None), ("seam torn % (10)", "torn_seam_pairs_pct"),
    ("p99 %", "strain_p99_pct"), ("p99 max %", "strain_p99_max_pct"), ("frag (10/20)", None),
    ("vol %", "volume_change_pct"), ("CPU s/frame", "seconds_per_frame"),
)


def cell(value: Any) -> str:
    """A number in 3 significant digits (None as '-')."""
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.3g}"
    return str(value)


def row_cells(row: dict[str, Any]) -> list[str]:
    """The table cells of one result row, in :data:`COLUMNS` order."""
    curve = row.get("tear_curve", {})
    out = []
    for title, key in COLUMNS:
        if title.startswith("torn % at"):
            out.append(" / ".join(cell(curve.get("torn_pairs_pct", {}).get(k)) for k in CURVE))
        elif title.startswith("frag"):
            out.append(" / ".join(cell(int(curve.get("fragments", {}).get(k, 0))) for k in ("10", "20")))
        else:
            assert key is not None  # only the two curve columns have no key
            out.append(cell(row.get(key)))
    if row.get("same_as"):
        out[-1] = f"= {row['same_as']}"
    return out


def results_table(results: dict[str, dict[str, dict[str, Any]]], label: str = "pair") -> str:
    """``results[pair][method] -> row`` as one Markdown table."""
    lines = [f"| {label} | method | " + " | ".join(t for t, _ in COLUMNS) + " |",
             "|---|---|" + "---|" * len(COLUMNS)]
    for pair, rows in results.items():
        for method, row in rows.items():
            lines.append(f"| {pair} | {method} | " + " | ".join(row_cells(row)) + " |")
    return "\n".join(lines) + "\n"


def criteria_table(criteria: dict[str, dict[str, dict[str, Any]]]) -> str:
    """``criteria[pair][truth] -> checks`` as a Markdown table of yes / **no**."""
    keys: list[str] = []
    for per_truth in criteria.values():
        for checks in per_truth.values():
            keys += [k for k, v in checks.items() if isinstance(v, bool) and k not in keys and k != "passed"]
    lines = ["| pair | truth | " + " | ".join(k.replace("_", " ") for k in keys) + " | passed |",
             "|---|---|" + "---|" * (len(keys) + 1)]
    for pair, per_truth in criteria.items():
        for truth, checks in per_truth.items():
            cells = ["n/a" if k not in checks else ("yes" if checks[k] else "**no**") for k in [*keys, "passed"]]
            lines.append(f"| {pair} | {truth} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def markdown_tables(out: dict[str, Any]) -> str:
    """Every table of a ``transfer_gt`` result: one per truth, then the criteria."""
    parts = []
    truths = sorted({t for per_pair in out["pairs"].values() for t in per_pair}, key=lambda t: t != "skinning")
    for truth in truths:
        per_truth = {p: r[truth] for p, r in out["pairs"].items() if truth in r}
        parts.append(f"### Truth: {truth}\n\n" + results_table(per_truth))
    if out.get("criteria"):
        parts.append(f"### Criteria for `{out['candidate']}`\n\n" + criteria_table(out["criteria"]))
    return "\n".join(parts)


def pair_axes(count: int, title: str) -> tuple[Any, list[Any]]:
    """A figure with one small panel per pair, four to a row."""
    import matplotlib.pyplot as plt

    cols = min(4, count)
    rows = (count + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 3.0 * rows), squeeze=False)
    for ax in axes.ravel()[count:]:
        ax.axis("off")
    fig.suptitle(title, fontsize=10)
    return fig, list(axes.ravel()[:count])


def write_charts(results: dict[str, dict[str, dict[str, dict[str, Any]]]], folder: Path, prefix: str = "") -> list[str]:
    """Per truth, pose error against worst-frame p99 strain for every pair; the tear curves (skinning truth)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    pairs = list(results)
    written = []
    for truth in sorted({t for r in results.values() for t in r}, key=lambda t: t != "skinning"):
        fig, axes = pair_axes(len(pairs), f"pose error against the {truth} truth vs worst-frame p99 strain")
        for ax, pair in zip(axes, pairs):
            for j, (method, r) in enumerate(results[pair].get(truth, {}).items()):
                if r.get("same_as"):
                    continue  # drawn as the row it equals
                ax.scatter(r["pose_error_pct"], r["strain_p99_max_pct"], s=36, color=f"C{j % 10}", alpha=0.8,
                           edgecolors="k", label=method, marker="os^Dv<>ph*"[j % 10])
            ax.set_title(pair, fontsize=9)
            ax.set_xlabel("pose error [% diag]", fontsize=8)
            ax.set_ylabel("p99 strain, worst frame [%]", fontsize=8)
            ax.set_yscale("symlog", linthresh=10)
            ax.grid(alpha=0.3)
        axes[0].legend(fontsize=6, loc="best")
        fig.tight_layout()
        written.append(str(folder / f"{prefix}fidelity_integrity_{truth}.png"))
        fig.savefig(written[-1], dpi=80)
        plt.close(fig)
    fig, axes = pair_axes(len(pairs), "torn pairs [%] over the tear threshold (skinning truth)")
    for ax, pair in zip(axes, pairs):
        for j, (method, r) in enumerate(results[pair].get("skinning", {}).items()):
            if r.get("same_as"):
                continue
            curve = r["tear_curve"]["torn_pairs_pct"]
            ax.plot([int(k) for k in CURVE], [curve[k] for k in CURVE], "os^Dv<>ph*"[j % 10] + "-",
                    color=f"C{j % 10}", label=method, alpha=0.8)
        ax.set_title(pair, fontsize=9)
        ax.set_xlabel("tear threshold [%]", fontsize=8)
        ax.set_ylabel("torn pairs [%]", fontsize=8)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=6)
    fig.tight_layout()
    written.append(str(folder / f"{prefix}tear_curves.png"))
    fig.savefig(written[-1], dpi=80)
    plt.close(fig)
    return written


def follow_strain_chart(rows: dict[str, dict[str, dict[str, Any]]], path: Path, what: str) -> str:
    """One panel per scene: follow error (mean, deg) against worst-frame p99 strain (%), a point per method.

    ``rows``: scene -> method -> row (``follow_rotation_deg``, ``strain_p99_max_pct``). The lower left corner is
    where a method both moves as driven and keeps the shape; the bars of issue 39 are drawn as dashed lines.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(rows)
    methods = list(dict.fromkeys(m for r in rows.values() for m in r))
    fig, axes = pair_axes(len(scenes), f"follow error against worst-frame strain: {what}")
    for ax, scene in zip(axes, scenes):
        for method, r in rows[scene].items():
            if r.get("same_as") or r.get("follow_rotation_deg") is None:
                continue
            j = methods.index(method)
            ax.scatter(r["follow_rotation_deg"], r["strain_p99_max_pct"], s=40, color=f"C{j % 10}", alpha=0.85,
                       edgecolors="k", label=method, marker="os^Dv<>ph*"[j % 10])
        ax.axvline(3.0, color="0.5", lw=0.8, ls="--")
        ax.set_title(scene, fontsize=9)
        ax.set_xlabel("follow error, mean [deg]", fontsize=8)
        ax.set_ylabel("p99 strain, worst frame [%]", fontsize=8)
        ax.set_xscale("symlog", linthresh=1)
        ax.set_yscale("symlog", linthresh=10)
        ax.set_xlim(left=0.0)
        ax.set_ylim(bottom=0.0)
        ax.grid(alpha=0.3)
    handles = {h.get_label(): h for ax in axes for h in ax.collections}
    fig.legend(list(handles.values()), list(handles), fontsize=7, loc="lower right")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return str(path)
