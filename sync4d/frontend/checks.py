"""Refusals of input the front end cannot turn into a subject and a camera: one line naming the input and
the fix, raised before the expensive work (reconstruction) starts."""

from __future__ import annotations

import numpy as np

from sync4d.errors import InputError

MIN_FRAMES = 3
#: every frame within this many grey levels (mean absolute difference) of the first: a still image
STILL_LEVELS = 0.5
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


def check_subject(masks: np.ndarray, *, min_area: float, source: str) -> None:
    """Refuse masks with no subject, or a subject that leaves the frame: its mask (nearly) empty in some
    frame while it fills others, or shrunk and on the frame's border (a subject only cut by the border, feet or
    a tail, still counts as in view, and so does one shrunk inside the frame).

    Raises:
        InputError: naming the video and the frames.
    """
    n_frames = len(masks)
    area = masks.reshape(n_frames, -1).mean(axis=1)
    if float(area.max()) < min_area:
        raise InputError(f"{source}: no subject found (nothing moves against the background); film a moving "
                         "subject, or point at it: reference.prompt=[x, y] or [x0, y0, x1, y1]")
    typical = float(np.median(area[area >= min_area]))
    on_border = masks[:, 0].any(1) | masks[:, -1].any(1) | masks[:, :, 0].any(1) | masks[:, :, -1].any(1)
    gone = np.flatnonzero((area < GONE_SHARE * typical) & ((area < min_area) | on_border))
    if len(gone):
        raise InputError(f"{source}: the subject leaves the frame (frames {summary(gone)}); trim the clip with "
                         "reference.max_frames / reference.stride to where it stays in view")


def summary(indices: np.ndarray) -> str:
    """'3, 4, 5' or '3..17 (15 frames)' for a list of frame indices."""
    if len(indices) <= 5:
        return ", ".join(str(int(i)) for i in indices)
    return f"{int(indices[0])}..{int(indices[-1])} ({len(indices)} frames)"
