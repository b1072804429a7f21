"""The simulated particle set of a transfer: control points (or the Gaussians themselves) with their parts."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sync4d.sim.control import make_control_points
from sync4d.types import PartMap, TargetGaussians


@dataclass
class Particles:
    """The simulated set: control points (or the Gaussians themselves) and their parts.

    Attributes:
        points: (P, 3) rest positions [m].
        part: (P,) part of each particle (majority of its Gaussians).
        gaussian_to_point: (N,) particle of each Gaussian.
        counts: (P,) Gaussians per particle.
        volume: (P,) rest volume of each particle [m^3], from geometry: every occupied control cell holds
            one cell volume (side^3), shared among the cell's per-part particles by their Gaussians; so
            neighbouring particles weigh the same however unevenly the Gaussians are spread. None when
            every Gaussian is simulated (the simulator then estimates the volume from occupancy).
    """

    points: np.ndarray
    part: np.ndarray
    gaussian_to_point: np.ndarray
    counts: np.ndarray
    volume: np.ndarray | None = None


def make_particles(target: TargetGaussians, part_map: PartMap, control_grid: int | None) -> Particles:
    """Downsample to control points when ``control_grid`` is set; each point takes its Gaussians' majority part.

    Control cells straddling two parts are split per part so that a particle never mixes parts.
    """
    means = target.means.astype(np.float64)
    if control_grid is None:
        n = len(means)
        return Particles(means, part_map.tgt_part.copy(), np.arange(n), np.ones(n, dtype=np.int64))
    points, g2p, _ = make_control_points(means, control_grid)
    key = g2p * part_map.num_parts + part_map.tgt_part  # split cells by part: key = (cell, part)
    _, g2p_split, counts_split = np.unique(key, return_inverse=True, return_counts=True)
    g2p_split = g2p_split.reshape(-1)
    sums = np.zeros((len(counts_split), 3))
    np.add.at(sums, g2p_split, means)
    part = np.zeros(len(counts_split), dtype=np.int64)
    part[g2p_split] = part_map.tgt_part
    cell_of = np.zeros(len(counts_split), dtype=np.int64)
    cell_of[g2p_split] = g2p
    side = float(np.ptp(means, axis=0).max()) / int(control_grid)
    share = counts_split / np.bincount(cell_of, weights=counts_split)[cell_of]
    return Particles(sums / counts_split[:, None], part, g2p_split.astype(np.int64), counts_split.astype(np.int64),
                     volume=share * side**3)
