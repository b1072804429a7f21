"""What the front end leaves in a run: ``recon/masks.mp4`` (the masks over the video) and
``recon/camera.json`` (intrinsics, per-frame world-to-camera, how they were found)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from sync4d.geometry import rotation_angle_deg
from sync4d.types import Camera, VideoClip

MASK_TINT = np.array([255, 60, 60], dtype=np.float32)


def mask_overlay(frames: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """(T, H, W, 3) uint8: the frames dimmed outside the (T, H, W) masks, tinted inside, outlines drawn."""
    import cv2

    out = frames.astype(np.float32) * np.where(masks[..., None], 1.0, 0.4)
    out = np.where(masks[..., None], 0.75 * out + 0.25 * MASK_TINT, out).astype(np.uint8)
    for t, m in enumerate(masks):
        contours, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(out[t], contours, -1, tuple(int(c) for c in MASK_TINT), max(1, frames.shape[2] // 200))
    return out


def camera_record(clip: VideoClip, camera: Camera | None) -> dict[str, Any]:
    """``camera.json``: intrinsics [px], per-frame world-to-camera (when the front end found them: world =
    the first frame's camera turned to Y up, x right, z towards the viewer; translations in units of the
    background's median depth in the first frame), each frame's rotation from the first [deg], and whether
    the camera is still."""
    record: dict[str, Any] = {"known": camera is not None or clip.intrinsics is not None}
    K = camera.K if camera is not None else clip.intrinsics
    if K is not None:
        record["K"] = np.round(np.asarray(K), 4).tolist()
    if clip.extrinsics is not None:
        ext = np.asarray(clip.extrinsics)
        record["world_to_camera"] = np.round(ext, 6).tolist()
        record["rotation_from_first_deg"] = np.round(rotation_angle_deg(ext[:, :3, :3] @ ext[0, :3, :3].T), 3).tolist()
        record["static"] = bool(np.allclose(ext, ext[:1], atol=1e-9))
    elif camera is not None:
        record["world_to_camera"] = np.round(camera.world_to_cam, 6).tolist()
        record["static"] = True
    return record


def write_video_inputs(folder: Path, clip: VideoClip, camera: Camera | None) -> None:
    """Write ``masks.mp4`` (the masks over the video) and ``camera.json`` of a reference video into ``folder``."""
    from sync4d.io.atomic import atomic_write_json
    from sync4d.io.video import write_video

    folder.mkdir(parents=True, exist_ok=True)
    write_video(folder / "masks.mp4", mask_overlay(clip.frames, clip.masks), clip.fps)
    atomic_write_json(folder / "camera.json", camera_record(clip, camera))
