"""The subject's masks from motion and colour: a seed where something moves against the background (or
where the prompt points), refined by GrabCut's colour graph cut, then carried frame by frame along the
optical flow, each carried mask refined again by GrabCut and joined by what moves there."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sync4d.frontend.motion import MotionEvidence

#: GrabCut's mask labels (OpenCV's GC_BGD, GC_FGD, GC_PR_BGD, GC_PR_FGD)
BGD, FGD, PR_BGD, PR_FGD = 0, 1, 2, 3
#: GrabCut may grow a prior by at most this fraction of its size (the square root of its area)
GROWTH = 0.1
#: colour histogram levels per RGB channel of the subject's colour model
BINS = 16
#: under a static camera a pixel within this colour distance (RGB levels of 255) of the clip's background
#: plate (the per-pixel median over the frames) shows the background there
PLATE_LEVELS = 10.0
#: a pixel whose colour is at least this much more the subject's than the background's is surely the subject's
SURE_LIKENESS = 0.9
#: patches the background's motion explains (of colours not surely the subject's) leave a carried mask
#: unless fewer than this share of it would remain
EXPLAINED_KEEP = 0.75
#: holes in a mask smaller than this share of its area are filled (colour speckles inside the subject)
HOLE_SHARE = 0.01
#: a carried mask is the subject lost when less than this share of the first frame's colour support remains
LOST_SUPPORT = 0.5
#: under a moving camera a carried mask is joined by the pixels within this share of its size of surely the
#: subject's colours that the background's motion does not explain: a part coming into view (a lid turning from
#: edge-on), which the flow cannot carry and GrabCut (at most ``GROWTH``) grows back too slowly
REVEAL = 0.2


def disk(radius: int) -> np.ndarray:
    """An elliptic structuring element of the given radius [px] (at least 1)."""
    import cv2

    r = max(1, int(radius))
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def morph(mask: np.ndarray, op: str, radius: int) -> np.ndarray:
    """``dilate``, ``erode``, ``open`` or ``close`` a (H, W) bool mask with a disk of ``radius`` [px]."""
    import cv2

    m = mask.astype(np.uint8)
    kernel = disk(radius)
    if op == "dilate":
        return cv2.dilate(m, kernel) > 0
    if op == "erode":
        return cv2.erode(m, kernel) > 0
    code = cv2.MORPH_OPEN if op == "open" else cv2.MORPH_CLOSE
    return cv2.morphologyEx(m, code, kernel) > 0


def components(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Connected components of a (H, W) bool mask: (H, W) int labels (0 = none) and (n + 1,) areas [px]."""
    import cv2

    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    return labels, stats[:, cv2.CC_STAT_AREA].astype(np.int64)


def largest_component(mask: np.ndarray) -> np.ndarray:
    """The (H, W) bool largest 8-connected component of ``mask`` (empty if none)."""
    labels, areas = components(mask)
    if len(areas) < 2:
        return np.zeros_like(mask, dtype=bool)
    return labels == 1 + int(np.argmax(areas[1:]))


def size_of(mask: np.ndarray) -> float:
    """A mask's size [px]: the square root of its area."""
    return float(np.sqrt(max(int(mask.sum()), 1)))


