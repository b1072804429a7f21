"""Plot a run's per-frame drift and displacement error: python docs/make_drift_figure.py <run> <out.png>."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def main(run: Path, out: Path) -> None:
    metrics = json.loads((run / "metrics.json").read_text())
    rows = metrics["per_frame"]
    frames = range(len(rows))
    fig, ax = plt.subplots(figsize=(6, 3))
    ax.plot(frames, [r["drift_pct"] for r in rows], label="drift (part centroids vs accumulated reference)")
    ax.plot(frames, [r["displacement_error_pct"] or 0.0 for r in rows], label="displacement error per frame pair")
    ax.set_xlabel("frame")
    ax.set_ylabel("% of bounding-box diagonal")
    ax.set_title(f"{metrics['frames']} frames, laptop -> shell")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=100)


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
