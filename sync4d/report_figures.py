"""Pictures a run writes beside its outputs: the reference's parts, and the part matching."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from sync4d.types import PartMap, Reference, TargetGaussians

PART_COLORS = np.array([
    [0.90, 0.10, 0.11], [0.22, 0.49, 0.72], [0.30, 0.69, 0.29], [0.60, 0.31, 0.64], [1.00, 0.50, 0.00],
    [0.65, 0.34, 0.16], [0.97, 0.51, 0.75], [0.40, 0.76, 0.65], [0.99, 0.75, 0.00], [0.55, 0.63, 0.80],
    [0.65, 0.85, 0.33], [0.90, 0.77, 0.58], [0.70, 0.70, 0.70], [0.10, 0.60, 0.60], [0.50, 0.00, 0.20],
])  # fmt: skip


def part_colors(labels: np.ndarray) -> np.ndarray:
    """(N, 3) RGB per part label (cycling a 15-colour palette); label -1 (outlier) is black."""
    labels = np.asarray(labels)
    colors = PART_COLORS[np.maximum(labels, 0) % len(PART_COLORS)]
    colors[labels < 0] = 0.0
    return colors


def _scatter(ax: Any, points: np.ndarray, labels: np.ndarray, title: str) -> None:
    ax.scatter(points[:, 0], points[:, 2], points[:, 1], c=part_colors(labels), s=2, depthshade=False)
    ax.set_title(title)
    span = np.ptp(points, axis=0).max() / 2
    mid = (points.max(axis=0) + points.min(axis=0)) / 2
    ax.set_xlim(mid[0] - span, mid[0] + span)
    ax.set_ylim(mid[2] - span, mid[2] + span)
    ax.set_zlim(mid[1] - span, mid[1] + span)
    ax.set_axis_off()
    ax.view_init(elev=20, azim=-60)


def _save(fig: Any, path: Path, logger: Any, tag: str) -> None:
    from io import BytesIO

    import matplotlib.pyplot as plt
    from PIL import Image

    from sync4d.io.atomic import atomic_write_bytes

    buffer = BytesIO()
    fig.savefig(buffer, format="png", dpi=100)
    plt.close(fig)
    atomic_write_bytes(path, buffer.getvalue())
    if logger is not None:
        logger.image(tag, np.asarray(Image.open(BytesIO(buffer.getvalue())).convert("RGB")))


def save_reference_parts(reference: Reference, path: Path, *, logger: Any = None) -> Path:
    """PNG of the reference's rest shape coloured by part (argmax skinning)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(5, 5))
    _scatter(fig.add_subplot(111, projection="3d"), reference.rest_vertices, reference.part_labels(),
             f"{reference.name}: {reference.num_bones} parts")
    _save(fig, path, logger, "parts/reference")
    return path


def save_match_figure(reference: Reference, target: TargetGaussians, part_map: PartMap, path: Path, *,
                      logger: Any = None) -> Path:
    """PNG of the reference and the target coloured by part, side by side (the paper's matching figure)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(10, 5))
    _scatter(fig.add_subplot(121, projection="3d"), reference.rest_vertices, part_map.ref_part, "reference parts")
    _scatter(fig.add_subplot(122, projection="3d"), target.means.astype(np.float64), part_map.tgt_part,
             f"{target.name}: matched parts")
    _save(fig, path, logger, "parts/match")
    return path
