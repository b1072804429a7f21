"""Pictures of a body fit over its video frames: mask tint, parts, skeleton and landmarks."""

from __future__ import annotations

from pathlib import Path

import numpy as np

PART_COLOURS = np.array(
    [[230, 25, 75], [60, 180, 75], [255, 225, 25], [0, 130, 200], [245, 130, 48], [145, 30, 180], [70, 240, 240],
     [240, 50, 230], [210, 245, 60], [250, 190, 212], [0, 128, 128], [220, 190, 255], [170, 110, 40],
     [255, 250, 200], [128, 0, 0], [170, 255, 195]], dtype=np.float64)


def project(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(..., 3) camera-frame points [m] -> (..., 2) pixels."""
    z = np.maximum(points[..., 2:3], 1e-6)
    return points[..., :2] / z * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]


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
) -> np.ndarray:
    """One frame with the fit drawn over it.

    Args:
        frame: (H, W, 3) uint8.
        K: (3, 3) intrinsics [px].
        joints: (J, 3) fitted joints in the camera frame [m].
        parents: (J,) parent per joint (-1 root).
        mask: (H, W) bool mask tinted grey-blue, or None.
        part_points: (V, 3) posed body vertices in the camera frame [m], drawn as dots coloured by part.
        part_labels: (V,) part index of each vertex.
        landmarks: (L, 2) detected 2D landmarks [px], drawn as small white crosses.

    Returns:
        (H, W, 3) uint8 picture.
    """
    import cv2

    img = frame.astype(np.float64).copy()
    if mask is not None:
        img[mask] = 0.6 * img[mask] + 0.4 * np.array([80.0, 120.0, 255.0])
    img = img.astype(np.uint8)
    scale = max(1, int(round(max(frame.shape[:2]) / 400)))
    if part_points is not None and part_labels is not None:
        uv = project(part_points, K)
        for (u, v), lab in zip(uv, part_labels):
            colour = tuple(int(c) for c in PART_COLOURS[lab % len(PART_COLOURS)])
            cv2.circle(img, (int(u), int(v)), scale, colour, -1)
    uvj = project(joints, K)
    for j, p in enumerate(parents):
        if p >= 0:
            cv2.line(img, tuple(int(a) for a in uvj[p]), tuple(int(a) for a in uvj[j]), (255, 255, 255), 2 * scale)
    for u, v in uvj:
        cv2.circle(img, (int(u), int(v)), 2 * scale + 1, (255, 0, 0), -1)
    if landmarks is not None:
        for u, v in landmarks:
            cv2.drawMarker(img, (int(u), int(v)), (0, 255, 0), cv2.MARKER_CROSS, 4 * scale + 2, scale)
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
