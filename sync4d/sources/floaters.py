"""Floater removal for splat targets: statistical outliers by distance, density and connectivity.

Generated and trained splats carry floaters: stray Gaussians far from the object, alone or in small
clouds. Left in, one of them sets the simulation domain (a Gaussian 10 km from a 20 cm object made the
grid cell 1.9 km) and the coverage ratio. Three tests, all O(N log N) on a sparse voxel hash so that
millions of Gaussians take seconds:

1. **distance**: the robust box is the per-axis ``quantile`` .. 1 - ``quantile`` range of the centres;
   a Gaussian farther than ``far_factor`` times the box's longest side outside it is removed;
2. **density**: the remaining centres are hashed into cubic voxels; a Gaussian whose voxel and its 26 neighbours hold fewer than ``min_neighbours`` centres is
   isolated and removed (radius-outlier removal);
3. **connectivity**: occupied voxels are joined to their 26 neighbours; connected pieces holding less
   than ``min_cluster_fraction`` of the Gaussians are floating clouds and removed.

The voxel side is chosen per splat, coarse to fine (the robust box's longest side over 8, 16, ..., 512):
the finest at which tests 2 and 3 remove at most ``max_noise_fraction`` of the Gaussians near the
object. A splat's spacing is unknown beforehand (a sparse LGM splat, a dense LucidDreamer one); voxels
finer than its spacing would cut the object itself apart, coarser ones let near floaters touch it.

What is left sets the simulation domain (its bounding box is the robust extent). A target of which
less than ``min_kept_fraction`` survives is refused: it is mostly noise, or the thresholds do not fit it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix

from sync4d.types import FloaterReport
from scipy.sparse.csgraph import connected_components

from sync4d.errors import ConfigError, InputError

log = logging.getLogger(__name__)

#: The 13 "forward" neighbour offsets of a voxel (the other 13 are their negatives); with the voxel
#: itself they make the 27-cell neighbourhood.
#: Voxels across the robust box tried, coarse to fine.
CELLS_ACROSS = (8, 16, 32, 64, 128, 256, 512)
_HALF = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) > (0, 0, 0)])


@dataclass
class FloaterConfig:
    """Floater removal settings (``target.floaters.*``).

    Attributes:
        enabled: run the removal (off keeps every Gaussian).
        quantile: per-axis quantile defining the robust box (0.01: the 1st to 99th percentile).
        far_factor: Gaussians farther than this many robust-box sizes outside the box are removed.
        min_neighbours: fewest centres in a Gaussian's 27-voxel neighbourhood (itself included) to keep it.
        min_cluster_fraction: smallest connected piece kept, as a fraction of all Gaussians.
        max_noise_fraction: the voxel size is the finest at which at most this fraction of the Gaussians
            near the object is isolated or in small pieces.
        min_kept_fraction: refuse the target when fewer than this fraction of its Gaussians are kept.
    """

    enabled: bool = True
    quantile: float = 0.01
    far_factor: float = 1.0
    min_neighbours: int = 4
    min_cluster_fraction: float = 0.01
    max_noise_fraction: float = 0.05
    min_kept_fraction: float = 0.5

    def validate(self) -> None:
        """Raise :class:`ConfigError` naming the offending ``target.floaters.*`` key."""
        checks = (
            ("quantile", 0.0 <= self.quantile < 0.5, "in [0, 0.5)"),
            ("far_factor", self.far_factor > 0, "> 0"),
            ("min_neighbours", self.min_neighbours >= 1, ">= 1"),
            ("min_cluster_fraction", 0.0 <= self.min_cluster_fraction < 1.0, "in [0, 1)"),
            ("max_noise_fraction", 0.0 < self.max_noise_fraction < 1.0, "in (0, 1)"),
            ("min_kept_fraction", 0.0 <= self.min_kept_fraction <= 1.0, "in [0, 1]"),
        )
        for key, ok, rule in checks:
            if not ok:
                raise ConfigError(f"target.floaters.{key}={getattr(self, key)}: must be {rule}")


def voxel_keys(cells: np.ndarray) -> np.ndarray:
    """(M,) int64 keys of non-negative (M, 3) integer voxel coordinates below 2^20 per axis."""
    c = cells.astype(np.int64)
    return (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]


def neighbour_pairs(unique_cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (a, b) of occupied voxels that touch (26-neighbourhood), each pair once.

    Args:
        unique_cells: (M, 3) distinct integer voxel coordinates >= 1 (so that -1 offsets stay >= 0),
            sorted by :func:`voxel_keys`.
    """
    keys = voxel_keys(unique_cells)
    rows, cols = [], []
    for offset in _HALF:
        probe = voxel_keys(unique_cells + offset)
        where = np.clip(np.searchsorted(keys, probe), 0, len(keys) - 1)
        hit = keys[where] == probe
        rows.append(np.flatnonzero(hit))
        cols.append(where[hit])
    return np.concatenate(rows), np.concatenate(cols)


