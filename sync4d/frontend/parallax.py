"""The subject's parts that never move, found by their parallax under a moving camera.

A part that never moves (a chest's box under its lid, a cabinet beside its door) is invisible to motion:
it moves with the room. But it stands off the room's planes (floor, walls), so under a moving camera its
picture does not follow the planes' homographies: over a few frames' baseline its dense flow leaves a
residual (parallax) that the floor next to it does not. What stands off the planes, thick, touching the
moving subject's mask and not running out of the picture is the subject's (:func:`join_static_parts`).
Parallax fades where the part meets the floor, so a mask that was joined by a part is then refined by
GrabCut (colour decides its outline near the joined mask).

Measured on the front end's suite (``docs/results/video_frontend.md``): the chest's and the appliance's
silhouettes stand 1.7-2.4 px off the planes at a 3-frame baseline, the room 0.23-0.29 px (medians). A moving subject's
flow smears a thin band around it over that baseline (a halo); a never-moving part is thick: a band
thinner than ``THICKNESS`` of the mask's size is left out.
"""

from __future__ import annotations

import numpy as np

from sync4d.frontend.motion import background_residual, dense_flow
from sync4d.frontend.segment import components, grabcut, largest_component, morph, pull_warp, size_of

#: frames between the two pictures whose parallax is compared (each frame against the one this many
#: before and after it; the clip's first and last ``BASELINE`` frames take the parts carried by the flow)
BASELINE = 3
#: a pixel stands off the background's planes when its flow to both frames leaves more than this [px]
#: unexplained by their homographies (the suite's room: 0.23-0.29 px median; its boxes' silhouettes 1.7-2.4 px)
OFF_PLANE_PX = 1.0
#: a part joins the mask only when its thickest point (the distance to its own outline) reaches this share
#: of the mask's size (the square root of its area): a moving subject's flow halo is a thin band
THICKNESS = 0.2


def off_plane(grey: np.ndarray, t: int, baseline: int) -> np.ndarray:
    """(H, W) bool: pixels of frame ``t`` whose flow to frames ``t - baseline`` and ``t + baseline`` both
    leave more than ``OFF_PLANE_PX`` unexplained by the background's planes
    (:func:`~sync4d.frontend.motion.background_residual`)."""
    out = np.ones(grey.shape[1:], bool)
    for s in (t - baseline, t + baseline):
        _, pixels, _ = background_residual(dense_flow(grey[t], grey[s]), static=False)
        out &= pixels > OFF_PLANE_PX
    return out


def attached_parts(candidate: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W) bool: the parts of ``candidate`` (off-plane pixels) that belong with ``mask``: cleaned (an
    opening of 1 px, a closing of 2 px), outside the mask, touching it (within 2 px), not touching the image
    border (the room runs out of the picture, a subject in view does not) and thick (:data:`THICKNESS`)."""
    import cv2

    parts = morph(morph(candidate, "open", 1), "close", 2) & ~mask
    labels, _ = components(parts)
    touching = np.unique(labels[morph(mask, "dilate", 2) & (labels > 0)])
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    keep = np.setdiff1d(touching, border)
    if not len(keep):
        return np.zeros_like(mask)
    depth = cv2.distanceTransform(parts.astype(np.uint8), cv2.DIST_L2, 3)
    thick = np.array([depth[labels == label].max() for label in keep])
    return np.isin(labels, keep[thick >= THICKNESS * size_of(mask)])


def join_static_parts(frames: np.ndarray, grey: np.ndarray, masks: np.ndarray,
                      flows: dict[tuple[int, int], np.ndarray], iterations: int, baseline: int = BASELINE) -> np.ndarray:
    """(T, H, W) bool ``masks`` joined by the never-moving parts attached to them (moving camera only).

    Frames with ``baseline`` frames on both sides get their parts from their own parallax
    (:func:`off_plane`, :func:`attached_parts`); the clip's first and last frames take the nearest such
    frame's parts carried along the neighbouring-frame ``flows`` (``{(t, s): (H, W, 2)}``, as
    :class:`~sync4d.frontend.motion.MotionEvidence`). A mask joined by a part is refined by GrabCut
    (:func:`~sync4d.frontend.segment.grabcut`, ``iterations``); each mask stays one connected piece.

    Args:
        frames: (T, H, W, 3) uint8 RGB frames.
        grey: (T, H, W) uint8 the same frames in grey.
        masks: (T, H, W) bool the moving subject's masks.
        flows: dense flows between neighbouring frames [px].
        iterations: GrabCut iterations per joined frame.
        baseline: frames between the pictures compared.
    """
    n_frames = len(grey)
    parts = np.zeros_like(masks)
    have = np.zeros(n_frames, bool)
    for t in range(baseline, n_frames - baseline):
        if masks[t].any():
            parts[t] = attached_parts(off_plane(grey, t, baseline), masks[t])
            have[t] = True
    if not have.any():
        return masks
    for step, ends in ((-1, range(baseline - 1, -1, -1)), (1, range(n_frames - baseline, n_frames))):
        for t in ends:
            if have[t - step] and (t, t - step) in flows:
                parts[t] = pull_warp(parts[t - step], flows[(t, t - step)]) & ~masks[t]
                have[t] = True
    out = masks.copy()
    for joined_at in np.flatnonzero(parts.reshape(n_frames, -1).any(axis=1)):
        joined = largest_component(masks[joined_at] | parts[joined_at])
        refined = largest_component(grabcut(frames[joined_at], joined, sure=None, iterations=iterations))
        out[joined_at] = refined if refined.any() else joined
    return out
