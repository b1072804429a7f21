"""People: found by BlazePose's detector and landmark model, segmented by MediaPipe's person segmentation.

The models come from the mediapipe 0.10.14 wheel (Apache-2.0; ``make models`` extracts them into
``models/mediapipe``) and run under LiteRT. Each frame: the person's region (a rotated square) from the
previous frame's landmarks, or from the detector when lost; ``selfie_segmentation.tflite`` on that
256x256 crop; the probability mapped back to the image.
"""

from __future__ import annotations

import logging

import numpy as np

from typing import TYPE_CHECKING

from sync4d.errors import InputError

if TYPE_CHECKING:
    from sync4d.recon.pose.blazepose import Roi

log = logging.getLogger(__name__)

SEGMENTER_FILE = "selfie_segmentation.tflite"
SEGMENTER_SIZE = 256
#: a clip shows a person when the landmark model's median pose-presence score over a few sampled frames
#: reaches this (measured: people 0.97-1.0; a cat 0.0, a shiba 0.7-0.87, the bear no detection)
PERSON_PRESENCE = 0.9


class PersonModels:
    """The three LiteRT models, loaded once (a missing file stops with the command that extracts it)."""

    def __init__(self) -> None:
        from sync4d.recon.pose.blazepose import ssd_anchors
        from sync4d.recon.pose.models import DETECTOR_FILE, LANDMARK_FILE, TFLiteModel, model_path

        self.detector = TFLiteModel(model_path(DETECTOR_FILE))
        self.landmarks = TFLiteModel(model_path(LANDMARK_FILE))
        self.segmenter = TFLiteModel(model_path(SEGMENTER_FILE))
        self.anchors = ssd_anchors()


def person_roi(models: PersonModels, frame: np.ndarray, previous: Roi | None) -> tuple[Roi | None, float]:
    """The person's region in ``frame`` (tracked from ``previous`` or detected) and the pose presence."""
    from sync4d.recon.pose.blazepose import detect, landmarks_in_roi, roi_from_points

    for roi in (previous, None):
        if roi is None:
            roi = detect(models.detector, frame, models.anchors)
            if roi is None:
                return None, 0.0
        pose = landmarks_in_roi(models.landmarks, frame, roi, flip_test=False)
        if pose.presence >= 0.5:
            return roi_from_points(pose.aux[0], pose.aux[1]), float(pose.presence)
    return None, 0.0


def segment_in_roi(models: PersonModels, frame: np.ndarray, roi: Roi) -> np.ndarray:
    """(H, W) person probability in [0, 1]: the segmenter on the region's crop, mapped back to the image."""
    import cv2

    from sync4d.recon.pose.blazepose import crop, roi_affine

    img = crop(frame, roi, SEGMENTER_SIZE)
    out = models.segmenter.run(img[None].astype(np.float32) / 255.0)
    prob = next(iter(out.values())).reshape(SEGMENTER_SIZE, SEGMENTER_SIZE).astype(np.float32)
    h, w = frame.shape[:2]
    return cv2.warpAffine(prob, roi_affine(roi, SEGMENTER_SIZE), (w, h), flags=cv2.INTER_LINEAR,
                          borderValue=0.0)


def shows_person(models: PersonModels, frames: np.ndarray, samples: int = 5) -> bool:
    """True when the pose model's median presence over ``samples`` spread frames reaches ``PERSON_PRESENCE``."""
    picks = np.unique(np.linspace(0, len(frames) - 1, samples).round().astype(int))
    scores = [person_roi(models, frames[t], None)[1] for t in picks]
    log.info("frontend: pose presence in %d sampled frames %s", len(picks), np.round(scores, 2).tolist())
    return float(np.median(scores)) >= PERSON_PRESENCE


def person_masks(models: PersonModels, frames: np.ndarray, threshold: float, *, source: str) -> np.ndarray:
    """(T, H, W) bool person masks; frames where nobody is found get an empty mask.

    Raises:
        InputError: nobody in any frame.
    """
    masks = np.zeros(frames.shape[:3], bool)
    roi: Roi | None = None
    for t, frame in enumerate(frames):
        roi, _ = person_roi(models, frame, roi)
        if roi is not None:
            masks[t] = segment_in_roi(models, frame, roi) > threshold
    if not masks.any():
        raise InputError(f"{source}: no person found in any frame; use frontend.subject.method=motion or a prompt")
    return masks