def pull_warp(mask: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """(H, W) bool: ``mask`` of another frame brought to this one by ``flow`` (H, W, 2) from this frame to
    the other (out(x) = mask(x + flow(x)))."""
    import cv2

    h, w = mask.shape
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    moved = cv2.remap(mask.astype(np.float32), uu + flow[..., 0], vv + flow[..., 1], cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return moved > 0.5


def grabcut(image: np.ndarray, prior: np.ndarray, *, sure: np.ndarray | None, iterations: int,
            band: float = 0.35) -> np.ndarray:
    """(H, W) bool subject refined by GrabCut from a (H, W) bool ``prior``.

    Labels: ``sure`` (default: the prior eroded by a tenth of its size) is foreground; the rest of the prior
    probably foreground; a band of ``band`` x its size around it probably background; beyond, background.
    """
    import cv2

    if not prior.any() or iterations <= 0:
        return prior.copy()
    size = size_of(prior)
    labels = np.full(prior.shape, BGD, np.uint8)
    labels[morph(prior, "dilate", int(band * size) + 2)] = PR_BGD
    labels[prior] = PR_FGD
    core = morph(prior, "erode", int(0.1 * size)) if sure is None else sure
    labels[core & prior] = FGD
    if (labels == BGD).sum() < 64 or not ((labels == PR_BGD) | (labels == BGD)).any():
        labels[[0, -1], :] = BGD
        labels[:, [0, -1]] = BGD
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    try:
        cv2.grabCut(np.ascontiguousarray(image[..., ::-1]), labels, (0, 0, 0, 0), bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:  # one colour class empty (e.g. a uniform frame): keep the prior
        return prior.copy()
    # colour decides the outline near the prior, never far from it: on a busy background GrabCut's colour
    # models also claim distant patches of the subject's colours
    out = ((labels == FGD) | (labels == PR_FGD)) & morph(prior, "dilate", int(GROWTH * size) + 1)
    return morph(out, "open", 1)


def box_grabcut(image: np.ndarray, box: np.ndarray, iterations: int) -> np.ndarray:
    """(H, W) bool subject inside a (H, W) bool box: GrabCut started from the box (outside: background)."""
    import cv2

    labels = np.where(box, PR_FGD, BGD).astype(np.uint8)
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    try:
        cv2.grabCut(np.ascontiguousarray(image[..., ::-1]), labels, (0, 0, 0, 0), bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:
        return box.copy()
    return morph((labels == FGD) | (labels == PR_FGD), "open", 1)


def seed_from_motion(moving: np.ndarray, flows: dict[tuple[int, int], np.ndarray],
                     min_area_px: float) -> tuple[int, np.ndarray] | None:
    """The frame whose largest coherent moving region is biggest and most stable (area x its overlap with the
    next frame's region carried back by the flow), and that region (H, W) bool; None when no frame has a
    region of at least ``min_area_px`` pixels."""
    h, w = moving.shape[1:]
    radius = max(3, int(0.03 * max(h, w)))
    regions = [largest_component(morph(morph(m, "open", 1), "close", radius)) for m in moving]
    best_t, best_score = -1, 0.0
    for t in range(len(regions) - 1):
        area = int(regions[t].sum())
        if area < min_area_px or not regions[t + 1].any():
            continue
        carried = pull_warp(regions[t + 1], flows[(t, t + 1)])
        overlap = (carried & regions[t]).sum() / max((carried | regions[t]).sum(), 1)
        if area * overlap > best_score:
            best_t, best_score = t, area * overlap
    if best_t < 0:
        return None
    return best_t, regions[best_t]


def seed_from_prompt(prompt: np.ndarray, moving: np.ndarray, image: np.ndarray) -> np.ndarray:
    """(H, W) bool prior from a prompt at work size: a box (x0, y0, x1, y1) is the prior itself (GrabCut
    finds the subject in it); a point (x, y) picks the moving region under it, else a box around it."""
    h, w = moving.shape
    if len(prompt) == 4:
        x0, y0, x1, y1 = np.round(prompt).astype(int)
        prior = np.zeros((h, w), bool)
        prior[max(y0, 0): min(y1, h), max(x0, 0): min(x1, w)] = True
        return prior
    x, y = int(np.clip(round(prompt[0]), 0, w - 1)), int(np.clip(round(prompt[1]), 0, h - 1))
    labels, _ = components(morph(moving, "close", max(2, int(0.02 * max(h, w)))))
    if labels[y, x] > 0:
        return labels == labels[y, x]
    half = max(h, w) // 6
    prior = np.zeros((h, w), bool)
    prior[max(y - half, 0): y + half, max(x - half, 0): x + half] = True
    return prior


def near_motion(moving: np.ndarray, carried: np.ndarray) -> np.ndarray:
    """(H, W) bool: the moving regions that lie mostly (over half) within a small reach of the carried mask
    (a limb the flow lost), clipped to that reach; a moving region reaching far beyond it is left out: it
    may be background parallax of the subject's colour (a sofa behind a cat)."""
    reach = morph(carried, "dilate", int(0.08 * size_of(carried)) + 1)
    labels, areas = components(moving)
    inside = np.bincount(labels[reach], minlength=len(areas))
    keep = np.flatnonzero(inside > 0.5 * areas)
    keep = keep[keep > 0]
    return np.isin(labels, keep) & reach


@dataclass(frozen=True)
class ColourModel:
    """Colour histograms of the subject and of its surroundings on the frame it was found on.

    Attributes:
        subject, background: (BINS^3,) normalised RGB histograms (plus the same small floor).
        support: the share of that frame's mask whose colour is more the subject's than the background's.
    """

    subject: np.ndarray
    background: np.ndarray
    support: float

    def likeness(self, image: np.ndarray) -> np.ndarray:
        """(H, W) in [0, 1]: how much more each pixel's colour is the subject's than the background's."""
        index = colour_bins(image)
        fg, bg = self.subject[index], self.background[index]
        return fg / (fg + bg)


def colour_bins(image: np.ndarray) -> np.ndarray:
    """(H, W) int histogram bin of each RGB pixel (``BINS`` levels per channel)."""
    q = (image.astype(np.int64) * BINS) // 256
    return (q[..., 0] * BINS + q[..., 1]) * BINS + q[..., 2]


def colour_model(image: np.ndarray, mask: np.ndarray) -> ColourModel:
    """The subject's and its surroundings' (a band of its size around it) colour histograms."""
    index = colour_bins(image)
    around = morph(mask, "dilate", int(0.5 * size_of(mask)) + 2) & ~mask
    # the same small floor on both: a colour seen on neither side is a tie (not the subject's)
    fg = np.bincount(index[mask], minlength=BINS**3) / max(int(mask.sum()), 1) + 1e-4
    bg = np.bincount(index[around], minlength=BINS**3) / max(int(around.sum()), 1) + 1e-4
    likeness = fg[index[mask]] / (fg[index[mask]] + bg[index[mask]])
    return ColourModel(fg, bg, float((likeness > 0.5).mean()) if mask.any() else 0.0)


def clip_colour_model(frames: np.ndarray, subject: np.ndarray, background: np.ndarray) -> ColourModel:
    """Colour histograms pooled over the clip: the subject's from ``subject`` (T, H, W) bool pixels, the
    background's from ``background`` (T, H, W) bool (support over the subject pixels, as :func:`colour_model`)."""
    index = colour_bins(frames)
    fg = np.bincount(index[subject], minlength=BINS**3) / max(int(subject.sum()), 1) + 1e-4
    bg = np.bincount(index[background], minlength=BINS**3) / max(int(background.sum()), 1) + 1e-4
    likeness = fg[index[subject]] / (fg[index[subject]] + bg[index[subject]])
    return ColourModel(fg, bg, float((likeness > 0.5).mean()) if subject.any() else 0.0)


def fill_holes(mask: np.ndarray, share: float) -> np.ndarray:
    """(H, W) bool ``mask`` with its holes (background components not touching the image border) smaller
    than ``share`` of its area filled."""
    labels, areas = components(~mask)
    h, w = mask.shape
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    small = np.flatnonzero(areas < share * mask.sum())
    small = np.setdiff1d(small[small > 0], border)
    return mask | np.isin(labels, small)


def revealed(carried: np.ndarray, likeness: np.ndarray, explained: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels within ``REVEAL`` x the ``carried`` mask's size of it whose ``likeness``
    (H, W) is at least ``SURE_LIKENESS`` and that ``explained`` (H, W) bool does not hold: a part of the
    subject coming into view, which the flow cannot carry: it carries only what the previous frame showed
    (measured on the default film's lid, ``docs/results/video_frontend.md``)."""
    reach = morph(carried, "dilate", int(REVEAL * size_of(carried)) + 1)
    return reach & (likeness >= SURE_LIKENESS) & ~explained


def follow(frames: np.ndarray, start: int, first: np.ndarray, evidence: MotionEvidence,
           iterations: int, *, reveal: bool = False) -> np.ndarray:
    """(T, H, W) bool masks of the subject: :func:`propagate` twice. The first pass's colour model learns
    the subject from every moving pixel, floor between a small animal's legs included; the second learns it
    from the moving pixels within the first pass's masks against everything outside them (every frame), so
    a floor tile of the subject's shade that the flow dragged along is the background's colour there.
    Holes under ``HOLE_SHARE`` of a mask are filled. ``reveal``: grow the carried masks by :func:`revealed`
    (the front end asks it under a moving camera only; why: ``docs/results/video_frontend.md``)."""
    masks = propagate(frames, start, first, evidence, iterations, reveal=reveal)
    subject = masks & evidence.moving
    if subject.sum() >= first.sum():
        outside = ~np.stack([morph(m, "dilate", 2) for m in masks])
        masks = propagate(frames, start, first, evidence, iterations, clip_colour_model(frames, subject, outside),
                          reveal=reveal)
    return np.stack([fill_holes(m, HOLE_SHARE) for m in masks])


def propagate(frames: np.ndarray, start: int, first: np.ndarray, evidence: MotionEvidence,
              iterations: int, model: ColourModel | None = None, *, reveal: bool = False) -> np.ndarray:
    """(T, H, W) bool masks carried from frame ``start`` (mask ``first``) forwards and backwards along the
    flow, each carried mask joined by what moves just around it and refined by GrabCut.

    The subject's colours keep the carried masks honest: ``model``, or learnt over the whole clip from what
    moves against what the background's motion surely explains (:func:`clip_colour_model`; the first mask's
    own colours when little moves); a mask keeps only pixels of the subject's colours (the floor the flow
    drags along falls off), and loses the patches the background's motion explains
    (:attr:`MotionEvidence.explained`) whose colours are not surely the subject's; a mask whose colours stop being the subject's (less than half the model's support) is
    the subject lost (it left the frame): that frame and those beyond stay empty.
    A mask grows only where the background's motion does not surely explain the picture (``still``); with
    ``reveal`` it also grows by :func:`revealed` (a part coming into view).
    """
    moving, flows = evidence.moving, evidence.flows
    n_frames = len(frames)
    masks = np.zeros(moving.shape, bool)
    if model is None and moving.sum() >= first.sum():  # the subject's colours are what moves
        model = clip_colour_model(frames, moving, evidence.still & ~moving)
    if model is None:  # a prompted subject that hardly moves: its first mask's colours
        model = colour_model(frames[start], first)
    else:
        kept = largest_component(first & (model.likeness(frames[start]) > 0.5))
        first = kept if kept.sum() >= LOST_SUPPORT * first.sum() else first
    masks[start] = first
    for step in (1, -1):
        t = start + step
        while 0 <= t < n_frames:
            carried = pull_warp(masks[t - step], flows[(t, t - step)])
            if not carried.any():
                break
            likeness = model.likeness(frames[t])
            like = likeness > 0.5
            joined = carried | (near_motion(moving[t], carried) & like)
            sure = morph(carried, "erode", int(0.15 * size_of(carried))) & like
            refined = grabcut(frames[t], joined, sure=sure, iterations=iterations)
            if reveal and evidence.explained is not None:
                refined |= revealed(carried, likeness, evidence.explained[t])
            refined &= carried | ~evidence.still[t]
            refined &= like
            if evidence.explained is not None:  # a patch of floor dragged along, not a lone pixel, not surely subject
                doubtful = morph(evidence.explained[t], "open", 1) & (likeness < SURE_LIKENESS)
                trimmed = refined & ~doubtful
                # ... unless that is much of the mask: the subject holding still against the background
                refined = trimmed if trimmed.sum() >= EXPLAINED_KEEP * refined.sum() else refined
            mask = largest_component(refined) if refined.any() else carried
            if like[mask].mean() < LOST_SUPPORT * model.support:
                break
            masks[t] = mask
            t += step
    return masks


def drop_plate(frames: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """(T, H, W) bool masks without the pixels that show the background, for a static camera.

    The background plate is the per-pixel median of the frames (T, H, W, 3): wherever the subject moves it
    uncovers the background in most frames (the floor between a trotting dog's legs). A mask pixel whose
    colour (and its neighbours', within 1 px) is within ``PLATE_LEVELS`` of the plate is background; a frame
    that would lose more than half its mask keeps it (the subject held still there, so the plate shows it).
    """
    plate = np.median(frames, axis=0).astype(np.float32)
    out = masks.copy()
    for t, mask in enumerate(masks):
        if not mask.any():
            continue
        differs = morph(np.linalg.norm(frames[t].astype(np.float32) - plate, axis=-1) > PLATE_LEVELS, "dilate", 1)
        kept = largest_component(mask & differs)
        if kept.sum() >= LOST_SUPPORT * mask.sum():
            out[t] = kept
    return out
