"""Fit a quadruped template skeleton to the silhouettes of a video with a static camera (torch, CPU).

Template: the average pose of the AI4Animation dog trot (27 joints: hips, spine, neck, head, four legs,
tail; CC BY-NC 4.0), made mirror-symmetric and scaled. Per frame the unknowns are the root's rotation
and position and every joint's rotation relative to the template (axis-angle); one scale, one body
thickness and small per-bone length changes are shared by the clip. A body of capsules around the
segments is projected and compared with the masks as a soft silhouette (binary cross-entropy on a
coarse pixel grid) plus a term keeping points along the segments inside the mask (the mask's distance
transform); priors: limb lengths (per-bone changes near zero, left/right equal), joint limits (rotation
beyond ``joint_limit_deg`` from the template; leg joints turn mostly about the body's lateral axis),
temporal smoothness of the joints and the root. Search: root headings on the first frame, the best few
tracked frame by frame through the clip, then left/right leg swaps as explicit hypotheses; where a
silhouette cannot tell hypotheses apart, the video's optical flow (with a soft z-buffer: near parts
hide far ones) chooses.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from sync4d.errors import InputError
from sync4d.types import Camera

log = logging.getLogger(__name__)
SMOOTH_FPS = 30.0  # the frame rate at which smooth_weight is stated
DTYPE = torch.float32  # float64 doubles the cost of the silhouette, the dominant term, for no gain at this resolution

DOG_FILE = Path(__file__).resolve().parents[4] / "shared" / "data" / "motion" / "dog_mocap" / "dog_trot_joint_pos.txt"
DOG_PARENTS = np.array([-1, 0, 1, 2, 3, 4, 2, 6, 7, 8, 9, 2, 11, 12, 13, 14, 0, 16, 17, 18, 0, 20, 21, 22, 0, 24, 25])
# recon_joints vocabulary -> template joint name (dog facing -x, +z its left)
VOCABULARY = (
    ("pelvis", "pelvis"),
    ("neck", "neck"),
    ("head", "head"),
    ("tail_base", "tail_base"),
    ("fl_upper", "fl_upper"),
    ("fl_middle", "fl_middle"),
    ("fl_paw", "fl_paw"),
    ("fr_upper", "fr_upper"),
    ("fr_middle", "fr_middle"),
    ("fr_paw", "fr_paw"),
    ("hl_upper", "hl_upper"),
    ("hl_middle", "hl_middle"),
    ("hl_paw", "hl_paw"),
    ("hr_upper", "hr_upper"),
    ("hr_middle", "hr_middle"),
    ("hr_paw", "hr_paw"),
)
DOG_NAMES = (
    "pelvis",
    "spine0",
    "spine1",
    "neck",
    "head",
    "head_end",
    "fl_scapula",
    "fl_upper",
    "fl_middle",
    "fl_wrist",
    "fl_paw",
    "fr_scapula",
    "fr_upper",
    "fr_middle",
    "fr_wrist",
    "fr_paw",
    "hl_upper",
    "hl_middle",
    "hl_hock",
    "hl_paw",
    "hr_upper",
    "hr_middle",
    "hr_hock",
    "hr_paw",
    "tail_base",
    "tail1",
    "tail_end",
)
# capsule radius of the segment ending at each joint, as a fraction of the template's body length
DOG_RADII = np.array(
    [
        0,
        0.10,
        0.10,
        0.07,
        0.07,
        0.06,
        0.05,
        0.05,
        0.04,
        0.03,
        0.03,
        0.05,
        0.05,
        0.04,
        0.03,
        0.03,
        0.06,
        0.05,
        0.035,
        0.03,
        0.06,
        0.05,
        0.035,
        0.03,
        0.04,
        0.03,
        0.025,
    ]
)


@dataclass
class QuadrupedFitConfig:
    """Weights, schedule and starts of the quadruped fit.

    Attributes:
        template_length: body length (nose to tail root) of the template before scaling [m]; the scale
            is fitted, this only sets the first guess of the depth.
        starts: root headings tried on the first frame (evenly spaced over 360 degrees about the up axis).
        tracks: the best starts (by first-frame loss) tracked through the clip; the lowest clip loss wins.
        grid: silhouettes are compared on a grid this many cells across the longer side.
        start_iterations: Adam steps per start on the first frame (half of them rigid: root, scale, thickness).
        frame_iterations: Adam steps per later frame, warm-started from the previous one.
        iterations: Adam steps of the clip fit.
        swap_iterations: Adam steps of the clip fit after the leg-swap test.
        lr: Adam step size (radians / template units).
        silhouette_weight: binary cross-entropy of the soft silhouette.
        inside_weight: segment points outside the mask (distance transform, in grid cells).
        length_weight: per-bone log-length changes and left/right differences.
        limit_weight: joint rotation beyond ``joint_limit_deg``.
        joint_limit_deg: rotation of a joint from the template allowed without penalty [deg].
        leg_off_plane_deg: rotation of a leg joint about the axes other than the body's lateral one allowed
            without penalty [deg] (legs swing in the sagittal plane; abduction and twist are small).
        smooth_weight: squared second differences of the joints and root (template units) at 30 frames a
            second; other frame rates scale the differences by (fps / 30)^2, the same acceleration prior.
        background_threshold: colour distance counted as foreground by the background model (0-255),
            when the video has no masks.
    """

    template_length: float = 0.9
    starts: int = 8
    tracks: int = 3
    grid: int = 48
    start_iterations: int = 120
    frame_iterations: int = 40
    iterations: int = 100
    swap_iterations: int = 40
    lr: float = 0.03
    silhouette_weight: float = 1.0
    inside_weight: float = 0.05
    length_weight: float = 1.0
    limit_weight: float = 1.0
    joint_limit_deg: float = 50.0
    leg_off_plane_deg: float = 15.0
    smooth_weight: float = 5.0
    background_threshold: float = 30.0


@dataclass(frozen=True)
class QuadrupedFit:
    """The fitted template motion.

    Attributes:
        joints: (T, J, 3) joints in the camera frame (OpenCV axes) [m]; the metric scale is the assumed
            ``template_length`` times the fitted scale only up to the camera's unknown depth.
        names: (J,) template joint names.
        parents: (J,) parent per joint.
        radii: (J,) fitted capsule radius of the segment ending at each joint [m].
        iou: (T,) silhouette IoU of the fitted body against the masks on the fit grid.
    """

    joints: np.ndarray
    names: tuple[str, ...]
    parents: np.ndarray
    radii: np.ndarray
    iou: np.ndarray


def dog_template() -> np.ndarray:
    """(27, 3) template joints, centred on the pelvis, body length 1 (template units), facing -x, y up, +z left.

    The trot's average pose: every segment points along its mean direction over the clip (pelvis-relative),
    with the mocap's mean segment lengths, then made mirror-symmetric about the z = 0 plane (a left joint
    and its right twin averaged with z negated; midline joints put on the plane), so that a leg and its
    mirrored twin are the same rotations conjugated by the mirror. No single frame of the clip.
    """
    from sync4d.io.mocap import read_joint_positions

    if not DOG_FILE.is_file():
        raise InputError(f"quadruped template {DOG_FILE} not found; it comes with ../shared/data/motion/dog_mocap")
    pos = read_joint_positions(DOG_FILE)
    offsets = np.zeros(pos.shape[1:])
    for j in range(1, len(DOG_PARENTS)):
        off = pos[:, j] - pos[:, DOG_PARENTS[j]]
        length = float(np.linalg.norm(off, axis=-1).mean())
        mean = off.mean(0)
        offsets[j] = mean / max(np.linalg.norm(mean), 1e-12) * length if length > 1e-9 else 0.0
    twin = np.array([_twin(n) for n in DOG_NAMES])
    mirror = np.array([1.0, 1.0, -1.0])
    sym = 0.5 * (offsets + offsets[twin] * mirror)
    sym[twin == np.arange(len(twin)), 2] = 0.0
    out = np.zeros_like(sym)
    for j in range(1, len(DOG_PARENTS)):
        out[j] = out[DOG_PARENTS[j]] + sym[j]
    return out / np.linalg.norm(out[4] - out[24])


def rodrigues(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) axis-angle -> (..., 3, 3) rotation matrices (smooth at zero)."""
    theta = v.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    k = v / theta
    kx, ky, kz = k.unbind(-1)
    zero = torch.zeros_like(kx)
    kmat = torch.stack([zero, -kz, ky, kz, zero, -kx, -ky, kx, zero], -1).reshape(v.shape[:-1] + (3, 3))
    th = theta[..., None]
    eye = torch.eye(3, dtype=v.dtype).expand(kmat.shape)
    return eye + torch.sin(th) * kmat + (1 - torch.cos(th)) * (kmat @ kmat)


