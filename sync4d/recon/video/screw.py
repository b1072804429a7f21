"""A joint from a part's recovered 3D motion over the whole clip: hinge, slide or fixed, decided by evidence.

Given the rigid motions M_t (T, 4, 4) of a part relative to its parent since frame 0 (recovered freely, one
per frame) and the part's rest points X (N, 3) [m], each kind of joint is fitted to all frames at once:

    * hinge: a line (axis a through pivot p) and an angle per frame; hypotheses are the screw axes of
      single frames (RANSAC over frames: a frame's motion alone fixes a screw), each scored over every frame
      with its best angle per frame (closed form), the best refined by least squares on its inlier frames;
    * slide: a direction and a travel per frame; hypotheses are single frames' mean displacements, refined
      as the principal direction of the inlier frames' displacements;
    * fixed: no motion.

A frame's residual r_t is the RMS distance between the part's points under M_t and under the joint, in
pixels of the frame's camera divided by the tracking stride (the unit of the image terms the motions came
from). The cost of a kind is sum_t log(1 + r_t^2) (a Cauchy likelihood of one stride: a bad frame costs
little more than a poor one and cannot turn the axis, yet a still joint on a part that turns keeps paying)
plus log(T) / 2 per parameter of the joint's line (hinge 4, slide 2, fixed 0: a BIC charge). The values per
frame are charged to no kind: they are what the motion is, and fixed is the joint whose values are all
zero (charging them, T - 1 each, made a plate turning 40 deg over 6 frames read as fixed). RANSAC
hypotheses are scored by the same sum, their inliers are the frames within ``OUTLIER``. The kind of least
cost wins.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

OUTLIER = 2.0  # a residual [strides] beyond which a frame is an outlier of a joint (for the refinement)
MIN_ANGLE = np.radians(2.0)  # frames turned less give no axis hypothesis

Project = Callable[[np.ndarray], np.ndarray]  # (T, N, 3) world points -> (T, N, 2) pixels [px] of each frame


@dataclass(frozen=True)
class ScrewFit:
    """The joint fitted to a part's motions.

    Attributes:
        kind: ``hinge``, ``slide`` or ``fixed``.
        axis: (3,) unit axis (hinge) or direction (slide), zeros when fixed.
        pivot: (3,) a point on the hinge's axis [m] (the points' centroid's foot on it; zeros otherwise).
        values: (T,) angle [rad] about ``axis`` or travel [m] along it, per frame (0 at frame 0).
        residuals: (T,) per-frame residual of the chosen joint [strides].
        costs: the penalised cost of every kind [strides^2].
    """

    kind: str
    axis: np.ndarray
    pivot: np.ndarray
    values: np.ndarray
    residuals: np.ndarray
    costs: dict[str, float]

    def motions(self) -> np.ndarray:
        """(T, 4, 4) the joint's motions since frame 0."""
        return joint_motions(self.kind, self.axis, self.pivot, self.values)


