"""Silhouette and joint fit of ``recon=video``: every moving part on one 1-DoF joint (hinge or slide).

With a static, known camera each tracked frame-0 point sits on its pixel's ray at an unknown depth. A
moving part p is one rigid body on a joint relative to the root part (the base): a hinge (axis a_p through
a pivot P_p, angle theta_{t,p}) or a slide (direction a_p, travel s_{t,p}). All parts are fitted together
by Adam on three image terms, each in units of the tracking grid's stride:

    * tracks: projected points against their flow tracks, where the tracks are still verified (consistent,
      inside the masks and matching their frame-0 patch: a plain face's tracks stick, see ``Tracks``);
    * inside: every projected point lies inside its frame's mask (distance transform outside it);
    * cover: every frame's mask pixels are near some projected point, or a point on a slide's path
      (truncated, so surfaces the first frame never saw cost a bounded amount);

plus a smoothness prior on neighbouring depths and on the joint values over time. The joint values are
fitted over a growing window of frames (a part that turns 100 degrees is followed, not jumped to), from a
few axis starts. Each part's joint kind is then chosen by the data terms: the hinge reading is relabelled
(points to the part whose motion explains their track and silhouette best) and refined, the part is put on
a slide from five 3D direction starts (the hinge's 3D displacement, the image motion lifted, that tilted
45 degrees towards and away from the camera, the view ray), each with its travel matched to the hinge's
image motion; the two best are fitted, relabelled and refined the same way, and the slide wins unless the
hinge explains the images 5 % better. When it wins, the hinge it beat had other labels and less refinement,
so a hinge searched from the slide's reading the same way (hinge lines, the best of them the slide reading's
free motion fitted as a hinge, each with its angles matched to the slide's image motion; the two best fitted,
relabelled and refined) is put against it by the same rule. A slide's path (its outline extruded along its direction: a
drawer's box) also covers mask pixels. The winner is refined, relabelled and refined again.

Then the joint stage: every hinge is set beside its depth reversal (its surface, axis and pivot reflected
through the fronto-parallel plane at its depth, its angles negated: nearly the same images under
near-affine viewing, a basin the search can settle in) and the reading the data terms prefer is kept; each
part is freed (a rigid motion per frame on top of its joint, fitted to the same terms), and its joint is fitted
to that motion relative to the root over the whole clip (:mod:`sync4d.recon.video.screw`: hinge, slide or
fixed by penalised residual, robust over frames), the part re-posed on it and refined.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import cv2
import numpy as np
import torch
from scipy.spatial import cKDTree

from sync4d.forked import run_forked, usable_workers
from sync4d.recon.video.gravity import aligned_axis
from sync4d.recon.video.screw import Project, ScrewFit, fit_hinge, fit_screw
from sync4d.recon.video.stages import PartInit, Tracks
from sync4d.types import Camera

log = logging.getLogger(__name__)

FLOW_WEIGHT = 1.0  # frame-to-frame flow term against the chained-track term
SLIDE_PREFERENCE = 0.05  # relative data-loss margin by which a slide beats a hinge
SWEEP = (0.25, 0.5, 0.75)
# a moving camera measures every point's depth by parallax, and the tracks' noise with it: the per-point depth
# residual off each part's plane is held 30x harder then (the filmed laptop's lid: 1x left it 2.7-3.2x too
# thick, 30x 0.9-1.2x, 300x flat, 0.4x; the hinge axes the same at 30x and 300x; docs/results/articulated.md)
MOVING_RESIDUAL = 30.0  # fractions of a joint's value whose poses also cover mask pixels
AXIS_STARTS = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 1.0, 0], [1.0, 0, 1.0], [0, 1.0, 1.0]])


@dataclass
class FitConfig:
    """Attributes:
    steps: Adam steps of a full fit (the starts and the refinement use fractions of it).
    lr: learning rate (depths, axes, pivots in object widths; joint values in rad or object widths).
    axis_starts: hinge-axis starts tried per fit (world x, y, z, each part's border with the root,
        then diagonals; at most 7).
    cover_weight: weight of the cover term against the track term.
    inside_weight: weight of the inside-the-mask term.
    smooth_weight: weight of the depth and temporal smoothness priors.
    relabel_rounds: relabel + refine rounds after the first fit.
    static_root_px: median track motion [px] under which the root counts as static.
    workers: the hinge starts, and a slide's two starts, fitted side by side, each in a forked process (0: one
        per usable core; 1: in turn here); the result does not depend on it.
    """

    steps: int = 240
    lr: float = 0.03
    axis_starts: int = 4
    cover_weight: float = 3.0
    inside_weight: float = 3.0
    smooth_weight: float = 1.0
    relabel_rounds: int = 1
    static_root_px: float = 1.0
    workers: int = 0


@dataclass(frozen=True)
class Scene:
    """What the fit sees, as tensors (float64).

    Attributes:
        rays: (N, 3) world direction of each point's frame-0 pixel with unit camera depth.
        centre: (3,) camera centre [m].
        K, w2c: (3, 3) intrinsics, (4, 4) world -> camera.
        tracks: (T, N, 2) [px]; trusted, verified: (T, N) bool (``Tracks.trusted``, ``Tracks.verified``).
        outside: (T, H, W) distance to the mask [px] (0 inside).
        cover_px: list of T (M_t, 2) sampled mask pixels [px].
        root_motion: (T, 4, 4) the root's rigid motion (identity when static).
        flow: (T-1, 3, H, W) forward flow u, v [px] and its consistency (1 or 0), for the flow term.
        stride: grid spacing [px]; width: object width [m]; z_ref: depth that fixes the scale [m].
        w2c_t: (T, 4, 4) world -> camera of every frame when the camera moves (None: ``w2c`` in every frame);
            then the still root stays put in the world and the camera's own translation fixes the scale.
        depth0: (N,) frame-0 depths to start from [m] (None: ``z_ref`` for every point).
        up: (3,) the world's up when known (None: unknown); joint axes near level or vertical are tried there.
    """

    rays: torch.Tensor
    centre: torch.Tensor
    K: torch.Tensor
    w2c: torch.Tensor
    tracks: torch.Tensor
    trusted: torch.Tensor
    verified: torch.Tensor
    outside: torch.Tensor
    cover_px: list[torch.Tensor]
    root_motion: torch.Tensor
    stride: float
    width: float
    z_ref: float
    flow: torch.Tensor | None = None
    w2c_t: torch.Tensor | None = None
    depth0: torch.Tensor | None = None
    up: torch.Tensor | None = None

    @property
    def root_still(self) -> bool:
        """Whether the root's motion is the identity in every frame."""
        return bool(torch.equal(self.root_motion, torch.eye(4, dtype=self.root_motion.dtype).expand_as(self.root_motion)))


@dataclass
class JointFit:
    """The fitted articulation (world frame, metres).

    Attributes:
        labels: (N,) part of each tracked point; root: the base part.
        depth: (N,) camera depth of each point in frame 0 [m].
        kinds: per part ``root``, ``hinge`` or ``slide``.
        axes: (B, 3) unit joint axis (zeros for the root); pivots: (B, 3) a point on each hinge axis [m].
        values: (T, B) joint value per frame [rad for hinges, m for slides] (0 at frame 0).
        root_motion: (T, 4, 4) the root's rigid motion.
        data_loss: the fit's final track + inside + cover terms.
    """

    labels: np.ndarray
    root: int
    depth: np.ndarray
    kinds: list[str]
    axes: np.ndarray
    pivots: np.ndarray
    values: np.ndarray
    root_motion: np.ndarray
    data_loss: float
    history: list[float] = field(default_factory=list)

    def transforms(self) -> np.ndarray:
        """(T, B, 4, 4) rest (frame 0) -> frame t rigid motion of every part, world frame."""
        n_frames, n_parts = self.values.shape
        out = np.tile(np.eye(4), (n_frames, n_parts, 1, 1))
        for b, kind in enumerate(self.kinds):
            local = np.tile(np.eye(4), (n_frames, 1, 1))
            if kind == "hinge":
                rot = rodrigues_np(self.axes[b], self.values[:, b])
                local[:, :3, :3] = rot
                local[:, :3, 3] = self.pivots[b] - rot @ self.pivots[b]
            elif kind == "slide":
                local[:, :3, 3] = self.values[:, b, None] * self.axes[b]
            out[:, b] = self.root_motion @ local
        return out


