"""Refusals of input the front end cannot turn into a subject and a camera: one line naming the input and
the fix, raised before the expensive work (reconstruction) starts."""

from __future__ import annotations

import numpy as np

from sync4d.errors import InputError

MIN_FRAMES = 3
#: every frame within this many grey levels (mean absolute difference) of the first: a still image
STILL_LEVELS = 0.5
#: at most this many frames in a row lost between frames that hold the subject are a detector's miss, not a
#: subject that left: they take the nearest held frame's mask (:func:`bridge_dropouts`)
MAX_DROPOUT = 2
#: a frame whose subject is smaller than this share of its typical area has lost it (it left the frame) when
#: what is left of it is nothing or touches the frame's border; a subject shrinking inside the frame (a lid turned
#: edge-on, a part that stopped moving) is still in view
GONE_SHARE = 0.25


def check_clip(frames: np.ndarray, source: str) -> None:
    """Refuse a clip shorter than ``MIN_FRAMES`` frames or one whose frames are all the same (a still image).

    Raises:
        InputError: naming the video and the fix.
    """
    if len(frames) < MIN_FRAMES:
        raise InputError(f"{source}: {len(frames)} frame(s); the video front end needs at least {MIN_FRAMES} "
                         "frames of a moving subject (check reference.max_frames / reference.stride)")
    first = frames[0].astype(np.int16)
    if all(float(np.abs(f.astype(np.int16) - first).mean()) < STILL_LEVELS for f in frames[1:]):
        raise InputError(f"{source}: every frame is the same (a still image); the reference must be a video "
                         "of a moving subject")


def check_prompt(prompt: tuple[float, ...], frame: int, width: int, height: int, n_frames: int) -> None:
    """Refuse a prompt that is neither a point (x, y) nor a box (x0, y0, x1, y1) inside the image [px], or a
    prompt frame outside the clip.

    Raises:
        InputError: naming ``reference.prompt``.
    """
    if len(prompt) not in (2, 4) or not np.all(np.isfinite(prompt)):
        raise InputError(f"reference.prompt={list(prompt)}: give a point [x, y] or a box [x0, y0, x1, y1] in pixels")
    xs, ys = np.asarray(prompt[0::2]), np.asarray(prompt[1::2])
    if xs.min() < 0 or ys.min() < 0 or xs.max() > width or ys.max() > height:
        raise InputError(f"reference.prompt={list(prompt)}: outside the {width}x{height} image; give pixel "
                         f"coordinates with 0 <= x <= {width} and 0 <= y <= {height}")
    if len(prompt) == 4 and (prompt[2] - prompt[0] < 2 or prompt[3] - prompt[1] < 2):
        raise InputError(f"reference.prompt={list(prompt)}: a box needs x1 > x0 and y1 > y0 (at least 2 px)")
    if not 0 <= frame < n_frames:
        raise InputError(f"reference.prompt_frame={frame}: the clip has frames 0..{n_frames - 1}")


def lost_frames(masks: np.ndarray, min_area: float) -> np.ndarray:
    """(T,) bool: frames whose subject is lost: its mask (nearly) empty, or under ``GONE_SHARE`` of its typical
    area and on the frame's border (all False when no frame holds a subject)."""
    area = masks.reshape(len(masks), -1).mean(axis=1)
    if float(area.max()) < min_area:
        return np.zeros(len(masks), bool)
    typical = float(np.median(area[area >= min_area]))
    on_border = masks[:, 0].any(1) | masks[:, -1].any(1) | masks[:, :, 0].any(1) | masks[:, :, -1].any(1)
    return (area < GONE_SHARE * typical) & ((area < min_area) | on_border)


def bridge_dropouts(masks: np.ndarray, min_area: float) -> np.ndarray:
    """``masks`` (T, H, W) bool with every run of at most ``MAX_DROPOUT`` lost frames (:func:`lost_frames`) that
    has held frames on both sides given the nearest held frame's mask (the earlier one on a tie)."""
    lost = lost_frames(masks, min_area)
    out = masks.copy()
    t = 0
    while t < len(masks):
        if not lost[t]:
            t += 1
            continue
        end = t
        while end < len(masks) and lost[end]:
            end += 1
        if t > 0 and end < len(masks) and end - t <= MAX_DROPOUT:
            for s in range(t, end):
                out[s] = masks[t - 1] if s - (t - 1) <= end - s else masks[end]
        t = end
    return out


def check_subject(masks: np.ndarray, *, min_area: float, source: str) -> None:
    """Refuse masks with no subject, or a subject that leaves the frame: its mask (nearly) empty in some
    frame while it fills others, or shrunk and on the frame's border (a subject only cut by the border, feet or
    a tail, still counts as in view, and so does one shrunk inside the frame).

    Raises:
        InputError: naming the video and the frames.
    """
    area = masks.reshape(len(masks), -1).mean(axis=1)
    if float(area.max()) < min_area:
        raise InputError(f"{source}: no subject found (nothing moves against the background); film a moving "
                         "subject, or point at it: reference.prompt=[x, y] or [x0, y0, x1, y1]")
    gone = np.flatnonzero(lost_frames(masks, min_area))
    if len(gone):
        raise InputError(f"{source}: the subject leaves the frame (frames {summary(gone)}); trim the clip with "
                         "reference.max_frames / reference.stride to where it stays in view")


def summary(indices: np.ndarray) -> str:
    """'3, 4, 5' or '3..17 (15 frames)' for a list of frame indices."""
    if len(indices) <= 5:
        return ", ".join(str(int(i)) for i in indices)
    return f"{int(indices[0])}..{int(indices[-1])} ({len(indices)} frames)"
