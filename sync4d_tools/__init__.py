"""Evaluation, reporting and benchmark tools around the sync4d library (which never imports them)."""

from __future__ import annotations

from sync4d.errors import InputError
from sync4d.types import Camera, ReferenceInput, VideoClip


def video_of(source: ReferenceInput) -> VideoClip:
    """The video of a reference source that must have one (a video source's), else one line naming it."""
    if source.video is None:
        raise InputError(f"reference '{source.name}': has no video; this tool needs one")
    return source.video


def camera_of(source: ReferenceInput) -> Camera:
    """The camera of a reference source that must have one (a render with its camera), else one line naming it."""
    if source.camera is None:
        raise InputError(f"reference '{source.name}': has no camera; give the video's camera (camera.npz or gt.npz)")
    return source.camera
