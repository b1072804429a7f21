"""``run_front_end``: a video in, the subject's masks and the camera out (a filled :class:`VideoClip`).

Order: the clip is checked (length, still image, prompt); frames are scaled to ``work_size``; background
corners are tracked; the subject is found (a person, what moves, or the prompt) and followed; the camera
is solved from the tracks off the subject; under a moving camera, a subject found by its motion is joined by
its never-moving parts too low for parallax (:mod:`~sync4d.frontend.sweep`); masks and intrinsics are scaled
back to the video's size.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

import numpy as np

from sync4d.errors import InputError
from sync4d.frontend.camera import CameraFit, background_only, solve_camera, static_camera
from sync4d.frontend.checks import bridge_dropouts, check_clip, check_prompt, check_subject
from sync4d.frontend.config import FrontEndConfig, SubjectConfig
from sync4d.frontend.geometry import ground_up, intrinsics_from_fov
from sync4d.frontend.motion import motion_evidence, picture_explained
from sync4d.frontend.parallax import join_static_parts
from sync4d.frontend.segment import (
    box_grabcut, drop_plate, follow, grabcut, largest_component, seed_from_motion, seed_from_prompt,
)
from sync4d.frontend.sweep import join_raised_parts
from sync4d.frontend.tracks import Tracks, track_corners
from sync4d.types import Camera, VideoClip

log = logging.getLogger(__name__)

#: the front end's world: the first frame's camera axes turned half a turn about x (x right, y up, z towards
#: the viewer), so an upright phone's world is Y up like the project's scenes (its own inverse)
CAMERA_TO_YUP = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class Prompt:
    """Where the subject is: a point (x, y) or a box (x0, y0, x1, y1) [px of the video] on frame ``frame``."""

    values: tuple[float, ...]
    frame: int = 0


@dataclass(frozen=True)
class FrontEndResult:
    """What the front end found.

    Attributes:
        clip: the input clip with ``masks`` (T, H, W) bool, ``intrinsics`` (3, 3) [px] and ``extrinsics``
            (T, 4, 4) world-to-camera filled in (world = frame 0's camera turned to Y up,
            :data:`CAMERA_TO_YUP`; translations in units of the background's median depth in frame 0).
        camera: the camera fit (mode, focal source, reprojection error) at the video's size.
        subject: how the masks were found: ``given``, ``person``, ``motion`` or ``prompt``.
        masks_given, camera_given: whether the input already had them (then they are kept as given).
        cpu_seconds: CPU time of the front end [s].
        up: (3,) the ground's normal in the world (:func:`~sync4d.frontend.geometry.ground_up` of the
            background points, a moving camera only), or None.
    """

    clip: VideoClip
    camera: CameraFit
    subject: str
    masks_given: bool
    camera_given: bool
    cpu_seconds: float
    up: np.ndarray | None = None


def scale_to(frames: np.ndarray, size: int) -> tuple[np.ndarray, float]:
    """Frames (T, H, W, 3) resized so their long side is at most ``size`` [px], and the factor used (<= 1)."""
    import cv2

    h, w = frames.shape[1:3]
    factor = min(1.0, size / max(h, w))
    if factor == 1.0:
        return frames, 1.0
    dims = (max(1, round(w * factor)), max(1, round(h * factor)))
    return np.stack([cv2.resize(f, dims, interpolation=cv2.INTER_AREA) for f in frames]), factor


def resize_masks(masks: np.ndarray, height: int, width: int) -> np.ndarray:
    """(T, h, w) bool masks resized to (T, height, width) (bilinear, then > 0.5)."""
    import cv2

    if masks.shape[1:] == (height, width):
        return masks
    return np.stack([cv2.resize(m.astype(np.float32), (width, height), interpolation=cv2.INTER_LINEAR) > 0.5
                     for m in masks])


def choose_method(config: SubjectConfig, prompt: Prompt | None, frames: np.ndarray) -> str:
    """``prompt`` when a prompt is given, else the configured method; ``auto`` asks the pose model."""
    if prompt is not None:
        return "prompt"
    if config.method == "prompt":
        raise InputError("frontend.subject.method=prompt needs reference.prompt=[x, y] or [x0, y0, x1, y1]")
    if config.method != "auto":
        return config.method
    from sync4d.frontend.person import PersonModels, shows_person

    return "person" if shows_person(PersonModels(), frames) else "motion"


def subject_masks(work: np.ndarray, grey: np.ndarray, method: str, config: SubjectConfig, *, static: bool,
                  prompt: Prompt | None, factor: float, source: str) -> np.ndarray:
    """(T, h, w) bool masks at work size by ``method`` (``person``, ``motion`` or ``prompt``)."""
    if method == "person":
        from sync4d.frontend.person import PersonModels, person_masks

        return np.stack([largest_component(m) for m in
                         person_masks(PersonModels(), work, config.person_threshold, source=source)])
    evidence = motion_evidence(grey, static=static, sigma=config.motion_sigma, min_px=config.min_motion_px)
    # the floor beside a moving subject: its flow is dragged along, its picture is the floor's a few frames away
    pictured = picture_explained(work, grey, static=static)
    evidence = replace(evidence, explained=pictured if evidence.explained is None else evidence.explained | pictured)
    moving, flows = evidence.moving, evidence.flows
    h, w = grey.shape[1:]
    if method == "prompt":
        assert prompt is not None
        start = prompt.frame
        values = np.asarray(prompt.values) * factor
        prior = seed_from_prompt(values, moving[start], work[start])
        if len(values) == 4:  # GrabCut's own start: outside the box background, inside undecided
            first = largest_component(box_grabcut(work[start], prior, max(config.grabcut_iters, 1)))
        else:  # the pixels next to the point are the subject
            sure = np.zeros((h, w), bool)
            x, y = int(min(values[0], w - 1)), int(min(values[1], h - 1))
            sure[max(y - 2, 0): y + 3, max(x - 2, 0): x + 3] = True
            first = largest_component(grabcut(work[start], prior, sure=sure, iterations=max(config.grabcut_iters, 1)))
    else:
        seed = seed_from_motion(moving, flows, config.min_area * h * w)
        if seed is None:
            raise InputError(f"{source}: no subject found (nothing moves against the background); film a moving "
                             "subject, or point at it: reference.prompt=[x, y] or [x0, y0, x1, y1]")
        start, region = seed
        # no sure core: the moving region is blurred by the flow beyond the subject; colour decides within it
        first = largest_component(grabcut(work[start], region, sure=np.zeros_like(region),
                                          iterations=max(config.grabcut_iters, 1)))
    log.info("frontend: subject seeded in frame %d (%d px at work size)", start, int(first.sum()))
    masks = follow(work, start, first, evidence, config.grabcut_iters, reveal=not static)
    if static:  # a subject found by its motion under a static camera: what shows the background plate is floor
        return drop_plate(work, masks) if method == "motion" else masks
    # a moving camera: the subject's parts that never move stand off the room's planes (parallax)
    return join_static_parts(work, grey, masks, flows, config.grabcut_iters) if method == "motion" else masks


def solved_camera(tracks: Tracks, masks: np.ndarray, K: np.ndarray, config: FrontEndConfig, focal_given: bool
                  ) -> CameraFit:
    """The camera solved from the ``tracks`` off the subject's ``masks`` (T, h, w) bool, from intrinsics ``K``
    (3, 3) [px at work size], in the front end's world (the first camera turned to Y up)."""
    fit = solve_camera(background_only(tracks, masks), K, config.camera, focal_given=focal_given)
    return replace(fit, extrinsics=fit.extrinsics @ CAMERA_TO_YUP, background_points=fit.background_points * [1, -1, -1])


