"""The subject's parts that never move, found by their parallax under a moving camera.

A part that never moves (a chest's box under its lid, a cabinet beside its door) is invisible to motion:
it moves with the room. But it stands off the room's planes (floor, walls), so under a moving camera its
picture does not follow the planes' homographies: over a few frames' baseline its dense flow leaves a
residual (parallax) that the floor next to it does not. What stands off the planes, thick, touching the
moving subject's mask and not running out of the picture is the subject's (:func:`join_static_parts`).
Parallax fades where the part meets the floor, so a mask that was joined by a part is then refined by
GrabCut (colour decides its outline near the joined mask).

A moving subject's flow smears a thin band around it over that baseline (a halo); a never-moving part is
thick: a band thinner than ``THICKNESS`` of the mask's size is left out. What it finds and misses, measured:
``docs/results/video_frontend.md``.
"""

from __future__ import annotations

import numpy as np

from sync4d.frontend.motion import background_residual, dense_flow
from sync4d.frontend.segment import components, grabcut, largest_component, morph, pull_warp, size_of

#: each frame's parallax is measured against the nearest frames before and after it where the room has
#: shifted by at least this much [px] (the neighbouring flows' medians added up): a slow camera gets a
#: longer baseline, a fast one a shorter (a fast camera's longer baseline widens a moving subject's halo)
ROOM_SHIFT_PX = 10.0
#: ... at most this many frames away (a frame with no such partner on both sides takes a neighbour's parts)
MAX_BASELINE = 6
#: a pixel stands off the background's planes when its flow to both frames leaves more than this [px]
#: unexplained by their homographies (the room's own residual is a fraction of a pixel)
OFF_PLANE_PX = 1.0
#: a part joins the mask only when its thickest point (the distance to its own outline) reaches this share
#: of the mask's size (the square root of its area): a moving subject's flow halo is a thin band
THICKNESS = 0.2


def partners(shifts: np.ndarray, t: int) -> tuple[int, int] | None:
    """The frames before and after ``t`` nearest to it where the room has shifted by ``ROOM_SHIFT_PX``
    (``shifts``: (T - 1,) the room's median flow [px] between neighbouring frames, added up), within
    ``MAX_BASELINE`` frames; None when either side has none."""
    found = []
    for direction in (-1, 1):
        moved, s = 0.0, t
        while moved < ROOM_SHIFT_PX:
            if not 0 <= s + direction < len(shifts) + 1 or abs(s + direction - t) > MAX_BASELINE:
                return None
            moved += float(shifts[min(s, s + direction)])
            s += direction
        found.append(s)
    return found[0], found[1]


