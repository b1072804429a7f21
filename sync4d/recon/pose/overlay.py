"""Pictures of a body fit over its video frames: mask tint, parts, skeleton and landmarks."""

from __future__ import annotations

from pathlib import Path

import numpy as np

PART_COLOURS = np.array(
    [[230, 25, 75], [60, 180, 75], [255, 225, 25], [0, 130, 200], [245, 130, 48], [145, 30, 180], [70, 240, 240],
     [240, 50, 230], [210, 245, 60], [250, 190, 212], [0, 128, 128], [220, 190, 255], [170, 110, 40],
     [255, 250, 200], [128, 0, 0], [170, 255, 195]], dtype=np.float64)


# a limb's colour by its side (RGB): a leg crossing to the other side, or legs swapped between frames, is seen
SIDE_COLOURS = {"left": (40, 170, 255), "right": (255, 120, 30), "mid": (255, 255, 255)}
LEFT_PREFIXES = ("l_", "fl_", "hl_")
RIGHT_PREFIXES = ("r_", "fr_", "hr_")

NEAR = 1e-3  # points nearer the camera plane than this [m] are not drawn (behind it: no image)
MARGIN = 2.0  # pixel coordinates further than this many image sizes outside the frame are not drawn


def project(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(..., 3) camera-frame points [m] -> (..., 2) pixels; NaN where a point is not in front of the camera
    (z < NEAR) or not finite."""
    points = np.asarray(points, dtype=np.float64)
    z = points[..., 2:3]
    with np.errstate(invalid="ignore", divide="ignore"):
        uv = points[..., :2] / z * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]
    bad = ~(np.isfinite(points).all(-1) & (points[..., 2] >= NEAR))
    uv[bad] = np.nan
    return uv


PICTURE_WIDTH = 800  # frames narrower than this are enlarged before drawing: a phone clip's work size is ~400 px


def enlarged(frame: np.ndarray, K: np.ndarray, mask: np.ndarray | None, landmarks: np.ndarray | None,
             width: int = PICTURE_WIDTH) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """``frame`` (H, W, 3) enlarged by a whole factor to at least ``width`` pixels, with the intrinsics (3, 3),
    the mask (H, W) and the landmarks (L, 2) [px] it is drawn with enlarged alike (unchanged when wide enough)."""
    import cv2

    factor = -(-width // frame.shape[1])
    if factor <= 1:
        return frame, K, mask, landmarks
    h, w = frame.shape[:2]
    big = cv2.resize(frame, (w * factor, h * factor), interpolation=cv2.INTER_LINEAR)
    K = np.diag([factor, factor, 1.0]) @ np.asarray(K, dtype=np.float64)
    K[:2, 2] += (factor - 1) / 2  # pixel centres: pixel i's centre i + 0.5 maps to factor * (i + 0.5)
    big_mask = None if mask is None else np.repeat(np.repeat(mask, factor, 0), factor, 1)
    big_marks = None if landmarks is None else (np.asarray(landmarks, dtype=np.float64) + 0.5) * factor - 0.5
    return big, K, big_mask, big_marks


def side_of(name: str) -> str:
    """"left", "right" or "mid" for a joint name of the body fits (people: ``l_``/``r_``; quadrupeds: ``fl_``,
    ``hl_``/``fr_``, ``hr_``; anything else the midline)."""
    if name.startswith(LEFT_PREFIXES):
        return "left"
    if name.startswith(RIGHT_PREFIXES):
        return "right"
    return "mid"


def draw_side_legend(img: np.ndarray, scale: int) -> None:
    """Write "left" and "right" in their limb colours in the picture's top-left corner (in place)."""
    import cv2

    y = 14 * scale
    for word in ("left", "right"):
        cv2.putText(img, word, (6 * scale, y), cv2.FONT_HERSHEY_SIMPLEX, 0.45 * scale, (0, 0, 0), 3 * scale)
        cv2.putText(img, word, (6 * scale, y), cv2.FONT_HERSHEY_SIMPLEX, 0.45 * scale, SIDE_COLOURS[word], scale)
        y += 16 * scale


def drawable(uv: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N,) True where pixel positions ``uv`` (N, 2) are finite and within MARGIN image sizes of the frame
    (so that they convert to the integers OpenCV draws with)."""
    lim = MARGIN * max(width, height)
    with np.errstate(invalid="ignore"):
        return np.isfinite(uv).all(-1) & (uv[:, 0] > -lim) & (uv[:, 0] < width + lim) & (uv[:, 1] > -lim) & (
            uv[:, 1] < height + lim)


def clip_segment(a: np.ndarray, b: np.ndarray, K: np.ndarray, width: int, height: int
                 ) -> tuple[tuple[int, int], tuple[int, int]] | None:
    """The image segment [px] of the camera-frame segment a-b (3,) [m]: cut at the near plane (z = NEAR),
    then to the frame (Liang-Barsky on a rectangle MARGIN image sizes wider); None when nothing is left
    or an end is not finite."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if not (np.isfinite(a).all() and np.isfinite(b).all()) or (a[2] < NEAR and b[2] < NEAR):
        return None
    if a[2] < NEAR or b[2] < NEAR:  # keep the part in front of the camera
        s = (NEAR - a[2]) / (b[2] - a[2])
        cut = a + s * (b - a)
        a, b = (cut, b) if a[2] < NEAR else (a, cut)
    ends = np.stack([a, b])
    p, q = ends[:, :2] / np.maximum(ends[:, 2:], NEAR) * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]
    lim = MARGIN * max(width, height)
    lo, hi = np.array([-lim, -lim]), np.array([width + lim, height + lim])
    d, t0, t1 = q - p, 0.0, 1.0
    for k in range(2):
        for num, den in ((p[k] - lo[k], -d[k]), (hi[k] - p[k], d[k])):
            if abs(den) < 1e-12:
                if num < 0:
                    return None
                continue
            t = num / den
            if den < 0:
                t0 = max(t0, t)
            else:
                t1 = min(t1, t)
    if t0 > t1:
        return None
    u, v = p + t0 * d, p + t1 * d
    return (int(round(u[0])), int(round(u[1]))), (int(round(v[0])), int(round(v[1])))


