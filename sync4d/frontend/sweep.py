"""The subject's parts that never move and hardly stand off the floor, found by a plane sweep over the clip.

:mod:`~sync4d.frontend.parallax` finds a never-moving part by its parallax over a few frames; a part only a
little above the floor (a laptop's 2 cm base) leaves well under a pixel there. Over the whole clip, with the
camera the front end found, it stands out: every other frame is warped onto frame ``t`` through the
homography of a horizontal plane at height ``h`` above the ground, for a range of ``h``; where the scene lies
at height ``h`` the warped frames agree with frame ``t``. A pixel is *raised* when the ground plane explains
it clearly worse than its best height does and that height is above the ground (a textureless patch, which
every height explains alike, is not). What is raised, touching the subject's mask, thick and not running out
of the picture joins the mask (:func:`~sync4d.frontend.parallax.attached_parts`, the same rules and vote as
the parallax cue), and GrabCut refines its outline. The ground is the plane the background's triangulated
points mostly lie on (:func:`~sync4d.frontend.geometry.ground_up`); without one (a static camera, no floor
in view) nothing is joined. What it finds and misses, measured: ``docs/results/video_frontend.md``.
"""

from __future__ import annotations

import numpy as np

from sync4d.frontend.geometry import ground_up
from sync4d.frontend.parallax import attached_parts, refine_joined
from sync4d.frontend.segment import morph, size_of

#: the heights swept, in units of the background points' spread (their median distance from their median);
#: one plane below the ground so that the ground itself is a minimum and not an edge of the range
SWEEP_HEIGHTS = np.array([-0.02, 0.0, 0.02, 0.04, 0.06, 0.08, 0.11, 0.15, 0.2, 0.27, 0.36, 0.5])
#: frames compared with frame ``t`` are at least this many frames away (a wider baseline, more parallax)
MIN_GAP = 3
#: ... and at most this many of them, spread over the clip
MAX_OTHERS = 8
#: a pixel is raised when the ground's photometric cost exceeds its best height's by more than this
#: [grey levels, 3x3 mean absolute difference, median over the compared frames]
GAP_GREY = 6.0
#: ... and its best height is at least this [units of the points' spread]
MIN_HEIGHT = 0.02
#: a raised part attaches to the mask within this share of the mask's size (the gap the moving part hides)
BRIDGE = 0.1
#: the ground plane holds the background points within this share of their spread (as ``ground_up``'s ``tol``)
GROUND_TOL = 0.02


def ground_plane(points: np.ndarray) -> tuple[np.ndarray, float, float] | None:
    """The ground under a moving camera from its background points (M, 3) [world, Y up]: (3,) unit normal,
    its offset (``normal @ x`` on the ground) and the points' spread (median distance from their median),
    or None when :func:`~sync4d.frontend.geometry.ground_up` finds no ground. The offset is the one holding
    the most points within ``GROUND_TOL`` of the spread."""
    up = ground_up(points, np.array([0.0, 1.0, 0.0]), tol=GROUND_TOL)
    if up is None:
        return None
    spread = float(np.median(np.linalg.norm(points - np.median(points, axis=0), axis=1))) + 1e-12
    heights = points @ up
    support = (np.abs(heights[:, None] - heights[None, :]) < GROUND_TOL * spread).sum(axis=1)
    return up, float(np.median(heights[support == support.max()])), spread


def plane_homography(K: np.ndarray, to_ref: np.ndarray, to_other: np.ndarray, normal: np.ndarray,
                     offset: float) -> np.ndarray:
    """(3, 3) homography taking frame ``ref``'s pixels to frame ``other``'s for points on the world plane
    ``normal @ x = offset``; ``to_ref``, ``to_other``: (4, 4) world-to-camera; ``K``: (3, 3) [px]."""
    r0, t0 = to_ref[:3, :3], to_ref[:3, 3]
    relative = to_other[:3, :3] @ r0.T
    shift = to_other[:3, 3] - relative @ t0
    normal_ref = r0 @ normal
    distance = offset + normal @ (r0.T @ t0)  # the plane in the reference camera: normal_ref @ x = distance
    return K @ (relative + np.outer(shift, normal_ref) / distance) @ np.linalg.inv(K)


def compared_frames(n_frames: int, t: int) -> list[int]:
    """At most ``MAX_OTHERS`` frames at least ``MIN_GAP`` from ``t``, evenly spread over the clip."""
    far = [s for s in range(n_frames) if abs(s - t) >= MIN_GAP]
    if len(far) <= MAX_OTHERS:
        return far
    return [far[i] for i in np.linspace(0, len(far) - 1, MAX_OTHERS).round().astype(int)]