def forward_kinematics(
    template: torch.Tensor,
    parents: np.ndarray,
    root_rot: torch.Tensor,
    root_pos: torch.Tensor,
    local: torch.Tensor,
    log_len: torch.Tensor,
    scale: torch.Tensor,
) -> torch.Tensor:
    """(T, J, 3) joint positions.

    Args:
        template: (J, 3) rest joints (template units).
        parents: (J,) parents (parents precede children).
        root_rot: (T, 3) root axis-angle; root_pos: (T, 3) root position [m].
        local: (T, J, 3) joint axis-angles relative to the template (the rotation of joint j turns its
            children's segments).
        log_len: (J,) log length change of the segment ending at each joint.
        scale: () metres per template unit.
    """
    rot_local = rodrigues(local)
    world_rot = [None] * len(parents)
    pos = [None] * len(parents)
    r0 = rodrigues(root_rot) @ rot_local[:, 0]
    world_rot[0], pos[0] = r0, root_pos
    for j in range(1, len(parents)):
        p = int(parents[j])
        off = (template[j] - template[p]) * torch.exp(log_len[j]) * scale
        pos[j] = pos[p] + (world_rot[p] @ off)
        world_rot[j] = world_rot[p] @ rot_local[:, j]
    return torch.stack(pos, 1)


