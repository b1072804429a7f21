"""Pictures of a part map: reference and target coloured by part, side by side (the paper's Fig. matching).

Removed outliers are drawn black, as in the paper. Drawing uses matplotlib's Agg backend (no display)
with an orthographic projection from a chosen view direction; points are depth-sorted so nearer points
cover farther ones.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # annotations only: matplotlib is imported when drawing
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from sync4d.match.result import MatchDiagnostics

OUTLIER_COLOR = np.array([0.0, 0.0, 0.0])


def part_colors(num_parts: int) -> np.ndarray:
    """(B, 3) distinct RGB colours in [0, 1] (tab20, then evenly spaced hues beyond 20 parts)."""
    import matplotlib

    if num_parts <= 20:
        cmap = matplotlib.colormaps["tab20"]
        # Interleave the light/dark pairs of tab20 so neighbouring indices differ strongly.
        order = list(range(0, 20, 2)) + list(range(1, 20, 2))
        return np.array([cmap(order[i])[:3] for i in range(num_parts)])
    cmap = matplotlib.colormaps["hsv"]
    return np.array([cmap(i / num_parts)[:3] for i in range(num_parts)])


def label_colors(labels: np.ndarray, num_parts: int) -> np.ndarray:
    """(N, 3) colour per point; labels < 0 (outliers) are black."""
    palette = part_colors(num_parts)
    labels = np.asarray(labels)
    out = np.tile(OUTLIER_COLOR, (len(labels), 1))
    valid = labels >= 0
    out[valid] = palette[labels[valid]]
    return out


def _view_basis(view: tuple[float, float]) -> np.ndarray:
    """(3, 3) rows right, up, towards-viewer for azimuth/elevation [deg] around world +y."""
    az, el = np.deg2rad(view[0]), np.deg2rad(view[1])
    toward = np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
    up_hint = np.array([0.0, 1.0, 0.0]) if abs(toward[1]) < 0.99 else np.array([0.0, 0.0, -1.0])
    right = np.cross(up_hint, toward)
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(toward, right), toward])


def draw_points(ax: Axes, points: np.ndarray, colors: np.ndarray, *, view: tuple[float, float], size: float) -> None:
    """Orthographic scatter of ``points`` (N, 3) with ``colors`` (N, 3) on a matplotlib axis."""
    basis = _view_basis(view)
    proj = points @ basis.T
    order = np.argsort(proj[:, 2])  # far first, near last
    shade = 0.75 + 0.25 * (proj[order, 2] - proj[:, 2].min()) / max(np.ptp(proj[:, 2]), 1e-12)
    ax.scatter(proj[order, 0], proj[order, 1], c=np.clip(colors[order] * shade[:, None], 0, 1), s=size, linewidths=0)
    ax.set_aspect("equal")
    ax.axis("off")


def match_figure(
    reference_points: np.ndarray,
    reference_labels: np.ndarray,
    target_points: np.ndarray,
    target_labels: np.ndarray,
    num_parts: int,
    *,
    views: tuple[tuple[float, float], ...] = ((30.0, 15.0),),
    titles: tuple[str, str] = ("reference", "target"),
    point_size: float = 2.0,
    suptitle: str = "",
) -> Figure:
    """A matplotlib figure: one row per view, reference left, target right, coloured by part.

    Args:
        reference_points: (V, 3) reference vertices (any frame; a common aligned frame reads best).
        reference_labels: (V,) part per reference vertex.
        target_points: (M, 3) target points in the same frame.
        target_labels: (M,) part per target point, -1 for removed outliers (drawn black).
        num_parts: B (fixes the colours so both sides agree).
        views: (azimuth, elevation) pairs [deg] around world +y.
        titles: column titles.
        point_size: marker area [pt^2].
        suptitle: figure title.

    Returns:
        matplotlib.figure.Figure (close it after saving).
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(views), 2, figsize=(8, 4 * len(views)), squeeze=False)
    for row, view in enumerate(views):
        draw_points(axes[row, 0], reference_points, label_colors(reference_labels, num_parts), view=view, size=point_size)
        draw_points(axes[row, 1], target_points, label_colors(target_labels, num_parts), view=view, size=point_size)
        if row == 0:
            axes[row, 0].set_title(titles[0])
            axes[row, 1].set_title(titles[1])
    if suptitle:
        fig.suptitle(suptitle, fontsize=9)
    fig.tight_layout()
    return fig


def figure_to_array(fig: Figure) -> np.ndarray:
    """(H, W, 3) uint8 RGB pixels of a matplotlib figure."""
    from PIL import Image

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    buf.seek(0)
    return np.asarray(Image.open(buf).convert("RGB"))


def save_match_figure(path: str | Path, diagnostics: MatchDiagnostics, num_parts: int, **kwargs: Any) -> np.ndarray:
    """Draw a :class:`sync4d.match.result.MatchDiagnostics` (common frame; outliers black) and write a PNG.

    Args:
        path: output .png.
        diagnostics: from :func:`sync4d.match.match_parts`.
        num_parts: B.
        **kwargs: forwarded to :func:`match_figure` (``views``, ``titles``, ``suptitle``, ...). The
            reference labels must be passed as ``reference_labels``.

    Returns:
        (H, W, 3) uint8 image that was written.
    """
    import matplotlib.pyplot as plt

    reference_labels = kwargs.pop("reference_labels", None)
    if reference_labels is None:
        reference_labels = diagnostics.reference_labels
    fig = match_figure(
        diagnostics.reference_points, reference_labels, diagnostics.target_points, diagnostics.vertex_part_final,
        num_parts, **kwargs,
    )
    image = figure_to_array(fig)
    plt.close(fig)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    from PIL import Image

    Image.fromarray(image).save(path)
    return image
