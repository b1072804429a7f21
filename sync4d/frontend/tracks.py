"""Sparse corner tracks through a clip (KLT), the camera's raw material.

Corners are tracked frame to frame by pyramidal Lucas-Kanade and kept while a backward track returns to
within ``FB_TOLERANCE_PX`` of where it started; lost corners are replaced by new ones away from the
living ones, so a long clip keeps about the requested number of tracks in every frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: forward-backward tolerance of a Lucas-Kanade step [px]
FB_TOLERANCE_PX = 0.7
LK_WINDOW = (15, 15)
LK_LEVELS = 3


@dataclass(frozen=True)
class Tracks:
    """Point tracks through a clip.

    Attributes:
        uv: (T, N, 2) pixel positions [px] (meaningless where not ``valid``).
        valid: (T, N) bool, the track exists in that frame (each track is one unbroken run of frames).
    """

    uv: np.ndarray
    valid: np.ndarray

    @property
    def num_frames(self) -> int:
        return int(self.uv.shape[0])


def detect_corners(grey: np.ndarray, count: int, *, avoid: np.ndarray | None = None,
                   min_distance: float = 6.0) -> np.ndarray:
    """(n, 2) up to ``count`` Shi-Tomasi corners [px] of a (H, W) uint8 image, outside ``avoid`` (H, W) bool."""
    import cv2

    allowed = None if avoid is None else np.where(avoid, 0, 255).astype(np.uint8)
    found = cv2.goodFeaturesToTrack(grey, maxCorners=int(count), qualityLevel=0.005, minDistance=min_distance,
                                    mask=allowed, blockSize=5)
    return np.zeros((0, 2), np.float32) if found is None else found.reshape(-1, 2).astype(np.float32)


def lk_step(grey_a: np.ndarray, grey_b: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Track (n, 2) points from ``grey_a`` to ``grey_b``; returns (positions (n, 2), ok (n,) bool), ok only
    where the forward-backward error is below ``FB_TOLERANCE_PX`` and the point stays in the image."""
    import cv2

    if len(points) == 0:
        return points.copy(), np.zeros(0, bool)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03)
    p0 = points.reshape(-1, 1, 2).astype(np.float32)
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(grey_a, grey_b, p0, None, winSize=LK_WINDOW, maxLevel=LK_LEVELS,
                                          criteria=criteria)
    back, st2, _ = cv2.calcOpticalFlowPyrLK(grey_b, grey_a, p1, None, winSize=LK_WINDOW, maxLevel=LK_LEVELS,
                                            criteria=criteria)
    p1, back = np.asarray(p1).reshape(-1, 2), np.asarray(back).reshape(-1, 2)
    h, w = grey_a.shape
    inside = (p1[:, 0] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= h - 1)
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) & inside & (np.linalg.norm(back - points, axis=1) < FB_TOLERANCE_PX)
    return p1, ok


def track_corners(grey: np.ndarray, count: int, *, avoid: np.ndarray | None = None) -> Tracks:
    """KLT tracks of about ``count`` corners through (T, H, W) uint8 frames, re-detected as they are lost.

    Args:
        grey: (T, H, W) uint8 frames.
        count: corners kept alive per frame.
        avoid: (T, H, W) bool, where no corner is started (e.g. the subject), or None.
    """
    n_frames = len(grey)
    columns: list[tuple[int, np.ndarray]] = []  # (first frame, (T, 2) positions) per track
    alive_ids: list[int] = []
    alive_pts = np.zeros((0, 2), np.float32)
    for t in range(n_frames):
        if t > 0:
            moved, ok = lk_step(grey[t - 1], grey[t], alive_pts)
            alive_ids = [i for i, k in zip(alive_ids, ok) if k]
            alive_pts = moved[ok]
            for i, p in zip(alive_ids, alive_pts):
                columns[i][1][t] = p
        if len(alive_pts) < 0.7 * count:
            block = np.zeros(grey[t].shape, bool)
            for p in alive_pts.astype(int):
                block[max(p[1] - 5, 0): p[1] + 6, max(p[0] - 5, 0): p[0] + 6] = True
            if avoid is not None:
                block |= avoid[t]
            new = detect_corners(grey[t], count - len(alive_pts), avoid=block)
            for p in new:
                track = np.full((n_frames, 2), np.nan, np.float32)
                track[t] = p
                columns.append((t, track))
                alive_ids.append(len(columns) - 1)
            alive_pts = np.concatenate([alive_pts, new]) if len(new) else alive_pts
    if not columns:
        return Tracks(uv=np.zeros((n_frames, 0, 2)), valid=np.zeros((n_frames, 0), bool))
    uv = np.stack([c[1] for c in columns], axis=1).astype(np.float64)
    valid = np.isfinite(uv[..., 0])
    return Tracks(uv=np.nan_to_num(uv), valid=valid)
