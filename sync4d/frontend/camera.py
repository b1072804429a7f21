"""The camera from the static background: intrinsics, static-camera test, per-frame poses, bundle adjustment.

Here the world is the first frame's camera frame (OpenCV axes), so ``extrinsics[0]`` is the identity (the
stage turns it to Y up for its callers). Poses come
from background corner tracks (the subject's tracks removed when its masks are known):

1. static camera: the background moves less than ``static_px`` in every frame (or has no texture to track:
   a plain backdrop) -> every pose the identity;
2. otherwise the pair (0, k) with the most rotation-compensated parallax gives an essential matrix
   (RANSAC) and ``recoverPose``; its inliers are triangulated and every other frame is placed by PnP
   (RANSAC), new tracks triangulated as frames are added; a camera that only turns (no parallax) gets
   rotations from the tracks' rays (Wahba) instead, its translations zero;
3. a bundle adjustment over all frames and points (Huber loss), the focal length refined with it when the
   camera both moves and turns.

Translations are in units of the median depth of the background seen in the first frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from sync4d.frontend.config import CameraConfig
from sync4d.frontend.geometry import pose_matrix, project, rays
from sync4d.geometry import best_rotation, rotation_angle_deg
from sync4d.frontend.tracks import Tracks

log = logging.getLogger(__name__)

#: a frame pair has parallax when its rotation-compensated track motion exceeds this [px] (median)
PARALLAX_PX = 1.5
MIN_COMMON = 12
#: largest believable turn of a hand-held camera between neighbouring frames [deg]
MAX_STEP_DEG = 12.0
#: a moving-camera solution is trusted when its median reprojection error stays below this [px]
MAX_BUNDLE_ERROR_PX = 1.0
#: without given intrinsics, the focal lengths the camera is solved from, as factors of the field-of-view guess's
#: (a ratio of 1.25 apart: about 79 to 37 deg at the 66 deg guess). The bundle adjustment refines the focal only
#: near its start (its reprojection error is flat over +-10 %), so every start is adjusted, a parabola through the
#: best start's and its neighbours' errors (in log focal) gives one more start, and the lowest error is kept
FOCAL_STARTS = (0.8, 1.0, 1.25, 1.5625, 1.953125)


@dataclass(frozen=True)
class CameraFit:
    """The camera found in a clip.

    Attributes:
        K: (3, 3) intrinsics [px].
        extrinsics: (T, 4, 4) world-to-camera per frame, world = frame 0's camera.
        static: the camera was found not to move.
        mode: ``static``, ``rotation`` (turns only, no parallax) or ``full`` (turns and moves).
        focal_source: ``given``, ``fov_guess`` or ``bundle`` (refined from the best of several starts).
        reprojection_px: median reprojection error of the background points after adjustment [px] (0 when
            static or rotation-only).
        background_points: (M, 3) triangulated background points [world units] (empty unless ``full``).
    """

    K: np.ndarray
    extrinsics: np.ndarray
    static: bool
    mode: str
    focal_source: str
    reprojection_px: float
    background_points: np.ndarray

    def as_dict(self) -> dict:
        """JSON-ready summary (``camera.json``)."""
        return {
            "K": np.round(self.K, 4).tolist(), "world_to_camera": np.round(self.extrinsics, 6).tolist(),
            "static": self.static, "mode": self.mode, "focal_source": self.focal_source,
            "reprojection_px": round(float(self.reprojection_px), 3),
            "rotation_from_first_deg": np.round(rotation_angle_deg(self.extrinsics[:, :3, :3]), 3).tolist(),
            "world": "the first frame's camera frame (OpenCV axes: x right, y down, z forward)",  # before the stage's turn
            "translation_unit": "the median depth of the background seen in the first frame",
        }


def background_only(tracks: Tracks, subject: np.ndarray | None) -> Tracks:
    """The tracks that never fall on the subject's (T, H, W) masks (dilated by a few pixels)."""
    if subject is None or tracks.uv.shape[1] == 0:
        return tracks
    import cv2

    grown = np.stack([cv2.dilate(m.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0 for m in subject])
    h, w = subject.shape[1:]
    u = np.clip(np.rint(tracks.uv[..., 0]).astype(int), 0, w - 1)
    v = np.clip(np.rint(tracks.uv[..., 1]).astype(int), 0, h - 1)
    on = grown[np.arange(len(u))[:, None], v, u] & tracks.valid
    keep = ~on.any(axis=0)
    return Tracks(uv=tracks.uv[:, keep], valid=tracks.valid[:, keep])


def static_camera(tracks: Tracks, static_px: float) -> bool:
    """True when the background's median motion since frame 0 stays below ``static_px`` in every frame."""
    for t in range(1, tracks.num_frames):
        common = tracks.valid[0] & tracks.valid[t]
        if common.sum() < MIN_COMMON:
            return False
        if np.median(np.linalg.norm(tracks.uv[t, common] - tracks.uv[0, common], axis=1)) > static_px:
            return False
    return True


def rotation_between(uv_a: np.ndarray, uv_b: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R (3, 3) taking frame a's rays to frame b's (camera only turning) and the (N,) inlier mask
    (a RANSAC homography rejects what moves on its own)."""
    import cv2

    _, found = cv2.findHomography(uv_a, uv_b, cv2.RANSAC, 1.5)
    inl = np.ones(len(uv_a), bool) if found is None else np.asarray(found).ravel() > 0
    return best_rotation(rays(uv_a[inl], K), rays(uv_b[inl], K)), inl


def parallax_px(uv_a: np.ndarray, uv_b: np.ndarray, K: np.ndarray, rotation: np.ndarray) -> float:
    """Median pixel distance between frame b's points and frame a's turned by ``rotation`` (what turning
    cannot explain: parallax from moving)."""
    turned = rays(uv_a, K) @ rotation.T @ K.T
    return float(np.median(np.linalg.norm(turned[:, :2] / turned[:, 2:3] - uv_b, axis=1)))


def rotation_only_poses(tracks: Tracks, K: np.ndarray) -> np.ndarray:
    """(T, 4, 4) poses of a camera that only turns: each frame turned from the earliest posed frame it
    shares enough tracks with."""
    n_frames = tracks.num_frames
    poses = np.tile(np.eye(4), (n_frames, 1, 1))
    for t in range(1, n_frames):
        base = next((s for s in range(t) if (tracks.valid[s] & tracks.valid[t]).sum() >= MIN_COMMON), t - 1)
        common = tracks.valid[base] & tracks.valid[t]
        if common.sum() < 4:
            poses[t] = poses[t - 1]
            continue
        rot, _ = rotation_between(tracks.uv[base, common], tracks.uv[t, common], K)
        poses[t, :3, :3] = rot @ poses[base, :3, :3]
    return poses


def best_pair(tracks: Tracks, K: np.ndarray) -> tuple[int, float]:
    """The frame k with the most rotation-compensated parallax against frame 0, and that parallax [px]."""
    best, best_parallax = 0, 0.0
    for t in range(1, tracks.num_frames):
        common = tracks.valid[0] & tracks.valid[t]
        if common.sum() < 2 * MIN_COMMON:
            continue
        rot, inl = rotation_between(tracks.uv[0, common], tracks.uv[t, common], K)
        value = parallax_px(tracks.uv[0, common], tracks.uv[t, common], K, rot)
        if value > best_parallax:
            best, best_parallax = t, value
    return best, best_parallax


def triangulate(pose_a: np.ndarray, pose_b: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray, K: np.ndarray,
                *, max_error_px: float = 2.0, min_angle_deg: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) seen at uv_a (N, 2) and uv_b from two poses, and (N,) which are usable: in front of
    both cameras, reprojected within ``max_error_px`` and seen under at least ``min_angle_deg``."""
    import cv2

    hom = cv2.triangulatePoints(K @ pose_a[:3], K @ pose_b[:3], uv_a.T.astype(np.float64), uv_b.T.astype(np.float64))
    pts = (hom[:3] / np.where(np.abs(hom[3]) < 1e-12, 1e-12, hom[3])).T
    ok = np.ones(len(pts), bool)
    for pose, uv in ((pose_a, uv_a), (pose_b, uv_b)):
        proj, z = project(pts, K, pose)
        ok &= (z > 0) & (np.linalg.norm(proj - uv, axis=1) < max_error_px)
    centre_a, centre_b = -pose_a[:3, :3].T @ pose_a[:3, 3], -pose_b[:3, :3].T @ pose_b[:3, 3]
    da, db = pts - centre_a, pts - centre_b
    cosang = np.sum(da * db, 1) / np.maximum(np.linalg.norm(da, axis=1) * np.linalg.norm(db, axis=1), 1e-12)
    ok &= cosang < np.cos(np.radians(min_angle_deg))
    return pts, ok


def initial_pair(tracks: Tracks, K: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pose of frame k from the essential matrix with frame 0; returns (pose (4, 4), points (N, 3) with NaN
    where not triangulated, over all tracks)."""
    import cv2

    common = np.flatnonzero(tracks.valid[0] & tracks.valid[k])
    a, b = tracks.uv[0, common], tracks.uv[k, common]
    E, inl = cv2.findEssentialMat(a, b, K, method=cv2.RANSAC, prob=0.999, threshold=1.0)
    if E is None or E.shape != (3, 3):
        E, inl = cv2.findEssentialMat(a, b, K, method=cv2.LMEDS)
    _, R, t, inl2 = cv2.recoverPose(E[:3], a, b, K, mask=inl)
    pose = pose_matrix(R, t.ravel())
    pts, ok = triangulate(np.eye(4), pose, a, b, K)
    ok &= inl2.ravel() > 0
    points = np.full((tracks.uv.shape[1], 3), np.nan)
    points[common[ok]] = pts[ok]
    return pose, points, common[ok]


def add_frame(t: int, tracks: Tracks, K: np.ndarray, poses: np.ndarray, posed: np.ndarray,
              points: np.ndarray) -> bool:
    """Place frame t by PnP on the known points it sees (in place), or turn it from the last posed frame
    (returns False then); triangulate the tracks it shares with earlier posed frames."""
    import cv2

    seen = np.flatnonzero(tracks.valid[t] & np.isfinite(points[:, 0]))
    placed = False
    if len(seen) >= 8:
        guess = poses[t - 1]
        rvec0, _ = cv2.Rodrigues(guess[:3, :3])
        ok, rvec, tvec, inl = cv2.solvePnPRansac(points[seen], tracks.uv[t, seen], K, None, rvec0.copy(),
                                                 guess[:3, 3].copy(), useExtrinsicGuess=True,
                                                 reprojectionError=2.0, iterationsCount=200)
        if ok and inl is not None and len(inl) >= max(MIN_COMMON, 0.3 * len(seen)):
            candidate = pose_matrix(cv2.Rodrigues(rvec)[0], tvec.ravel())
            # a hand turns a phone by a few degrees per frame: a larger jump is a PnP failure
            placed = float(rotation_angle_deg(candidate[:3, :3] @ guess[:3, :3].T)) < MAX_STEP_DEG
            if placed:
                poses[t] = candidate
    if not placed:
        prev = t - 1
        common = tracks.valid[prev] & tracks.valid[t]
        rot = rotation_between(tracks.uv[prev, common], tracks.uv[t, common], K)[0] if common.sum() >= 4 else np.eye(3)
        poses[t] = pose_matrix(rot @ poses[prev, :3, :3], rot @ poses[prev, :3, 3])
    posed[t] = True
    fresh = np.flatnonzero(tracks.valid[t] & ~np.isfinite(points[:, 0]))
    for s in np.flatnonzero(posed[:t]):
        pair = fresh[tracks.valid[s, fresh]]
        if len(pair) == 0:
            continue
        pts, usable = triangulate(poses[s], poses[t], tracks.uv[s, pair], tracks.uv[t, pair], K, min_angle_deg=1.0)
        points[pair[usable]] = pts[usable]
        fresh = fresh[~np.isin(fresh, pair[usable])]
    return placed


def incremental_poses(tracks: Tracks, K: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(T, 4, 4) poses, (N, 3) points (NaN where none) from the pair (0, k) outwards, and the fraction of
    frames PnP placed (the others only turned from their predecessor)."""
    n_frames = tracks.num_frames
    poses = np.tile(np.eye(4), (n_frames, 1, 1))
    posed = np.zeros(n_frames, bool)
    posed[0] = True
    poses[k], points, _ = initial_pair(tracks, K, k)
    posed[k] = True
    placed = [add_frame(t, tracks, K, poses, posed, points) for t in range(1, n_frames) if t != k]
    return poses, points, float(np.mean(placed)) if placed else 1.0


def solve_camera(tracks: Tracks, K: np.ndarray, config: CameraConfig, *, focal_given: bool) -> CameraFit:
    """The camera of a clip from its background tracks (see the module's docstring); without ``focal_given`` and
    with ``config.refine_focal``, solved from each of :data:`FOCAL_STARTS` and the best kept."""
    n_frames = tracks.num_frames
    source = "given" if focal_given else "fov_guess"
    empty = np.zeros((0, 3))
    if tracks.valid.sum(axis=1).max(initial=0) < MIN_COMMON:
        log.warning("frontend camera: the background has no texture to track (%d corners at most); the camera "
                    "is taken as static", int(tracks.valid.sum(axis=1).max(initial=0)))
        return CameraFit(K, np.tile(np.eye(4), (n_frames, 1, 1)), True, "static", source, 0.0, empty)
    if static_camera(tracks, config.static_px):
        return CameraFit(K, np.tile(np.eye(4), (n_frames, 1, 1)), True, "static", source, 0.0, empty)
    from threadpoolctl import threadpool_limits

    # the adjustment's matrices are small: BLAS threads only fight over the cores (a 320x480 clip's camera:
    # 13 s CPU on one thread, 24 s on two, more under load), and one thread gives the same answer anywhere
    with threadpool_limits(limits=1, user_api="blas"):
        if focal_given or not config.refine_focal:
            return moving_camera(tracks, K, config, focal_given=focal_given)
        return focal_search(tracks, K, config)


def with_focal(K: np.ndarray, factor: float) -> np.ndarray:
    """``K`` with its focal length scaled by ``factor``."""
    out = np.array(K, dtype=np.float64)
    out[0, 0] *= factor
    out[1, 1] *= factor
    return out


def parabola_vertex(x: np.ndarray, y: np.ndarray) -> float | None:
    """The x of the minimum of the parabola through three points, None when it opens downwards."""
    a, b, _ = np.polyfit(x, y, 2)
    return float(-b / (2 * a)) if a > 0 else None


def focal_search(tracks: Tracks, K: np.ndarray, config: CameraConfig) -> CameraFit:
    """:func:`moving_camera` from every focal of :data:`FOCAL_STARTS`, one more from the parabola's minimum
    through the best start and its neighbours; the moving-camera solution that reprojects best (else the
    guess's)."""
    fits = [moving_camera(tracks, with_focal(K, f), config, focal_given=False, warn=False) for f in FOCAL_STARTS]
    error = np.array([reprojection_or_inf(fit) for fit in fits])
    if not np.isfinite(error).any():  # no start gave a moving camera: the guess's answer, said as such
        return moving_camera(tracks, K, config, focal_given=False)
    best = int(np.argmin(error))
    if 0 < best < len(error) - 1 and np.isfinite(error[best - 1:best + 2]).all():
        vertex = parabola_vertex(np.log(FOCAL_STARTS[best - 1:best + 2]), error[best - 1:best + 2])
        if vertex is not None:
            fits.append(moving_camera(tracks, with_focal(K, float(np.exp(vertex))), config, focal_given=False,
                                      warn=False))
    chosen = min(fits, key=reprojection_or_inf)
    log.info("frontend camera: focal %.1f px (starts %s: errors %s px)", chosen.K[0, 0],
             ", ".join(f"{K[0, 0] * f:.0f}" for f in FOCAL_STARTS), np.round(error, 3).tolist())
    return chosen


def reprojection_or_inf(fit: CameraFit) -> float:
    """A moving-camera fit's median reprojection error [px]; inf for any other mode."""
    return fit.reprojection_px if fit.mode == "full" else float("inf")


def moving_camera(tracks: Tracks, K: np.ndarray, config: CameraConfig, *, focal_given: bool,
                  warn: bool = True) -> CameraFit:
    """A moving camera's poses from ``K``: the best pair's relative pose, PnP for the rest, a bundle adjustment
    (the focal refined unless ``focal_given``); a turning-only camera when there is too little parallax or the
    solution does not fit (a warning unless not ``warn``: one of several starts)."""
    from sync4d.frontend.bundle import bundle_adjust

    source = "given" if focal_given else "fov_guess"
    empty = np.zeros((0, 3))
    k, parallax = best_pair(tracks, K)
    log.info("frontend camera: best pair (0, %d), rotation-compensated parallax %.2f px", k, parallax)
    if k == 0 or parallax < PARALLAX_PX:
        return CameraFit(K, rotation_only_poses(tracks, K), False, "rotation", source, 0.0, empty)
    poses, points, placed = incremental_poses(tracks, K, k)
    adjusted = bundle_adjust(tracks, K, poses, points, iterations=config.bundle_iters,
                             refine_focal=config.refine_focal and not focal_given, scale_frame=k)
    if not adjusted.median_error_px <= MAX_BUNDLE_ERROR_PX:
        (log.warning if warn else log.info)("frontend camera: the moving-camera solution does not fit (PnP placed %.0f%% of the frames, "
                    "%.2f px after adjustment); a turning-only camera is used", 100 * placed, adjusted.median_error_px)
        return CameraFit(K, rotation_only_poses(tracks, K), False, "rotation", source, 0.0, empty)
    if adjusted.focal_changed:
        source = "bundle"
    pts = adjusted.points[np.isfinite(adjusted.points[:, 0])]
    depth = project(pts, adjusted.K, np.eye(4))[1]
    scale = float(np.median(depth[depth > 0])) if (depth > 0).any() else 1.0
    ext = adjusted.poses.copy()
    ext[:, :3, 3] /= scale
    return CameraFit(adjusted.K, ext, False, "full", source, adjusted.median_error_px, pts / scale)
