"""Fit the project's human skeleton to BlazePose landmarks over a whole clip (torch, CPU).

The skeleton has 17 joints (pelvis root, hips, knees, ankles, toes, neck, head, shoulders, elbows,
wrists), each read from one or two BlazePose landmarks. Per-frame joint positions X_t (T, J, 3) in the
camera frame are optimised jointly over the clip against:

* the 2D landmarks, reprojected through the camera (Huber, in units of the focal length, weighted by
  the model's visibility);
* the metric world landmarks relative to the pelvis (the model's 3D pose; fixes depth within the body);
* one set of bone lengths for the whole clip (a variable, left and right tied), so the body is rigid;
* joint limits: knees bend forward only, elbows and knees never fold below ``min_hinge_deg``;
* temporal smoothness (squared accelerations of every joint, so the prior does not depend on the frame
  rate);
* the video's optical flow: each joint's image motion from frame t to t+1 follows the DIS flow at its
  landmark's pixel, where that flow is reliable (on the person, forward-backward consistent). The
  landmarks' errors drift with the pose; the flow measures the body's own motion.

The clip's depth comes from the metric world landmarks and the focal length (a 1.7 m person spanning
h pixels is at z = f 1.7 / h), so the assumed field of view sets the distance, not the pose.

A moving camera (per-frame world-to-camera poses [m]; the video front end's are put in metres by
:func:`sync4d.recon.body_video.ground_camera`): each frame's joints stay in that frame's camera (the image
terms are unchanged), but the smoothness acts on the body in the world, ``R_t^T (X_t - c_t)``, so a pan or
a shake is the camera's motion, not the body's; the result is given in the first frame's camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from sync4d.recon.pose.blazepose import PoseTrack

# name, parent, BlazePose landmark indices averaged
HUMAN_SKELETON: tuple[tuple[str, int, tuple[int, ...]], ...] = (
    ("pelvis", -1, (23, 24)),
    ("l_hip", 0, (23,)),
    ("r_hip", 0, (24,)),
    ("l_knee", 1, (25,)),
    ("r_knee", 2, (26,)),
    ("l_ankle", 3, (27,)),
    ("r_ankle", 4, (28,)),
    ("l_toe", 5, (31,)),
    ("r_toe", 6, (32,)),
    ("neck", 0, (11, 12)),
    ("head", 9, (7, 8)),
    ("l_shoulder", 9, (11,)),
    ("r_shoulder", 9, (12,)),
    ("l_elbow", 11, (13,)),
    ("r_elbow", 12, (14,)),
    ("l_wrist", 13, (15,)),
    ("r_wrist", 14, (16,)),
)
JOINT_NAMES = tuple(n for n, _, _ in HUMAN_SKELETON)
PARENTS = np.array([p for _, p, _ in HUMAN_SKELETON], dtype=np.int64)
# (hip, knee, ankle) and (shoulder, elbow, wrist) triples for the hinge limits
KNEES = ((1, 3, 5), (2, 4, 6))
# the smoothness weight is stated for this frame rate; other rates scale the second difference by (fps/10)^2
SMOOTH_FPS = 10.0
ELBOWS = ((11, 13, 15), (12, 14, 16))


@dataclass
class HumanFitConfig:
    """Weights and schedule of the body fit (all losses are means over joints and frames).

    Attributes:
        reprojection_weight: 2D landmarks, squared error in focal-length units (~1/f^2 per px^2).
        world_weight: pelvis-relative world landmarks [1/m^2].
        bone_weight: bone lengths against the clip's shared lengths [1/m^2].
        smooth_weight: squared joint accelerations times (0.1 s)^4, i.e. the squared second difference
            of positions at 10 frames a second; other frame rates give the same prior [1/m^2].
        limit_weight: joint-limit violations [1/m^2].
        min_hinge_deg: smallest allowed elbow/knee angle [deg] (180 = straight).
        huber_px: reprojection and flow errors beyond this are down-weighted (Huber) [px].
        flow_weight: the fitted joints' image motion between frames against the optical flow at their
            landmarks (:attr:`PoseTrack.flow`), in the reprojection's units.
        iterations: L-BFGS iterations.
    """

    reprojection_weight: float = 1.0
    world_weight: float = 0.5
    bone_weight: float = 1.0
    smooth_weight: float = 0.5
    limit_weight: float = 1.0
    min_hinge_deg: float = 30.0
    huber_px: float = 10.0
    iterations: int = 60
    flow_weight: float = 1.0


@dataclass(frozen=True)
class HumanFit:
    """The fitted body motion.

    Attributes:
        joints: (T, J, 3) joint positions in the (first frame's) camera frame (OpenCV axes, y down) [m].
        names: (J,) joint names (:data:`JOINT_NAMES`).
        parents: (J,) parent index, -1 for the pelvis.
        bone_lengths: (J,) length of the segment ending at each joint (0 for the root) [m].
        reprojection_px: (T,) mean visible-landmark reprojection error per frame [px].
        extrinsics: (T, 4, 4) the per-frame world-to-camera poses the fit was seen by [m], or None (static).
    """

    joints: np.ndarray
    names: tuple[str, ...]
    parents: np.ndarray
    bone_lengths: np.ndarray
    reprojection_px: np.ndarray
    extrinsics: np.ndarray | None = None


def gather_joints(points: np.ndarray) -> np.ndarray:
    """(T, 33, D) per-landmark values -> (T, J, D) per skeleton joint (mean of its landmarks)."""
    return np.stack([points[:, list(idx)].mean(1) for _, _, idx in HUMAN_SKELETON], axis=1)


def initial_translation(world: np.ndarray, uv: np.ndarray, weight: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(T, 3) camera-frame position of the pelvis so the world landmarks reproject onto ``uv``.

    Linear least squares per frame: ``fx (X + tx) = (u - cx) (Z + tz)`` and the same for y.

    Args:
        world: (T, J, 3) pelvis-relative positions [m].
        uv: (T, J, 2) image positions [px].
        weight: (T, J) confidence per joint.
        K: (3, 3) intrinsics [px].
    """
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    out = np.zeros((len(world), 3))
    for t in range(len(world)):
        du, dv = uv[t, :, 0] - cx, uv[t, :, 1] - cy
        w = np.sqrt(np.clip(weight[t], 1e-3, None))
        rows_u = np.stack([np.full_like(du, fx), np.zeros_like(du), -du], 1)
        rows_v = np.stack([np.zeros_like(dv), np.full_like(dv, fy), -dv], 1)
        rhs_u = du * world[t, :, 2] - fx * world[t, :, 0]
        rhs_v = dv * world[t, :, 2] - fy * world[t, :, 1]
        a = np.concatenate([rows_u * w[:, None], rows_v * w[:, None]])
        b = np.concatenate([rhs_u * w, rhs_v * w])
        out[t] = np.linalg.lstsq(a, b, rcond=None)[0]
    return out


def _hinge_losses(x: torch.Tensor, min_cos: float) -> torch.Tensor:
    """Joint-limit penalty: knees bend forward only; no elbow/knee folds tighter than the minimum angle."""
    pelvis, lhip, rhip, neck = x[:, 0], x[:, 1], x[:, 2], x[:, 9]
    up = torch.nn.functional.normalize(neck - pelvis, dim=-1)
    left = torch.nn.functional.normalize(lhip - rhip, dim=-1)
    forward = torch.nn.functional.normalize(torch.cross(left, up, dim=-1), dim=-1)
    loss = x.new_zeros(())
    for a, b, c in KNEES + ELBOWS:
        u, v = x[:, a] - x[:, b], x[:, c] - x[:, b]
        cos = (u * v).sum(-1) / (u.norm(dim=-1) * v.norm(dim=-1) + 1e-9)
        # the angle at b is acos(cos); too tight a fold means cos > min_cos
        loss = loss + torch.relu(cos - min_cos).pow(2).mean() * (u.norm(dim=-1) * v.norm(dim=-1)).mean()
    for a, b, c in KNEES:
        mid = 0.5 * (x[:, a] + x[:, c])
        ahead = ((x[:, b] - mid) * forward).sum(-1)
        loss = loss + torch.relu(-ahead - 0.01).pow(2).mean()  # a knee 1 cm behind the hip-ankle line
    return loss


def camera_tensors(extrinsics: np.ndarray | None, frames: int) -> tuple[torch.Tensor, torch.Tensor]:
    """((T, 3, 3) rotations, (T, 3) translations [m]) of world-to-camera ``extrinsics`` (T, 4, 4), float64; the
    identity for a static camera (None)."""
    if extrinsics is None:
        return torch.eye(3, dtype=torch.float64).repeat(frames, 1, 1), torch.zeros((frames, 3), dtype=torch.float64)
    e = torch.tensor(np.asarray(extrinsics), dtype=torch.float64)
    return e[:, :3, :3], e[:, :3, 3]


def fit_human(track: PoseTrack, K: np.ndarray, config: HumanFitConfig, fps: float = 10.0,
              extrinsics: np.ndarray | None = None) -> HumanFit:
    """Fit the 17-joint skeleton to a :class:`PoseTrack` seen by a camera with intrinsics ``K``.

    Args:
        track: BlazePose output of T frames.
        K: (3, 3) intrinsics [px].
        config: weights and schedule.
        fps: the video's frame rate [1/s]; the smoothness acts on accelerations.
        extrinsics: (T, 4, 4) world-to-camera per frame of a moving camera, translations in metres (the
            front end's are not: :func:`sync4d.recon.body_video.ground_camera`), or None for a static camera.
    """
    world = gather_joints(track.world)
    world = world - world[:, :1]
    uv = gather_joints(track.landmarks_2d)
    vis = gather_joints(track.visibility[..., None])[..., 0] * track.found[:, None]
    trans = initial_translation(world, uv, vis, K)
    x0 = world + trans[:, None]
    seg = np.flatnonzero(PARENTS >= 0)
    lengths0 = np.median(np.linalg.norm(world[:, seg] - world[:, PARENTS[seg]], axis=-1), axis=0)
    mirror = np.array([_mirror(JOINT_NAMES[j]) for j in seg])
    lengths0 = 0.5 * (lengths0 + lengths0[mirror])

    dt = torch.float64
    x = torch.tensor(x0, dtype=dt, requires_grad=True)
    log_len = torch.tensor(np.log(np.maximum(lengths0, 1e-3)), dtype=dt, requires_grad=True)
    K_t = torch.tensor(K, dtype=dt)
    uv_t, vis_t, world_t = (torch.tensor(a, dtype=dt) for a in (uv, vis, world))
    seg_t, par_t, mir_t = (torch.tensor(a) for a in (seg, PARENTS[seg], mirror))
    focal = float(K[0, 0])
    flow = flow_targets(track, vis)
    min_cos = float(np.cos(np.radians(config.min_hinge_deg)))
    moving = extrinsics is not None
    rot, cam_t = camera_tensors(extrinsics, len(x0))
    opt = torch.optim.LBFGS([x, log_len], lr=1.0, max_iter=config.iterations, line_search_fn="strong_wolfe")

    def in_world(points: torch.Tensor) -> torch.Tensor:
        """(T, J, 3) camera-frame points -> the world, R_t^T (X - c_t)."""
        return torch.einsum("tji,tkj->tki", rot, points - cam_t[:, None])

    def closure() -> torch.Tensor:
        opt.zero_grad()
        proj = _project(x, K_t)
        err = (proj - uv_t).norm(dim=-1) / focal
        hub = config.huber_px / focal
        l_rep = (_huber(err, hub) * vis_t).sum() / vis_t.sum().clamp_min(1.0)
        rel = x - x[:, :1]
        l_world = ((rel - world_t).pow(2).sum(-1) * (0.2 + vis_t)).mean()
        seg_len = (x[:, seg_t] - x[:, par_t]).norm(dim=-1)
        lengths = 0.5 * (log_len.exp() + log_len.exp()[mir_t])
        l_bone = (seg_len - lengths).pow(2).mean()
        xw = in_world(x) if moving else x
        second = (xw[2:] - 2 * xw[1:-1] + xw[:-2]) * (fps / SMOOTH_FPS) ** 2  # acceleration x (0.1 s)^2
        l_smooth = second.pow(2).sum(-1).mean() if len(x) > 2 else x.new_zeros(())
        l_limit = _hinge_losses(x, min_cos)
        l_flow = _flow_loss(proj, flow, focal, hub) if flow is not None else x.new_zeros(())
        loss = (
            config.flow_weight * l_flow * 1e2
            + config.reprojection_weight * l_rep * 1e2
            + config.world_weight * l_world
            + config.bone_weight * l_bone
            + config.smooth_weight * l_smooth
            + config.limit_weight * l_limit
        )
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        joints = x.detach().numpy()
        err_px = (_project(x, K_t) - uv_t).norm(dim=-1).numpy()
        if moving:
            first = np.asarray(extrinsics, dtype=np.float64)[0]
            joints = in_world(x).numpy() @ first[:3, :3].T + first[:3, 3]  # the first frame's camera
    bone = np.zeros(len(PARENTS))
    bone[seg] = np.linalg.norm(joints[:, seg] - joints[:, PARENTS[seg]], axis=-1).mean(0)
    rep = (err_px * vis).sum(1) / np.maximum(vis.sum(1), 1e-9)
    return HumanFit(joints=joints, names=JOINT_NAMES, parents=PARENTS.copy(), bone_lengths=bone, reprojection_px=rep,
                    extrinsics=None if extrinsics is None else np.asarray(extrinsics, dtype=np.float64))


def flow_targets(track: PoseTrack, vis: np.ndarray) -> tuple[torch.Tensor, torch.Tensor] | None:
    """((T-1, J, 2) flow at each joint [px], (T-1, J) weight), or None without flow in the track.

    A joint read from two landmarks takes their mean flow, and only where both are reliable; the weight
    is the joint's visibility in both frames.
    """
    if track.flow is None or len(track.flow) == 0:
        return None
    fl = gather_joints(track.flow)
    ok = np.isfinite(fl).all(-1) * vis[1:] * vis[:-1]
    return torch.tensor(np.nan_to_num(fl), dtype=torch.float64), torch.tensor(ok, dtype=torch.float64)


def _flow_loss(proj: torch.Tensor, flow: tuple[torch.Tensor, torch.Tensor], focal: float, hub: float) -> torch.Tensor:
    """Huber error of the projected joints' motion against the flow, in focal-length units."""
    target, weight = flow
    err = (proj[1:] - proj[:-1] - target).norm(dim=-1) / focal
    return (_huber(err, hub) * weight).sum() / weight.sum().clamp_min(1.0)


def _huber(err: torch.Tensor, delta: float) -> torch.Tensor:
    """Huber penalty of non-negative errors: quadratic below ``delta``, linear above."""
    return torch.where(err < delta, 0.5 * err**2, delta * (err - 0.5 * delta))


def _project(x: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    z = x[..., 2:3].clamp_min(1e-3)
    return (x[..., :2] / z) * torch.stack([K[0, 0], K[1, 1]]) + torch.stack([K[0, 2], K[1, 2]])


def _mirror(name: str) -> int:
    """Index of the segment-end joint's left/right twin (itself if it has none), into the segment list."""
    seg = [JOINT_NAMES[j] for j in np.flatnonzero(PARENTS >= 0)]
    twin = "r_" + name[2:] if name.startswith("l_") else "l_" + name[2:] if name.startswith("r_") else name
    return seg.index(twin)
