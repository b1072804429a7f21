"""The labels' ceiling: the exact truth rendered through ``recon=video``'s own representation.

The tracked frame-0 points get their exact part and depth, the parts their exact joints; the surfaces later
frames reveal are added by the method's own step (:func:`sync4d.recon.video.reveal.reveal`), the points
skinned and rendered as the method's are (Gaussians of half a grid spacing, front-to-back compositing).
What this scores is the best a method with this representation can reach; the part of the gap it leaves
is the representation's, not the fit's.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from sync4d.recon.video.images import backproject
from sync4d.recon.video import VideoFit
from sync4d.recon.video.joints import JointFit
from sync4d.recon.video.reconstructor import build_reference
from sync4d.recon.video.reveal import reveal
from sync4d.recon.video.stages import Tracks
from sync4d.types import Camera, Reference, VideoClip
from sync4d_tools.articulated.truth import CaseTruth, camera_at
from sync4d_tools.evaluate.recon_hinge import render_bone_labels


@dataclass(frozen=True)
class Splats:
    """What the label score renders (the fields of ``VideoFit`` it reads).

    Attributes:
        reference: the articulated reference (its part labels and bone motion).
        means: (N, 3) rest Gaussian centres [m]; sigma: (N,) sizes [m]; opacity: (N,).
        camera: the static camera (frame 0's when it moves); object_width: the object's width [m] (the soft
            z-buffer's scale).
        extrinsics: (T, 4, 4) world-to-camera of every frame when the camera moves, else None.
    """

    reference: Reference
    means: np.ndarray
    sigma: np.ndarray
    opacity: np.ndarray
    camera: Camera
    object_width: float
    extrinsics: np.ndarray | None = None


def frame_cameras(camera: Camera, extrinsics: np.ndarray | None) -> Camera | list[Camera]:
    """``camera`` when static (``extrinsics`` None), else each frame's: its intrinsics with the (T, 4, 4) poses."""
    if extrinsics is None:
        return camera
    return [replace(camera, world_to_cam=np.asarray(w, np.float64)) for w in extrinsics]


def rendered_labels(fit: Splats | VideoFit, gt_labels: np.ndarray) -> list[np.ndarray]:
    """Per frame, the bone rendered at each gt object pixel (in the order of ``np.nonzero``), seen through
    that frame's camera when it moves."""
    cameras = frame_cameras(fit.camera, fit.extrinsics)
    out = []
    for t in range(fit.reference.num_frames):
        pix = np.argwhere(gt_labels[t] > 0)[:, ::-1].astype(np.float64)
        out.append(render_bone_labels(fit.reference, fit.means, fit.sigma, fit.opacity, camera_at(cameras, t), t, pix,
                                      tau=0.02 * fit.object_width))
    return out


def exact_joint_fit(tracks: Tracks, truth: CaseTruth) -> JointFit:
    """The tracked frame-0 points with their exact parts (0 the base) and depths, and the exact joints."""
    uv = np.floor(tracks.uv0).astype(int)
    lab0, dep0 = truth.part_labels[0], truth.depth[0]
    on = (lab0 > 0) & (dep0 > 0)
    ov, ou = np.nonzero(on)
    near = cKDTree(np.stack([ou, ov], 1)).query(uv)[1]  # a point just off the truth's object: nearest object pixel
    labels = lab0[ov[near], ou[near]].astype(np.int64) - 1
    depth = dep0[ov[near], ou[near]].astype(np.float64)
    values = np.concatenate([np.zeros((len(truth.values), 1)), truth.values], 1)
    return JointFit(labels=labels, root=0, depth=depth, kinds=["root", *truth.kinds],
                    axes=np.concatenate([np.zeros((1, 3)), truth.axes]),
                    pivots=np.concatenate([np.zeros((1, 3)), truth.pivots]),
                    values=values, root_motion=np.tile(np.eye(4), (len(values), 1, 1)), data_loss=0.0)


def exact_splats(tracks: Tracks, masks: np.ndarray, truth: CaseTruth, clip: VideoClip, camera: Camera,
                 object_width: float, extrinsics: np.ndarray | None = None) -> Splats:
    """The exact truth in the method's representation (frame-0 points, revealed surfaces, Gaussian sizes);
    ``camera`` frame 0's, ``extrinsics`` (T, 4, 4) every frame's in the truth's world when the camera moves."""
    joints = exact_joint_fit(tracks, truth)
    means = backproject(tracks.uv0, joints.depth, camera)
    cameras = frame_cameras(camera, extrinsics)
    extra, extra_labels = reveal(means, joints.labels, joints.transforms(), masks, tracks, cameras)
    means, labels = np.concatenate([means, extra]), np.concatenate([joints.labels, extra_labels])
    ref = build_reference(joints, means, labels, clip, camera, "exact truth")
    depth = means @ camera.world_to_cam[2, :3] + camera.world_to_cam[2, 3]
    sigma = 0.5 * tracks.stride * depth / camera.K[0, 0]
    return Splats(reference=ref, means=means, sigma=sigma, opacity=np.full(len(means), 0.9), camera=camera,
                  object_width=object_width, extrinsics=extrinsics)
