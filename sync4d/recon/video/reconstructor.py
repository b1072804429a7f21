"""``recon=video``: an articulated object from a monocular video with a static camera, on the CPU.

Stages (each a module with its own config block, results passed as dataclasses):
    1. masks (:func:`~sync4d.recon.video.stages.video_masks`): the input's, or a median background model;
    2. flow and tracks (:func:`~sync4d.recon.video.stages.track_grid`): a grid of frame-0 mask pixels
       chained through dense optical flow, trusted while forward-backward consistent and inside the masks,
       verified while their patch still matches frame 0's (the fit uses only verified tracks);
    3. initialisation (:func:`~sync4d.recon.video.stages.init_parts`): parts by clustering position and
       track displacement, refined by affine motion; the root is the part that moves least;
    4. silhouette and joint fit (:func:`~sync4d.recon.video.joints.fit_joints`): depths, one hinge or slide
       per moving part and its value per frame, against tracks and masks; joint kinds chosen by the data; each
       hinge judged against its depth reversal, then every joint fitted to the part's freely recovered
       motion over the whole clip (kind by evidence) and the part re-posed on it;
    5. skinning (:func:`build_reference`): the points as the canonical shape (frame 0's pose), each
       skinned to its part, bones at the parts' centroids, bone motion from the joints.

Only the surface the first frame sees is reconstructed. The monocular scale is fixed by the depth of the
world origin (a known camera) or 1 m.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from scipy.spatial import cKDTree

from sync4d.errors import ConfigError, InputError
from sync4d.forked import cpu_seconds
from sync4d.recon.video.images import (
    camera_moves, default_camera, pnp_transforms, sample_image, static_depths,
)
from sync4d.recon.video.joints import FitConfig, JointFit, fit_joints, make_scene
from sync4d.recon.video.reveal import reveal
from sync4d.recon.video.softsplat import project_points
from sync4d.recon.video.stages import (
    InitConfig, MaskConfig, PartInit, TrackConfig, Tracks, init_parts, reference_depth, track_grid, video_masks,
)
from sync4d.registry import register
from sync4d.types import Camera, Reference, ReferenceInput, VideoClip

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class VideoFit:
    """Everything ``recon=video`` found, for evaluation (no side channels).

    Attributes:
        reference: the articulated reference.
        camera: the camera used (given, or a default one).
        masks: (T, H, W) bool masks used.
        tracks: the tracked points; init: the first labels; joints: the fitted articulation.
        means: (N, 3) canonical Gaussian centres [m] (= reference.rest_vertices).
        sigma: (N,) isotropic Gaussian sizes [m]; opacity: (N,) in (0, 1).
        object_width: the object's width in frame 0 [m].
        extrinsics: (T, 4, 4) world-to-camera of every frame when the camera moves, else None (``camera``
            is then frame 0's).
        seconds: wall time of the reconstruction [s].
        cpu_seconds: CPU time of this process during it [s] (the wall time of an idle machine, as the fit
            runs on one thread; on a shared machine the wall time is longer).
    """

    reference: Reference
    camera: Camera
    masks: np.ndarray
    tracks: Tracks
    init: PartInit
    joints: JointFit
    means: np.ndarray
    sigma: np.ndarray
    opacity: np.ndarray
    object_width: float
    seconds: float
    cpu_seconds: float
    extrinsics: np.ndarray | None = None


@register("recon", "video")
class VideoReconstructor:
    """Fit parts on 1-DoF joints (hinges and slides) to ``ReferenceInput.video`` (static camera)."""

    @dataclass
    class Config:
        """``recon=video`` options.

        Attributes:
            bones: number of parts B (>= 1), the root (base) included.
            seed: seed of the generator that samples the mask pixels of the cover term (the only random choice).
            opacity: opacity of the output Gaussians.
            masks, tracks, init, fit: the stages' blocks (:class:`MaskConfig`, :class:`TrackConfig`,
                :class:`InitConfig`, :class:`FitConfig`).
        """

        bones: int = 2
        seed: int = 0
        opacity: float = 0.9
        masks: MaskConfig = field(default_factory=MaskConfig)
        tracks: TrackConfig = field(default_factory=TrackConfig)
        init: InitConfig = field(default_factory=InitConfig)
        fit: FitConfig = field(default_factory=FitConfig)

        def validate(self) -> None:
            if isinstance(self.bones, bool) or not isinstance(self.bones, int) or self.bones < 1:
                raise ConfigError(f"recon.bones={self.bones!r}: needs a positive integer (parts, the base included)")
            if self.tracks.points < 4 * self.bones:
                raise ConfigError(f"recon.tracks.points={self.tracks.points}: needs at least 4 x recon.bones")
            if self.fit.steps < 3 or self.fit.axis_starts < 1 or self.fit.relabel_rounds < 0:
                raise ConfigError(f"recon.fit: steps={self.fit.steps} >= 3, axis_starts={self.fit.axis_starts} >= 1 "
                                  f"and relabel_rounds={self.fit.relabel_rounds} >= 0 needed")
            if self.fit.workers < 0:
                raise ConfigError(f"recon.fit.workers={self.fit.workers}: needs >= 0 (0: one per core, 1: no processes)")
            if not -1.0 <= self.tracks.patch_ncc <= 1.0:
                raise ConfigError(f"recon.tracks.patch_ncc={self.tracks.patch_ncc}: a correlation, needs -1 <= patch_ncc <= 1")
            if not 0.0 < self.opacity < 1.0:
                raise ConfigError(f"recon.opacity={self.opacity}: needs 0 < opacity < 1")

    def __init__(self, config: Config, *, device: str = "cpu") -> None:
        config.validate()
        self.config = config
        self.device = device  # the fit is sized for the CPU

    def reconstruct(self, source: ReferenceInput) -> Reference:
        """The articulated reference fitted to the video of ``source``."""
        return self.reconstruct_detailed(source).reference

    def reconstruct_detailed(self, source: ReferenceInput) -> VideoFit:
        """Run every stage on the video of ``source``; returns the reference and the stages' results."""
        if source.video is None:
            raise InputError(f"recon=video (the default reconstructor) needs a video, but reference '{source.name}' has "
                             "none; use reference=video (or reference.video=true on the laptop), or pick the "
                             "reconstructor for this input: recon=mocap, recon=lab4d, recon=skinning_fit or "
                             "recon=ground_truth")
        clip = source.video.validate()
        if clip.num_frames < 2:
            raise InputError(f"recon=video: '{clip.source}' has {clip.num_frames} frame; need at least 2")
        config = self.config
        start, cpu_start = time.perf_counter(), cpu_seconds()
        rng = np.random.default_rng(config.seed)
        extrinsics = np.array(clip.extrinsics, np.float64) if camera_moves(clip.extrinsics) else None
        camera = source.camera if source.camera is not None else default_camera(clip, config.init.fov_deg)
        if extrinsics is not None:  # frame 0's pose of the moving camera
            camera = Camera(K=camera.K, world_to_cam=np.asarray(extrinsics[0], np.float64), width=camera.width,
                            height=camera.height).validate()
        if source.world_up is not None:  # the reference comes out Y up (matching and the target assume it)
            upright = np.linalg.inv(upright_frame(source.world_up))
            camera = replace(camera, world_to_cam=camera.world_to_cam @ upright)
            extrinsics = None if extrinsics is None else extrinsics @ upright
        masks = video_masks(clip, config.masks)
        tracks = track_grid(clip.frames, masks, config.tracks)
        if extrinsics is None:
            init = init_parts(tracks, config.bones, config.init, static_px=config.fit.static_root_px)
            z_ref, depth0 = reference_depth(camera), None
            root_motion = self._root_motion(tracks, init, camera, z_ref)
        else:
            init, z_ref, depth0 = self._moving_camera_init(tracks, camera, extrinsics)
            root_motion = np.tile(np.eye(4), (clip.num_frames, 1, 1))
        log.info("recon=video: %d points (stride %d px), root part %d %s (median motion %s px), camera %s",
                 len(tracks.uv0), tracks.stride, init.root, "static" if init.root_static else "moving",
                 np.round(init.motion_px, 2), "moving" if extrinsics is not None else "static")
        # the reference is Y up when the world's up is known (above): joints near level or vertical are tried there
        up = np.array([0.0, 1.0, 0.0]) if source.world_up is not None else None
        scene = make_scene(tracks, masks, camera, init, z_ref, root_motion, rng, extrinsics=extrinsics, depth0=depth0,
                           up=up)
        threads = torch.get_num_threads()
        # the fit's tensors are small: one thread is several times faster than two fighting for a shared
        # CPU (measured 6.7 s vs 90 s for the same short fit on this machine under load)
        torch.set_num_threads(1)
        try:
            joints = fit_joints(scene, tracks, init, config.fit)
        finally:
            torch.set_num_threads(threads)
        log.info("recon=video: joints %s, data loss %.4f", joints.kinds, joints.data_loss)
        means = scene.centre.numpy() + joints.depth[:, None] * scene.rays.numpy()
        cameras = camera if extrinsics is None else [Camera(K=camera.K, world_to_cam=w, width=camera.width,
                                                             height=camera.height) for w in extrinsics]
        extra, extra_labels = reveal(means, joints.labels, joints.transforms(), masks, tracks, cameras)
        log.info("recon=video: %d points added for surfaces the first frame does not see", len(extra))
        means, labels = np.concatenate([means, extra]), np.concatenate([joints.labels, extra_labels])
        depth = means @ camera.world_to_cam[2, :3] + camera.world_to_cam[2, 3]
        # half the grid spacing: neighbouring Gaussians still overlap, and a part's splats bleed less over
        # its neighbour (exact frame-0 surface, suite clips: label score +0.01 to +0.03)
        sigma = 0.5 * tracks.stride * depth / camera.K[0, 0]
        ref = build_reference(joints, means, labels, clip, camera, source.name)
        seconds, cpu = time.perf_counter() - start, cpu_seconds() - cpu_start
        log.info("recon=video: %d frames reconstructed in %.1f s (%.1f s CPU)", clip.num_frames, seconds, cpu)
        return VideoFit(reference=ref, camera=camera, masks=masks, tracks=tracks, init=init, joints=joints,
                        means=means, sigma=sigma, opacity=np.full(len(means), config.opacity),
                        object_width=scene.width, seconds=seconds, cpu_seconds=cpu, extrinsics=extrinsics)

    def _moving_camera_init(self, tracks: Tracks, camera: Camera, extrinsics: np.ndarray
                            ) -> tuple[PartInit, float, np.ndarray]:
        """Parts, the scale depth and starting depths under a moving camera: every track is first read as a
        point standing still in the world (its depth by triangulation along its frame-0 ray); the parts are
        clustered on what that leaves unexplained (a still camera leaves the whole track, so this is the
        static camera's clustering), the root is the part that moves least, and it stands still (its tracks'
        triangulated depths start the fit; the other parts start at the root's median depth)."""
        config = self.config
        depth, _, still = static_depths(tracks.uv0, tracks.uv, tracks.trusted, camera.K, extrinsics)
        own_motion = replace(tracks, uv=tracks.uv - still + tracks.uv0[None])
        init = init_parts(own_motion, config.bones, config.init, static_px=config.fit.static_root_px)
        root = init.labels == init.root
        z_ref = float(np.median(depth[root]))
        if not init.root_static:
            log.warning("recon=video: the root part moves %.2f px beyond the camera's motion; it is taken as still "
                        "in the world (the camera explains the rest)", float(init.motion_px[init.root]))
        depth0 = np.clip(depth, z_ref / 3.0, z_ref * 3.0)
        # the moving parts start at the depth of the root point next to them in the image (a lid at its hinge)
        near = cKDTree(tracks.uv0[root]).query(tracks.uv0[~root])[1]
        depth0[~root] = depth0[root][near]
        return replace(init, root_static=True), z_ref, depth0

    @staticmethod
    def _root_motion(tracks: Tracks, init: PartInit, camera: Camera, z_ref: float) -> np.ndarray:
        """(T, 4, 4) the root's motion: identity when static, else PnP of its tracks (points at z_ref)."""
        n_frames = tracks.uv.shape[0]
        if init.root_static:
            return np.tile(np.eye(4), (n_frames, 1, 1))
        own = init.labels == init.root
        c2w = np.linalg.inv(camera.world_to_cam)
        homo = np.concatenate([tracks.uv0[own], np.ones((int(own.sum()), 1))], 1)
        pts = c2w[:3, 3] + z_ref * (np.linalg.inv(camera.K) @ homo.T).T @ c2w[:3, :3].T
        log.warning("recon=video: the root part moves; its motion comes from PnP of its tracks on a "
                    "fronto-parallel plane (a single view cannot tell its shape)")
        return pnp_transforms(pts, tracks.uv[:, own], tracks.trusted[:, own], camera)


