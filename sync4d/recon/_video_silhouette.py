"""Silhouette-driven articulated tracking for ``recon=video`` (NumPy / OpenCV, no gradients).

Why: with a known static camera the masks constrain an articulated pose strongly, even where the
optical flow fails (a lid folding shut shows only its textureless back). Gradient descent on a soft
silhouette falls into local minima for large motions; a derivative-free pattern search over each
bone's few degrees of freedom, started from the previous frame's pose, does not need a good gradient.

Model used here (a discretised stand-in for the Gaussians, all in world units [m]):
    * a dense point cloud: every foreground pixel of the first frame back-projected on its viewing ray
      (``x = c + d r``); each point belongs to one part (bone);
    * parts form a kinematic tree: the root moves freely (6 DoF), every other part rotates about a ball
      joint (3 DoF) carried by its parent; the joint is the centre of the image boundary between the two
      parts in the first frame (rigid parts connected by joints);
    * a non-root part's initial surface is a plane through its joint whose orientation (two tilt angles)
      is estimated from the silhouettes of all frames (the part seen at many angles, like a turntable);
    * labels are re-estimated by silhouette consistency: a point belongs to the bone whose motion keeps
      it inside the masks of all frames (robust to occlusion: an occluded point still projects inside the
      occluder's mask);
    * a pose sequence scores its mean IoU minus a frame-to-frame optical-flow term (:func:`flow_penalty`):
      the silhouettes pose each frame, the texture's motion judges shape hypotheses they cannot tell apart.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable

import cv2
import numpy as np


# --------------------------------------------------------------------------------------------------
# Small pure helpers
# --------------------------------------------------------------------------------------------------


def rotvec_to_matrix(v: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of a rotation vector (3,) [rad] (Rodrigues)."""
    return cv2.Rodrigues(np.asarray(v, np.float64).reshape(3, 1))[0]