def robust_box(points: np.ndarray, quantile: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis ``quantile`` and 1 - ``quantile`` of (N, 3) points [m]."""
    lo, hi = np.quantile(points, [quantile, 1.0 - quantile], axis=0)
    return lo, hi


def voxel_status(pts: np.ndarray, origin: np.ndarray, cell: float, config: FloaterConfig) -> tuple[np.ndarray, np.ndarray]:
    """Density and connectivity tests of (M, 3) centres on voxels of side ``cell`` [m] from ``origin``.

    Returns:
        keep: (M,) bool, in a dense voxel of a piece holding >= ``min_cluster_fraction`` of the centres.
        sparse: (M,) bool, in a voxel whose 27-neighbourhood holds < ``min_neighbours`` centres.
    """
    coords = np.floor((pts - origin) / cell).astype(np.int64) + 1  # +1: every neighbour offset stays >= 0
    keys = voxel_keys(coords)
    unique_keys, first, inverse, counts = np.unique(keys, return_index=True, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    a, b = neighbour_pairs(coords[first])
    neighbourhood = counts.copy()
    np.add.at(neighbourhood, a, counts[b])
    np.add.at(neighbourhood, b, counts[a])
    dense = neighbourhood >= config.min_neighbours
    # connectivity among the dense voxels only: a chain of isolated voxels must not bridge two pieces
    both = dense[a] & dense[b]
    m = len(unique_keys)
    graph = coo_matrix((np.ones(int(both.sum())), (a[both], b[both])), shape=(m, m))
    _, label = connected_components(graph, directed=False)
    piece = np.bincount(label, weights=counts * dense, minlength=label.max() + 1)
    big = piece[label] >= config.min_cluster_fraction * len(pts)
    return (dense & big)[inverse], ~dense[inverse]


def find_floaters(means: np.ndarray, config: FloaterConfig) -> tuple[np.ndarray, FloaterReport]:
    """Which Gaussians are floaters (see the module docstring).

    Args:
        means: (N, 3) finite Gaussian centres [m].
        config: the thresholds.

    Returns:
        keep: (N,) bool, True for Gaussians of the object.
        report: the counts per test, the voxel size chosen and the kept / removed bounding boxes.
    """
    config.validate()
    pts = np.asarray(means, dtype=np.float64)
    n = len(pts)
    lo, hi = robust_box(pts, config.quantile)
    size = max(float((hi - lo).max()), 1e-12)
    margin = config.far_factor * size
    near = np.all((pts >= lo - margin) & (pts <= hi + margin), axis=1)
    idx = np.flatnonzero(near)
    # coarse to fine: the finest voxel at which the object still holds (1 - max_noise_fraction) of the
    # near Gaussians; finer voxels would start cutting the object itself into pieces
    chosen = None
    for cells_across in CELLS_ACROSS:
        cell = size / cells_across
        keep_near, sparse_near = voxel_status(pts[idx], lo - margin, cell, config)
        if chosen is not None and keep_near.mean() < 1.0 - config.max_noise_fraction:
            break
        chosen = (cell, keep_near, sparse_near)
    assert chosen is not None
    cell, keep_near, sparse_near = chosen
    keep = np.zeros(n, dtype=bool)
    keep[idx] = keep_near
    removed = ~keep
    removed_sparse = int(sparse_near.sum())
    report = FloaterReport(
        total=n, removed_far=n - len(idx), removed_sparse=removed_sparse,
        removed_clusters=int(removed.sum()) - (n - len(idx)) - removed_sparse, cell=float(cell),
        kept_box=np.stack([pts[keep].min(0), pts[keep].max(0)]) if keep.any() else np.zeros((2, 3)),
        removed_box=np.stack([pts[removed].min(0), pts[removed].max(0)]) if removed.any() else None,
    )  # fmt: skip
    return keep, report


def remove_floaters(means: np.ndarray, config: FloaterConfig, *, source: str) -> tuple[np.ndarray, FloaterReport]:
    """:func:`find_floaters`, logged, refusing a target of which too little is left.

    Args:
        means: (N, 3) Gaussian centres [m].
        config: the thresholds; ``config.enabled`` False keeps everything.
        source: names the input in the log and the error (e.g. the file).

    Returns:
        keep: (N,) bool mask; report: as :func:`find_floaters` (None when disabled).

    Raises:
        InputError: fewer than ``min_kept_fraction`` of the Gaussians are kept.
    """
    if not config.enabled:
        return np.ones(len(means), dtype=bool), None  # type: ignore[return-value]
    keep, report = find_floaters(means, config)
    kept = int(keep.sum())
    if kept < config.min_kept_fraction * report.total or kept == 0:
        raise InputError(
            f"{source}: floater removal kept only {kept} of {report.total} Gaussians "
            f"({report.removed_far} far, {report.removed_sparse} isolated, {report.removed_clusters} in small pieces; "
            f"target.floaters.min_kept_fraction={config.min_kept_fraction}); the splat is mostly scattered noise: "
            "check the file, or loosen target.floaters (min_neighbours, min_cluster_fraction) or set "
            "target.floaters.enabled=false"
        )
    if report.removed and report.removed_box is not None:
        box = np.round(report.removed_box, 4).tolist()
        log.info("floaters: removed %d of %d Gaussians from %s (%d far, %d isolated, %d in small pieces; "
                 "removed box %s m); simulation domain: %s m", report.removed, report.total, source,
                 report.removed_far, report.removed_sparse, report.removed_clusters, box,
                 np.round(report.kept_box, 4).tolist())
    else:
        log.info("floaters: none found among %d Gaussians of %s", report.total, source)
    return keep, report