def upright_frame(up: np.ndarray) -> np.ndarray:
    """(4, 4) the least rotation taking the unit direction ``up`` (3,) to +Y (identity when it is +Y)."""
    u = np.asarray(up, np.float64) / np.linalg.norm(up)
    y = np.array([0.0, 1.0, 0.0])
    axis, cos = np.cross(u, y), float(np.clip(u @ y, -1.0, 1.0))
    out = np.eye(4)
    if np.linalg.norm(axis) < 1e-12:
        out[:3, :3] = np.eye(3) if cos > 0 else np.diag([1.0, -1.0, -1.0])
        return out
    k = axis / np.linalg.norm(axis)
    skew = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    angle = np.arccos(cos)
    out[:3, :3] = np.eye(3) + np.sin(angle) * skew + (1 - np.cos(angle)) * skew @ skew
    return out


def build_reference(joints: JointFit, means: np.ndarray, labels: np.ndarray, clip: VideoClip, camera: Camera,
                    name: str) -> Reference:
    """The skinning stage: points (N, 3) [m] with hard part weights from labels (N,), bones at part
    centroids, G_t = the root's motion."""
    n_parts = len(joints.kinds)
    weights = np.eye(n_parts)[labels]
    centres = np.stack([means[labels == b].mean(0) for b in range(n_parts)])
    covs = np.stack([np.cov(means[labels == b].T) + 1e-6 * np.eye(3) if (labels == b).sum() > 3
                     else 1e-4 * np.eye(3) for b in range(n_parts)])
    world = joints.transforms()  # (T, B, 4, 4) rest -> t, world
    glob = world[:, joints.root].copy()
    bones = np.einsum("tij,tbjk->tbik", np.linalg.inv(glob), world)
    uv, _ = project_points(torch.as_tensor(means), torch.as_tensor(camera.K), torch.as_tensor(camera.world_to_cam))
    colours = sample_image(clip.frames[0], uv.numpy()) / 255.0
    return Reference(rest_vertices=means, rest_faces=None, bone_centers=centres, bone_covariances=covs,
                     skinning=weights, bone_transforms=bones, global_transforms=glob, fps=clip.fps,
                     vertex_colors=np.clip(colours, 0.0, 1.0), name=name).validate()