def rodrigues_np(axis: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """(T, 3, 3) rotations by ``angles`` (T,) [rad] about the unit ``axis`` (3,)."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    s, c = np.sin(angles)[:, None, None], np.cos(angles)[:, None, None]
    return np.eye(3)[None] + s * k[None] + (1 - c) * (k @ k)[None]


def _rodrigues(axis: torch.Tensor, angles: torch.Tensor) -> torch.Tensor:
    """(T, 3, 3) rotations by ``angles`` (T,) about ``axis`` (3,) (normalised here)."""
    a = axis / axis.norm().clamp_min(1e-9)
    zero = torch.zeros((), dtype=a.dtype)
    k = torch.stack([torch.stack([zero, -a[2], a[1]]), torch.stack([a[2], zero, -a[0]]),
                     torch.stack([-a[1], a[0], zero])])
    s, c = torch.sin(angles)[:, None, None], torch.cos(angles)[:, None, None]
    return torch.eye(3, dtype=a.dtype)[None] + s * k[None] + (1 - c) * (k @ k)[None]


def _rodrigues_batch(rotvec: torch.Tensor) -> torch.Tensor:
    """(M, 3, 3) rotations of rotation vectors (M, 3) [rad] (smooth at zero)."""
    theta2 = (rotvec**2).sum(1)
    theta = torch.sqrt(theta2 + 1e-24)
    zero = torch.zeros_like(rotvec[:, 0])
    k = torch.stack([torch.stack([zero, -rotvec[:, 2], rotvec[:, 1]], 1),
                     torch.stack([rotvec[:, 2], zero, -rotvec[:, 0]], 1),
                     torch.stack([-rotvec[:, 1], rotvec[:, 0], zero], 1)], 1)
    small = theta2 < 1e-8
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2.clamp_min(1e-24))
    return torch.eye(3, dtype=rotvec.dtype)[None] + a[:, None, None] * k + b[:, None, None] * (k @ k)


def make_scene(tracks: Tracks, masks: np.ndarray, camera: Camera, init: PartInit, z_ref: float,
               root_motion: np.ndarray, rng: np.random.Generator, *, cover_samples: int = 400,
               extrinsics: np.ndarray | None = None, depth0: np.ndarray | None = None,
               up: np.ndarray | None = None) -> Scene:
    """The fit's tensors: rays, tracks, distance-to-mask images and the pixels left to the moving parts
    (``extrinsics`` (T, 4, 4): the per-frame camera when it moves; ``depth0`` (N,) [m]: starting depths;
    ``up`` (3,): the world's up when known)."""
    c2w = np.linalg.inv(camera.world_to_cam)
    homo = np.concatenate([tracks.uv0, np.ones((len(tracks.uv0), 1))], 1)
    rays = (np.linalg.inv(camera.K) @ homo.T).T @ c2w[:3, :3].T
    outside = np.stack([cv2.distanceTransform((~m).astype(np.uint8), cv2.DIST_L2, 3) for m in masks])
    cover = []
    # a static root cannot reach pixels that were background in frame 0, so those must be covered by the
    # frame-0 surface of the moving parts; other mask pixels may show surface frame 0 never saw (a laptop's
    # keyboard under its lid), which the cover term would otherwise pull the parts over
    seen = cv2.dilate(masks[0].astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    # under a moving camera frame 0's mask is elsewhere in later frames: every mask pixel is sampled (carrying
    # frame 0's surface into each frame by the still root's depths measured worse on the filmed laptop)
    static = bool(np.allclose(root_motion, np.eye(4))) and extrinsics is None
    for m in masks:
        vv, uu = np.nonzero(m & ~seen if static else m)
        pick = rng.choice(len(vv), size=min(cover_samples, len(vv)), replace=False)
        cover.append(torch.as_tensor(np.stack([uu[pick], vv[pick]], 1) + 0.5, dtype=torch.float64))
    span = np.ptp(tracks.uv0, axis=0).max() + tracks.stride
    d = torch.float64
    return Scene(rays=torch.as_tensor(rays, dtype=d), centre=torch.as_tensor(c2w[:3, 3], dtype=d),
                 K=torch.as_tensor(camera.K, dtype=d), w2c=torch.as_tensor(camera.world_to_cam, dtype=d),
                 tracks=torch.as_tensor(tracks.uv, dtype=d), trusted=torch.as_tensor(tracks.trusted),
                 verified=torch.as_tensor(tracks.verified),
                 outside=torch.as_tensor(outside, dtype=d), cover_px=cover,
                 root_motion=torch.as_tensor(root_motion, dtype=d), stride=float(tracks.stride),
                 width=float(span * z_ref / camera.K[0, 0]), z_ref=z_ref, flow=_flow_tensor(tracks),
                 w2c_t=None if extrinsics is None else torch.as_tensor(extrinsics, dtype=d),
                 depth0=None if depth0 is None else torch.as_tensor(depth0, dtype=d),
                 up=None if up is None else torch.as_tensor(up, dtype=d))


def _flow_tensor(tracks: Tracks) -> torch.Tensor | None:
    """(T-1, 3, H, W) float64: flow u, v [px] and 1 where it is consistent (for bilinear sampling)."""
    if tracks.flow is None or tracks.flow_ok is None:
        return None
    both = np.concatenate([tracks.flow, tracks.flow_ok[..., None].astype(np.float32)], -1)
    return torch.as_tensor(both, dtype=torch.float64).permute(0, 3, 1, 2).contiguous()


def to_camera(scene: Scene, x: torch.Tensor, first: int = 0) -> torch.Tensor:
    """Camera coordinates of world points: (F, N, 3) of frames first.. (each frame's camera), or (N, 3) of
    frame ``first``."""
    if scene.w2c_t is None:
        return x @ scene.w2c[:3, :3].T + scene.w2c[:3, 3]
    if x.dim() == 2:
        w = scene.w2c_t[first]
        return x @ w[:3, :3].T + w[:3, 3]
    w = scene.w2c_t[first:first + x.shape[0]]
    return torch.einsum("tij,tnj->tni", w[:, :3, :3], x) + w[:, None, :3, 3]


def project(scene: Scene, x: torch.Tensor, first: int = 0) -> torch.Tensor:
    """(F, N, 2) pixels of world points (F, N, 3) in frames first.. (or (N, 2) of (N, 3) in frame ``first``)."""
    uv = to_camera(scene, x, first) @ scene.K.T
    return _Divided.apply(uv[..., :2], uv[..., 2:3].clamp_min(1e-6))


class _Divided(torch.autograd.Function):
    """``num / den`` for num (..., 2) and den (..., 1) with autograd's own gradients (the same formulas, to the
    bit), the denominator's summed over the pair by one addition: autograd reduces that broadcast with a sum
    over an axis of two, the fit's slowest reduction (half a projection's backward)."""

    @staticmethod
    def forward(ctx: Any, num: torch.Tensor, den: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(num, den)
        return num / den

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor
                 ) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        num, den = ctx.saved_tensors
        needs = ctx.needs_input_grad
        grad_den = None
        if needs[1]:
            each = -grad * ((num / den) / den)
            grad_den = each[..., 0:1] + each[..., 1:2]
        return (grad / den if needs[0] else None), grad_den


def sample_outside(scene: Scene, uv: torch.Tensor, first: int = 0) -> torch.Tensor:
    """(F, N) distance to the mask [px] of frames first.. at pixels uv (F, N, 2), bilinear; outside the image: far."""
    _, h, w = scene.outside.shape
    grid = torch.stack([uv[..., 0] / w * 2 - 1, uv[..., 1] / h * 2 - 1], -1)[:, None]
    out = torch.nn.functional.grid_sample(scene.outside[first:first + len(uv), None], grid, align_corners=False, padding_mode="border")
    off = ((uv[..., 0] < 0) | (uv[..., 0] > w) | (uv[..., 1] < 0) | (uv[..., 1] > h)).double() * 10.0
    return out[:, 0, 0] + off


class Articulation(torch.nn.Module):
    """Depths, joints and joint values of every part; ``posed`` gives the world points of any frame."""

    def __init__(self, scene: Scene, labels: np.ndarray, root: int, kinds: list[str], axes: np.ndarray,
                 pivots: np.ndarray, values: np.ndarray, log_depth: np.ndarray) -> None:
        super().__init__()
        d = torch.float64
        self.scene, self.root, self.kinds = scene, root, list(kinds)
        self.labels = torch.as_tensor(labels, dtype=torch.long)
        # each part's surface: a plane (inverse depth affine in normalised image coordinates) plus a small
        # per-point log-depth residual; free per-point depths let a warped surface turned about a far pivot
        # mimic a larger turn about the true hinge (measured on the two-plate test: 16 deg for 40)
        self.coords = torch.cat([torch.ones(len(labels), 1, dtype=d), (scene.rays @ scene.w2c[:3, :3].T)[:, :2]], 1)
        inv = np.exp(-np.asarray(log_depth))
        plane = np.zeros((len(kinds), 3))
        plane[:, 0] = [inv[labels == b].mean() if (labels == b).any() else inv.mean() for b in range(len(kinds))]
        if scene.w2c_t is not None:  # a moving camera measured the depths: each part's plane fitted to them
            coords = self.coords.numpy()
            for b in range(len(kinds)):
                own = labels == b
                if own.sum() >= 3:
                    plane[b] = np.linalg.lstsq(coords[own], inv[own], rcond=None)[0]
        self.plane = torch.nn.Parameter(torch.as_tensor(plane, dtype=d))
        self.resid = torch.nn.Parameter(torch.zeros(len(labels), dtype=d))
        self.axes = torch.nn.Parameter(torch.as_tensor(axes, dtype=d))
        self.pivot0 = torch.as_tensor(pivots, dtype=d)
        self.pivot_delta = torch.nn.Parameter(torch.zeros_like(self.pivot0))  # [object widths]
        self.values = torch.nn.Parameter(torch.as_tensor(values[1:], dtype=d))  # frame 0 is the rest
        # a free rigid motion per frame and part on top of the joint (rotation vector, translation in object
        # widths, about the part's posed centroid): the per-part fit whose motions the joint is fitted to
        self.free: torch.nn.Parameter | None = None

    def log_depth(self) -> torch.Tensor:
        """(N,) log camera depth of every point in frame 0 [log m]."""
        inv = (self.plane[self.labels] * self.coords).sum(1).clamp_min(1e-3)
        return -torch.log(inv) + self.resid

    def rest(self) -> torch.Tensor:
        """(N, 3) frame-0 world points on their rays [m]."""
        return self.scene.centre + torch.exp(self.log_depth())[:, None] * self.scene.rays

    def pivots(self) -> torch.Tensor:
        return self.pivot0 + self.scene.width * self.pivot_delta

    def part_transforms(self, fraction: float = 1.0) -> torch.Tensor:
        """(T, B, 3, 4) rest -> frame t motion of every part (root motion included), at ``fraction`` of each
        joint value."""
        n_parts = len(self.kinds)
        vals = torch.cat([torch.zeros(1, n_parts, dtype=self.values.dtype), self.values], 0) * fraction
        # a still root's motion is the identity: multiplying by it returns its operand to the bit (and so
        # does its gradient), so it is skipped (the static suite's rows; about 5 % of a fit step)
        still = self.scene.root_still
        out = []
        for b, kind in enumerate(self.kinds):
            if kind == "hinge":
                rot = _rodrigues(self.axes[b], vals[:, b])
                trans = self.pivots()[b] - rot @ self.pivots()[b]
            else:
                rot = torch.eye(3, dtype=vals.dtype).expand(len(vals), 3, 3)
                unit = self.axes[b] / self.axes[b].norm().clamp_min(1e-9)
                trans = (vals[:, b] * self.scene.width if kind == "slide" else 0.0 * vals[:, b])[:, None] * unit
            if still:
                out.append(torch.cat([rot, trans[..., None]], -1))
                continue
            g = self.scene.root_motion
            out.append(torch.cat([g[:, :3, :3] @ rot, (g[:, :3, :3] @ trans[..., None])[..., 0:1] + g[:, :3, 3:]], -1))
        motion = torch.stack(out, 1)
        return motion if self.free is None or fraction != 1.0 else self._freed(motion)

    def _freed(self, motion: torch.Tensor) -> torch.Tensor:
        """(T, B, 3, 4) ``motion`` with each frame's free motion of every part applied after it."""
        assert self.free is not None
        still = torch.as_tensor([b != self.root for b in range(len(self.kinds))], dtype=self.free.dtype)
        free = torch.cat([torch.zeros_like(self.free[:1]), self.free], 0) * still[None, :, None]  # (T, B, 6)
        n_frames, n_parts = free.shape[:2]
        rest = self.rest()
        centre0 = torch.stack([rest[self.labels == b].mean(0) if bool((self.labels == b).any())
                               else rest.mean(0) for b in range(n_parts)])  # (B, 3)
        centre = torch.einsum("tbij,bj->tbi", motion[..., :3], centre0) + motion[..., 3]
        rot = _rodrigues_batch(free[..., :3].reshape(-1, 3)).reshape(n_frames, n_parts, 3, 3)
        shift = centre - torch.einsum("tbij,tbj->tbi", rot, centre) + free[..., 3:] * self.scene.width
        return torch.cat([rot @ motion[..., :3], (rot @ motion[..., 3:])+ shift[..., None]], -1)

    def swept(self, kinds: tuple[str, ...] = ("slide",), frames: int | None = None) -> torch.Tensor:
        """(T, M, 3) world points (of the first ``frames`` frames when given) of the parts of ``kinds`` at
        fractions SWEEP of each frame's joint value. A sliding part's sides (a drawer's box) are the extrusion
        of its outline along its direction: the surface a slide reveals lies on its own path, so the path
        covers mask pixels too (the cover term). A hinge's path is not its surface (fitting with it measured
        worse on lids), but joint kinds are
        compared with every kind's path (``kind_loss``), so that a lid read as a slide gains nothing from it."""
        use = torch.as_tensor([self.kinds[b] in kinds for b in range(len(self.kinds))])[self.labels]
        rest = self.rest()[use]
        out = [rest[None].expand(len(self.values) + 1, -1, -1)[:frames, :0]]
        for frac in SWEEP if use.any() else ():
            out.append(moved(self.part_transforms(frac)[:frames], self.labels[use], rest))
        return torch.cat(out, 1)

    def posed(self, frames: int | None = None) -> torch.Tensor:
        """(T, N, 3) world points of every frame (of the first ``frames`` when given)."""
        return moved(self.part_transforms()[:frames], self.labels, self.rest())


def moved(motion: torch.Tensor, labels: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """(F, N, 3) points (N, 3) under their part's motion (F, B, 3, 4), parts ``labels`` (N,).

    The same batched product as ``einsum("tnij,nj->tni", j[..., :3], points) + j[..., 3]`` with ``j =
    motion[:, labels]`` (values and gradients to the bit), but each point's rotations are gathered already
    in the product's layout: no strided copy of the (F, N, 3, 4) per-point transforms (2x faster, a fit
    step's largest single cost before)."""
    per_part = motion.permute(1, 0, 2, 3)
    # index_select, not indexing: the same rows, and its backward adds them up in the same order, 3x faster
    rot = torch.index_select(per_part[..., :3].contiguous(), 0, labels)
    shift = torch.index_select(per_part[..., 3].contiguous(), 0, labels)
    n_points, n_frames = rot.shape[:2]
    x = _Rotated.apply(rot.reshape(n_points, n_frames * 3, 3), points).reshape(n_points, n_frames, 3)
    return (x + shift).permute(1, 0, 2).contiguous()


class _Rotated(torch.autograd.Function):
    """``torch.bmm(rot, points[:, :, None])`` for rot (N, M, 3) and points (N, 3), with the gradient of
    ``rot`` an elementwise product: bmm's own backward forms that outer product as a batched product over a
    contraction of length one (the same numbers, 0 + g * p, several times slower here)."""

    @staticmethod
    def forward(ctx: Any, rot: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(rot, points)
        return torch.bmm(rot, points[:, :, None])

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor
                 ) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        rot, points = ctx.saved_tensors
        grad_rot = grad * points[:, None, :] if ctx.needs_input_grad[0] else None
        grad_points = rot.transpose(1, 2).bmm(grad)[..., 0] if ctx.needs_input_grad[1] else None
        return grad_rot, grad_points


def visible(uv: torch.Tensor, depth: torch.Tensor, stride: float) -> torch.Tensor:
    """(F, N) bool: points (F, N) pixels uv, camera depths [m], nearest the camera in their stride cell
    (within 2 % of the depth), i.e. not hidden behind another modelled point."""
    cell = torch.floor(uv / stride).long()
    # one key per (frame, cell): every frame's cells in one pass (a frame's keys stay far below 2**40)
    key = (cell[..., 0] * 100003 + cell[..., 1] + torch.arange(len(cell))[:, None] * 2**40).reshape(-1)
    flat = depth.reshape(-1)
    uniq, inv = torch.unique(key, return_inverse=True)
    near = torch.full((len(uniq),), np.inf, dtype=depth.dtype).scatter_reduce(0, inv, flat, "amin")
    return (flat <= near[inv] * 1.02).reshape(depth.shape)


def flow_term(model: Articulation, posed: torch.Tensor, uv: torch.Tensor, frames: int) -> torch.Tensor:
    """Frame-to-frame image motion of the posed moving points against the flow at their pixel, where the
    flow is consistent and the point visible (Charbonnier, strides); posed (frames, N, 3) [m] and their
    pixels uv (frames, N, 2) include frame 0."""
    sc = model.scene
    if sc.flow is None or frames < 2:
        return torch.zeros((), dtype=uv.dtype)
    _, _, h, w = sc.flow.shape
    moving = torch.nonzero(model.labels != model.root)[:, 0]
    with torch.no_grad():  # the root's points only hide others: the flow is sampled at the moving ones alone
        pc = to_camera(sc, posed[:-1].detach())
        seen = visible(uv[:-1].detach(), pc[..., 2], sc.stride)[:, moving]
        at = uv[:-1, moving].detach()
        grid = torch.stack([at[..., 0] / w * 2 - 1, at[..., 1] / h * 2 - 1], -1)[:, None]
        fl = torch.nn.functional.grid_sample(sc.flow[: frames - 1], grid, align_corners=False)[:, :, 0]  # (F, 3, N)
        ok = (fl[:, 2] > 0.99) & seen
    if not ok.any():
        return torch.zeros((), dtype=uv.dtype)
    mov = torch.index_select(uv, 1, moving)
    err = pair_sum((mov[1:] - mov[:-1] - fl[:, :2].transpose(1, 2)) ** 2) / sc.stride**2
    return (torch.sqrt(err + 1.0) - 1.0)[ok].mean()


def data_terms(model: Articulation, frames: int, *, with_flow: bool = True, swept: tuple[str, ...] = ("slide",),
               verified_only: bool = True) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Track (chained tracks + frame-to-frame flow unless ``with_flow`` is false), inside and cover terms over
    frames 1..frames-1, in strides (see the module docstring); the chained tracks are the verified ones, or
    every trusted one when ``verified_only`` is false."""
    sc = model.scene
    posed = model.posed(frames)
    uv_all = project(sc, posed)
    uv = uv_all[1:]
    # the track and inside terms count moving points only, so only theirs are compared or sampled (gathered by
    # index_select: the same values and gradients as a boolean mask's, cheaper)
    moving = torch.nonzero(model.labels != model.root)[:, 0]
    trusted = (sc.verified if verified_only else sc.trusted)[1:frames, moving]
    err = pair_sum((torch.index_select(uv, 1, moving) - sc.tracks[1:frames, moving]) ** 2) / sc.stride**2
    track = (torch.sqrt(err + 1.0) - 1.0)[trusted].mean() if trusted.any() else torch.zeros((), dtype=uv.dtype)
    if with_flow:
        track = track + FLOW_WEIGHT * flow_term(model, posed, uv_all, frames)
    inside = (sample_outside(sc, torch.index_select(uv, 1, moving), 1) / sc.stride).clamp(max=10.0).mean()
    if not len(moving):
        return track, inside, torch.zeros((), dtype=uv.dtype)
    return track, inside, cover_term(sc, torch.cat([uv, project(sc, model.swept(swept, frames)[1:], 1)], 1))


def pair_sum(x: torch.Tensor) -> torch.Tensor:
    """``x.sum(-1)`` of x (..., 2): the same numbers and gradient by one addition (a sum over an axis of two
    is one of a fit step's slower reductions)."""
    return _PairSum.apply(x)


class _PairSum(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, x: torch.Tensor) -> torch.Tensor:
        return x[..., 0] + x[..., 1]

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> torch.Tensor:
        return grad[..., None].expand(*grad.shape, 2)


def cover_term(sc: Scene, uv: torch.Tensor) -> torch.Tensor:
    """Mean over frames 1.. of the mean distance [strides, capped at 4] from each cover pixel to its nearest
    projected point, uv (F, M, 2) of frames 1..F."""
    frames = [t for t in range(1, len(uv) + 1) if len(sc.cover_px[t])]
    if not frames:
        return torch.zeros((), dtype=uv.dtype)
    pts = uv[[t - 1 for t in frames]]
    px = torch.cat([sc.cover_px[t] for t in frames])
    counts = [len(sc.cover_px[t]) for t in frames]
    # the nearest point by a k-d tree, the distance to it differentiated (torch.cdist is slow here); a tree
    # per frame (one tree over all frames breaks the ties between equally near points differently), built
    # once per query, so its cheapest build (unbalanced, loose nodes: 1.6x) wins; the distances in one pass
    flat = pts.detach().numpy()
    near = torch.as_tensor(np.concatenate([
        cKDTree(flat[k], balanced_tree=False, compact_nodes=False).query(sc.cover_px[t].numpy())[1] + k * pts.shape[1]
        for k, t in enumerate(frames)]))
    dist = ((px - torch.index_select(pts.reshape(-1, 2), 0, near)).norm(dim=1) / sc.stride).clamp(max=4.0)
    if len(set(counts)) == 1:
        return dist.reshape(len(frames), counts[0]).mean(1).mean()
    return torch.stack([d.mean() for d in dist.split(counts)]).mean()


def prior_terms(model: Articulation, pairs: torch.Tensor) -> torch.Tensor:
    """Surfaces near their planes, joint values smooth in time, hinges near where they started."""
    depth = (model.resid**2).mean() * (100.0 if model.scene.w2c_t is None else 100.0 * MOVING_RESIDUAL)
    vals = torch.cat([torch.zeros_like(model.values[:1]), model.values], 0)
    accel = ((vals[2:] - 2 * vals[1:-1] + vals[:-2]) ** 2).mean() if len(vals) > 2 else torch.zeros(())
    drift = (model.pivot_delta.norm(dim=1) - 0.5).clamp_min(0.0).pow(2).sum()
    # the monocular scale (a moving camera's translation fixes it instead)
    gauge = (model.log_depth().mean() - np.log(model.scene.z_ref)) ** 2 if model.scene.w2c_t is None else 0.0
    return depth + accel + drift + gauge


def neighbour_pairs(uv0: np.ndarray, labels: np.ndarray, stride: float) -> torch.Tensor:
    """(P, 2) index pairs of grid neighbours within one part."""
    pairs = np.array(sorted(cKDTree(uv0).query_pairs(1.5 * stride)), dtype=np.int64).reshape(-1, 2)
    same = labels[pairs[:, 0]] == labels[pairs[:, 1]] if len(pairs) else np.zeros(0, bool)
    pairs = pairs[same]
    return torch.as_tensor(pairs if len(pairs) else np.zeros((1, 2), np.int64))


def optimise(model: Articulation, config: FitConfig, steps: int, pairs: torch.Tensor, *, windows: int = 4,
             verified_only: bool = True) -> float:
    """Adam over a growing window of frames, then all frames; returns the final data loss (tracks as in
    :func:`data_terms`)."""
    n_frames = model.values.shape[0] + 1
    opt = torch.optim.Adam([{"params": [model.resid, model.axes, model.pivot_delta], "lr": config.lr},
                            {"params": [model.plane], "lr": config.lr / model.scene.z_ref},
                            {"params": [model.values], "lr": config.lr * 2}])
    ends = [max(2, int(np.ceil(n_frames * (k + 1) / windows))) for k in range(windows)] + [n_frames]
    per = max(1, steps // len(ends))
    last_end = 1
    data = torch.zeros(())
    for end in ends:
        with torch.no_grad():  # new frames start where the window's last frame is
            if end > last_end and last_end > 1:
                model.values[last_end - 1:end - 1] = model.values[last_end - 2]
        last_end = end
        for _ in range(per):
            opt.zero_grad(set_to_none=True)
            track, inside, cover = data_terms(model, end, verified_only=verified_only)
            data = track + config.inside_weight * inside + config.cover_weight * cover
            loss = data + config.smooth_weight * prior_terms(model, pairs)
            loss.backward()
            opt.step()
    return float(data.detach())


def kind_loss(model: Articulation, config: FitConfig) -> float:
    """The data loss over all frames by which joint kinds are compared: without the flow term, which shapes
    the fit but lets a far-pivot hinge out-fit a slide on a plain sliding plate (docs/results/articulated.md)."""
    with torch.no_grad():
        track, inside, cover = data_terms(model, model.values.shape[0] + 1, with_flow=False, swept=("slide", "hinge"))
        return float(track + config.inside_weight * inside + config.cover_weight * cover)


def _start(scene: Scene, tracks: Tracks, labels: np.ndarray, root: int) -> tuple[np.ndarray, np.ndarray]:
    """(B, 3) hinge pivots at each part's border with the root and (B, 3) unit axes along that border (a
    lid's hinge line; image-plane directions at the reference depth)."""
    n_parts = int(labels.max()) + 1
    rest = (scene.centre + scene.z_ref * scene.rays).numpy()
    pivots, border = np.zeros((n_parts, 3)), np.tile([1.0, 0, 0], (n_parts, 1))
    root_uv = tracks.uv0[labels == root]
    for b in range(n_parts):
        own = np.flatnonzero(labels == b)
        if b == root or not len(own) or not len(root_uv):
            continue
        dist = cKDTree(root_uv).query(tracks.uv0[own])[0]
        near = rest[own[dist <= np.quantile(dist, 0.1)]]
        pivots[b] = near.mean(0)
        if len(near) >= 3:
            border[b] = np.linalg.svd(near - near.mean(0), full_matrices=False)[2][0]
    return pivots, border


def axis_start(s: int, border: np.ndarray) -> np.ndarray:
    """(B, 3) hinge-axis start ``s``: world x, y, z, then each part's border with the root, then diagonals."""
    if s == 3:
        return border
    return np.tile(AXIS_STARTS[s if s < 3 else s - 1], (len(border), 1))


def relabel(model: Articulation, tracks: Tracks, *, margin: float = 0.25) -> np.ndarray:
    """(N,) labels: each point to the part whose motion explains its track and silhouette best (depth of a
    point judged under another part: that part's nearest point's); ties within ``margin`` keep the label."""
    sc = model.scene
    labels = model.labels.numpy()
    n_parts = len(model.kinds)
    with torch.no_grad():
        trans = model.part_transforms()
        depth = torch.exp(model.log_depth()).numpy()
        cost = np.full((len(labels), n_parts), np.inf)
        for b in range(n_parts):
            own = np.flatnonzero(labels == b)
            if not len(own):
                continue
            d = depth[own[cKDTree(tracks.uv0[own]).query(tracks.uv0)[1]]]
            d = np.where(labels == b, depth, d)
            rest = sc.centre + torch.as_tensor(d)[:, None] * sc.rays
            x = torch.einsum("tij,nj->tni", trans[:, b, :, :3], rest) + trans[:, b, None, :, 3]
            uv = project(sc, x)
            err = torch.sqrt(((uv - sc.tracks) ** 2).sum(-1) / sc.stride**2 + 1.0) - 1.0
            ok = sc.verified.double()
            track = (err * ok).sum(0) / ok.sum(0).clamp_min(1.0)
            inside = (sample_outside(sc, uv, 0) / sc.stride).clamp(max=10.0).mean(0)
            cost[:, b] = (track + inside).numpy()
    best = np.argmin(cost, 1)
    gain = cost[np.arange(len(labels)), labels] - cost[np.arange(len(labels)), best]
    out = np.where(gain > margin, best, labels)
    return out if all((out == b).sum() >= 3 for b in range(n_parts)) else labels


def start_model(scene: Scene, labels: np.ndarray, root: int, kinds: list[str], border: np.ndarray,
                pivots: np.ndarray, n_frames: int, log_d: np.ndarray, s: int) -> Articulation:
    """The model of hinge start ``s`` (:func:`axis_start`), every joint value zero."""
    return Articulation(scene, labels, root, kinds, axis_start(s, border), pivots, np.zeros((n_frames, len(kinds))),
                        log_d)


def fit_start(make: Callable[[int], Articulation], pairs: torch.Tensor, config: FitConfig, s: int
              ) -> tuple[float, dict[str, torch.Tensor]]:
    """Start ``s`` fitted: its data loss and the model's parameters."""
    model = make(s)
    # the starts follow every consistent track: a sticking track under-reports its part's motion but
    # still points the way, and a start needs any cue to reach the right basin (the lever's starts all
    # ended at about 4x the truth's loss on verified tracks alone); every later fit uses verified tracks only
    loss = optimise(model, config, config.steps // 3, pairs, verified_only=False)
    return loss, model.state_dict()


def fit_hinge_starts(make: Callable[[int], Articulation], count: int, pairs: torch.Tensor, config: FitConfig
                     ) -> tuple[Articulation, list[float]]:
    """The best of ``count`` hinge starts (``make(s)`` builds start s), fitted side by side in forked
    processes (``config.workers``), and every start's data loss."""
    fitted = run_forked([partial(fit_start, make, pairs, config, s) for s in range(count)],
                        usable_workers(config.workers))
    best, best_loss, history = None, np.inf, []
    for s, (loss, state) in enumerate(fitted):
        history.append(loss)
        log.info("recon=video: hinge start %d (axes %s): data loss %.4f", s, np.round(state["axes"].numpy(), 2).tolist(),
                 loss)
        if loss < best_loss:
            best, best_loss = make(s), loss
            best.load_state_dict(state)
    assert best is not None, "at least one hinge start runs"
    return best, history


def fit_joints(scene: Scene, tracks: Tracks, init: PartInit, config: FitConfig) -> JointFit:
    """Fit every moving part's joint (see the module docstring); kinds chosen by the data terms (the camera is
    the scene's)."""
    labels, root = init.labels.copy(), init.root
    n_parts, n_frames = int(labels.max()) + 1, tracks.uv.shape[0]
    pivots, border = _start(scene, tracks, labels, root)
    pairs = neighbour_pairs(tracks.uv0, labels, tracks.stride)
    log_d = np.full(len(labels), np.log(scene.z_ref)) if scene.depth0 is None else np.log(scene.depth0.numpy())
    kinds = ["root" if b == root else "hinge" for b in range(n_parts)]
    best, history = fit_hinge_starts(partial(start_model, scene, labels, root, kinds, border, pivots, n_frames, log_d),
                                     max(1, min(config.axis_starts, len(AXIS_STARTS) + 1)), pairs, config)
    best = choose_kinds(best, tracks, config, history)
    pairs = neighbour_pairs(tracks.uv0, best.labels.numpy(), tracks.stride)
    best_loss = optimise(best, config, config.steps // 2, pairs, windows=1)
    for _ in range(config.relabel_rounds):
        best_loss = relabel_and_refine(best, tracks, config, config.steps // 2)
    best = depth_reversals(best, tracks, config)
    refit_joints(best, tracks, config)
    pairs = neighbour_pairs(tracks.uv0, best.labels.numpy(), tracks.stride)
    best_loss = optimise(best, config, config.steps // 4, pairs, windows=1)
    if scene.up is not None:
        best, best_loss = gravity_aligned(best, config, pairs, best_loss)
    return joint_fit_of(best, best_loss, history)


def gravity_aligned(model: Articulation, config: FitConfig, pairs: torch.Tensor, loss: float
                    ) -> tuple[Articulation, float]:
    """``model`` with its joint axes near level or vertical put exactly there (:mod:`.gravity`) and its joints
    refined with the axes so held, beside ``model``'s joints refined as long with the axes free; the surfaces
    are held in both (refined under a held axis they warp to imitate the free one's motion: the filmed laptop's
    lid 1.0 -> 2.1x as thick). The aligned reading is kept unless the free one explains the images
    ``SLIDE_PREFERENCE`` better (:func:`kind_loss`; fewer degrees of freedom win a tie, as a slide does against
    a hinge). Returns the model kept and its data loss (``model`` and ``loss`` when no axis is near)."""
    assert model.scene.up is not None
    up = model.scene.up.numpy()
    with torch.no_grad():
        axes = model.axes.numpy().copy()
        values = np.concatenate([np.zeros((1, len(model.kinds))), model.values.numpy()], 0)
    aligned = axes.copy()
    for b, kind in enumerate(model.kinds):
        target = aligned_axis(axes[b], up) if kind in ("hinge", "slide") else None
        if target is not None:
            aligned[b] = target * np.linalg.norm(axes[b])
    if np.array_equal(aligned, axes):
        return model, loss
    trials = [copy_with(model, list(model.kinds), a, values) for a in (aligned, axes)]
    losses, kinds = [], []
    for trial, held in zip(trials, (True, False)):
        frozen = [trial.plane, trial.resid] + ([trial.axes] if held else [])
        for p in frozen:  # Adam skips a parameter without a gradient
            p.requires_grad_(False)
        losses.append(optimise(trial, config, config.steps // 8, pairs, windows=1))
        kinds.append(kind_loss(trial, config))
        for p in frozen:
            p.requires_grad_(True)
    log.info("recon=video: axes level or vertical: kind loss %.4f (axes free %.4f)", kinds[0], kinds[1])
    keep = 0 if kinds[0] <= kinds[1] * (1.0 + SLIDE_PREFERENCE) else 1
    return trials[keep], losses[keep]


def depth_reversals(model: Articulation, tracks: Tracks, config: FitConfig) -> Articulation:
    """Each hinge part against its depth reversal (:func:`mirrored`), refined the same way; the reading the
    data terms (:func:`kind_loss`) prefer is kept."""
    pairs = neighbour_pairs(tracks.uv0, model.labels.numpy(), tracks.stride)
    best, best_kind = model, kind_loss(model, config)
    for b in [b for b, kind in enumerate(model.kinds) if kind == "hinge"]:
        trial = mirrored(best, b)
        optimise(trial, config, config.steps // 4, pairs, windows=1)
        trial_kind = kind_loss(trial, config)
        log.info("recon=video: part %d reversed in depth: kind loss %.4f (as found %.4f)", b, trial_kind, best_kind)
        if trial_kind < best_kind:
            best, best_kind = trial, trial_kind
    return best


def free_motions(model: Articulation, config: FitConfig, steps: int) -> np.ndarray:
    """(T, B, 4, 4) every part's rest -> frame t world motion, each frame's free: the model's joints with a
    rigid motion per frame and part fitted on top (Adam on the data terms, depths and joints held)."""
    n_frames, n_parts = model.values.shape[0] + 1, len(model.kinds)
    model.free = torch.nn.Parameter(torch.zeros(n_frames - 1, n_parts, 6, dtype=torch.float64))
    opt = torch.optim.Adam([model.free], lr=config.lr)
    for _ in range(steps):
        opt.zero_grad(set_to_none=True)
        track, inside, cover = data_terms(model, n_frames)
        (track + config.inside_weight * inside + config.cover_weight * cover).backward()
        opt.step()
    with torch.no_grad():
        motion = model.part_transforms().numpy()
    model.free = None
    out = np.tile(np.eye(4), (n_frames, n_parts, 1, 1))
    out[:, :, :3] = motion
    return out


def root_frame_motions(model: Articulation, config: FitConfig) -> tuple[np.ndarray, np.ndarray, Project]:
    """Every part's free motion (:func:`free_motions`, ``config.steps // 8`` steps) relative to the root, (T, B,
    4, 4); the rest points (N, 3); and the projection of root-frame points (T, N, 3) to each frame's pixels."""
    sc = model.scene
    motions = free_motions(model, config, config.steps // 8)
    root_motion = sc.root_motion.numpy()
    with torch.no_grad():
        rest = model.rest().numpy()

    def project_np(x: np.ndarray) -> np.ndarray:
        world = np.einsum("tij,tnj->tni", root_motion[:, :3, :3], x) + root_motion[:, None, :3, 3]
        return project(sc, torch.as_tensor(world)).numpy()

    inv_root = np.linalg.inv(root_motion)
    return np.stack([inv_root @ motions[:, b] for b in range(motions.shape[1])], 1), rest, project_np


def refit_joints(model: Articulation, tracks: Tracks, config: FitConfig) -> list[ScrewFit | None]:
    """Every moving part's joint fitted to its freely recovered motion relative to the root over the whole
    clip (:func:`~sync4d.recon.video.screw.fit_screw`: kind by evidence, robust over frames), the model
    set to those joints and refined; returns the screw fits (root: None)."""
    sc = model.scene
    motions, rest, project_np = root_frame_motions(model, config)
    labels = model.labels.numpy()
    kinds, axes = list(model.kinds), model.axes.detach().numpy().copy()
    pivots = model.pivots().detach().numpy().copy()
    values = np.concatenate([np.zeros((1, len(kinds))), model.values.detach().numpy()], 0)
    fits: list[ScrewFit | None] = []
    for b in range(len(kinds)):
        own = labels == b
        if b == model.root or own.sum() < 3:
            fits.append(None)
            continue
        screw = fit_screw(motions[:, b], rest[own], project_np, sc.stride)
        log.info("recon=video: part %d's joint from its whole motion: %s (costs %s; was a %s)", b, screw.kind,
                 {k: round(float(v), 1) for k, v in screw.costs.items()}, kinds[b])
        kinds[b], axes[b] = screw.kind, screw.axis if screw.kind != "fixed" else axes[b]
        if screw.kind == "hinge":
            pivots[b] = screw.pivot
        values[:, b] = screw.values / (sc.width if screw.kind == "slide" else 1.0)
        fits.append(screw)
    with torch.no_grad():
        model.kinds = kinds
        model.axes.copy_(torch.as_tensor(axes))
        model.pivot0 = torch.as_tensor(pivots)
        model.pivot_delta.zero_()
        model.values.copy_(torch.as_tensor(values[1:]))
    return fits


def mirrored(model: Articulation, b: int) -> Articulation:
    """A copy of ``model`` with hinge part ``b`` reversed in depth: its surface reflected through the
    fronto-parallel plane at its mean depth (points stay on their rays), its axis and pivot reflected with
    it and its angles negated. Under near-affine viewing both images are nearly the same (a plane's tilt has a
    two-fold ambiguity), so the fit can settle in either; the data terms judge them side by side."""
    sc = model.scene
    with torch.no_grad():
        out = copy_with(model, list(model.kinds), model.axes.numpy().copy(),
                        np.concatenate([np.zeros((1, len(model.kinds))), model.values.numpy()], 0))
        own = model.labels == b
        inv = torch.exp(-model.log_depth())
        mean_inv = float(inv[own].mean())
        # inverse depth affine in the image: reflecting the depth about the mean is, to first order,
        # reflecting the inverse depth (plane) and the residual
        out.plane[b] = torch.as_tensor([2.0 * mean_inv - float(model.plane[b, 0]), -float(model.plane[b, 1]),
                                        -float(model.plane[b, 2])], dtype=out.plane.dtype)
        out.resid[own] = -model.resid[own]
        w2c = sc.w2c.numpy()
        flip = np.diag([1.0, 1.0, -1.0])
        axis_c = w2c[:3, :3] @ model.axes[b].numpy()
        axis = w2c[:3, :3].T @ (flip @ axis_c)
        pivot_c = w2c[:3, :3] @ model.pivots()[b].numpy() + w2c[:3, 3]
        pivot_c[2] = 2.0 / mean_inv - pivot_c[2]
        pivot = w2c[:3, :3].T @ (pivot_c - w2c[:3, 3])
        out.axes[b] = torch.as_tensor(axis)
        out.pivot0 = out.pivots().clone()
        out.pivot0[b] = torch.as_tensor(pivot)
        out.pivot_delta.zero_()
        out.values[:, b] = -model.values[:, b]
    return out


def relabel_and_refine(model: Articulation, tracks: Tracks, config: FitConfig, steps: int) -> float:
    """Relabel the points under the model's motions, then refine it; returns the data loss."""
    new = relabel(model, tracks)
    log.info("recon=video: relabelled %d of %d points", int((new != model.labels.numpy()).sum()), len(new))
    model.labels = torch.as_tensor(new)
    return optimise(model, config, steps, neighbour_pairs(tracks.uv0, new, tracks.stride), windows=1)


def choose_kinds(hinge: Articulation, tracks: Tracks, config: FitConfig, history: list[float]) -> Articulation:
    """Each moving part as a hinge or a slide. Both readings are relabelled and refined the same way before
    their data terms are compared (labels a hinge absorbed should not decide against the slide); a hinge
    with a far pivot imitates a slide, so the slide, with fewer degrees of freedom, wins unless the hinge
    explains the images clearly better; a slide that wins then meets a hinge searched from its own reading
    (:func:`hinge_from`), by the same rule."""
    relabel_and_refine(hinge, tracks, config, config.steps // 4)
    best, best_kind = hinge, kind_loss(hinge, config)
    for b in [b for b in range(len(hinge.kinds)) if b != hinge.root]:
        trial = slide_from(best, b, tracks, config)
        history.append(relabel_and_refine(trial, tracks, config, config.steps // 4))
        trial_kind = kind_loss(trial, config)
        log.info("recon=video: part %d as a slide: kind loss %.4f (as a %s %.4f)", b, trial_kind, best.kinds[b], best_kind)
        if trial_kind < best_kind * (1.0 + SLIDE_PREFERENCE):
            # the hinge it beat was fitted on other labels and refined less: a hinge from the slide's reading,
            # searched and refined as the slide was, is the like-for-like rival
            rival = hinge_from(trial, best, b, tracks, config)
            history.append(relabel_and_refine(rival, tracks, config, config.steps // 4))
            rival_kind = kind_loss(rival, config)
            log.info("recon=video: part %d as a hinge from the slide's reading: kind loss %.4f (as a slide %.4f)",
                     b, rival_kind, trial_kind)
            best, best_kind = (trial, trial_kind) if trial_kind < rival_kind * (1.0 + SLIDE_PREFERENCE) else \
                (rival, rival_kind)
    return best


def hinge_from(slide: Articulation, hinge: Articulation, b: int, tracks: Tracks, config: FitConfig) -> Articulation:
    """Part ``b`` of the slide reading ``slide`` back on a hinge, on the slide's labels and surfaces, searched
    as :func:`slide_from` searches a slide: hinge lines (the hinge reading ``hinge``'s, the part's border with
    the root, the line in the part's plane across the slide's direction, the world's axes through the border,
    the hinge of the slide reading's free motion), each start's angles per frame matching the slide's image
    motion (Gauss-Newton), and the hinge reading's own joint as it was; the two best by :func:`kind_loss`
    fitted, the better kept."""
    kinds = list(slide.kinds)
    kinds[b] = "hinge"
    base = np.concatenate([np.zeros((1, len(kinds))), slide.values.detach().numpy()], 0)
    with torch.no_grad():
        own = (slide.labels == b).numpy()
        x0 = slide.rest().numpy()[own]
        target = project(slide.scene, slide.posed()[:, torch.as_tensor(own)]).numpy()
    lines = hinge_lines(slide, hinge, b)
    screw = screw_hinge(slide, b, config)
    if screw is not None:
        lines.append((screw[0], screw[1]))
    joints = [(axis, pivot, gauss_newton_angles(x0, axis, pivot, target, slide.scene)) for axis, pivot in lines]
    joints.append((hinge.axes.detach().numpy()[b], hinge.pivots().detach().numpy()[b],
                   np.concatenate([[0.0], hinge.values.detach().numpy()[:, b]])))
    trials = []
    for axis, pivot, angles in joints:
        axes, values = slide.axes.detach().numpy().copy(), base.copy()  # copy_with's tensors share the arrays
        axes[b], values[:, b] = axis, angles
        trials.append(with_pivot(copy_with(slide, kinds, axes, values), b, pivot))
    starts = sorted(((kind_loss(t, config), i, t) for i, t in enumerate(trials)), key=lambda x: x[:2])
    log.info("recon=video: part %d's hinge starts from the slide's reading: kind losses %s (start %s best)", b,
             [round(k, 4) for k, _, _ in sorted(starts, key=lambda x: x[1])], starts[0][1])
    pairs = neighbour_pairs(tracks.uv0, slide.labels.numpy(), tracks.stride)
    picked = [trial for _, _, trial in starts[:2]]
    fitted = run_forked([partial(fit_copy, trial, pairs, config) for trial in picked], usable_workers(config.workers))
    loss, i = min((loss, i) for i, (loss, _) in enumerate(fitted))
    picked[i].load_state_dict(fitted[i][1])
    return picked[i]


def hinge_lines(slide: Articulation, hinge: Articulation, b: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(unit axis, pivot [m]) hinge-line starts for part ``b`` of the slide reading: the hinge reading's line,
    the part's border with the root (its frame-0 points nearest the root's in the image: their mean and
    principal direction), the line in the part's plane across the slide's direction and the world's x, y, z,
    these through the border's mean."""
    labels = slide.labels.numpy()
    with torch.no_grad():
        rest = slide.rest().numpy()
        uv0 = project(slide.scene, slide.rest(), 0).numpy()
    own, root = np.flatnonzero(labels == b), labels == slide.root
    dist = cKDTree(uv0[root]).query(uv0[own])[0]
    near = rest[own[dist <= np.quantile(dist, 0.1)]]
    pivot = near.mean(0)
    border = np.linalg.svd(near - pivot, full_matrices=False)[2][0] if len(near) >= 3 else np.array([1.0, 0, 0])
    normal = np.linalg.svd(rest[own] - rest[own].mean(0), full_matrices=False)[2][-1]
    direction = slide.axes.detach().numpy()[b]
    across = np.cross(direction, normal)
    old = hinge.axes.detach().numpy()[b]
    axes = [old, border, across, *np.eye(3)]
    return [(a / max(float(np.linalg.norm(a)), 1e-12), p) for a, p in
            zip(axes, [hinge.pivots().detach().numpy()[b]] + [pivot] * (len(axes) - 1))]


def gauss_newton_angles(x0: np.ndarray, axis: np.ndarray, pivot: np.ndarray, target: np.ndarray, scene: Scene,
                        iters: int = 6) -> np.ndarray:
    """(T,) angle [rad] about the line (``pivot``, unit ``axis``) per frame whose projected rest points x0
    (N, 3) best match target pixels (T, N, 2) (Gauss-Newton, numerical derivative; the root's motion applied),
    0 at frame 0."""
    g = scene.root_motion.numpy()

    def pixels(theta: np.ndarray) -> np.ndarray:
        x = np.einsum("tij,nj->tni", rodrigues_np(axis, theta), x0 - pivot) + pivot
        x = np.einsum("tij,tnj->tni", g[:, :3, :3], x) + g[:, None, :3, 3]
        return project(scene, torch.as_tensor(x)).numpy()

    theta = np.zeros(len(target))
    for _ in range(iters):
        uv = pixels(theta)
        jac = (pixels(theta + 1e-4) - uv) / 1e-4
        step = ((target - uv) * jac).sum((1, 2)) / np.maximum((jac**2).sum((1, 2)), 1e-12)
        theta = theta + np.clip(step, -0.5, 0.5)
    return theta - theta[0]


def with_pivot(model: Articulation, b: int, pivot: np.ndarray) -> Articulation:
    """``model`` with part ``b``'s pivot at ``pivot`` (3,) [m]."""
    with torch.no_grad():
        model.pivot0 = model.pivots().clone()
        model.pivot0[b] = torch.as_tensor(pivot)
        model.pivot_delta.zero_()
    return model


def screw_hinge(model: Articulation, b: int, config: FitConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(axis, pivot [m], angles (T,) [rad]) of the hinge fitted to part ``b``'s free motion relative to the
    root on a copy of ``model`` (:func:`root_frame_motions`); None when no frame turns by
    :data:`~sync4d.recon.video.screw.MIN_ANGLE`."""
    values = np.concatenate([np.zeros((1, len(model.kinds))), model.values.detach().numpy()], 0)
    copy = copy_with(model, list(model.kinds), model.axes.detach().numpy().copy(), values)
    motions, rest, project_np = root_frame_motions(copy, config)
    own = model.labels.numpy() == b
    x0 = rest[own]
    target = project_np(np.einsum("tij,nj->tni", motions[:, b, :3, :3], x0) + motions[:, b, None, :3, 3])
    axis, pivot, angles, res = fit_hinge(motions[:, b], x0, target, project_np, model.scene.stride)
    if not np.isfinite(res).all():
        return None
    return axis, pivot, angles - angles[0]


def copy_with(model: Articulation, kinds: list[str], axes: np.ndarray, values: np.ndarray) -> Articulation:
    """A new model with the same labels, surfaces and pivots as ``model``, and these kinds, axes and values
    (values (T, B) in the model's units, frame 0 included)."""
    with torch.no_grad():
        out = Articulation(model.scene, model.labels.numpy(), model.root, kinds, axes, model.pivot0.numpy(), values,
                           model.log_depth().numpy())
        out.plane.copy_(model.plane)
        out.resid.copy_(model.resid)
        out.pivot_delta.copy_(model.pivot_delta)
    return out


def slide_from(model: Articulation, b: int, tracks: Tracks, config: FitConfig) -> Articulation:
    """Part ``b`` of ``model`` on a slide, searched over 3D directions: the direction of the part's 3D
    displacement under the current joint, its image-plane motion lifted into the image plane, that tilted
    towards and away from the camera by 45 degrees, and the view ray (a drawer pulled towards the camera);
    each start's travel per frame matches the current joint's image motion (Gauss-Newton), the two
    best by data loss are fitted, the better kept."""
    sc = model.scene
    with torch.no_grad():
        own = (model.labels == b).numpy()
        x0 = model.rest().numpy()[own]
        xt = model.posed().numpy()[:, own]
    target = project(sc, torch.as_tensor(xt)).numpy()
    kinds = list(model.kinds)
    kinds[b] = "slide"
    starts: list[tuple[float, int, Articulation]] = []
    for direction in slide_directions(x0, xt, target, sc):
        axes = model.axes.detach().numpy().copy()
        axes[b] = direction
        values = np.concatenate([np.zeros((1, len(kinds))), model.values.detach().numpy()], 0)
        values[:, b] = gauss_newton_travel(x0, direction, target, sc) / sc.width
        trial = copy_with(model, kinds, axes, values)
        starts.append((kind_loss(trial, config), len(starts), trial))
    starts.sort(key=lambda x: x[:2])
    pairs = neighbour_pairs(tracks.uv0, model.labels.numpy(), tracks.stride)
    picked = [trial for _, _, trial in starts[:2]]
    fitted = run_forked([partial(fit_copy, trial, pairs, config) for trial in picked], usable_workers(config.workers))
    loss, i = min((loss, i) for i, (loss, _) in enumerate(fitted))
    picked[i].load_state_dict(fitted[i][1])
    return picked[i]


def fit_copy(model: Articulation, pairs: torch.Tensor, config: FitConfig) -> tuple[float, dict[str, torch.Tensor]]:
    """A slide start refined (one window, ``config.steps // 8`` steps): its data loss and parameters."""
    loss = optimise(model, config, config.steps // 8, pairs, windows=1)
    return loss, model.state_dict()


def slide_directions(x0: np.ndarray, xt: np.ndarray, uv: np.ndarray, scene: Scene) -> list[np.ndarray]:
    """Unit slide-direction starts (world) for a part with rest points x0 (N, 3), posed points xt (T, N, 3)
    and their pixels uv (T, N, 2) under its current joint."""
    disp = (xt - x0[None]).mean(1)
    d3 = np.linalg.svd(disp, full_matrices=False)[2][0] if np.abs(disp).max() > 0 else np.array([1.0, 0, 0])
    c2w = np.linalg.inv(scene.w2c.numpy())
    ray = x0.mean(0) - scene.centre.numpy()
    ray /= max(np.linalg.norm(ray), 1e-12)
    flow = (uv - uv[:1]).mean(1)
    flow2 = np.linalg.svd(flow, full_matrices=False)[2][0] if np.abs(flow).max() > 0 else np.array([1.0, 0])
    lateral = c2w[:3, :3] @ np.array([flow2[0], flow2[1], 0.0])
    lateral -= ray * (lateral @ ray)
    lateral /= max(np.linalg.norm(lateral), 1e-12)
    out = [d3, lateral, lateral + ray, lateral - ray, ray]
    return [d / np.linalg.norm(d) for d in out]


def gauss_newton_travel(x0: np.ndarray, direction: np.ndarray, target: np.ndarray, scene: Scene, iters: int = 4) -> np.ndarray:
    """(T,) travel [m] along ``direction`` whose projected rest points x0 (N, 3) best match target pixels
    (T, N, 2), per frame, by a few Gauss-Newton steps on the pinhole projection."""
    w2c, K = scene.w2c.numpy(), scene.K.numpy()
    if scene.w2c_t is None:
        pc0, dc = (x0 @ w2c[:3, :3].T + w2c[:3, 3])[None], (w2c[:3, :3] @ direction)[None, None]
    else:  # each frame's camera
        w2c_t = scene.w2c_t.numpy()
        pc0 = np.einsum("tij,nj->tni", w2c_t[:, :3, :3], x0) + w2c_t[:, None, :3, 3]
        dc = np.einsum("tij,j->ti", w2c_t[:, :3, :3], direction)[:, None]
    s = np.zeros(len(target))
    for _ in range(iters):
        pc = pc0 + s[:, None, None] * dc  # (T, N, 3)
        z = np.maximum(pc[..., 2], 1e-6)
        uv = np.stack([K[0, 0] * pc[..., 0] / z + K[0, 2], K[1, 1] * pc[..., 1] / z + K[1, 2]], -1)
        jac = np.stack([K[0, 0] * (dc[..., 0] * z - pc[..., 0] * dc[..., 2]) / z**2,
                        K[1, 1] * (dc[..., 1] * z - pc[..., 1] * dc[..., 2]) / z**2], -1)
        s = s + ((target - uv) * jac).sum((1, 2)) / np.maximum((jac**2).sum((1, 2)), 1e-12)
    return s - s[0]


def joint_fit_of(model: Articulation, loss: float, history: list[float]) -> JointFit:
    """The fitted articulation of ``model`` as a :class:`JointFit` (slide values in metres)."""
    with torch.no_grad():
        axes = model.axes.numpy() / np.linalg.norm(model.axes.numpy(), axis=1, keepdims=True).clip(1e-9)
        values = np.concatenate([np.zeros((1, len(model.kinds))), model.values.numpy()], 0)
        for b, kind in enumerate(model.kinds):
            if kind == "slide":
                values[:, b] *= model.scene.width
            elif kind == "root":
                axes[b], values[:, b] = 0.0, 0.0
        return JointFit(labels=model.labels.numpy().copy(), root=model.root,
                        depth=torch.exp(model.log_depth()).numpy().copy(), kinds=list(model.kinds), axes=axes,
                        pivots=model.pivots().numpy().copy(), values=values,
                        root_motion=model.scene.root_motion.numpy().copy(), data_loss=loss, history=history)