def segment_ends(
    joints: torch.Tensor, parents: np.ndarray, radii: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(T, S, 3) parent and child ends [m, camera frame] of every segment and (T, S) its radius divided by
    its midpoint's depth (times the focal length: the radius in pixels)."""
    seg = np.flatnonzero(parents >= 0)
    a, b = joints[:, parents[seg]], joints[:, seg]
    return a, b, radii[seg] / (0.5 * (a[..., 2] + b[..., 2])).clamp_min(1e-3)


def project_points(x: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(..., 2) pixel positions of camera-frame points x (..., 3) [m] under intrinsics K (3, 3)."""
    return x[..., :2] / x[..., 2:].clamp_min(1e-3) * K[0, 0] + K[:2, 2]


def soft_silhouette(
    joints: torch.Tensor,
    parents: np.ndarray,
    radii: torch.Tensor,
    K: torch.Tensor,
    grid_uv: torch.Tensor,
    tau_px: float,
) -> torch.Tensor:
    """(T, P) soft occupancy of capsules around the segments at pixel positions ``grid_uv`` (P, 2).

    Each segment projects to a 2D segment with a radius ``r f / z`` (z at its midpoint); occupancy is the
    union of ``sigmoid((radius - distance) / tau_px)`` over segments.
    """
    a, b, r_px = segment_ends(joints, parents, radii)
    ua, ub = project_points(a, K), project_points(b, K)
    r_px = r_px * K[0, 0]
    d = ub - ua  # (T, S, 2)
    rel = grid_uv[None, None] - ua[:, :, None]  # (T, S, P, 2)
    s = ((rel * d[:, :, None]).sum(-1) / (d * d).sum(-1).clamp_min(1e-9)[..., None]).clamp(0, 1)
    dist = (rel - s[..., None] * d[:, :, None]).norm(dim=-1)
    occ = torch.sigmoid((r_px[..., None] - dist) / tau_px)
    return 1 - torch.exp(torch.log1p(-occ.clamp(max=1 - 1e-6)).sum(1))


def predicted_flow(
    joints: torch.Tensor,
    parents: np.ndarray,
    radii: torch.Tensor,
    K: torch.Tensor,
    grid_uv: torch.Tensor,
    tau_px: float,
    depth_tau: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Image motion of the capsule body from frame t to t+1 at pixel positions ``grid_uv`` (P, 2).

    Each segment's point nearest to a pixel (in the image at t) keeps its place along the segment at t+1;
    where segments overlap, the nearest in depth wins (a soft z-buffer over ``exp(-dz / depth_tau)``, dz
    [m]). Returns the (T-1, P, 2) flow [px] and (T-1, P) the body's soft occupancy at t.
    """
    a, b, r_px = segment_ends(joints, parents, radii)
    ua, ub = project_points(a, K), project_points(b, K)
    r_px = r_px * K[0, 0]
    d = (ub - ua)[:-1]
    rel = grid_uv[None, None] - ua[:-1, :, None]  # (T-1, S, P, 2)
    s = ((rel * d[:, :, None]).sum(-1) / (d * d).sum(-1).clamp_min(1e-9)[..., None]).clamp(0, 1)
    dist = (rel - s[..., None] * d[:, :, None]).norm(dim=-1)
    occ = torch.sigmoid((r_px[:-1, :, None] - dist) / tau_px)  # (T-1, S, P)
    sv = s[..., None]
    p0 = a[:-1, :, None] * (1 - sv) + b[:-1, :, None] * sv  # (T-1, S, P, 3)
    p1 = a[1:, :, None] * (1 - sv) + b[1:, :, None] * sv
    flow = project_points(p1, K) - project_points(p0, K)
    z = p0[..., 2]
    w = occ * torch.exp(-(z - z.min(1, keepdim=True).values) / depth_tau)
    body = 1 - torch.exp(torch.log1p(-occ.clamp(max=1 - 1e-6)).sum(1))
    return (w[..., None] * flow).sum(1) / w.sum(1).clamp_min(1e-6)[..., None], body


def video_flow(frames: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(T-1, P, 2) DIS optical flow (OpenCV, medium preset) from frame t to t+1 at pixels ``uv`` (P, 2) [px]."""
    import cv2

    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    grey = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in frames]
    h, w = grey[0].shape
    iu = np.clip(uv[:, 0].astype(int), 0, w - 1)
    iv = np.clip(uv[:, 1].astype(int), 0, h - 1)
    return np.stack([dis.calc(grey[t], grey[t + 1], None)[iv, iu] for t in range(len(grey) - 1)])


def mask_box(masks: np.ndarray, margin: float = 0.15) -> tuple[int, int, int, int]:
    """(u0, v0, u1, v1) pixel box around every frame's mask, enlarged by ``margin`` of its size each side."""
    ys, xs = np.nonzero(masks.any(0))
    h, w = masks.shape[1:]
    du, dv = margin * (xs.max() - xs.min() + 1), margin * (ys.max() - ys.min() + 1)
    return (
        max(0, int(xs.min() - du)),
        max(0, int(ys.min() - dv)),
        min(w, int(xs.max() + du) + 1),
        min(h, int(ys.max() + dv) + 1),
    )


def _grid(box: tuple[int, int, int, int], cells: int) -> tuple[np.ndarray, int, int]:
    """Cell centres (P, 2) [px] of a grid ``cells`` across the longer side of ``box``, and its size."""
    u0, v0, u1, v1 = box
    step = max(u1 - u0, v1 - v0) / cells
    gw, gh = max(1, int(round((u1 - u0) / step))), max(1, int(round((v1 - v0) / step)))
    us = u0 + (np.arange(gw) + 0.5) * (u1 - u0) / gw
    vs = v0 + (np.arange(gh) + 0.5) * (v1 - v0) / gh
    uu, vv = np.meshgrid(us, vs)
    return np.stack([uu.ravel(), vv.ravel()], 1), gw, gh


def _coarse_masks(masks: np.ndarray, box: tuple[int, int, int, int], gw: int, gh: int) -> np.ndarray:
    import cv2

    u0, v0, u1, v1 = box
    return np.stack(
        [cv2.resize(m[v0:v1, u0:u1].astype(np.float32), (gw, gh), interpolation=cv2.INTER_AREA) for m in masks]
    )


def _outside_distance(coarse: np.ndarray) -> np.ndarray:
    import cv2

    return np.stack([cv2.distanceTransform((m < 0.5).astype(np.uint8), cv2.DIST_L2, 3) for m in coarse])


def _initial_root(mask: np.ndarray, camera: Camera, length: float, world_up: np.ndarray) -> np.ndarray:
    """(3,) camera-frame root guess: the mask centroid back-projected at the depth its width implies."""
    ys, xs = np.nonzero(mask)
    width_px = max(xs.max() - xs.min(), ys.max() - ys.min(), 4)
    K = camera.K
    z = K[0, 0] * length / width_px
    u, v = xs.mean(), ys.mean()
    return np.array([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])


def _heading_rotation(up_cam: np.ndarray, angle: float) -> np.ndarray:
    """Axis-angle (3,) taking the template (y up, facing -x) to the camera frame, turned by ``angle`` about up."""
    from scipy.spatial.transform import Rotation

    # template y -> camera up; template -x then turned about up by angle
    up = up_cam / np.linalg.norm(up_cam)
    fwd = np.cross(up, [0.0, 0.0, 1.0]) if abs(up[2]) < 0.9 else np.cross(up, [1.0, 0.0, 0.0])
    fwd /= np.linalg.norm(fwd)
    base = np.stack([-fwd, up, np.cross(-fwd, up)], axis=1)  # columns: images of template x, y, z
    turn = Rotation.from_rotvec(up * angle).as_matrix()
    return Rotation.from_matrix(turn @ base).as_rotvec()


class _Problem:
    """The tensors of one fit: coarse masks, distance fields, grid, camera, template."""

    def __init__(
        self, masks: np.ndarray, camera: Camera, cfg: QuadrupedFitConfig, frames: np.ndarray | None = None
    ) -> None:
        self.box = mask_box(masks)
        uv, self.gw, self.gh = _grid(self.box, cfg.grid)
        coarse = _coarse_masks(masks, self.box, self.gw, self.gh)
        dt = DTYPE
        self.target = torch.tensor(coarse.reshape(len(masks), -1), dtype=dt)
        self.outside = torch.tensor(_outside_distance(coarse), dtype=dt)
        self.uv = torch.tensor(uv, dtype=dt)
        self.K = torch.tensor(camera.K, dtype=dt)
        self.tau = max(self.box[2] - self.box[0], self.box[3] - self.box[1]) / cfg.grid * 0.5
        self.template = torch.tensor(dog_template(), dtype=dt)
        self.radii = torch.tensor(DOG_RADII, dtype=dt)
        self.camera = camera
        self.twin = np.array([_twin(n) for n in DOG_NAMES])
        self.rate = 1.0  # frame rate / SMOOTH_FPS
        self.leg_joints = np.array([j for j, n in enumerate(DOG_NAMES) if n[:3] in ("fl_", "fr_", "hl_", "hr_")])
        self.flow = None if frames is None or len(frames) < 2 else torch.tensor(video_flow(frames, uv), dtype=dt)


def _twin(name: str) -> int:
    """Index of the left/right twin of a template joint (itself if none)."""
    for a, b in (("fl_", "fr_"), ("fr_", "fl_"), ("hl_", "hr_"), ("hr_", "hl_")):
        if name.startswith(a):
            return DOG_NAMES.index(b + name[3:])
    return DOG_NAMES.index(name)


def _joints(prob: _Problem, params: dict[str, torch.Tensor]) -> torch.Tensor:
    return forward_kinematics(
        prob.template,
        DOG_PARENTS,
        params["root_rot"],
        params["root_pos"],
        params["local"],
        params["log_len"],
        params["log_scale"].exp(),
    )


def _losses(
    prob: _Problem,
    frames: np.ndarray,
    params: dict[str, torch.Tensor],
    cfg: QuadrupedFitConfig,
    history: torch.Tensor | None = None,
):
    """Total loss, joints (T, J, 3) and soft silhouettes (T, P) of ``params`` on ``frames``.

    ``history``: (2, J + 1, 3) root-relative joints and root of the two frames before a one-frame fit
    (template units), for the smoothness term.
    """
    scale = params["log_scale"].exp()
    joints = _joints(prob, params)
    occ = soft_silhouette(
        joints, DOG_PARENTS, prob.radii * scale * params["log_thick"].exp(), prob.K, prob.uv, prob.tau
    )
    tgt = prob.target[frames]
    bce = -(tgt * torch.log(occ.clamp(1e-5)) + (1 - tgt) * torch.log((1 - occ).clamp(1e-5))).mean()
    # points along segments must land inside the mask
    seg = np.flatnonzero(DOG_PARENTS >= 0)
    s = torch.linspace(0, 1, 5, dtype=DTYPE)[None, None, :, None]
    pts = joints[:, DOG_PARENTS[seg]][:, :, None] * (1 - s) + joints[:, seg][:, :, None] * s
    uv = pts[..., :2] / pts[..., 2:].clamp_min(1e-3) * prob.K[0, 0] + prob.K[:2, 2]
    u0, v0, u1, v1 = prob.box
    gx = (uv[..., 0] - u0) / (u1 - u0) * 2 - 1
    gy = (uv[..., 1] - v0) / (v1 - v0) * 2 - 1
    grid = torch.stack([gx, gy], -1).reshape(len(frames), 1, -1, 2)
    dist = torch.nn.functional.grid_sample(
        prob.outside[frames][:, None], grid, align_corners=False, padding_mode="border"
    )
    inside = dist.pow(2).mean()
    # root-relative joints and the root itself (template units): both move smoothly
    rel = torch.cat([joints - joints[:, :1], joints[:, :1]], 1) / scale
    if history is not None:
        rel = torch.cat([history, rel])
    second = (rel[2:] - 2 * rel[1:-1] + rel[:-2]) * prob.rate**2
    smooth = second.pow(2).sum(-1).mean() if len(rel) > 2 else joints.new_zeros(())
    lengths, limit = shape_priors(prob, params, cfg)
    total = (
        cfg.silhouette_weight * bce
        + cfg.inside_weight * inside
        + cfg.length_weight * lengths
        + cfg.limit_weight * limit
        + cfg.smooth_weight * smooth
    )
    return total, joints, occ


def shape_priors(
    prob: _Problem, params: dict[str, torch.Tensor], cfg: QuadrupedFitConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """The unweighted limb-length prior and joint-limit penalty of ``params``."""
    ll = params["log_len"]
    lengths = ll.pow(2).mean() + (ll - ll[prob.twin]).pow(2).mean()
    local = params["local"]
    limit = torch.relu(local.norm(dim=-1) - math.radians(cfg.joint_limit_deg)).pow(2).mean()
    # legs swing in the body's sagittal plane: their rotations turn mostly about the lateral (z) axis
    off = local[:, prob.leg_joints, :2].norm(dim=-1)
    limit = limit + torch.relu(off - math.radians(cfg.leg_off_plane_deg)).pow(2).mean()
    return lengths, limit


def _run(
    prob: _Problem,
    frames: np.ndarray,
    params: dict[str, torch.Tensor],
    cfg: QuadrupedFitConfig,
    steps: int,
    *,
    free: tuple[str, ...] | None = None,
    history: torch.Tensor | None = None,
):
    """``steps`` Adam steps on ``params`` (only the names in ``free``, default all); returns (loss, joints, IoU)."""
    opt = torch.optim.Adam([v for k, v in params.items() if free is None or k in free], lr=cfg.lr)
    for _ in range(steps):
        opt.zero_grad()
        loss, _, _ = _losses(prob, frames, params, cfg, history)
        loss.backward()
        opt.step()
    with torch.no_grad():
        loss, joints, occ = _losses(prob, frames, params, cfg, history)
    pred, tgt = occ > 0.5, prob.target[frames] > 0.5
    iou = ((pred & tgt).sum(1) / (pred | tgt).sum(1).clamp_min(1)).numpy()
    return float(loss), joints.numpy().astype(np.float64), iou


LEGS = {pair: [DOG_NAMES.index(n) for n in DOG_NAMES if n.startswith(pair)] for pair in ("fl_", "fr_", "hl_", "hr_")}
MIRROR = torch.tensor([-1.0, -1.0, 1.0], dtype=DTYPE)  # axis-angle under the z -> -z mirror: -M v


def swap_legs(local: torch.Tensor, pairs: tuple[str, ...]) -> torch.Tensor:
    """(T, J, 3) joint rotations with each pair's left and right legs exchanged and mirrored (``"f"``, ``"h"``).

    On the mirror-symmetric template this puts each leg where the mirror image of its twin was.
    """
    out = local.clone()
    for pair in pairs:
        left, right = LEGS[pair + "l_"], LEGS[pair + "r_"]
        out[:, left], out[:, right] = local[:, right] * MIRROR, local[:, left] * MIRROR
    return out


def flow_error(prob: _Problem, params: dict[str, torch.Tensor]) -> float:
    """Mean distance [grid cells] between the body's predicted image motion and the video's optical flow, over
    the cells inside both the mask and the body; 0 when the video has fewer than two frames."""
    if prob.flow is None:
        return 0.0
    with torch.no_grad():
        joints = _joints(prob, params)
        scale = params["log_scale"].exp()
        flow, body = predicted_flow(
            joints,
            DOG_PARENTS,
            prob.radii * scale * params["log_thick"].exp(),
            prob.K,
            prob.uv,
            prob.tau,
            0.03 * float(scale),
        )
        keep = (body > 0.5) & (prob.target[:-1] > 0.5)
        err = (flow - prob.flow).norm(dim=-1)
    return float(err[keep].mean()) / (2 * prob.tau) if keep.any() else 0.0


RIGID = ("root_rot", "root_pos", "log_scale", "log_thick")
CLIP = ("log_len", "log_scale", "log_thick")


def _frame_params(params: dict[str, torch.Tensor], t: int) -> dict[str, torch.Tensor]:
    """Leaf copies of frame ``t``'s per-frame tensors and of the clip's shared ones."""
    return {
        k: (v.detach()[t : t + 1] if k not in CLIP else v.detach()).clone().requires_grad_(True)
        for k, v in params.items()
    }


def _track(prob: _Problem, start: dict[str, torch.Tensor], cfg: QuadrupedFitConfig, n: int) -> dict[str, torch.Tensor]:
    """Clip parameters from a first-frame fit: every later frame warm-started from the previous one (root
    extrapolated at constant velocity), smoothed against the two frames before it."""
    frames = [start]
    for t in range(1, n):
        prev = frames[-1]
        cur = _frame_params(prev, 0)
        if t >= 2:
            with torch.no_grad():
                cur["root_pos"] += prev["root_pos"].detach() - frames[-2]["root_pos"].detach()
        with torch.no_grad():
            past = [
                torch.cat([j - j[:, :1], j[:, :1]], 1) / p["log_scale"].exp()
                for p, j in ((p, _joints(prob, p)) for p in frames[-2:])
            ]
        history = torch.cat(past) if len(past) == 2 else None
        _run(prob, np.array([t]), cur, cfg, cfg.frame_iterations, history=history)
        frames.append(cur)
    return {
        k: (
            torch.cat([p[k].detach() for p in frames]) if k not in CLIP else frames[-1][k].detach().clone()
        ).requires_grad_(True)
        for k in frames[0]
    }


def fit_quadruped(
    masks: np.ndarray,
    camera: Camera,
    cfg: QuadrupedFitConfig,
    *,
    source: str,
    world_up: np.ndarray | None = None,
    frames: np.ndarray | None = None,
    fps: float = SMOOTH_FPS,
) -> QuadrupedFit:
    """Fit the dog template to (T, H, W) bool masks seen by a static ``camera``.

    1. first frame: ``starts`` root headings about the up axis, each fitted rigidly (root, scale, body
       thickness) and then with its joints; the lowest loss wins;
    2. every later frame warm-started from the previous one (root extrapolated at constant velocity),
       smoothed against the two frames before it;
    3. the whole clip refined together, for each of the ``tracks`` best starts;
    4. each track with the fore and/or hind legs swapped left for right (mirrored): a silhouette cannot
       tell these apart, nor a heading from its mirror in depth; the hypothesis whose predicted image
       motion best matches the optical flow of ``frames`` (near parts hide far ones) wins and is refined.

    Args:
        masks: (T, H, W) bool subject masks.
        camera: the camera (intrinsics used; the fit is in its frame).
        cfg: weights, schedule, starts.
        source: the video's name, for messages.
        world_up: (3,) world up direction, used to orient the starts; None = the camera's -y.
        frames: (T, H, W, 3) uint8 video frames for the optical flow; None = no flow (the clip loss ranks
            the hypotheses).
        fps: the video's frame rate [1/s]; the smoothness acts on accelerations.

    Raises:
        InputError: a frame's mask is empty.
    """
    empty = np.flatnonzero(~masks.any((1, 2)))
    if len(empty):
        raise InputError(
            f"{source}: the subject's mask is empty in {len(empty)} frame(s) (first: {empty[0]}); "
            "give masks (reference.masks) or a video with a static camera and a moving subject"
        )
    n = len(masks)
    prob = _Problem(masks, camera, cfg, frames)
    prob.rate = fps / SMOOTH_FPS
    up_cam = np.array([0.0, -1.0, 0.0])
    if world_up is not None:
        up_cam = camera.world_to_cam[:3, :3] @ np.asarray(world_up, dtype=np.float64)
    root0 = _initial_root(masks[0], camera, cfg.template_length, up_cam)
    dt = DTYPE
    nj = len(DOG_PARENTS)
    first = np.arange(1)
    starts = []
    for k in range(cfg.starts):
        rot = _heading_rotation(up_cam, 2 * math.pi * k / cfg.starts)
        params = {
            "root_rot": torch.tensor(rot[None], dtype=dt, requires_grad=True),
            "root_pos": torch.tensor(root0[None], dtype=dt, requires_grad=True),
            "local": torch.zeros(1, nj, 3, dtype=dt, requires_grad=True),
            "log_len": torch.zeros(nj, dtype=dt, requires_grad=True),
            "log_scale": torch.tensor(math.log(cfg.template_length), dtype=dt, requires_grad=True),
            "log_thick": torch.zeros((), dtype=dt, requires_grad=True),
        }
        _run(prob, first, params, cfg, cfg.start_iterations // 2, free=RIGID)
        loss, _, iou = _run(prob, first, params, cfg, cfg.start_iterations - cfg.start_iterations // 2)
        log.info(
            "quadruped start %d/%d (heading %.0f deg): loss %.4f, IoU %.3f",
            k + 1,
            cfg.starts,
            360 * k / cfg.starts,
            loss,
            iou.mean(),
        )
        starts.append((loss, k, params))
    # hypotheses: each tracked start, with and without the fore and hind legs swapped (the silhouette
    # cannot tell them apart, nor a heading from its mirror in depth); the optical flow decides, the
    # clip loss when the video has no flow
    best = None
    for _, k, params in sorted(starts, key=lambda x: x[0])[: cfg.tracks]:
        full = _track(prob, params, cfg, n)
        loss, _, _ = _run(prob, np.arange(n), full, cfg, cfg.iterations)
        for pairs in ((), ("f",), ("h",), ("f", "h")) if prob.flow is not None else ((),):
            trial = {**full, "local": swap_legs(full["local"].detach(), pairs)}
            score = flow_error(prob, trial) if prob.flow is not None else loss
            log.info(
                "quadruped hypothesis heading %.0f deg, legs swapped: %s: %s %.4f",
                360 * k / cfg.starts,
                "+".join(pairs) or "none",
                "flow error" if prob.flow is not None else "loss",
                score,
            )
            if best is None or score < best[0]:
                best = (score, trial)
    full = {k: v.detach().clone().requires_grad_(True) for k, v in best[1].items()}
    loss, joints, iou = _run(prob, np.arange(n), full, cfg, cfg.swap_iterations if prob.flow is not None else 0)
    radii = DOG_RADII * float((full["log_scale"].exp() * full["log_thick"].exp()).detach())
    log.info(
        "quadruped fit of %s: %d frames, silhouette IoU %.3f (min %.3f), loss %.4f",
        source,
        n,
        iou.mean(),
        iou.min(),
        loss,
    )
    return QuadrupedFit(joints=joints, names=DOG_NAMES, parents=DOG_PARENTS.copy(), radii=radii, iou=iou)


def render_silhouettes(
    joints: np.ndarray, parents: np.ndarray, camera: Camera, radii: np.ndarray | None = None
) -> np.ndarray:
    """(T, H, W) bool silhouettes of capsules around ``joints`` (camera frame) at full size.

    ``radii``: (J,) radius of the segment ending at each joint [m]; None = the template's, scaled to the body.
    """
    if radii is None:
        radii = DOG_RADII * float(np.linalg.norm(joints[0, 4] - joints[0, 24]))
    uv, gw, gh = _grid((0, 0, camera.width, camera.height), max(camera.width, camera.height))
    out = []
    with torch.no_grad():
        for t in range(len(joints)):  # one frame at a time: (S, P) distances at full resolution
            occ = soft_silhouette(
                torch.tensor(joints[t : t + 1], dtype=DTYPE),
                parents,
                torch.tensor(radii, dtype=DTYPE),
                torch.tensor(camera.K, dtype=DTYPE),
                torch.tensor(uv, dtype=DTYPE),
                0.5,
            )
            out.append(occ.numpy()[0].reshape(gh, gw) > 0.5)
    return np.stack(out)
