"""The nearest of a frame's projected points to its fixed cover pixels, as a k-d tree built on all the points as
they are now answers it (``cKDTree(points, balanced_tree=False, compact_nodes=False).query(pixels)``), to the
index and ties included, with less of that tree built at every Adam step.

A static camera's still root projects every step to the same pixels (to rounding), so its points' tree is kept
per frame: each pixel keeps its ``CANDIDATES`` nearest still points and the distance to the farthest of them;
still points that moved at most ``delta`` since are no nearer than that distance less ``delta``, so a candidate
nearer than that bound is the nearest still point (a frame whose bound fails builds its tree again). Only the
moving points' tree is built each step, and each pixel takes the nearer of the two answers. A pixel whose two
nearest points are equally near (a still root's grid points about a pixel centre, a swept copy on its posed
point) is answered by the tree on all the points, as before: how such a tree breaks a tie is its own, and one
breaking ties another way changes the fit (docs/results/articulated.md, "What was tried and failed").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

CANDIDATES = 8  # nearest still points kept per pixel: more move the bound out, each costs a distance per step
TIE = 1e-9  # relative gap under which two points count as equally near (rounding could order them either way)


def tree(points: np.ndarray) -> cKDTree:
    """The k-d tree whose answers are the reference: built once per query, so its cheapest build (unbalanced,
    loose nodes: 1.6x faster than the default) won when every step built one."""
    return cKDTree(points, balanced_tree=False, compact_nodes=False)


@dataclass
class _Still:
    points: np.ndarray  # (S, 2) the still points the candidates were found among
    candidates: np.ndarray  # (M, k) their indices, nearest first
    bound: np.ndarray  # (M,) the distance to each pixel's farthest candidate, less a rounding margin


def _dist(points: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Euclidean distances of ``points`` (M, ..., 2) to ``pixels`` (M, 2), as (M, ...)."""
    return np.sqrt(((points - pixels.reshape(len(pixels), *([1] * (points.ndim - 2)), 2)) ** 2).sum(-1))


class NearestPoints:
    """Per frame and still-point count, the still points' candidates (see the module docstring)."""

    def __init__(self) -> None:
        self.frames: dict[tuple[int, int], _Still] = {}

    def nearest(self, key: int, points: np.ndarray, pixels: np.ndarray, still: np.ndarray | None = None
                ) -> np.ndarray:
        """(M,) index of the nearest of ``points`` (P, 2) to each of ``pixels`` (M, 2), as :func:`tree` on
        ``points`` answers it. ``still``: indices of points that stay put between calls (a hint: moved ones
        cost a rebuild, never a wrong answer); ``key`` names the frame (its pixels the same at every call)."""
        if still is None or len(still) <= CANDIDATES or len(points) - len(still) < 2:
            return tree(points).query(pixels)[1]
        moving = np.ones(len(points), bool)
        moving[still] = False
        moving_idx = np.flatnonzero(moving)
        s_near, s_dist, s_tied = self._still(key, points[still], pixels)
        m_dist, m_near = tree(points[moving_idx]).query(pixels, 2)
        m_dist = _dist(points[moving_idx][m_near], pixels)  # own arithmetic, as for the still candidates
        use_still = s_dist < m_dist[:, 0]
        found = np.where(use_still, still[s_near], moving_idx[m_near[:, 0]])
        best = np.minimum(s_dist, m_dist[:, 0])
        tied = (np.abs(s_dist - m_dist[:, 0]) <= TIE * best + 1e-12) | np.where(
            use_still, s_tied, m_dist[:, 1] - m_dist[:, 0] <= TIE * best + 1e-12)
        if tied.any():
            found[tied] = tree(points).query(pixels[tied])[1]
        return found

    def _still(self, key: int, points: np.ndarray, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each pixel's nearest still point (index into ``points``), its distance, and whether the next
        candidate is as near."""
        frame = self.frames.get((key, len(points)))
        if frame is not None:
            delta = float(np.sqrt(((points - frame.points) ** 2).sum(1).max()))
            out = self._from_candidates(frame, points, pixels)
            if (out[1] < frame.bound - delta).all():
                return out
        dist, cand = tree(points).query(pixels, CANDIDATES)
        frame = _Still(points.copy(), cand, dist[:, -1] * (1.0 - TIE) - 1e-12)
        self.frames[(key, len(points))] = frame
        return self._from_candidates(frame, points, pixels)

    @staticmethod
    def _from_candidates(frame: _Still, points: np.ndarray, pixels: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        dist = _dist(points[frame.candidates], pixels)
        pick = dist.argmin(1)
        rows = np.arange(len(pixels))
        near = dist[rows, pick]
        second = np.partition(dist, 1, axis=1)[:, 1]
        return frame.candidates[rows, pick], near, second - near <= TIE * near + 1e-12