def off_plane(grey: np.ndarray, t: int, others: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: pixels of frame ``t`` whose flow to both frames ``others`` leaves more than
    ``OFF_PLANE_PX`` unexplained by the background's planes (:func:`~sync4d.frontend.motion.background_residual`)."""
    out = np.ones(grey.shape[1:], bool)
    for s in others:
        _, pixels, _ = background_residual(dense_flow(grey[t], grey[s]), static=False)
        out &= pixels > OFF_PLANE_PX
    return out


def attached_parts(candidate: np.ndarray, mask: np.ndarray, reach: int = 2) -> np.ndarray:
    """(H, W) bool: the parts of ``candidate`` (off-plane pixels) that belong with ``mask``: cleaned (an
    opening of 1 px, a closing of 2 px), outside the mask, touching it (within ``reach`` px), not touching the
    image border (the room runs out of the picture, a subject in view does not) and thick (:data:`THICKNESS`)."""
    import cv2

    parts = morph(morph(candidate, "open", 1), "close", 2) & ~mask
    labels, _ = components(parts)
    touching = np.unique(labels[morph(mask, "dilate", reach) & (labels > 0)])
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    keep = np.setdiff1d(touching, border)
    if not len(keep):
        return np.zeros_like(mask)
    depth = cv2.distanceTransform(parts.astype(np.uint8), cv2.DIST_L2, 3)
    thick = np.array([depth[labels == label].max() for label in keep])
    return np.isin(labels, keep[thick >= THICKNESS * size_of(mask)])


def measured_parts(grey: np.ndarray, masks: np.ndarray, flows: dict[tuple[int, int], np.ndarray]
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(T, H, W) bool the parts attached to each frame's mask (:func:`off_plane` against its
    :func:`partners`, :func:`attached_parts`) and (T,) bool which frames hold their parts. A part of the
    subject that never moves is seen in most frames: when at most half the measured frames found one, none
    is kept (a sofa a walking cat passes by); else a measured frame that found none (a lid seen edge-on)
    counts as not measured, so it takes a neighbour's parts."""
    n_frames = len(grey)
    shifts = np.array([float(np.median(np.linalg.norm(flows[(t, t + 1)], axis=-1))) for t in range(n_frames - 1)])
    parts = np.zeros_like(masks)
    measured = np.zeros(n_frames, bool)
    for t in range(n_frames):
        others = partners(shifts, t)
        if others is not None and masks[t].any():
            parts[t] = attached_parts(off_plane(grey, t, others), masks[t])
            measured[t] = True
    found = measured & parts.reshape(n_frames, -1).any(axis=1)
    if found.sum() <= 0.5 * measured.sum():  # a part in a few frames only: scenery the subject passes by
        return np.zeros_like(masks), measured
    return parts, found


def carry_parts(parts: np.ndarray, have: np.ndarray, masks: np.ndarray,
                flows: dict[tuple[int, int], np.ndarray]) -> np.ndarray:
    """(T, H, W) bool ``parts`` where frames without them (``have`` False) take their neighbour's, carried
    along the neighbouring-frame ``flows`` (forwards, then backwards), outside ``masks``."""
    parts, have = parts.copy(), have.copy()
    n_frames = len(parts)
    for order in (range(n_frames), range(n_frames - 1, -1, -1)):
        previous = None
        for t in order:
            if not have[t] and previous is not None and abs(t - previous) == 1:
                parts[t] = pull_warp(parts[previous], flows[(t, previous)]) & ~masks[t]
                have[t] = True
            previous = t if have[t] else None
    return parts


def join_static_parts(frames: np.ndarray, grey: np.ndarray, masks: np.ndarray,
                      flows: dict[tuple[int, int], np.ndarray], iterations: int) -> np.ndarray:
    """(T, H, W) bool ``masks`` joined by the never-moving parts attached to them (moving camera only).

    Each frame's parts come from its own parallax (:func:`measured_parts`), or are carried from a
    neighbour's along the neighbouring-frame ``flows`` (``{(t, s): (H, W, 2)}``, as
    :class:`~sync4d.frontend.motion.MotionEvidence`; :func:`carry_parts`). A mask joined by a part is
    refined by GrabCut (:func:`~sync4d.frontend.segment.grabcut`, ``iterations``); each mask stays one
    connected piece.

    Args:
        frames: (T, H, W, 3) uint8 RGB frames.
        grey: (T, H, W) uint8 the same frames in grey.
        masks: (T, H, W) bool the moving subject's masks.
        flows: dense flows between neighbouring frames [px].
        iterations: GrabCut iterations per joined frame.
    """
    parts, have = measured_parts(grey, masks, flows)
    if not parts.any():
        return masks
    return refine_joined(frames, masks, carry_parts(parts, have, masks, flows), iterations)


def refine_joined(frames: np.ndarray, masks: np.ndarray, parts: np.ndarray, iterations: int) -> np.ndarray:
    """(T, H, W) bool each frame's mask joined by its ``parts`` (T, H, W) bool and, where a part joined,
    refined by GrabCut (``iterations``); each mask stays one connected piece."""
    out = masks.copy()
    for joined_at in np.flatnonzero(parts.reshape(len(parts), -1).any(axis=1)):
        joined = largest_component(masks[joined_at] | parts[joined_at])
        refined = largest_component(grabcut(frames[joined_at], joined, sure=None, iterations=iterations))
        out[joined_at] = refined if refined.any() else joined
    return out