def run_front_end(clip: VideoClip, config: FrontEndConfig, *, prompt: Prompt | None = None, masks_given: bool = False,
                  camera_given: bool = False) -> FrontEndResult:
    """The subject's masks and the camera of ``clip`` (see the module docstring).

    Args:
        clip: the video; its masks are used when ``masks_given``, its intrinsics when not None, its
            extrinsics when ``camera_given``.
        config: the front end's options.
        prompt: where the subject is, when the clip is ambiguous.

    Raises:
        InputError: too short, a still image, a prompt outside the image, no subject, a subject leaving
            the frame.
    """
    import cv2

    cpu = time.process_time()
    config.validate()
    cv2.setRNGSeed(0)  # GrabCut's k-means draws from OpenCV's global generator: the same clip, the same masks
    n_frames, height, width = clip.frames.shape[:3]
    check_clip(clip.frames, clip.source)
    if prompt is not None:
        check_prompt(prompt.values, prompt.frame, width, height, n_frames)
    work, factor = scale_to(clip.frames, config.subject.work_size)
    grey = np.stack([np.asarray(f.mean(axis=2), np.uint8) for f in work])
    focal_given = clip.intrinsics is not None
    K = np.asarray(clip.intrinsics, np.float64) if focal_given else intrinsics_from_fov(width, height, config.camera.fov_deg)
    K_work = np.diag([factor, factor, 1.0]) @ K
    tracks = track_corners(grey, config.camera.features)
    if masks_given:
        masks_work, method = resize_masks(clip.masks, *grey.shape[1:]), "given"
    else:
        method = choose_method(config.subject, prompt, work)
        masks_work = subject_masks(work, grey, method, config.subject, static=static_camera(tracks, config.camera.static_px),
                                   prompt=prompt, factor=factor, source=clip.source)
        masks_work = bridge_dropouts(masks_work, config.subject.min_area)  # a frame the detector missed
        check_subject(masks_work, min_area=config.subject.min_area, source=clip.source)
    if camera_given and clip.extrinsics is not None:
        fit = CameraFit(K_work, np.asarray(clip.extrinsics, np.float64), False, "given", "given", 0.0, np.zeros((0, 3)))
    else:
        fit = solved_camera(tracks, masks_work, K_work, config, focal_given)
        if method == "motion" and fit.mode == "full":  # parts too low for parallax: a sweep over the clip
            masks_work = join_raised_parts(work, grey, masks_work, fit.K, fit.extrinsics, fit.background_points,
                                           config.subject.grabcut_iters)
    K_full = np.diag([1.0 / factor, 1.0 / factor, 1.0]) @ fit.K
    fit = replace(fit, K=K_full)
    masks = clip.masks if masks_given else resize_masks(masks_work, height, width)
    out = replace(clip, masks=np.ascontiguousarray(masks), intrinsics=K_full, extrinsics=fit.extrinsics).validate()
    seconds = time.process_time() - cpu
    log.info("frontend: %s masks, camera %s (focal %s, %.1f px), %.1f s CPU", method, fit.mode, fit.focal_source,
             K_full[0, 0], seconds)
    up = ground_up(fit.background_points, np.array([0.0, 1.0, 0.0])) if len(fit.background_points) else None
    return FrontEndResult(out, fit, method, masks_given, camera_given, seconds, up)


