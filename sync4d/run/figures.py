"""Pictures a run writes beside its outputs: the reference's parts, and the part matching.

Drawing is :mod:`sync4d.match.pictures`'s; this module only picks what a run shows and writes it (atomically,
and to TensorBoard).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from sync4d.io.atomic import atomic_write_bytes
from sync4d.match.pictures import draw_points, figure_to_array, label_colors, match_figure
from sync4d.types import PartMap, Reference, TargetGaussians


def _write_png(path: Path, image: np.ndarray, logger: Any, tag: str) -> Path:
    from io import BytesIO

    from PIL import Image

    buffer = BytesIO()
    Image.fromarray(image).save(buffer, format="png")
    atomic_write_bytes(path, buffer.getvalue())
    if logger is not None:
        logger.image(tag, image)
    return path


def save_reference_parts(reference: Reference, path: Path, *, logger: Any = None) -> Path:
    """PNG of the reference's rest shape coloured by part (argmax skinning, paper Sec. 3.3)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4, 4))
    draw_points(ax, reference.rest_vertices, label_colors(reference.part_labels(), reference.num_bones),
                view=(30.0, 15.0), size=2.0)
    ax.set_title(f"{reference.name}: {reference.num_bones} parts")
    image = figure_to_array(fig)
    plt.close(fig)
    return _write_png(path, image, logger, "parts/reference")


def save_match_figure(reference: Reference, target: TargetGaussians, part_map: PartMap, path: Path, *,
                      logger: Any = None) -> Path:
    """PNG of the reference and the target's Gaussians coloured by part, side by side."""
    import matplotlib.pyplot as plt

    fig = match_figure(reference.rest_vertices, part_map.ref_part, target.means.astype(np.float64), part_map.tgt_part,
                       part_map.num_parts, titles=(f"reference ({reference.name})", f"target ({target.name})"))
    image = figure_to_array(fig)
    plt.close(fig)
    return _write_png(path, image, logger, "parts/match")