def plane_differences(grey: np.ndarray, masks: np.ndarray, t: int, s: int, homography: np.ndarray) -> np.ndarray:
    """(H, W) float32: frame ``s`` warped onto frame ``t`` by ``homography`` (``t``'s pixels to ``s``'s),
    its 3x3 mean absolute grey difference from frame ``t``; NaN where the window leaves frame ``s`` or meets
    its subject (``masks`` (T, H, W) bool: a moving part says nothing about the still scene behind it)."""
    import cv2

    height, width = grey.shape[1:]
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    warped = cv2.warpPerspective(grey[s].astype(np.float32), homography, (width, height), flags=flags,
                                 borderValue=np.nan)
    subject = cv2.warpPerspective(masks[s].astype(np.float32), homography, (width, height), flags=flags,
                                  borderValue=0.0)
    valid = np.isfinite(warped) & (subject == 0)
    difference = np.where(valid, np.abs(warped - grey[t].astype(np.float32)), 0.0).astype(np.float32)
    weight = cv2.blur(valid.astype(np.float32), (3, 3))  # a box filter's running sums carry NaN along rows
    return np.where(weight > 0.999, cv2.blur(difference, (3, 3)) / np.maximum(weight, 1e-6), np.nan)


def raised_pixels(grey: np.ndarray, masks: np.ndarray, t: int, K: np.ndarray, extrinsics: np.ndarray,
                  ground: tuple[np.ndarray, float, float]) -> np.ndarray:
    """(H, W) bool pixels of frame ``t`` standing above the ground (module docstring).

    Args:
        grey: (T, H, W) uint8 frames; masks: (T, H, W) bool their subject.
        K: (3, 3) intrinsics at the frames' size [px]; extrinsics: (T, 4, 4) world-to-camera.
        ground: :func:`ground_plane`.
    """
    normal, offset, spread = ground
    others = compared_frames(len(grey), t)
    cost = np.full((len(SWEEP_HEIGHTS),) + grey.shape[1:], np.inf, np.float32)
    for i, level in enumerate(SWEEP_HEIGHTS):
        stacked = np.stack([plane_differences(grey, masks, t, s, plane_homography(
            K, extrinsics[t], extrinsics[s], normal, offset + level * spread)) for s in others])
        seen = np.isfinite(stacked).sum(axis=0) * 2 > len(others)  # measured in most compared frames
        cost[i][seen] = np.nanmedian(stacked[:, seen], axis=0)
    ground_cost = cost[int(np.argmin(np.abs(SWEEP_HEIGHTS)))]
    best = np.argmin(cost, axis=0)
    with np.errstate(invalid="ignore"):
        gap = ground_cost - cost.min(axis=0)
    return np.isfinite(gap) & (gap > GAP_GREY) & (SWEEP_HEIGHTS[best] >= MIN_HEIGHT)


def bridged_part(raised: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W) bool the ``raised`` parts attached to ``mask`` (:func:`~sync4d.frontend.parallax.attached_parts`
    within ``BRIDGE`` of the mask's size), with the gap between them closed: next to a moving part the still
    scene is hidden in most frames, so it is not judged and leaves a gap (a lid over its base's back edge)."""
    reach = max(2, int(np.ceil(BRIDGE * size_of(mask))))
    part = attached_parts(raised, mask, reach=reach)
    return morph(mask | part, "close", reach) & ~mask if part.any() else part


def carried_by_plane(parts: np.ndarray, have: np.ndarray, K: np.ndarray, extrinsics: np.ndarray,
                     ground: tuple[np.ndarray, float, float]) -> np.ndarray:
    """(T, H, W) bool ``parts`` where a frame without them (``have`` False) takes the nearest frame's, moved
    by the homography of the ground plane (a never-moving part lies near it: a frame's own misses are few)."""
    import cv2

    normal, offset, _ = ground
    out = parts.copy()
    height, width = parts.shape[1:]
    holders = np.flatnonzero(have)
    for t in np.flatnonzero(~have):
        s = int(holders[np.argmin(np.abs(holders - t))])
        h = plane_homography(K, extrinsics[t], extrinsics[s], normal, offset)
        out[t] = cv2.warpPerspective(parts[s].astype(np.uint8), h, (width, height),
                                     flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP) > 0
    return out


def join_raised_parts(frames: np.ndarray, grey: np.ndarray, masks: np.ndarray, K: np.ndarray,
                      extrinsics: np.ndarray, points: np.ndarray, iterations: int) -> np.ndarray:
    """(T, H, W) bool ``masks`` joined by the never-moving parts standing above the ground next to them.

    Args:
        frames: (T, H, W, 3) uint8 RGB; grey: (T, H, W) uint8 the same in grey.
        masks: (T, H, W) bool the subject's masks.
        K: (3, 3) intrinsics at the frames' size [px]; extrinsics: (T, 4, 4) world-to-camera (Y-up world).
        points: (M, 3) the background's triangulated points in the same world.
        iterations: GrabCut iterations per joined frame.
    """
    ground = ground_plane(points) if len(points) else None
    if ground is None or len(frames) < 2 * MIN_GAP:
        return masks
    parts = np.zeros_like(masks)
    for t in range(len(frames)):
        if masks[t].any():
            parts[t] = bridged_part(raised_pixels(grey, masks, t, K, extrinsics, ground), masks[t])
    have = np.asarray(parts.reshape(len(parts), -1).any(axis=1))
    if have.sum() <= 0.5 * len(frames):  # seen in a few frames only: scenery the subject passes by
        return masks
    # GrabCut trims what joined; the moving part's mask stays whole (a lid seen edge-on is a band too thin
    # for GrabCut's opening)
    return masks | refine_joined(frames, masks, carried_by_plane(parts, have, K, extrinsics, ground) & ~masks,
                                 iterations)
