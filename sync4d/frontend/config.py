"""The front end's typed configuration: one block per stage (subject masks, camera), defaults here only."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from sync4d.errors import ConfigError


@dataclass
class SubjectConfig:
    """How the subject's masks are found.

    Attributes:
        method: ``auto`` (a person when the person segmenter finds one in most sampled frames, else the
            largest coherent thing moving against the camera-compensated background), ``motion``,
            ``person`` (the mediapipe selfie segmentation model) or ``prompt`` (``prompt`` is required; set
            automatically when a prompt is given).
        work_size: the long side [px] the masks are computed at (then scaled back to the video's size).
        motion_sigma: a pixel moves against the background when its camera-compensated residual flow
            exceeds this many robust standard deviations of the background's residual.
        min_motion_px: ... and at least this many pixels (at ``work_size``) per frame pair.
        min_area: a subject smaller than this fraction of the frame counts as no subject.
        grabcut_iters: GrabCut iterations per frame (colour graph cut refining the propagated mask).
        person_threshold: person probability above which a pixel is the person.
    """

    method: Literal["auto", "motion", "person", "prompt"] = "auto"
    work_size: int = 320
    motion_sigma: float = 4.0
    min_motion_px: float = 0.6
    min_area: float = 0.004
    grabcut_iters: int = 3
    person_threshold: float = 0.5


@dataclass
class CameraConfig:
    """How the camera is found.

    Attributes:
        fov_deg: field of view across the image's long side [deg] assumed when no intrinsics are given
            (a phone's main camera: about 65-70 deg on the long side).
        refine_focal: refine the focal length in the bundle adjustment when the camera moves enough.
        static_px: the camera is static when the background moves less than this [px at work size]
            in every frame (then every extrinsic is the identity).
        features: background corners tracked per frame.
        bundle_iters: function evaluations of the bundle adjustment (0 = none).
    """

    fov_deg: float = 66.0
    refine_focal: bool = True
    static_px: float = 0.35
    features: int = 400
    bundle_iters: int = 60


@dataclass
class FrontEndConfig:
    """The video front end: ``subject`` (masks) and ``camera`` blocks (:class:`SubjectConfig`,
    :class:`CameraConfig`)."""

    subject: SubjectConfig = field(default_factory=SubjectConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)

    def validate(self) -> FrontEndConfig:
        s, c = self.subject, self.camera
        if s.work_size < 32:
            raise ConfigError(f"frontend.subject.work_size={s.work_size}: needs at least 32 px")
        if not 0.0 < s.min_area < 1.0 or not 0.0 < s.person_threshold < 1.0:
            raise ConfigError("frontend.subject: min_area and person_threshold must be in (0, 1)")
        if s.motion_sigma <= 0 or s.min_motion_px < 0 or s.grabcut_iters < 0:
            raise ConfigError("frontend.subject: motion_sigma > 0, min_motion_px >= 0, grabcut_iters >= 0 needed")
        if not 5.0 <= c.fov_deg <= 170.0:
            raise ConfigError(f"frontend.camera.fov_deg={c.fov_deg}: needs a field of view in [5, 170] deg")
        if c.static_px < 0 or c.features < 20 or c.bundle_iters < 0:
            raise ConfigError("frontend.camera: static_px >= 0, features >= 20, bundle_iters >= 0 needed")
        return self
