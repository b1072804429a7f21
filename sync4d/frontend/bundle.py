"""A small bundle adjustment: camera poses, background points and optionally the focal length, refined
together by minimising the reprojection error (Huber loss, sparse Jacobian, ``scipy.optimize``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sync4d.frontend.geometry import pose_matrix
from sync4d.geometry import matrix_to_rotation_vector, nearest_rotation, rotation_vector_to_matrix
from sync4d.frontend.tracks import Tracks

#: the focal length is kept only when the refinement moved it by less than this factor (else: not constrained)
MAX_FOCAL_CHANGE = 1.6
#: Huber scale of the reprojection residual [px]
HUBER_PX = 1.0
#: LSMR's tolerances inside each trust-region step: scipy's defaults (1e-6) stop the inner solve early, and a
#: small baseline's pan-versus-slide valley is then walked in tiny steps (docs/results/video_frontend.md)
STEP_TOLERANCE = 1e-12


@dataclass(frozen=True)
class BundleResult:
    """Attributes:
    poses: (T, 4, 4) world-to-camera; points: (N, 3) (NaN where none); K: (3, 3);
    median_error_px: median reprojection error after adjustment [px]; focal_changed: K's focal was refined.
    """

    poses: np.ndarray
    points: np.ndarray
    K: np.ndarray
    median_error_px: float
    focal_changed: bool


@dataclass(frozen=True)
class Observations:
    """(M,) frame and point index of each observation and its (M, 2) pixel [px]."""

    frame: np.ndarray
    point: np.ndarray
    uv: np.ndarray


def observations(tracks: Tracks, points: np.ndarray) -> tuple[Observations, np.ndarray]:
    """Observations of the triangulated points, and the (P,) indices of those points among all tracks."""
    used = np.flatnonzero(np.isfinite(points[:, 0]))
    frame, col = np.nonzero(tracks.valid[:, used])
    return Observations(frame=frame, point=col, uv=tracks.uv[frame, used[col]]), used


def residuals(x: np.ndarray, obs: Observations, n_frames: int, n_points: int, K: np.ndarray,
              refine_focal: bool, scale_frame: int, scale: float) -> np.ndarray:
    """Reprojection residuals [px] (2M,) and one gauge residual fixing the scale (|t_k| = ``scale``)."""
    cams = x[: 6 * (n_frames - 1)].reshape(n_frames - 1, 6)
    pts = x[6 * (n_frames - 1): 6 * (n_frames - 1) + 3 * n_points].reshape(n_points, 3)
    focal = K[0, 0] * np.exp(x[-1]) if refine_focal else K[0, 0]
    rvec = np.concatenate([np.zeros((1, 3)), cams[:, :3]])
    tvec = np.concatenate([np.zeros((1, 3)), cams[:, 3:]])
    rot = rotation_vector_to_matrix(rvec)
    cam = np.einsum("mij,mj->mi", rot[obs.frame], pts[obs.point]) + tvec[obs.frame]
    z = np.where(np.abs(cam[:, 2]) < 1e-6, 1e-6, cam[:, 2])
    uv = focal * cam[:, :2] / z[:, None] + K[:2, 2]
    gauge = 10.0 * (np.linalg.norm(tvec[scale_frame]) - scale) if scale_frame > 0 else 0.0
    return np.concatenate([(uv - obs.uv).ravel(), [gauge]])


def sparsity(obs: Observations, n_frames: int, n_points: int, refine_focal: bool, scale_frame: int) -> object:
    """The Jacobian's sparsity pattern (which parameters each residual depends on)."""
    from scipy.sparse import lil_matrix

    n_cam = 6 * (n_frames - 1)
    n_params = n_cam + 3 * n_points + int(refine_focal)
    m = len(obs.frame)
    pattern = lil_matrix((2 * m + 1, n_params), dtype=np.int8)
    rows = np.arange(m)
    for k in range(2):
        r = 2 * rows + k
        moving = obs.frame > 0
        for j in range(6):
            pattern[r[moving], 6 * (obs.frame[moving] - 1) + j] = 1
        for j in range(3):
            pattern[r, n_cam + 3 * obs.point + j] = 1
        if refine_focal:
            pattern[r, n_params - 1] = 1
    if scale_frame > 0:
        pattern[2 * m, 6 * (scale_frame - 1) + 3: 6 * (scale_frame - 1) + 6] = 1
    return pattern


def bundle_adjust(tracks: Tracks, K: np.ndarray, poses: np.ndarray, points: np.ndarray, *, iterations: int,
                  refine_focal: bool, scale_frame: int) -> BundleResult:
    """Refine poses (frame 0 fixed), points and optionally the focal length (see the module docstring)."""
    from scipy.optimize import least_squares

    obs, used = observations(tracks, points)
    n_frames, n_points = len(poses), len(used)
    if iterations <= 0 or n_points < 8:
        return BundleResult(poses, points, K, float("nan"), False)
    cams = np.concatenate([[np.concatenate([matrix_to_rotation_vector(nearest_rotation(p[:3, :3])), p[:3, 3]]) for p in poses[1:]]]).ravel()
    x0 = np.concatenate([cams, points[used].ravel()] + ([np.zeros(1)] if refine_focal else []))
    scale = float(np.linalg.norm(poses[scale_frame, :3, 3]))
    args = (obs, n_frames, n_points, K, refine_focal, scale_frame, scale)
    solved = least_squares(residuals, x0, jac_sparsity=sparsity(obs, n_frames, n_points, refine_focal, scale_frame),
                           loss="huber", f_scale=HUBER_PX, x_scale="jac", max_nfev=iterations, method="trf",
                           tr_options={"atol": STEP_TOLERANCE, "btol": STEP_TOLERANCE}, args=args)
    x = solved.x
    focal_factor = float(np.exp(x[-1])) if refine_focal else 1.0
    focal_changed = refine_focal and 1.0 / MAX_FOCAL_CHANGE < focal_factor < MAX_FOCAL_CHANGE
    if refine_focal and not focal_changed:  # the focal ran off: not constrained by this clip; keep the guess
        return bundle_adjust(tracks, K, poses, points, iterations=iterations, refine_focal=False,
                             scale_frame=scale_frame)
    cams_out = x[: 6 * (n_frames - 1)].reshape(-1, 6)
    out_poses = np.concatenate([[np.eye(4)], [pose_matrix(rotation_vector_to_matrix(c[:3]), c[3:]) for c in cams_out]])
    out_points = points.copy()
    out_points[used] = x[6 * (n_frames - 1): 6 * (n_frames - 1) + 3 * n_points].reshape(-1, 3)
    K_out = K.copy()
    K_out[0, 0] = K_out[1, 1] = K[0, 0] * focal_factor
    err = np.linalg.norm(residuals(x, *args)[:-1].reshape(-1, 2), axis=1)
    return BundleResult(out_poses, out_points, K_out, float(np.median(err)), bool(focal_changed))