def about_pivot(rot: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """(4, 4) rigid transform x -> rot (x - pivot) + pivot (a rotation about the point ``pivot`` [m])."""
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = pivot - rot @ pivot
    return out


def raster_points(uv: np.ndarray, shape: tuple[int, int], stride: int, *, grow: int = 1,
                  cells: np.ndarray | None = None) -> np.ndarray:
    """(H // stride, W // stride) bool image of pixel points (N, 2) (u, v) [px], closed over ``grow`` cells.

    A dense point cloud rasterised at a coarse stride approximates the object's silhouette; a
    morphological closing fills the gaps between neighbouring points without growing the outline.
    ``cells``: (H // stride, W // stride) uint8 cells of other points, already drawn (``grow=0`` output as
    uint8): the pose search draws a static part once, not at every evaluation.
    """
    h, w = shape[0] // stride, shape[1] // stride
    iu = np.floor(uv[:, 0] / stride).astype(np.int64)
    iv = np.floor(uv[:, 1] / stride).astype(np.int64)
    keep = (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
    img = np.zeros((h, w), np.uint8) if cells is None else cells.copy()
    img[iv[keep], iu[keep]] = 1
    if grow > 0:
        # constant zero border: the erosion must not treat the outside of the image as foreground
        img = cv2.morphologyEx(img, cv2.MORPH_CLOSE, np.ones((2 * grow + 1, 2 * grow + 1), np.uint8),
                               borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return img > 0


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two bool images (1 when both are empty)."""
    union = np.count_nonzero(a | b)
    return 1.0 if union == 0 else np.count_nonzero(a & b) / union


def downsample_mask(mask: np.ndarray, stride: int) -> np.ndarray:
    """(H // stride, W // stride) bool: cells more than half covered by the (H, W) mask."""
    h, w = mask.shape[0] // stride * stride, mask.shape[1] // stride * stride
    cells = mask[:h, :w].reshape(h // stride, stride, w // stride, stride).mean((1, 3))
    return cells > 0.5


def outside_distance(mask: np.ndarray) -> np.ndarray:
    """(H, W) float32 distance [cells] from each pixel to the mask (0 inside)."""
    return cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE).astype(np.float32)


def pattern_search(
    objective: Callable[[np.ndarray], float], x0: np.ndarray, steps: np.ndarray, *, shrink: float = 0.5,
    min_scale: float = 1.0 / 16, max_evals: int = 400,
) -> tuple[np.ndarray, float]:
    """Maximise ``objective`` by compass search (Hooke-Jeeves without pattern moves).

    Each round tries x +- step_k along every coordinate k and keeps any improvement; when a round
    improves nothing, all steps shrink by ``shrink`` until they fall below ``min_scale`` x their start.

    Args:
        objective: maps a parameter vector (D,) to a score (higher is better).
        x0: (D,) start.
        steps: (D,) initial step per coordinate.

    Returns:
        (best x (D,), best score).
    """
    x = np.asarray(x0, np.float64).copy()
    best = objective(x)
    scale, evals = 1.0, 1
    while scale >= min_scale and evals < max_evals:
        improved = False
        for k in range(len(x)):
            for sign in (1.0, -1.0):
                trial = x.copy()
                trial[k] += sign * scale * steps[k]
                score = objective(trial)
                evals += 1
                if score > best:
                    x, best, improved = trial, score, True
                    break
        if not improved:
            scale *= shrink
    return x, best


def ray_plane_depths(rays: np.ndarray, origin: np.ndarray, point: np.ndarray, normal: np.ndarray,
                     *, min_cos: float = 0.15) -> np.ndarray:
    """(N,) distances along unit rays (N, 3) from ``origin`` to the plane through ``point`` with ``normal``.

    Rays nearly parallel to the plane (|cos| < ``min_cos``) are clamped to that angle, so the depth stays
    finite.
    """
    cos = rays @ normal
    cos = np.where(np.abs(cos) < min_cos, np.copysign(min_cos, cos + 1e-12), cos)
    return float((point - origin) @ normal) / cos


def tilted_normal(view_dir: np.ndarray, tilt: np.ndarray, cam_rot: np.ndarray) -> np.ndarray:
    """(3,) unit plane normal: the direction ``-view_dir`` (facing the camera) turned by tilt (2,) [rad]
    about the camera's x then y axes (``cam_rot``: camera-to-world rotation (3, 3))."""
    rx = rotvec_to_matrix(cam_rot[:, 0] * tilt[0])
    ry = rotvec_to_matrix(cam_rot[:, 1] * tilt[1])
    n = ry @ rx @ (-view_dir)
    return n / np.linalg.norm(n)


def boundary_pivot(label_img: np.ndarray, child: int, parent: int, *, radius: int = 2) -> np.ndarray | None:
    """(2,) mean pixel (u, v) of ``child``'s pixels within ``radius`` px of ``parent``'s, or None.

    Args:
        label_img: (H, W) int part image, -1 = background.
    """
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    near_parent = cv2.dilate((label_img == parent).astype(np.uint8), kernel) > 0
    vv, uu = np.nonzero(near_parent & (label_img == child))
    if len(uu) == 0:
        return None
    return np.array([uu.mean(), vv.mean()]) + 0.5


def kinematic_tree(label_img: np.ndarray, n_parts: int, root: int, *, radius: int = 2) -> np.ndarray:
    """(n_parts,) parent of each part (-1 for the root): a maximum spanning tree of the parts' shared
    image boundary lengths (parts that touch over a long boundary are joined); parts touching nothing
    hang from the root."""
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    grown = [cv2.dilate((label_img == b).astype(np.uint8), kernel) > 0 for b in range(n_parts)]
    contact = np.zeros((n_parts, n_parts))
    for a in range(n_parts):
        for b in range(n_parts):
            if a != b:
                contact[a, b] = np.count_nonzero(grown[a] & (label_img == b))
    contact = contact + contact.T
    parent = np.full(n_parts, -1)
    in_tree = {root}
    while len(in_tree) < n_parts:  # Prim's algorithm on -contact
        best, pair = -1.0, None
        for a in in_tree:
            for b in range(n_parts):
                if b not in in_tree and contact[a, b] > best:
                    best, pair = contact[a, b], (a, b)
        assert pair is not None
        parent[pair[1]] = pair[0]
        in_tree.add(pair[1])
    return parent


# --------------------------------------------------------------------------------------------------
# The tracker
# --------------------------------------------------------------------------------------------------


@dataclass
class SilhouetteScene:
    """Inputs of the silhouette tracker (world units [m], pixels [px]).

    Attributes:
        uv0: (M, 2) first-frame foreground pixels (u, v) [px] (the dense cloud's pixels).
        rays: (M, 3) unit viewing rays of ``uv0`` (world).
        cam_center: (3,) camera centre (world).
        cam_rot: (3, 3) camera-to-world rotation.
        K: (3, 3) intrinsics.
        world_to_cam: (4, 4).
        masks: (T, h, w) bool masks at ``stride``.
        stride: raster stride [px].
        image_shape: (H, W) full-resolution size.
        base_depth: (M,) depth along the rays of the root's (fronto-parallel) initial surface [m].
        width: object size [m] (translation steps).
        flow: optional (T-1, H, W, 2) forward optical flow [px] between consecutive frames.
        flow_valid: optional (T-1, H, W) bool: where ``flow`` is trusted (forward-backward consistent, in the mask).
        flow_weight: weight of :func:`flow_penalty` in each frame's score (:func:`track`) [IoU per raster
            cell of mean residual over all points]; 0 scores silhouettes only.
        flow_cap: [raster cells] cap of one point's flow residual (outliers: occlusion, textureless areas).
    """

    uv0: np.ndarray
    rays: np.ndarray
    cam_center: np.ndarray
    cam_rot: np.ndarray
    K: np.ndarray
    world_to_cam: np.ndarray
    masks: np.ndarray
    stride: int
    image_shape: tuple[int, int]
    base_depth: np.ndarray
    width: float
    flow: np.ndarray | None = None
    flow_valid: np.ndarray | None = None
    flow_weight: float = 0.0
    flow_cap: float = 2.0

    @property
    def uses_flow(self) -> bool:
        return self.flow is not None and self.flow_valid is not None and self.flow_weight > 0

    def flow_targets(self, posed_prev: np.ndarray, t: int) -> tuple[np.ndarray, np.ndarray]:
        """Where the optical flow carries each point from frame t-1 into frame t.

        Args:
            posed_prev: (M, 3) the points posed at frame t-1 (world) [m].
            t: the frame being fitted (>= 1).

        Returns:
            (M, 2) target pixels [px] in frame t and (M,) bool: the flow at the point's frame t-1 pixel
            is trusted (``flow_valid``) and the pixel is inside the image.
        """
        assert self.flow is not None and self.flow_valid is not None
        uv = self.project(posed_prev)
        h, w = self.flow.shape[1:3]
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        # pixel k covers [k, k + 1) (as the raster), and OpenCV's flow sample k sits at its centre k + 0.5
        iu = np.clip(np.floor(uv[:, 0]).astype(int), 0, w - 1)
        iv = np.clip(np.floor(uv[:, 1]).astype(int), 0, h - 1)
        ok = inside & self.flow_valid[t - 1][iv, iu]
        # bilinear sample of the flow at the (sub-pixel) projections
        mx = (uv[:, 0] - 0.5).astype(np.float32).reshape(-1, 1)
        my = (uv[:, 1] - 0.5).astype(np.float32).reshape(-1, 1)
        f = cv2.remap(self.flow[t - 1].astype(np.float32), mx, my, cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_REPLICATE).reshape(-1, 2)
        return uv + f, ok

    def project(self, points: np.ndarray, motion: np.ndarray | None = None) -> np.ndarray:
        """(N, 2) pixels of world points (N, 3), first moved by the rigid ``motion`` (4, 4) when given (one
        composed matrix, so each point is transformed once)."""
        m = self.world_to_cam if motion is None else self.world_to_cam @ motion
        pc = points @ m[:3, :3].T + m[:3, 3]
        z = np.maximum(pc[:, 2], 1e-6)
        uv = np.empty((len(points), 2))
        uv[:, 0] = self.K[0, 0] * pc[:, 0] / z + self.K[0, 2]
        uv[:, 1] = self.K[1, 1] * pc[:, 1] / z + self.K[1, 2]
        return uv

    def render(self, points: np.ndarray) -> np.ndarray:
        """(h, w) bool silhouette of world points at the scene's stride."""
        return raster_points(self.project(points), self.image_shape, self.stride)

    def render_parts(self, points_by_part: list[np.ndarray], transforms: np.ndarray) -> np.ndarray:
        """(h, w) bool silhouette of each part's points (N_b, 3) moved by its transform (B, 4, 4) [m].

        Same image as ``render(posed_points(...))``: a part's rigid motion and the camera's extrinsics are
        composed into one 3x4 matrix, so each point is transformed once (the pose search's inner loop)."""
        uv = [self.project(pts, transforms[b]) for b, pts in enumerate(points_by_part) if len(pts)]
        if not uv:
            return np.zeros((self.image_shape[0] // self.stride, self.image_shape[1] // self.stride), bool)
        return raster_points(np.concatenate(uv), self.image_shape, self.stride)


@dataclass
class Articulation:
    """Parts, joints and shape of the tracker's point cloud.

    Attributes:
        labels: (M,) part of each point.
        parent: (B,) kinematic parent (-1 = root).
        pivots: (B, 3) canonical joint position of each non-root part (root: its centroid) [m].
        tilts: (B, 2) plane tilt of each non-root part [rad].
        axes: (B, 3) hinge axis (world, unit) of a 1-DoF joint, or NaN for a ball joint (3 DoF).
    """

    labels: np.ndarray
    parent: np.ndarray
    pivots: np.ndarray
    tilts: np.ndarray
    axes: np.ndarray | None = None
    free: bool = False  # every non-root part moves freely (6 DoF) relative to its parent: joint estimation

    def __post_init__(self) -> None:
        if self.axes is None:
            self.axes = np.full((len(self.parent), 3), np.nan)

    def is_hinge(self, b: int) -> bool:
        assert self.axes is not None
        return bool(np.isfinite(self.axes[b]).all())

    @property
    def n_parts(self) -> int:
        return len(self.parent)

    def copy(self) -> Articulation:
        assert self.axes is not None
        return Articulation(labels=self.labels.copy(), parent=self.parent.copy(), pivots=self.pivots.copy(),
                            tilts=self.tilts.copy(), axes=self.axes.copy(), free=self.free)

    def order(self) -> list[int]:
        """Parts ordered root first, each after its parent."""
        out = [int(np.flatnonzero(self.parent < 0)[0])]
        while len(out) < self.n_parts:
            out += [b for b in range(self.n_parts) if b not in out and self.parent[b] in out]
        return out


def canonical_points(scene: SilhouetteScene, art: Articulation) -> np.ndarray:
    """(M, 3) canonical points: the root's on its initial surface, every other part's on its tilted plane."""
    depth = scene.base_depth.copy()
    for b in range(art.n_parts):
        if art.parent[b] < 0:
            continue
        sel = art.labels == b
        view = art.pivots[b] - scene.cam_center
        normal = tilted_normal(view / np.linalg.norm(view), art.tilts[b], scene.cam_rot)
        d = ray_plane_depths(scene.rays[sel], scene.cam_center, art.pivots[b], normal)
        pivot_depth = np.linalg.norm(view)
        depth[sel] = np.clip(d, 0.5 * pivot_depth, 2.0 * pivot_depth)
    return scene.cam_center + depth[:, None] * scene.rays


def horizontal_root_depths(scene: SilhouetteScene, art: Articulation, root: int, up: np.ndarray) -> np.ndarray | None:
    """(R,) depths along the rays of the root's R points that put them on the plane through the mean of its
    children's joints perpendicular to ``up`` (3,) (world), clipped to [0.5, 2] x that joint's distance;
    None when the root has no points or no children. A static part's silhouette leaves its depth free; a
    part at rest on a support is the usual case (a laptop's base, a box under its lid)."""
    sel = art.labels == root
    children = np.flatnonzero(art.parent == root)
    if not sel.any() or len(children) == 0:
        return None
    pivot = art.pivots[children].mean(0)
    pivot_depth = float(np.linalg.norm(pivot - scene.cam_center))
    depth = ray_plane_depths(scene.rays[sel], scene.cam_center, pivot, up / np.linalg.norm(up))
    return np.clip(np.where(depth > 0, depth, 2.0 * pivot_depth), 0.5 * pivot_depth, 2.0 * pivot_depth)


_EYE4 = np.eye(4)


@dataclass(frozen=True)
class PoseLayout:
    """How an articulation's flat pose vector is read (see :func:`pose_layout`): computed once per search
    instead of once per evaluation (the pose search evaluates hundreds of thousands of poses per fit).

    Attributes:
        offsets: (B + 1,) start of each part's parameters.
        order: parts, root first, each after its parent.
        hinge: (B,) bool, part is a 1-DoF hinge.
    """

    offsets: np.ndarray
    order: tuple[int, ...]
    hinge: np.ndarray


def pose_layout(art: Articulation) -> PoseLayout:
    """The articulation's :class:`PoseLayout` (valid until its parents, axes or ``free`` change)."""
    assert art.axes is not None
    return PoseLayout(offsets=param_offsets(art), order=tuple(art.order()), hinge=np.isfinite(art.axes).all(1))


def pose_transforms(params: np.ndarray, art: Articulation, width: float,
                    layout: PoseLayout | None = None) -> np.ndarray:
    """(B, 4, 4) bone transforms from parameters: root (6,) = rotation vector [rad] about its pivot and
    translation [object widths]; a ball-jointed part (3,) = rotation vector about its joint, which its
    parent carries; a hinged part (1,) = angle [rad] about its axis (canonical frame) through its joint.
    ``layout``: the articulation's :func:`pose_layout`, when the caller has it."""
    layout = pose_layout(art) if layout is None else layout
    offsets = layout.offsets
    out = np.empty((art.n_parts, 4, 4))
    out[:] = _EYE4
    assert art.axes is not None
    for b in layout.order:
        p = params[offsets[b]: offsets[b + 1]]
        if art.parent[b] < 0 or art.free:
            out[b] = about_pivot(rotvec_to_matrix(p[:3]), art.pivots[b])
            out[b, :3, 3] += p[3:6] * width
            if art.parent[b] >= 0:
                out[b] = out[art.parent[b]] @ out[b]
        else:
            rv = art.axes[b] * p[0] if layout.hinge[b] else p[:3]
            out[b] = out[art.parent[b]] @ about_pivot(rotvec_to_matrix(rv), art.pivots[b])
    return out


def param_offsets(art: Articulation) -> np.ndarray:
    """(B + 1,) start of each part's parameters in the flat pose vector (root 6, ball 3, hinge 1)."""
    sizes = [6 if art.parent[b] < 0 or art.free else (1 if art.is_hinge(b) else 3) for b in range(art.n_parts)]
    return np.concatenate([[0], np.cumsum(sizes)]).astype(int)


def joint_from_motion(transforms: np.ndarray, prior: np.ndarray, *, prior_weight: float = 1e-3,
                      axis: np.ndarray | None = None) -> np.ndarray:
    """(3,) the point that moves least under relative rigid motions (T, 4, 4): the least-squares solution
    of (R_t - I) p = -t_t for all t, plus ``prior_weight`` |p - prior|^2 (regularises the directions the
    motion leaves free). With a hinge ``axis`` (3,), p moves from ``prior`` only perpendicular to it: along a
    hinge every point of the axis fits, and the prior (the part boundary) is the better guess."""
    a = transforms[:, :3, :3] - np.eye(3)
    lhs = np.einsum("tji,tjk->ik", a, a) + prior_weight * np.eye(3)
    rhs = -np.einsum("tji,tj->i", a, transforms[:, :3, 3]) + prior_weight * prior
    p = np.linalg.solve(lhs, rhs)
    if axis is not None:
        delta = p - prior
        p = prior + delta - (delta @ axis) * axis
    return p


def hinge_axis(rotvecs: np.ndarray, *, min_ratio: float = 0.9) -> np.ndarray | None:
    """(3,) unit axis when the rotation vectors (T, 3) [rad] of a joint are nearly collinear, else None.

    A joint whose rotations all share one axis is a hinge: the axis is the principal direction of the
    rotation vectors, accepted when it carries at least ``min_ratio`` of their energy (sum of squares).
    Its sign makes the largest rotation positive.
    """
    if len(rotvecs) < 2 or not np.any(rotvecs):
        return None
    _, sv, vt = np.linalg.svd(rotvecs, full_matrices=False)
    if sv[0] ** 2 < min_ratio * (sv**2).sum():
        return None
    axis = vt[0]
    big = rotvecs[np.argmax(np.linalg.norm(rotvecs, axis=1))]
    return axis if big @ axis >= 0 else -axis


def posed_points(points: np.ndarray, labels: np.ndarray, transforms: np.ndarray) -> np.ndarray:
    """(M, 3) points moved rigidly by their part's transform (B, 4, 4)."""
    t = transforms[labels]
    return np.einsum("nij,nj->ni", t[:, :3, :3], points) + t[:, :3, 3]


def fit_frame(scene: SilhouetteScene, art: Articulation, points: np.ndarray, t: int, x0: np.ndarray,
              *, rot_step: float, trans_step: float, max_evals: int, root_motion: bool = True) -> tuple[np.ndarray, float]:
    """Pose parameters of frame t maximising the silhouette IoU, by pattern search from ``x0``
    (``root_motion`` False keeps the root's parameters at ``x0``'s)."""
    offsets = param_offsets(art)
    steps = np.full(offsets[-1], rot_step)
    for b in range(art.n_parts):
        if art.parent[b] < 0 or art.free:
            steps[offsets[b] + 3: offsets[b] + 6] = trans_step
        if art.parent[b] < 0 and not root_motion:
            steps[offsets[b]: offsets[b] + 6] = 0.0

    groups = [points[art.labels == b] for b in range(art.n_parts)]
    layout = pose_layout(art)
    # a static root keeps x0's parameters, so its projection is the same at every evaluation
    fixed = [] if root_motion else [b for b in range(art.n_parts) if art.parent[b] < 0 and len(groups[b])]
    moving = [b for b in range(art.n_parts) if b not in fixed and len(groups[b])]
    tf0 = pose_transforms(x0, art, scene.width, layout)
    fixed_uv = [scene.project(groups[b], tf0[b]) for b in fixed] or [np.zeros((0, 2))]
    fixed_cells = raster_points(np.concatenate(fixed_uv), scene.image_shape, scene.stride, grow=0).astype(np.uint8)

    def score(x: np.ndarray) -> float:
        tf = pose_transforms(x, art, scene.width, layout)
        uv = [scene.project(groups[b], tf[b]) for b in moving] or [np.zeros((0, 2))]
        silhouette = raster_points(np.concatenate(uv), scene.image_shape, scene.stride, cells=fixed_cells)
        return mask_iou(silhouette, scene.masks[t])

    return pattern_search(score, x0, steps, max_evals=max_evals)


def track(scene: SilhouetteScene, art: Articulation, init: np.ndarray | None = None, *,
          rot_step_deg: float = 8.0, trans_step: float = 0.02, max_evals: int = 300, root_motion: bool = True,
          frames: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame pose parameters (T, D) and scores (T,), frame by frame from frame 0 (identity).

    Each frame's pose maximises its silhouette IoU (:func:`fit_frame`), started from a constant-velocity
    prediction (or from ``init`` when given, a previous round's poses); the better start wins. A frame's
    score is its IoU, minus ``scene.flow_weight`` x :func:`flow_penalty` when the scene has flow: the
    silhouettes pose each frame, and the texture's motion judges the shape hypotheses (tilts, joints)
    that the searches compare by the mean score.
    """
    points = canonical_points(scene, art)
    n_frames = scene.masks.shape[0] if frames is None else min(frames, scene.masks.shape[0])
    dim = int(param_offsets(art)[-1])
    params = np.zeros((n_frames, dim))
    ious = np.zeros(n_frames)
    ious[0] = mask_iou(scene.render(points), scene.masks[0])
    for t in range(1, n_frames):
        # constant velocity and constant position: the first fails at a turning point, the second in fast motion
        starts = [params[t - 1] + (params[t - 1] - params[t - 2] if t >= 2 else 0.0)]
        if t >= 2:
            starts.append(params[t - 1].copy())
        if init is not None:
            starts.append(init[t])
        best = None
        for x0 in starts:
            x, s = fit_frame(scene, art, points, t, x0, rot_step=math.radians(rot_step_deg), trans_step=trans_step,
                             max_evals=max_evals, root_motion=root_motion)
            if best is None or s > best[1]:
                best = (x, s)
        params[t], ious[t] = best
        if scene.uses_flow:
            ious[t] -= scene.flow_weight * flow_penalty(scene, art, points, params[t - 1], params[t], t)
    return params, ious


def sequence_ious(scene: SilhouetteScene, art: Articulation, params: np.ndarray) -> np.ndarray:
    """(T',) silhouette IoU of each frame posed by ``params`` (T', D) (without the flow term)."""
    points = canonical_points(scene, art)
    return np.array([mask_iou(scene.render(posed_points(points, art.labels, pose_transforms(p, art, scene.width))),
                              scene.masks[t]) for t, p in enumerate(params)])


def flow_penalty(scene: SilhouetteScene, art: Articulation, points: np.ndarray, prev: np.ndarray, cur: np.ndarray,
                 t: int) -> float:
    """Mean over all M points (M, 3) of the distance [raster cells, capped at ``scene.flow_cap``] between a
    point's projection under the pose parameters ``cur`` of frame t and where the optical flow carries its
    projection under ``prev`` (frame t-1); points on untrusted flow add nothing.

    A hinged part's first-frame tilt and how far it swings can trade off in the silhouettes (measured on
    the laptop-hinge renders: IoU 0.9826 for a lid leaning 14 deg back and swinging 110 deg, 0.9805 for
    the true 90 deg swing); the motion of the texture inside the part does not.
    """
    tf_prev = pose_transforms(prev, art, scene.width)
    tf_cur = pose_transforms(cur, art, scene.width)
    target, ok = scene.flow_targets(posed_points(points, art.labels, tf_prev), t)
    uv = scene.project(posed_points(points[ok], art.labels[ok], tf_cur))
    miss = np.linalg.norm(uv - target[ok], axis=1) / scene.stride
    return float(np.minimum(miss, scene.flow_cap).sum()) / max(len(points), 1)


def part_surface_planes(points: np.ndarray, art: Articulation) -> tuple[np.ndarray, np.ndarray]:
    """(B, 3) points and (B, 3) unit normals of each part's canonical surface plane (world) [m]: the
    least-squares plane of its canonical points (M, 3) (:func:`canonical_points`), which lie on one plane in
    this model (a moving part's tilted plane through its joint, the root's stand-in plane); NaN for a part
    with under 3 points."""
    centres = np.full((art.n_parts, 3), np.nan)
    normals = np.full((art.n_parts, 3), np.nan)
    for b in range(art.n_parts):
        own = points[art.labels == b]
        if len(own) >= 3:
            centres[b] = own.mean(0)
            normals[b] = np.linalg.svd(own - centres[b], full_matrices=False)[2][2]
    return centres, normals


def motion_residual(scene: SilhouetteScene, art: Articulation, params: np.ndarray, frame: np.ndarray,
                    start: np.ndarray, end: np.ndarray, *, cap_px: float = 2.0) -> tuple[float, int]:
    """How well the articulation predicts image corner motions, over the moving (non-root) parts.

    A corner moving from ``start`` (P, 2) in frame ``frame`` (P,) to ``end`` (P, 2) [px] is scored when it
    starts where exactly one part projects in that frame and that part is not the root: it is put on the
    part's posed surface plane along its viewing ray, moved by the part's frame-to-frame motion and
    projected; its residual is the distance to ``end``, capped at ``cap_px`` [px] (occlusion, corners
    sliding along edges). The root's moving corners are left out: with a static root they are shadows and
    reflections of the moving parts.

    Why: silhouettes cannot tell a lid's first-frame tilt from how far it swings (docs/results.md); the
    motion of its texture can, where it has texture.

    Returns:
        (mean residual [px], number of corners scored); (nan, 0) when none is scored.
    """
    points = canonical_points(scene, art)
    centres, normals = part_surface_planes(points, art)
    points_by_part = [points[art.labels == b] for b in range(art.n_parts)]
    c2w = np.linalg.inv(scene.world_to_cam)
    h, w = scene.masks.shape[1:]
    residuals = []
    for t in np.unique(frame):
        if t + 1 >= len(params):
            continue
        here = np.flatnonzero(frame == t)
        tf_t, tf_next = pose_transforms(params[t], art, scene.width), pose_transforms(params[t + 1], art, scene.width)
        coverage = np.stack([scene.render_parts([points_by_part[b]], tf_t[b: b + 1]) for b in range(art.n_parts)])
        cell = np.floor(start[here] / scene.stride).astype(int)
        inside = (cell[:, 0] >= 0) & (cell[:, 0] < w) & (cell[:, 1] >= 0) & (cell[:, 1] < h)
        cu, cv = np.clip(cell[:, 0], 0, w - 1), np.clip(cell[:, 1], 0, h - 1)
        covered = coverage[:, cv, cu] & inside  # (B, P_t)
        for b in range(art.n_parts):
            if art.parent[b] < 0 or not np.isfinite(normals[b]).all():
                continue
            sel = here[covered[b] & (covered.sum(0) == 1)]
            if len(sel) == 0:
                continue
            centre = tf_t[b, :3, :3] @ centres[b] + tf_t[b, :3, 3]
            normal = tf_t[b, :3, :3] @ normals[b]
            rays = pixel_rays(start[sel], scene.K, c2w[:3, :3])
            depth = ray_plane_depths(rays, scene.cam_center, centre, normal)
            ok = np.isfinite(depth) & (depth > 0)
            moved = scene.project(scene.cam_center + depth[ok, None] * rays[ok], tf_next[b] @ np.linalg.inv(tf_t[b]))
            residuals.append(np.minimum(np.linalg.norm(moved - end[sel][ok], axis=1), cap_px))
    if not residuals or sum(len(r) for r in residuals) == 0:
        return float("nan"), 0
    all_res = np.concatenate(residuals)
    return float(all_res.mean()), len(all_res)


def relabel_costs(scene: SilhouetteScene, art: Articulation, params: np.ndarray, *,
                  tracks: np.ndarray | None = None, track_ok: np.ndarray | None = None, flow_weight: float = 1.0,
                  flow_cap: float = 2.0, candidate_surface: bool = True) -> np.ndarray:
    """(M, B) mean over the frames of ``params`` (T', D) of each point's distance [cells] from the mask when
    moved by each bone, plus the flow-track term (see :func:`relabel`).

    With ``candidate_surface`` a point's cost under bone b puts it where it would be as part of b (on its
    first-frame ray at b's surface); otherwise at its current part's depth, where a point mislabelled
    near a joint moves along the wrong arc under the other part's motion and tends to stay."""
    if candidate_surface:
        points_as = [canonical_points(scene, replace(art, labels=np.full(len(art.labels), b)))
                     for b in range(art.n_parts)]
    else:
        points_as = [canonical_points(scene, art)] * art.n_parts
    n_frames = len(params)
    dist = [outside_distance(m) for m in scene.masks[:n_frames]]
    h, w = scene.masks.shape[1:]
    cost = np.zeros((len(art.labels), art.n_parts))
    for t in range(n_frames):
        tf = pose_transforms(params[t], art, scene.width)
        for b in range(art.n_parts):
            uv = scene.project(points_as[b], tf[b]) / scene.stride
            iu = np.clip(np.floor(uv[:, 0]).astype(int), 0, w - 1)
            iv = np.clip(np.floor(uv[:, 1]).astype(int), 0, h - 1)
            outside = (uv[:, 0] < 0) | (uv[:, 0] >= w) | (uv[:, 1] < 0) | (uv[:, 1] >= h)
            cost[:, b] += np.where(outside, float(max(h, w)), dist[t][iv, iu])
            if tracks is not None and track_ok is not None and flow_weight > 0 and t < len(tracks):
                miss = np.linalg.norm(uv - tracks[t] / scene.stride, axis=1)
                cost[:, b] += flow_weight * np.where(track_ok[t], np.minimum(miss, flow_cap), 0.0)
    return cost / n_frames


def relabel(scene: SilhouetteScene, art: Articulation, params: np.ndarray, *, smooth_px: int = 7,
            min_points: int = 20, margin: float = 0.5, tie_part: int | None = None,
            tracks: np.ndarray | None = None, track_ok: np.ndarray | None = None, flow_weight: float = 1.0,
            flow_cap: float = 2.0, candidate_surface: bool = True) -> np.ndarray:
    """(M,) labels: each point goes to the bone whose motion keeps it inside the masks of all frames.

    The cost of bone b for point i is the mean over frames of the distance [cells] from the mask of
    J_{t,b} x_i's projection over the frames ``params`` covers (T' <= T), with x_i on its first-frame ray
    at bone b's surface with ``candidate_surface``, else at its current part's (:func:`relabel_costs`);
    costs are box-filtered over ``smooth_px`` in the first frame (neighbouring pixels belong to the same
    part unless the evidence says otherwise). A point changes part only when
    its best cost beats its current part's by ``margin`` cells: bones that barely move relative to each
    other explain a point equally well, and a tie is no evidence.

    With ``tie_part`` (the root), a point whose cost under that part is within ``margin`` of its best goes
    to it instead: near a joint a child's motion is small, so the silhouettes cannot tell the parts apart,
    and a label there left from the flow clustering is as likely wrong as right; the part that needs no
    extra motion to explain the point is the simpler explanation.

    With flow ``tracks`` (T, M, 2) [px] and ``track_ok`` (T, M) (trusted frames), each cost also gets
    ``flow_weight`` x the mean over frames of the distance [cells, capped at ``flow_cap``] between a
    point's track and its projection under the bone (untrusted frames add nothing): a part turning in
    the image plane hardly changes the silhouette near its joint, but its texture moves.
    """
    cost = relabel_costs(scene, art, params, tracks=tracks, track_ok=track_ok, flow_weight=flow_weight,
                         flow_cap=flow_cap, candidate_surface=candidate_surface)
    # smooth the costs over the first frame's image
    H, W = scene.image_shape
    iu0 = np.clip(scene.uv0[:, 0].astype(int), 0, W - 1)
    iv0 = np.clip(scene.uv0[:, 1].astype(int), 0, H - 1)
    sm = np.zeros_like(cost)
    count = np.zeros((H, W), np.float32)
    count[iv0, iu0] = 1.0
    cnt = cv2.blur(count, (smooth_px, smooth_px))[iv0, iu0]
    for b in range(art.n_parts):
        img = np.zeros((H, W), np.float32)
        img[iv0, iu0] = cost[:, b]
        sm[:, b] = cv2.blur(img, (smooth_px, smooth_px))[iv0, iu0] / np.maximum(cnt, 1e-6)
    labels = np.argmin(sm, 1)
    current = sm[np.arange(len(sm)), art.labels]
    if tie_part is None:
        labels = np.where(sm[np.arange(len(sm)), labels] < current - margin, labels, art.labels)
    else:
        labels = np.where(sm[:, tie_part] <= sm[np.arange(len(sm)), labels] + margin, tie_part, labels)
    if any(np.count_nonzero(labels == b) < min_points for b in range(art.n_parts)):
        return art.labels.copy()
    return labels


# --------------------------------------------------------------------------------------------------
# Driver: from the first mask, initial labels and a camera to labels, shape and per-frame poses
# --------------------------------------------------------------------------------------------------


def pixel_rays(uv: np.ndarray, K: np.ndarray, cam_rot: np.ndarray) -> np.ndarray:
    """(N, 3) unit world directions of the viewing rays through pixels (N, 2) [px]."""
    dirs = np.concatenate([uv, np.ones((len(uv), 1))], 1) @ np.linalg.inv(K).T
    world = dirs @ cam_rot.T
    return world / np.linalg.norm(world, axis=1, keepdims=True)


def make_articulation(scene: SilhouetteScene, labels: np.ndarray, n_parts: int, root: int,
                      tilts: np.ndarray | None = None, axes: np.ndarray | None = None) -> Articulation:
    """Kinematic tree, joints (boundary centres on the root's initial surface), tilts and hinge axes for
    ``labels`` (M,) of the scene's points, after merging label islands."""
    h, w = scene.masks.shape[1:]
    label_img = np.full((h, w), -1)
    iu = np.clip((scene.uv0[:, 0] // scene.stride).astype(int), 0, w - 1)
    iv = np.clip((scene.uv0[:, 1] // scene.stride).astype(int), 0, h - 1)
    label_img[iv, iu] = labels
    label_img = merge_label_islands(label_img, n_parts)
    labels = label_img[iv, iu]
    parent = kinematic_tree(label_img, n_parts, root)
    base = scene.cam_center + scene.base_depth[:, None] * scene.rays
    pivots = np.zeros((n_parts, 3))
    forward = scene.cam_rot[:, 2]
    # joints lie on the initial (fronto-parallel) surface at the cloud's median depth
    depth_fp = float(np.median(scene.base_depth * (scene.rays @ forward)))
    for b in range(n_parts):
        members = labels == b
        pivots[b] = base[members].mean(0) if members.any() else base.mean(0)
        if parent[b] < 0:
            continue
        p = boundary_pivot(label_img, b, int(parent[b]), radius=1)
        if p is None:  # parts that do not touch: the joint is the child's centroid
            continue
        ray = pixel_rays(p[None] * scene.stride, scene.K, scene.cam_rot)[0]
        pivots[b] = scene.cam_center + ray * depth_fp / float(ray @ forward)
    return Articulation(labels=labels.copy(), parent=parent, pivots=pivots,
                        tilts=np.zeros((n_parts, 2)) if tilts is None else tilts.copy(),
                        axes=None if axes is None else axes.copy())


def tilt_grid(scene: SilhouetteScene, art: Articulation, b: int, *, frames: int, grid_deg: tuple[float, ...],
              root_motion: bool, max_evals: int) -> list[tuple[float, np.ndarray]]:
    """(mean score, tilt (2,) [rad]) of tracking the first ``frames`` frames with part b's plane at each
    tilt of the grid (both angles in ``grid_deg``), best first; ``art`` is left as it was."""
    keep = art.tilts[b].copy()
    cells = []
    for ta in grid_deg:
        for tb in grid_deg:
            art.tilts[b] = np.radians([ta, tb])
            _, scores = track(scene, art, None, root_motion=root_motion, frames=frames, max_evals=max_evals)
            cells.append((float(scores.mean()), art.tilts[b].copy()))
    art.tilts[b] = keep
    return sorted(cells, key=lambda c: -c[0])


def search_tilts(scene: SilhouetteScene, art: Articulation, *, frames: int, grid_deg: tuple[float, ...],
                 root_motion: bool, max_evals: int, refine_deg: float = 0.0) -> Articulation:
    """Each non-root part's plane tilt, scored by the mean score of tracking the first ``frames`` frames:
    the best of a grid (both angles in ``grid_deg``; empty = keep the current tilt), then a pattern
    search with ``refine_deg`` initial steps (0 = none). Parts are searched root outwards."""

    def score(b: int, tilt: np.ndarray) -> float:
        art.tilts[b] = tilt
        _, scores = track(scene, art, None, root_motion=root_motion, frames=frames, max_evals=max_evals)
        return float(scores.mean())

    for b in art.order():
        if art.parent[b] < 0:
            continue
        best = (score(b, art.tilts[b].copy()), art.tilts[b].copy())
        if grid_deg:
            cell = tilt_grid(scene, art, b, frames=frames, grid_deg=grid_deg, root_motion=root_motion,
                             max_evals=max_evals)[0]
            best = max(best, cell, key=lambda c: c[0])
        if refine_deg > 0:
            tilt, value = pattern_search(lambda x: score(b, x), best[1], np.radians([refine_deg] * 2),
                                         min_scale=0.25, max_evals=20)
            best = (value, tilt)
        art.tilts[b] = best[1]
    return art


def detect_hinges(scene: SilhouetteScene, art: Articulation, *, root_motion: bool, frames: int, max_evals: int,
                  min_ratio: float, parts: list[int] | None = None) -> np.ndarray:
    """(B, 3) hinge axes: ``art``'s, with each ball joint (of ``parts``, default all) whose rotations over
    the first ``frames`` frames share one axis (:func:`hinge_axis`) turned into a hinge (1 DoF), which
    keeps the tracking from drifting where the silhouette is ambiguous."""
    assert art.axes is not None
    params, _ = track(scene, art, None, root_motion=root_motion, frames=frames, max_evals=max_evals)
    offsets = param_offsets(art)
    axes = art.axes.copy()
    for b in range(art.n_parts) if parts is None else parts:
        if art.parent[b] < 0 or art.is_hinge(b):
            continue
        axis = hinge_axis(params[:, offsets[b]: offsets[b] + 3], min_ratio=min_ratio)
        if axis is not None:
            axes[b] = axis
    return axes


def search_joint_and_tilt(scene: SilhouetteScene, art: Articulation, *, root_motion: bool, max_evals: int,
                          tilt_step_deg: float, pivot_step: float, search_evals: int = 40,
                          search_axis: bool = False, search_depth: bool = False,
                          parts: list[int] | None = None) -> tuple[Articulation, float]:
    """Each non-root part's joint position (moved in the camera's image plane, steps ``pivot_step``
    object widths), plane tilt and, for a hinge with ``search_axis``, axis direction (both in steps of
    ``tilt_step_deg``) by a
    pattern search on the mean IoU of tracking the whole sequence. With ``search_depth`` the joint also
    moves along its viewing ray (same step): the first view fixes only the joint's pixel, and a hinge at
    the wrong depth swings its part along the wrong arc. A joint placed from a wrong part
    boundary, or an axis estimated from the first frames only, makes the part swing about the wrong line;
    the whole sequence's silhouettes tell. ``parts`` limits the search to those parts. Returns the
    articulation and its mean score (see :func:`track`)."""
    assert art.axes is not None
    best_score = -1.0
    for b in art.order():
        if art.parent[b] < 0 or (parts is not None and b not in parts):
            continue
        pivot0, tilt0, axis0 = art.pivots[b].copy(), art.tilts[b].copy(), art.axes[b].copy()
        hinge = art.is_hinge(b) and search_axis
        if hinge:  # two directions perpendicular to the axis: small rotations of it
            perp = np.linalg.svd(axis0[None])[2][1:]

        ray = (pivot0 - scene.cam_center) / np.linalg.norm(pivot0 - scene.cam_center)

        def score(x: np.ndarray) -> float:
            art.pivots[b] = pivot0 + (scene.cam_rot[:, 0] * x[0] + scene.cam_rot[:, 1] * x[1]) * scene.width
            art.tilts[b] = tilt0 + x[2:4]
            if hinge:
                axis = axis0 + perp[0] * x[4] + perp[1] * x[5]
                art.axes[b] = axis / np.linalg.norm(axis)
            if search_depth:  # the last parameter: along the joint's viewing ray
                art.pivots[b] = art.pivots[b] + ray * x[-1] * scene.width
            _, scores = track(scene, art, None, root_motion=root_motion, max_evals=max_evals)
            return float(scores.mean())

        step = math.radians(tilt_step_deg)
        steps = np.array([pivot_step, pivot_step, step, step] + ([step, step] if hinge else [])
                         + ([pivot_step] if search_depth else []))
        x, best_score = pattern_search(score, np.zeros(len(steps)), steps, min_scale=0.25, max_evals=search_evals)
        score(x)  # leave the articulation at the best parameters
    return art, best_score


def hinge_params_to_ball(params: np.ndarray, art: Articulation) -> np.ndarray:
    """(T, D') pose parameters of the same poses with every hinge (angle) turned into a ball joint
    (rotation vector = axis x angle); (T, D) ``params`` of ``art``."""
    ball = Articulation(labels=art.labels, parent=art.parent, pivots=art.pivots, tilts=art.tilts)
    src, dst = param_offsets(art), param_offsets(ball)
    out = np.zeros((len(params), int(dst[-1])))
    for b in range(art.n_parts):
        p = params[:, src[b]: src[b + 1]]
        out[:, dst[b]: dst[b + 1]] = p * art.axes[b] if art.is_hinge(b) else p
    return out


def nearest_index(points: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """(Q,) index of the nearest of ``points`` (N, D) to each of ``queries`` (Q, D)."""
    from scipy.spatial import cKDTree

    return cKDTree(points).query(queries)[1]


def part_motion_px(tracks: np.ndarray, ok: np.ndarray, labels: np.ndarray, n_parts: int) -> np.ndarray:
    """(n_parts,) median image displacement [px] from the first frame of each part's trusted track
    samples (NaN for a part without any)."""
    disp = np.linalg.norm(tracks - tracks[:1], axis=-1)  # (T, N)
    out = np.full(n_parts, np.nan)
    for b in range(n_parts):
        sel = ok[1:] & (labels == b)[None]
        if sel.any():
            out[b] = float(np.median(disp[1:][sel]))
    return out


def merge_label_islands(label_img: np.ndarray, n_parts: int) -> np.ndarray:
    """(H, W) part image where every part keeps only its largest 4-connected region; the other regions
    (islands, e.g. a thin rim mislabelled where flow tracks break at an occluding edge) join the part
    that most of their one-pixel border belongs to. Rigid parts are connected in the first view.

    Args:
        label_img: (H, W) int, -1 = background, parts in [0, n_parts).
    """
    out = label_img.copy()
    kernel = np.ones((3, 3), np.uint8)
    for _ in range(3):  # a merged island can make another part's island; a few passes settle it
        changed = False
        for b in range(n_parts):
            count, comp = cv2.connectedComponents((out == b).astype(np.uint8), connectivity=4)
            if count <= 2:
                continue
            sizes = np.bincount(comp.ravel(), minlength=count)
            sizes[0] = 0
            keep = int(np.argmax(sizes))
            for c in range(1, count):
                if c == keep:
                    continue
                island = comp == c
                ring = (cv2.dilate(island.astype(np.uint8), kernel) > 0) & ~island & (out >= 0) & (out != b)
                if ring.any():
                    out[island] = np.bincount(out[ring], minlength=n_parts).argmax()
                    changed = True
        if not changed:
            break
    return out