def complete_video(clip: VideoClip, camera: Camera | None, config: FrontEndConfig, *, masks_given: bool,
                   prompt: Prompt | None = None) -> tuple[VideoClip, Camera]:
    """A reference video with whatever it lacks found by the front end: masks when not ``masks_given``, the
    camera when ``camera`` is None. Returns the clip (masks, intrinsics, per-frame extrinsics) and the
    first frame's :class:`Camera` (the one a static-camera reconstructor uses)."""
    clip, camera, _ = complete_video_up(clip, camera, config, masks_given=masks_given, prompt=prompt)
    return clip, camera


def complete_video_up(clip: VideoClip, camera: Camera | None, config: FrontEndConfig, *, masks_given: bool,
                      prompt: Prompt | None = None) -> tuple[VideoClip, Camera, np.ndarray | None]:
    """:func:`complete_video`, and the ground's normal in the found camera's world when the front end found
    one (:attr:`FrontEndResult.up`), else None."""
    if masks_given and camera is not None:
        return clip, camera, None
    given = clip
    if camera is not None:
        moving = clip.extrinsics is not None  # a given camera's per-frame poses are kept
        given = replace(clip, intrinsics=camera.K, extrinsics=clip.extrinsics if moving else
                        np.tile(camera.world_to_cam, (clip.num_frames, 1, 1)))
    found = run_front_end(given, config, prompt=prompt, masks_given=masks_given, camera_given=camera is not None)
    out = found.clip
    assert out.extrinsics is not None  # run_front_end always fills the camera
    first = camera if camera is not None else Camera(K=np.asarray(out.intrinsics), world_to_cam=out.extrinsics[0],
                                                     width=out.frames.shape[2], height=out.frames.shape[1]).validate()
    return out, first, found.up if camera is None else None
