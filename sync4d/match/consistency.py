"""How well a part map of the target agrees with the reference it came from, measured on the map alone.

Two label-free agreements, each in [0, 1], of the parts given to the target's Gaussians with the
reference's parts:

* ``connected``: the share of points lying in the largest connected piece of their part (over a
  k-nearest-neighbour graph; pieces of fewer than k points, stray points below the graph's resolution,
  are left out of both agreements): a reference part is one piece, so should its image be;
* ``contacts``: the share of the target's part-to-part contacts (neighbour pairs of different parts)
  between parts that touch in the reference too: the map keeps the reference's structure.

``auto`` (:mod:`sync4d.match.auto`) keeps the map that keeps more of the reference's structure.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class Consistency:
    """The agreements of one part map with its reference (each in [0, 1]); ``kept`` is their product."""

    connected: float
    contacts: float

    @property
    def kept(self) -> float:
        """connected x contacts: the share of the reference's structure the map keeps."""
        return self.connected * self.contacts


def neighbour_edges(points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(E,) and (E,) endpoints of the k-nearest-neighbour edges of ``points`` (each point to its k nearest)."""
    k = int(min(k, len(points) - 1))
    _, idx = cKDTree(points).query(points, k + 1)
    return np.repeat(np.arange(len(points)), k), idx[:, 1:].reshape(-1)


def part_pieces(points: np.ndarray, parts: np.ndarray, k: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Connected pieces of each part over the k-nearest-neighbour graph: (M,) piece id per point and (M,)
    bool, the point lies in a piece of at least ``k`` points (smaller pieces are below the graph's
    resolution: a stray point or two, not a region)."""
    a, b = neighbour_edges(points, k)
    same = parts[a] == parts[b]
    graph = coo_matrix((np.ones(int(same.sum())), (a[same], b[same])), shape=(len(points), len(points)))
    _, piece = connected_components(graph, directed=False)
    return piece, np.bincount(piece)[piece] >= k


def connected_share(points: np.ndarray, parts: np.ndarray, k: int = 8) -> float:
    """Share of the points (in pieces of at least k points) lying in the largest piece of their part."""
    piece, resolved = part_pieces(points, parts, k)
    kept = 0
    for p in np.unique(parts[resolved]):
        kept += int(np.bincount(piece[resolved & (parts == p)]).max())
    return kept / max(int(resolved.sum()), 1)


def contact_pairs(points: np.ndarray, parts: np.ndarray, num_parts: int, k: int = 8) -> np.ndarray:
    """(B, B) number of neighbour edges between each pair of parts (symmetric, zero diagonal)."""
    a, b = neighbour_edges(points, k)
    counts = np.zeros((num_parts, num_parts))
    np.add.at(counts, (parts[a], parts[b]), 1.0)
    counts = counts + counts.T
    np.fill_diagonal(counts, 0.0)
    return counts


def consistency(
    points: np.ndarray, parts: np.ndarray, ref_points: np.ndarray, ref_labels: np.ndarray, num_parts: int, *, k: int = 8
) -> Consistency:
    """The agreements of a target part map with the reference (see the module docstring).

    Args:
        points: (M, 3) target points; parts: (M,) their reference parts (>= 0).
        ref_points: (V, 3) reference points (any frame); ref_labels: (V,) their parts.
        num_parts: B; k: neighbours of the graphs.
    """
    parts = np.asarray(parts, dtype=np.int64)
    resolved = part_pieces(points, parts, k)[1]
    target_contacts = contact_pairs(points[resolved], parts[resolved], num_parts, k)
    touching = contact_pairs(ref_points, np.asarray(ref_labels, dtype=np.int64), num_parts, k) > 0
    total = target_contacts.sum()
    contacts = float(target_contacts[touching].sum() / total) if total > 0 else 1.0
    return Consistency(connected_share(points[resolved], parts[resolved], k), contacts)