def draw_fit(
    frame: np.ndarray,
    *,
    K: np.ndarray,
    joints: np.ndarray,
    parents: np.ndarray,
    mask: np.ndarray | None = None,
    part_points: np.ndarray | None = None,
    part_labels: np.ndarray | None = None,
    landmarks: np.ndarray | None = None,
    names: tuple[str, ...] | None = None,
) -> np.ndarray:
    """One frame with the fit drawn over it.

    Points behind the camera, not finite or far outside the frame are skipped and segments are cut at the
    camera plane and the frame, so any fit (a body partly behind the camera, NaN joints) can be drawn.

    Args:
        frame: (H, W, 3) uint8.
        K: (3, 3) intrinsics [px].
        joints: (J, 3) fitted joints in the camera frame [m].
        parents: (J,) parent per joint (-1 root).
        mask: (H, W) bool mask tinted grey-blue, or None.
        part_points: (V, 3) posed body vertices in the camera frame [m], drawn as dots coloured by part.
        part_labels: (V,) part index of each vertex.
        landmarks: (L, 2) detected 2D landmarks [px], drawn as small white crosses.
        names: (J,) joint names: each bone is coloured by its child joint's side (:func:`side_of`) and a legend
            drawn; None = every bone white.

    Returns:
        (H, W, 3) uint8 picture.
    """
    import cv2

    h, w = frame.shape[:2]
    img = frame.astype(np.float64).copy()
    if mask is not None:
        img[mask] = 0.6 * img[mask] + 0.4 * np.array([80.0, 120.0, 255.0])
    img = np.ascontiguousarray(img.astype(np.uint8))
    scale = max(1, int(round(max(frame.shape[:2]) / 400)))
    if part_points is not None and part_labels is not None:
        uv = project(part_points, K)
        for (u, v), lab in zip(uv[drawable(uv, w, h)], np.asarray(part_labels)[drawable(uv, w, h)]):
            colour = tuple(int(c) for c in PART_COLOURS[int(lab) % len(PART_COLOURS)])
            cv2.circle(img, (int(round(u)), int(round(v))), max(1, scale // 2), colour, -1)
    joints = np.asarray(joints, dtype=np.float64)
    for j, p in enumerate(parents):
        seg = clip_segment(joints[p], joints[j], K, w, h) if p >= 0 else None
        if seg is not None:
            colour = SIDE_COLOURS[side_of(names[j]) if names is not None else "mid"]
            cv2.line(img, seg[0], seg[1], colour, 2 * scale)
    uvj = project(joints, K)
    for u, v in uvj[drawable(uvj, w, h)]:
        cv2.circle(img, (int(round(u)), int(round(v))), 2 * scale + 1, (255, 0, 0), -1)
    if landmarks is not None:
        lm = np.asarray(landmarks, dtype=np.float64)
        for u, v in lm[drawable(lm, w, h)]:
            cv2.drawMarker(img, (int(round(u)), int(round(v))), (0, 255, 0), cv2.MARKER_CROSS, 4 * scale + 2, scale)
    if names is not None:
        draw_side_legend(img, scale)
    return img


def contact_sheet(pictures: list[np.ndarray], *, columns: int = 4, width: int = 1600) -> np.ndarray:
    """Tile pictures of one size into a grid about ``width`` pixels wide (uint8)."""
    import cv2

    h, w = pictures[0].shape[:2]
    cols = min(columns, len(pictures))
    cell_w = width // cols
    cell_h = int(round(h * cell_w / w))
    rows = (len(pictures) + cols - 1) // cols
    sheet = np.zeros((rows * cell_h, cols * cell_w, 3), dtype=np.uint8)
    for i, pic in enumerate(pictures):
        r, c = divmod(i, cols)
        sheet[r * cell_h: (r + 1) * cell_h, c * cell_w: (c + 1) * cell_w] = cv2.resize(pic, (cell_w, cell_h))
    return sheet


def write_pictures(folder: Path, pictures: list[np.ndarray], fps: float, *, stem: str = "body_fit") -> list[Path]:
    """Write ``<stem>.png`` (a contact sheet of up to 8 evenly spaced frames) and ``<stem>.mp4`` (every frame)."""
    import imageio.v2 as imageio

    from sync4d.io.video import write_video

    folder.mkdir(parents=True, exist_ok=True)
    pick = np.unique(np.linspace(0, len(pictures) - 1, min(8, len(pictures))).round().astype(int))
    sheet = folder / f"{stem}.png"
    imageio.imwrite(sheet, contact_sheet([pictures[i] for i in pick]))
    movie = folder / f"{stem}.mp4"
    write_video(movie, np.stack(pictures), fps)
    return [sheet, movie]