def joint_motions(kind: str, axis: np.ndarray, pivot: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(T, 4, 4) rigid motions of a ``hinge`` (angles ``values`` [rad] about the line through ``pivot`` along
    the unit ``axis``), a ``slide`` (travel [m] along ``axis``) or ``fixed`` (identity)."""
    out = np.tile(np.eye(4), (len(values), 1, 1))
    if kind == "hinge":
        rot = Rotation.from_rotvec(values[:, None] * axis[None]).as_matrix()
        out[:, :3, :3] = rot
        out[:, :3, 3] = pivot - rot @ pivot
    elif kind == "slide":
        out[:, :3, 3] = values[:, None] * axis[None]
    return out


def hinge_angles(axis: np.ndarray, pivot: np.ndarray, x0: np.ndarray, xt: np.ndarray) -> np.ndarray:
    """(T,) the angle [rad] about the line (``pivot``, unit ``axis``) that best carries the rest points x0
    (N, 3) onto xt (T, N, 3) in least squares (closed form)."""
    u = x0 - pivot
    u_perp = u - (u @ axis)[:, None] * axis
    v = xt - pivot
    cos = np.einsum("tnj,nj->t", v, u_perp)
    sin = np.einsum("tnj,nj->t", v, np.cross(axis, u_perp))
    return np.arctan2(sin, cos)


def _apply(motions: np.ndarray, x0: np.ndarray) -> np.ndarray:
    return np.einsum("tij,nj->tni", motions[:, :3, :3], x0) + motions[:, None, :3, 3]


def frame_residuals(pred: np.ndarray, target_uv: np.ndarray, project: Project, stride: float) -> np.ndarray:
    """(T,) RMS image distance [strides] between the projections of pred (T, N, 3) and target_uv (T, N, 2)."""
    return np.sqrt(((project(pred) - target_uv) ** 2).sum(-1).mean(1)) / stride


def robust_cost(res: np.ndarray) -> float:
    """sum_t log(1 + r_t^2) of the frames' residuals r_t (T,) [strides] (Cauchy)."""
    return float(np.log1p(res**2).sum())


def _hinge_of(axis: np.ndarray, pivot: np.ndarray, x0: np.ndarray, xt: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The hinge (unit axis, pivot at the points' centroid's foot, angles) through ``pivot`` along ``axis``."""
    axis = axis / np.linalg.norm(axis)
    c = x0.mean(0)
    pivot = pivot + ((c - pivot) @ axis) * axis
    return axis, pivot, hinge_angles(axis, pivot, x0, xt)


def fit_hinge(motions: np.ndarray, x0: np.ndarray, target: np.ndarray, project: Project, stride: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(axis, pivot, angles (T,), residuals (T,)) of the hinge fitted to ``motions`` (T, 4, 4) of rest
    points x0 (N, 3) whose recovered pixels are ``target`` (T, N, 2): RANSAC over frames, then least squares
    on the inlier frames (infinite residuals when no frame turns by MIN_ANGLE)."""
    xt = _apply(motions, x0)
    rotvec = Rotation.from_matrix(motions[:, :3, :3]).as_rotvec()
    angle = np.linalg.norm(rotvec, axis=1)
    frames = np.flatnonzero(angle > MIN_ANGLE)
    if not len(frames):  # no frame turns: no axis to read (a hinge cannot explain it better than a slide)
        return np.zeros(3), np.zeros(3), np.zeros(len(motions)), np.full(len(motions), np.inf)
    best: tuple[float, np.ndarray, np.ndarray] | None = None
    for t in frames:
        axis = rotvec[t] / max(angle[t], 1e-12)
        pivot = np.linalg.lstsq(np.eye(3) - motions[t, :3, :3], motions[t, :3, 3], rcond=None)[0]
        axis, pivot, ang = _hinge_of(axis, pivot, x0, xt)
        cost = robust_cost(frame_residuals(_apply(joint_motions("hinge", axis, pivot, ang), x0), target, project, stride))
        if best is None or cost < best[0]:
            best = (cost, axis, pivot)
    assert best is not None
    _, axis, pivot = best
    res = frame_residuals(_apply(joint_motions("hinge", axis, pivot, hinge_angles(axis, pivot, x0, xt)), x0),
                          target, project, stride)
    inl = res < OUTLIER
    if inl.sum() >= 2:
        axis, pivot = _refine_hinge(axis, pivot, x0, xt[inl], target[inl], project_subset(project, inl), stride)
    axis, pivot, ang = _hinge_of(axis, pivot, x0, xt)
    res = frame_residuals(_apply(joint_motions("hinge", axis, pivot, ang), x0), target, project, stride)
    return axis, pivot, ang, res


def project_subset(project: Project, frames: np.ndarray) -> Project:
    """``project`` for a subset of frames (bool (T,)): called with only those frames' points."""
    def sub(x: np.ndarray) -> np.ndarray:
        full = np.empty((len(frames),) + x.shape[1:])
        full[frames] = x
        full[~frames] = x[:1]  # any points in front of the camera
        return project(full)[frames]
    return sub


def _refine_hinge(axis: np.ndarray, pivot: np.ndarray, x0: np.ndarray, xt: np.ndarray, target: np.ndarray,
                  project: Project, stride: float) -> tuple[np.ndarray, np.ndarray]:
    """Axis and pivot by least squares of the image residuals over frames (angles in closed form per step)."""
    scale = float(np.linalg.norm(x0 - x0.mean(0), axis=1).mean()) or 1.0

    def residuals(p: np.ndarray) -> np.ndarray:
        a = p[:3] / max(np.linalg.norm(p[:3]), 1e-12)
        piv = pivot + scale * p[3:]
        ang = hinge_angles(a, piv, x0, xt)
        return ((project(_apply(joint_motions("hinge", a, piv, ang), x0)) - target) / stride).ravel()

    sol = least_squares(residuals, np.concatenate([axis, np.zeros(3)]), max_nfev=30, loss="soft_l1", f_scale=1.0)
    return sol.x[:3] / np.linalg.norm(sol.x[:3]), pivot + scale * sol.x[3:]


def fit_slide(motions: np.ndarray, x0: np.ndarray, target: np.ndarray, project: Project, stride: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(direction, travel (T,) [m], residuals (T,)) of the slide fitted to ``motions`` (RANSAC over frames'
    mean displacements, then the principal direction of the inlier frames')."""
    xt = _apply(motions, x0)
    disp = (xt - x0[None]).mean(1)
    norms = np.linalg.norm(disp, axis=1)
    best: tuple[float, np.ndarray] | None = None

    def evaluate(direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        travel = disp @ direction
        return travel, frame_residuals(_apply(joint_motions("slide", direction, np.zeros(3), travel), x0), target,
                                       project, stride)

    for t in np.flatnonzero(norms > 1e-9 * max(norms.max(), 1e-12)) if norms.max() > 0 else []:
        direction = disp[t] / norms[t]
        cost = robust_cost(evaluate(direction)[1])
        if best is None or cost < best[0]:
            best = (cost, direction)
    if best is None:
        return np.array([1.0, 0, 0]), np.zeros(len(motions)), evaluate(np.array([1.0, 0, 0]))[1]
    direction = best[1]
    inl = evaluate(direction)[1] < OUTLIER
    if inl.sum() >= 2:
        d = np.linalg.svd(disp[inl], full_matrices=False)[2][0]
        direction = d * np.sign(d @ direction)
    travel, res = evaluate(direction)
    return direction, travel, res


def fit_screw(motions: np.ndarray, x0: np.ndarray, project: Project, stride: float) -> ScrewFit:
    """The joint of least penalised cost (module docstring) for motions (T, 4, 4) since frame 0 of a part
    with rest points x0 (N, 3) [m]; ``project`` maps (T, N, 3) world points to each frame's pixels."""
    n_frames = len(motions)
    target = project(_apply(motions, x0))
    axis, pivot, angles, res_h = fit_hinge(motions, x0, target, project, stride)
    direction, travel, res_s = fit_slide(motions, x0, target, project, stride)
    res_f = frame_residuals(np.broadcast_to(x0, (n_frames,) + x0.shape), target, project, stride)
    penalty = 0.5 * np.log(n_frames)  # per parameter of the joint's line (BIC)
    costs = {"hinge": robust_cost(res_h) + 4 * penalty, "slide": robust_cost(res_s) + 2 * penalty,
             "fixed": robust_cost(res_f)}
    kind = min(costs, key=lambda k: costs[k])
    if kind == "hinge":
        return ScrewFit(kind, axis, pivot, angles - angles[0], res_h, costs)
    if kind == "slide":
        return ScrewFit(kind, direction, np.zeros(3), travel - travel[0], res_s, costs)
    return ScrewFit(kind, np.zeros(3), np.zeros(3), np.zeros(n_frames), res_f, costs)
