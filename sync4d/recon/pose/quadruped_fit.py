"""Fit a skinned quadruped template (:mod:`sync4d.recon.pose.templates`) to the silhouettes of a video (torch, CPU).

Per frame the unknowns are the root's rotation and position (in the first frame's camera frame) and every
joint's rotation relative to the template (axis-angle, in the template's axes); per clip one scale, one
girth, a log length change per bone and a log girth change per bone (left and right tied by a prior). The
posed mesh (linear blend skinning of the template's vertices; a bone's vertices stretch along it with its
length and across it with its girth) is projected by the camera of each frame (per-frame extrinsics when
the camera moves) and rasterised softly (each triangle's signed edge distance through a sigmoid, the
union over triangles) on a coarse grid; the loss is the binary cross-entropy against the masks, plus
points along the skeleton's segments inside the mask (distance transform); priors: bone lengths and
girths (per-bone changes near zero, left/right equal), joint limits (``joint_limit_deg`` from the
template; leg joints turn mostly about the body's lateral axis), smooth root-relative joints and root
(accelerations); with video frames whose flow explains the masks' change (:func:`flow_gate`), each one-frame
tracking fit also pays the body's predicted image motion from the frame before against the video's optical
flow (Cauchy, where the flow is trusted: a walk in place and a turn toward the camera fill the same silhouettes
but move the body's texture differently) and holds the clip's shape near the start's. Search: root headings on
the first frame, the best few tracked frame by frame (and, when the masks travel a body length or more and no
track faces that way, a start heading along the travel: animals walk head first), then left/right leg swaps as hypotheses ranked by
:func:`hypothesis_score` (plus, for such a walk, each hypothesis' backward travel; near vertices hide far ones).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np
import torch

from sync4d.errors import InputError
from sync4d.geometry import rotation_vector_to_matrix_torch
from sync4d.recon.pose.templates import BodyTemplate, body_template
from sync4d.rng import deterministic_torch
from sync4d.surface import area_samples
from sync4d.types import Camera

log = logging.getLogger(__name__)
SMOOTH_FPS = 30.0  # the frame rate at which smooth_weight is stated
DTYPE = torch.float32
SAMPLES = 1200  # surface samples of the template drawn as discs for the silhouette
SAMPLE_RADIUS = 0.6  # disc radius in units of the samples' mean spacing (fills the gaps between them)
# the masks' travel over a clip [body lengths] from which it is read as a walk (the walk cue acts): a walk in place
# or a survey reads a few tenths from the masks' noise and a camera turned into object motion
WALK_BODY_LENGTHS = 1.0
Params = dict[str, torch.Tensor]


@dataclass
class QuadrupedFitConfig:
    """Template, weights, schedule and starts of the quadruped fit.

    Attributes:
        template: registered body template (:func:`sync4d.recon.pose.templates.register_template`).
        template_length: body length (head to tail base) before scaling [m]; the scale is fitted, this only
            sets the first guess of the depth.
        starts: root headings tried on the first frame (evenly spaced over 360 degrees about the up axis).
        tracks: the best starts (by first-frame loss) tracked through the clip.
        grid: silhouettes are compared on a grid this many cells across the longer side of the masks' box.
        start_iterations: Adam steps per start on the first frame (half of them rigid: root, scale, girth).
        frame_iterations: Adam steps per later frame, warm-started from the previous one.
        iterations: Adam steps of the clip fit.
        swap_iterations: Adam steps of the clip fit after the leg-swap test.
        lr: Adam step size (radians / template units).
        silhouette_weight: binary cross-entropy of the soft silhouette.
        inside_weight: skeleton points outside the mask (distance transform, in grid cells).
        length_weight: per-bone log length and girth changes and their left/right differences.
        limit_weight: joint rotation beyond ``joint_limit_deg``.
        joint_limit_deg: rotation of a joint from the template allowed without penalty [deg].
        leg_off_plane_deg: rotation of a leg joint about the axes other than the lateral one allowed without
            penalty [deg].
        smooth_weight: squared accelerations of the root-relative joints and the root (template units) at 30
            frames a second; other frame rates scale second differences by (fps / 30)^2.
        flow_weight: the body's predicted image motion against the video's optical flow (:func:`flow_term`),
            between consecutive frames of a fit (and from the last tracked frame in the tracking); 0 = off.
        shape_hold_weight: squared log change of the clip's shape (scale, girth, bone lengths and girths) in a
            one-frame tracking fit from the tracked start's: a real animal does not change its build frame by
            frame; 0 = the shape free while tracking.
        rank_by_loss: the tracks' leg swaps ranked by the clip loss (without the flow term) plus the robust flow
            residual over mask and body (:func:`hypothesis_score`) instead of the raw residual.
        travel_start: when the masks travel at least one body length over the clip (:func:`mask_travel`: a walk,
            not a survey in place) and no tracked body faces that way, a start heading along the travel is fitted
            on the first frame and tracked too: animals walk head first, and a head-on dog's silhouette and flow
            fit facing either way.
        travel_rank: when the masks travel at least one body length, each hypothesis is charged its backward
            travel (its root's displacement against its own heading, in body lengths: :func:`travel`) in the
            ranking.
        flow_in_clip: the flow term also in the clip steps (every frame pair of the clip); False = only in the
            one-frame tracking fits and the ranking (with it, the orbit's last clip steps drift: fox walk orbit
            25.6 -> 28.9 % in 40 steps).
        flow_min_explained: the flow term, the shape hold and the loss ranking are used only when the video's flow
            explains at least this share of the masks' change between frames (:func:`mask_change_missed`); below
            it (the head-on clips) the fit runs without them, the leg swaps ranked by the flow error.
        flow_robust_cells: the flow residual's Cauchy scale [grid cells]: larger residuals count little
            (a wrong flow, a leg that moved more than the flow's patch could see).
        background_threshold: colour distance counted as foreground by the background model (0-255), when the
            video has no masks.
    """

    template: str = "fox"
    template_length: float = 0.9
    starts: int = 8
    tracks: int = 2
    grid: int = 40
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
    flow_weight: float = 1.0
    flow_robust_cells: float = 1.0
    shape_hold_weight: float = 10.0
    rank_by_loss: bool = True
    travel_start: bool = True
    travel_rank: bool = True
    flow_in_clip: bool = False
    flow_min_explained: float = 0.8
    background_threshold: float = 30.0


@dataclass(frozen=True)
class QuadrupedFit:
    """The fitted template motion.

    Attributes:
        joints: (T, J, 3) joints in the first frame's camera frame (OpenCV axes) [m]; the metric scale is the
            assumed ``template_length`` times the fitted scale, only up to the unknown depth.
        names: (J,) template joint names.
        parents: (J,) parent per joint.
        vertices: (T, V, 3) the posed template mesh in the same frame [m].
        faces: (F, 3) its triangles.
        silhouettes: (T, H, W) bool the posed mesh rasterised by each frame's camera.
        iou: (T,) silhouette IoU of the fitted body against the masks on the fit grid.
    """

    joints: np.ndarray
    names: tuple[str, ...]
    parents: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray
    silhouettes: np.ndarray
    iou: np.ndarray


class TemplateTensors:
    """A template's arrays as tensors, with what skinning needs precomputed (top-4 joints per vertex,
    offsets split along and across each joint's bone)."""

    def __init__(self, template: BodyTemplate) -> None:
        self.template = template
        self.parents = template.parents
        self.joints = torch.tensor(template.joints, dtype=DTYPE)
        top = np.argsort(-template.weights, axis=1)[:, :4]
        w = np.take_along_axis(template.weights, top, 1)
        self.top = torch.tensor(top)
        self.w = torch.tensor(w / w.sum(1, keepdims=True), dtype=DTYPE)
        child = np.full(len(template.parents), -1)
        for j in range(len(template.parents) - 1, 0, -1):
            child[template.parents[j]] = j
        self.child = child
        axis = np.zeros_like(template.joints)
        has = child >= 0
        axis[has] = template.joints[child[has]] - template.joints[has]
        axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-9)
        off = template.vertices[:, None] - template.joints[top]  # (V, 4, 3)
        along = (off * axis[top]).sum(-1, keepdims=True) * axis[top]
        self.along = torch.tensor(along, dtype=DTYPE)
        self.across = torch.tensor(off - along, dtype=DTYPE)
        self.faces = torch.tensor(template.faces)
        face, bary, spacing = surface_samples(template.vertices, template.faces, SAMPLES)
        self.sample_corners = torch.tensor(template.faces[face])  # (N, 3) vertex indices
        self.sample_bary = torch.tensor(bary, dtype=DTYPE)  # (N, 3)
        self.sample_radius = SAMPLE_RADIUS * spacing  # template units
        self.twin = template.twin
        self.leg_joints = template.leg_joints
        self.segments = np.flatnonzero(template.parents >= 0)


def surface_samples(vertices: np.ndarray, faces: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray, float]:
    """``count`` fixed samples uniform by area on a mesh (:func:`sync4d.surface.area_samples`): (N,) face index,
    (N, 3) barycentric weights, and the mean spacing sqrt(area / N) (the mesh's units). Deterministic (its own
    seeded generator)."""
    tri = vertices[faces]
    sampled = area_samples(tri, count, np.random.default_rng(0))
    if sampled is None:
        raise InputError("quadruped_fit: the body template's mesh has zero area")
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return sampled[0], sampled[1], float(np.sqrt(area.sum() / count))


def body_samples(tt: TemplateTensors, verts: torch.Tensor) -> torch.Tensor:
    """(T, N, 3) the template's fixed surface samples on the posed vertices (T, V, 3)."""
    return (verts[:, tt.sample_corners] * tt.sample_bary[None, ..., None]).sum(2)


def pose_body(tt: TemplateTensors, params: Params) -> tuple[torch.Tensor, torch.Tensor]:
    """(T, J, 3) joints and (T, V, 3) skinned vertices [m] of ``params`` (first camera frame)."""
    scale = params["log_scale"].exp()
    rot_local = rotation_vector_to_matrix_torch(params["local"])
    n = len(tt.parents)
    rots: list[torch.Tensor] = [rotation_vector_to_matrix_torch(params["root_rot"]) @ rot_local[:, 0]]
    pos: list[torch.Tensor] = [params["root_pos"]]
    for j in range(1, n):
        p = int(tt.parents[j])
        off = (tt.joints[j] - tt.joints[p]) * torch.exp(params["log_len"][j]) * scale
        pos.append(pos[p] + rots[p] @ off)
        rots.append(rots[p] @ rot_local[:, j])
    joints, world_rot = torch.stack(pos, 1), torch.stack(rots, 1)
    child_len = torch.cat([params["log_len"], params["log_len"].new_zeros(1)])[torch.tensor(tt.child)].exp()
    girth = (params["log_thick"] + params["log_girth"]).exp()
    local_off = (tt.along * child_len[tt.top][..., None] + tt.across * girth[tt.top][..., None]) * scale
    moved = torch.einsum("tvkij,vkj->tvki", world_rot[:, tt.top], local_off) + joints[:, tt.top]
    return joints, (moved * tt.w[None, ..., None]).sum(2)


def to_cameras(points: torch.Tensor, cams: torch.Tensor | None) -> torch.Tensor:
    """(T, N, 3) points in the first camera's frame -> each frame's camera frame (``cams``: (T, 4, 4) first
    camera -> frame t camera; None = a static camera)."""
    if cams is None:
        return points
    return points @ cams[:, :3, :3].transpose(1, 2) + cams[:, None, :3, 3]


def project_points(x: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(..., 2) pixel positions of camera-frame points x (..., 3) [m] under intrinsics K (3, 3)."""
    return x[..., :2] / x[..., 2:].clamp_min(1e-3) * torch.stack([K[0, 0], K[1, 1]]) + K[:2, 2]


def soft_point_silhouette(uv: torch.Tensor, radius_px: torch.Tensor, grid_uv: torch.Tensor, tau_px: float
                          ) -> torch.Tensor:
    """(T, P) soft occupancy at pixels ``grid_uv`` (P, 2) of discs of radius ``radius_px`` (T, N) around the
    projected surface samples ``uv`` (T, N, 2) [px]: ``sigmoid((r - d) / tau_px)`` for the disc whose edge is
    nearest (found without gradients, then differentiated exactly: 2x cheaper than a soft maximum over all
    samples, and the nearest disc is the only one a max passes gradients to anyway)."""
    t, p = uv.shape[0], grid_uv.shape[0]
    with torch.no_grad():
        nearest = (torch.cdist(grid_uv[None].expand(t, p, 2).contiguous(), uv.detach()) - radius_px[:, None]).argmin(2)
    centre = torch.gather(uv, 1, nearest[..., None].expand(t, p, 2))
    edge = torch.gather(radius_px, 1, nearest) - (grid_uv[None] - centre).pow(2).sum(-1).clamp_min(1e-12).sqrt()
    return torch.sigmoid(edge / tau_px)


def rasterise(vertices: np.ndarray, faces: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) bool silhouette of a camera-frame mesh (V, 3) [m] (triangles with a vertex behind the camera
    are skipped)."""
    import cv2

    out = np.zeros((height, width), np.uint8)
    z = vertices[:, 2]
    uv = vertices[:, :2] / np.maximum(z, 1e-6)[:, None] * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]
    ok = (z[faces] > 1e-3).all(1) & np.isfinite(uv[faces]).all((1, 2)) & (np.abs(uv[faces]) < 1e5).all((1, 2))
    for tri in np.round(uv[faces[ok]] * 16).astype(np.int32):  # one at a time: a union, not an even-odd fill
        cv2.fillConvexPoly(out, tri, 1, lineType=cv2.LINE_8, shift=4)
    return out.astype(bool)


def video_flow(frames: np.ndarray, uv: np.ndarray, masks: np.ndarray, fb_tol_px: float = 1.0
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """(T-1, P, 2) DIS optical flow (OpenCV, medium preset) from frame t to t+1 at pixels ``uv`` (P, 2) [px],
    (T-1, P) where it is trusted on the subject (on the mask at t, landing on the mask at t+1: off it the flow is
    the background's; and consistent), (T-1, P) where it is consistent (back within ``fb_tol_px`` by the backward
    flow: not occluded, not smeared; the background's cells too), and the share of the masks' change the flow
    explains (:func:`mask_change_explained`)."""
    import cv2

    # OpenCV's stubs omit the DIS optical flow factory that the module has.
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)  # type: ignore[attr-defined]
    grey = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in frames]
    h, w = grey[0].shape

    def pixel(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.clip(p[:, 1].astype(int), 0, h - 1), np.clip(p[:, 0].astype(int), 0, w - 1)

    flows, ok, consistent, missed = [], [], [], np.zeros(2)
    for t in range(len(grey) - 1):
        fwd = dis.calc(grey[t], grey[t + 1], None)[pixel(uv)]
        end = pixel(uv + fwd)
        back_full = dis.calc(grey[t + 1], grey[t], None)
        back = back_full[end]
        consistent.append(np.linalg.norm(fwd + back, axis=1) < fb_tol_px)
        ok.append(masks[t][pixel(uv)] & masks[t + 1][end] & consistent[-1])
        flows.append(fwd)
        missed += mask_change_missed(masks[t], masks[t + 1], back_full)
    return np.stack(flows), np.stack(ok), np.stack(consistent), float(1.0 - missed[0] / max(missed[1], 1.0))


def mask_change_missed(mask: np.ndarray, following: np.ndarray, back: np.ndarray) -> np.ndarray:
    """(2,) pixels where ``following`` differs from ``mask`` carried along by the backward flow ``back`` (H, W, 2)
    [px] from the following frame, and from ``mask`` as it is.

    Summed over a clip, 1 - their ratio is the share of the masks' change the flow explains: near 1 when the flow
    moves the body's outline as the masks move, low when the motion is mostly toward the camera or too small and
    flat for the flow to follow (the head-on clips: docs/results/people_animals.md)."""
    import cv2

    h, w = mask.shape
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    carried = cv2.remap(mask.astype(np.float32), gx + back[..., 0], gy + back[..., 1], cv2.INTER_LINEAR) > 0.5
    return np.array([float((carried ^ following).sum()), float((mask ^ following).sum())])


def mask_box(masks: np.ndarray, margin: float = 0.15) -> tuple[int, int, int, int]:
    """(u0, v0, u1, v1) pixel box around every frame's mask, enlarged by ``margin`` of its size each side."""
    ys, xs = np.nonzero(masks.any(0))
    h, w = masks.shape[1:]
    du, dv = margin * (xs.max() - xs.min() + 1), margin * (ys.max() - ys.min() + 1)
    return (max(0, int(xs.min() - du)), max(0, int(ys.min() - dv)), min(w, int(xs.max() + du) + 1),
            min(h, int(ys.max() + dv) + 1))


def grid_cells(box: tuple[int, int, int, int], cells: int) -> tuple[np.ndarray, int, int]:
    """Cell centres (P, 2) [px] of a grid ``cells`` across the longer side of ``box``, and its size."""
    u0, v0, u1, v1 = box
    step = max(u1 - u0, v1 - v0) / cells
    gw, gh = max(1, int(round((u1 - u0) / step))), max(1, int(round((v1 - v0) / step)))
    us = u0 + (np.arange(gw) + 0.5) * (u1 - u0) / gw
    vs = v0 + (np.arange(gh) + 0.5) * (v1 - v0) / gh
    uu, vv = np.meshgrid(us, vs)
    return np.stack([uu.ravel(), vv.ravel()], 1), gw, gh


def coarse_masks(masks: np.ndarray, box: tuple[int, int, int, int], gw: int, gh: int) -> np.ndarray:
    """(T, gh, gw) float mask coverage of each grid cell."""
    import cv2

    u0, v0, u1, v1 = box
    return np.stack([cv2.resize(m[v0:v1, u0:u1].astype(np.float32), (gw, gh), interpolation=cv2.INTER_AREA)
                     for m in masks])


def outside_distance(coarse: np.ndarray) -> np.ndarray:
    """(T, gh, gw) distance [cells] of each cell from the mask (0 inside)."""
    import cv2

    return np.stack([cv2.distanceTransform((m < 0.5).astype(np.uint8), cv2.DIST_L2, 3) for m in coarse])


def relative_cameras(extrinsics: np.ndarray | None) -> np.ndarray | None:
    """(T, 4, 4) first camera -> frame t camera from (T, 4, 4) world-to-camera matrices; None if static."""
    if extrinsics is None:
        return None
    ext = np.asarray(extrinsics, dtype=np.float64)
    rel = ext @ np.linalg.inv(ext[0])
    return None if np.allclose(rel, np.eye(4)[None], atol=1e-9) else rel


class QuadrupedProblem:
    """The tensors of one fit: coarse masks, distance fields, grid, cameras, template, flow, frame rate."""

    def __init__(self, masks: np.ndarray, camera: Camera, config: QuadrupedFitConfig, *,
                 frames: np.ndarray | None = None, extrinsics: np.ndarray | None = None,
                 fps: float = SMOOTH_FPS) -> None:
        self.box = mask_box(masks)
        uv, self.gw, self.gh = grid_cells(self.box, config.grid)
        coarse = coarse_masks(masks, self.box, self.gw, self.gh)
        self.target = torch.tensor(coarse.reshape(len(masks), -1), dtype=DTYPE)
        self.outside = torch.tensor(outside_distance(coarse), dtype=DTYPE)
        self.uv = torch.tensor(uv, dtype=DTYPE)
        self.K = torch.tensor(camera.K, dtype=DTYPE)
        self.tau = max(self.box[2] - self.box[0], self.box[3] - self.box[1]) / config.grid * 0.5
        self.tt = TemplateTensors(body_template(config.template))
        self.camera = camera
        rel = relative_cameras(extrinsics)
        self.cams = None if rel is None else torch.tensor(rel, dtype=DTYPE)
        self.rate = fps / SMOOTH_FPS
        self.flow: torch.Tensor | None = None
        self.flow_ok: torch.Tensor | None = None  # (T-1, P) where the flow is trusted (:func:`video_flow`)
        self.flow_consistent: torch.Tensor | None = None  # (T-1, P) forward-backward consistent, on or off the mask
        self.flow_explained: float | None = None  # the share of the masks' change the flow explains
        if frames is not None and len(frames) >= 2:
            flow, ok, consistent, self.flow_explained = video_flow(frames, uv, masks)
            self.flow, self.flow_ok = torch.tensor(flow, dtype=DTYPE), torch.tensor(ok)
            self.flow_consistent = torch.tensor(consistent)

    def cams_of(self, frames: np.ndarray) -> torch.Tensor | None:
        return None if self.cams is None else self.cams[torch.as_tensor(frames)]


def body_silhouette(prob: QuadrupedProblem, verts: torch.Tensor, cams: torch.Tensor | None, scale: torch.Tensor
                    ) -> torch.Tensor:
    """(T, P) soft silhouette of the posed body (T, V, 3) on the grid, seen by cameras ``cams``."""
    pts = to_cameras(body_samples(prob.tt, verts), cams)
    radius = prob.tt.sample_radius * scale * prob.K[0, 0] / pts[..., 2].clamp_min(1e-3)
    return soft_point_silhouette(project_points(pts, prob.K), radius, prob.uv, prob.tau)


def silhouette_terms(prob: QuadrupedProblem, frames: np.ndarray, joints: torch.Tensor, verts: torch.Tensor,
                     scale: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Binary cross-entropy of the soft silhouette, the skeleton-inside-mask term and the (T, P) occupancy."""
    cams = prob.cams_of(frames)
    occ = body_silhouette(prob, verts, cams, scale)
    tgt = prob.target[frames]
    bce = -(tgt * torch.log(occ.clamp(1e-5)) + (1 - tgt) * torch.log((1 - occ).clamp(1e-5))).mean()
    seg, par = prob.tt.segments, prob.tt.parents
    s = torch.linspace(0, 1, 5, dtype=DTYPE)[None, None, :, None]
    pts = joints[:, par[seg]][:, :, None] * (1 - s) + joints[:, seg][:, :, None] * s
    uv = project_points(to_cameras(pts.reshape(len(frames), -1, 3), cams), prob.K)
    u0, v0, u1, v1 = prob.box
    grid = torch.stack([(uv[..., 0] - u0) / (u1 - u0) * 2 - 1, (uv[..., 1] - v0) / (v1 - v0) * 2 - 1], -1)
    dist = torch.nn.functional.grid_sample(prob.outside[frames][:, None], grid[:, None], align_corners=False,
                                           padding_mode="border")
    return bce, dist.pow(2).mean(), occ


def shape_priors(prob: QuadrupedProblem, params: Params, config: QuadrupedFitConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """The unweighted bone length and girth prior and the joint-limit penalty of ``params``."""
    twin = prob.tt.twin
    lengths = params["log_len"].new_zeros(())
    for key in ("log_len", "log_girth"):
        v = params[key]
        lengths = lengths + v.pow(2).mean() + (v - v[twin]).pow(2).mean()
    local = params["local"]
    limit = torch.relu(local.norm(dim=-1) - math.radians(config.joint_limit_deg)).pow(2).mean()
    off = local[:, prob.tt.leg_joints, :2].norm(dim=-1)  # legs swing about the lateral (z) axis
    limit = limit + torch.relu(off - math.radians(config.leg_off_plane_deg)).pow(2).mean()
    return lengths, limit


def smoothness(prob: QuadrupedProblem, joints: torch.Tensor, scale: torch.Tensor, history: torch.Tensor | None
               ) -> torch.Tensor:
    """Mean squared acceleration of the root-relative joints and the root (template units)."""
    rel = torch.cat([joints - joints[:, :1], joints[:, :1]], 1) / scale
    if history is not None:
        rel = torch.cat([history, rel])
    if len(rel) <= 2:
        return joints.new_zeros(())
    second = (rel[2:] - 2 * rel[1:-1] + rel[:-2]) * prob.rate**2
    return second.pow(2).sum(-1).mean()


def clip_loss(prob: QuadrupedProblem, frames: np.ndarray, params: Params, config: QuadrupedFitConfig,
              history: torch.Tensor | None = None, prev: torch.Tensor | None = None, anchor: Params | None = None
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Total loss, joints (T, J, 3) and soft silhouettes (T, P) of ``params`` on ``frames``.

    ``history``: (2, J + 1, 3) root-relative joints and root of the two frames before a one-frame fit
    (template units), for the smoothness term; ``prev``: (1, V, 3) the vertices of the frame before it, for the
    flow term; ``anchor``: the clip's shape a one-frame fit is held near (``shape_hold_weight``).
    """
    joints, verts = pose_body(prob.tt, params)
    # the scale's exp taken once per term, as before the flow term: without the flow the sums are main's to the bit
    bce, inside, occ = silhouette_terms(prob, frames, joints, verts, params["log_scale"].exp())
    lengths, limit = shape_priors(prob, params, config)
    total = (config.silhouette_weight * bce + config.inside_weight * inside + config.length_weight * lengths
             + config.limit_weight * limit
             + config.smooth_weight * smoothness(prob, joints, params["log_scale"].exp(), history))
    if config.flow_weight > 0 and (prev is not None or config.flow_in_clip):
        total = total + config.flow_weight * flow_term(prob, frames, verts, params["log_scale"].exp(), prev,
                                                       config.flow_robust_cells)
    if anchor is not None and config.shape_hold_weight > 0:
        total = total + config.shape_hold_weight * sum((params[k] - anchor[k]).pow(2).mean() for k in CLIP)
    return total, joints, occ


def run_steps(prob: QuadrupedProblem, frames: np.ndarray, params: Params, config: QuadrupedFitConfig, steps: int, *,
              free: tuple[str, ...] | None = None, history: torch.Tensor | None = None,
              prev: torch.Tensor | None = None, anchor: Params | None = None) -> tuple[float, np.ndarray, np.ndarray]:
    """``steps`` Adam steps on ``params`` (only the names in ``free``, default all); returns (loss, joints
    (T, J, 3), IoU (T,) on the grid). ``history``, ``prev``, ``anchor``: :func:`clip_loss`'s, for a one-frame fit."""
    opt = torch.optim.Adam([v for k, v in params.items() if free is None or k in free], lr=config.lr)
    with deterministic_torch():  # a run is reproducible whatever torch's thread count
        for _ in range(steps):
            opt.zero_grad()
            loss, _, _ = clip_loss(prob, frames, params, config, history, prev, anchor)
            loss.backward()
            opt.step()
    with torch.no_grad():
        loss, joints, occ = clip_loss(prob, frames, params, config, history, prev, anchor)
    pred, tgt = occ > 0.5, prob.target[frames] > 0.5
    iou = ((pred & tgt).sum(1) / (pred | tgt).sum(1).clamp_min(1)).numpy()
    return float(loss), joints.numpy().astype(np.float64), iou


MIRROR = torch.tensor([-1.0, -1.0, 1.0], dtype=DTYPE)  # axis-angle under the z -> -z mirror: -M v


def swap_legs(tt: TemplateTensors, local: torch.Tensor, pairs: tuple[str, ...]) -> torch.Tensor:
    """(T, J, 3) joint rotations with each pair's left and right legs exchanged and mirrored (``"f"``, ``"h"``).

    On a mirror-symmetric template this puts each leg where the mirror image of its twin was.
    """
    out = local.clone()
    for pair in pairs:
        left, right = tt.template.leg(pair + "l_"), tt.template.leg(pair + "r_")
        out[:, left], out[:, right] = local[:, right] * MIRROR, local[:, left] * MIRROR
    return out


def flow_weights(prob: QuadrupedProblem, uv: torch.Tensor, z: torch.Tensor, cells: torch.Tensor | None = None
                 ) -> torch.Tensor:
    """(T, P, V) how much each vertex, projected at ``uv`` (T, V, 2) [px] with depth ``z`` (T, V), moves each
    grid cell: near the cell (a Gaussian of one cell), the nearest in depth first (a soft z-buffer: 5 % of the
    body's depth range costs a factor e), not normalised. No gradient: which vertices a cell sees is held
    while the motion they carry is differentiated."""
    with torch.no_grad():
        grid = prob.uv if cells is None else prob.uv[cells]  # ``cells``: only these grid cells (P of them)
        d2 = (grid[None, :, None] - uv[:, None]).pow(2).sum(-1)  # (T, P, V)
        lo, hi = z.min(1, keepdim=True).values, z.max(1, keepdim=True).values
        depth = (z - lo) / (0.05 * (hi - lo).clamp_min(1e-6))
        return torch.exp(-d2 / (2 * (2 * prob.tau) ** 2) - depth[:, None])


def predicted_flow(prob: QuadrupedProblem, verts: torch.Tensor, scale: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """(T-1, P, 2) image motion [px] of the posed mesh from frame t to t+1 at the grid cells (each cell takes
    the motion of the vertices near it, the nearest in depth first) and (T-1, P) the body's occupancy at t."""
    cam = to_cameras(verts, prob.cams)
    uv = project_points(cam, prob.K)
    motion = uv[1:] - uv[:-1]  # (T-1, V, 2): the body's and the camera's motion
    w = flow_weights(prob, uv[:-1], cam[:-1, :, 2])
    flow = (w[..., None] * motion[:, None]).sum(2) / w.sum(2).clamp_min(1e-12)[..., None]
    return flow, body_silhouette(prob, verts[:-1], None if prob.cams is None else prob.cams[:-1], scale)


def flow_term(prob: QuadrupedProblem, frames: np.ndarray, verts: torch.Tensor, scale: torch.Tensor,
              prev: torch.Tensor | None, robust_cells: float) -> torch.Tensor:
    """Mean Cauchy penalty [grid cells] of the body's image motion against the video's flow between the
    consecutive frames of a fit (``prev``: (1, V, 3) the vertices of the frame before ``frames[0]``, held, for
    a one-frame tracking fit), over the cells where the flow is trusted and the body is (at the earlier frame).

    The silhouette cannot tell a leg swinging in place from the body turning toward the camera; their texture
    moves differently. Cauchy: a wrong flow or a leg faster than the flow's patch costs little."""
    if prob.flow is None or prob.flow_ok is None:
        return verts.new_zeros(())
    idx = np.asarray(frames)
    if prev is not None:
        verts, idx = torch.cat([prev, verts]), np.concatenate([[idx[0] - 1], idx])
    pairs = np.flatnonzero(np.diff(idx) == 1)
    if len(pairs) == 0:
        return verts.new_zeros(())
    cams = prob.cams_of(idx)
    cam = to_cameras(verts, cams)
    uv = project_points(cam, prob.K)
    with torch.no_grad():
        body = body_silhouette(prob, verts[pairs], None if cams is None else cams[pairs], scale) > 0.5
        keep = body & prob.flow_ok[idx[pairs]] & (prob.target[idx[pairs]] > 0.5)
    total, count = verts.new_zeros(()), 0
    for k, (i, t) in enumerate(zip(pairs, idx[pairs])):  # only the trusted cells: a fifth of the grid or less
        cells = torch.nonzero(keep[k]).squeeze(1)
        if len(cells) == 0:
            continue
        w = flow_weights(prob, uv[i: i + 1].detach(), cam[i: i + 1, :, 2].detach(), cells)[0]
        motion = (w / w.sum(1, keepdim=True).clamp_min(1e-12)) @ (uv[i + 1] - uv[i])
        r2 = (motion - prob.flow[t, cells]).pow(2).sum(-1) / (2 * prob.tau * robust_cells) ** 2
        total, count = total + torch.log1p(r2).sum(), count + len(cells)
    return total / max(count, 1)


def flow_error(prob: QuadrupedProblem, params: Params) -> float:
    """Mean distance [grid cells] between the body's predicted image motion and the video's optical flow, over
    the cells inside both the mask and the body; 0 when the video has fewer than two frames."""
    if prob.flow is None:
        return 0.0
    with torch.no_grad():
        _, verts = pose_body(prob.tt, params)
        flow, body = predicted_flow(prob, verts, params["log_scale"].exp())
        keep = (body > 0.5) & (prob.target[:-1] > 0.5)
        err = (flow - prob.flow).norm(dim=-1)
    return float(err[keep].mean()) / (2 * prob.tau) if keep.any() else 0.0


RIGID = ("root_rot", "root_pos", "log_scale", "log_thick")
CLIP = ("log_len", "log_girth", "log_scale", "log_thick")


def initial_root(mask: np.ndarray, camera: Camera, length: float, height: float) -> np.ndarray:
    """(3,) camera-frame root guess: the mask centroid back-projected at the depth where a body ``height`` [m]
    tall spans the mask's vertical extent (the height, unlike the length, does not depend on the heading)."""
    ys, xs = np.nonzero(mask)
    height_px = max(ys.max() - ys.min() + 1, 4)
    K = camera.K
    z = K[1, 1] * height / height_px
    return np.array([(xs.mean() - K[0, 2]) / K[0, 0] * z, (ys.mean() - K[1, 2]) / K[1, 1] * z, z])


def heading_rotation(up_cam: np.ndarray, angle: float) -> np.ndarray:
    """Axis-angle (3,) taking the template (y up, facing -x) to the camera frame, turned by ``angle`` about up."""
    from scipy.spatial.transform import Rotation

    up = up_cam / np.linalg.norm(up_cam)
    fwd = np.cross(up, [0.0, 0.0, 1.0]) if abs(up[2]) < 0.9 else np.cross(up, [1.0, 0.0, 0.0])
    fwd /= np.linalg.norm(fwd)
    base = np.stack([-fwd, up, np.cross(-fwd, up)], axis=1)  # columns: images of template x, y, z
    turn = Rotation.from_rotvec(up * angle).as_matrix()
    return Rotation.from_matrix(turn @ base).as_rotvec()


def ground_heading(params: Params, up_cam: np.ndarray) -> np.ndarray:
    """(3,) unit: the body's mean heading over the clip on the ground plane (the template's -x turned by the root;
    zero when the body stands upright on its head)."""
    up = up_cam / np.linalg.norm(up_cam)
    with torch.no_grad():
        rot = rotation_vector_to_matrix_torch(params["root_rot"]) @ rotation_vector_to_matrix_torch(params["local"][:, 0])
        fwd = (-rot[:, :, 0]).numpy().astype(np.float64)
    heading = (fwd - (fwd @ up)[:, None] * up).sum(0)
    norm = float(np.linalg.norm(heading))
    return heading / norm if norm > 0 else heading


def travel(prob: QuadrupedProblem, params: Params, up_cam: np.ndarray) -> tuple[np.ndarray, float]:
    """The root's displacement over the clip on the ground plane (3,) [body lengths, first camera frame] and its
    forward travel: that displacement along the body's mean heading (:func:`ground_heading`), negative when the
    body walks backwards. Body lengths: the template's unit is its length, so the clip's scale is one."""
    up = up_cam / np.linalg.norm(up_cam)
    root = params["root_pos"].detach().numpy().astype(np.float64)
    disp = root[-1] - root[0]
    disp = (disp - (disp @ up) * up) / float(params["log_scale"].detach().exp())
    return disp, float(disp @ ground_heading(params, up_cam))


def travel_heading(disp: np.ndarray, up_cam: np.ndarray) -> float:
    """The heading angle (about ``up_cam``, :func:`heading_rotation`'s convention) along a displacement (3,)."""
    from scipy.spatial.transform import Rotation

    up = up_cam / np.linalg.norm(up_cam)
    base = -Rotation.from_rotvec(heading_rotation(up_cam, 0.0)).as_matrix()[:, 0]  # the template's -x: its forward
    return math.atan2(float(np.cross(base, disp) @ up), float(base @ disp))


def leaf(x: np.ndarray | float) -> torch.Tensor:
    return torch.tensor(np.asarray(x), dtype=DTYPE).requires_grad_(True)


def start_params(prob: QuadrupedProblem, rot: np.ndarray, root: np.ndarray, length: float, frames: int = 1
                 ) -> Params:
    """Parameters of the template at rest, root rotation ``rot`` (3,) and position ``root`` (3,) on every frame."""
    nj = len(prob.tt.parents)
    return {"root_rot": leaf(np.tile(rot, (frames, 1))), "root_pos": leaf(np.tile(root, (frames, 1))),
            "local": leaf(np.zeros((frames, nj, 3))), "log_len": leaf(np.zeros(nj)),
            "log_girth": leaf(np.zeros(nj)), "log_scale": leaf(math.log(length)), "log_thick": leaf(0.0)}


def frame_params(params: Params, t: int) -> Params:
    """Leaf copies of frame ``t``'s per-frame tensors and of the clip's shared ones."""
    return {k: (v.detach()[t: t + 1] if k not in CLIP else v.detach()).clone().requires_grad_(True)
            for k, v in params.items()}


def start_root(prob: QuadrupedProblem, mask: np.ndarray, config: QuadrupedFitConfig) -> np.ndarray:
    """(3,) the first frame's root guess for every start (:func:`initial_root` at the template's height)."""
    tmpl = prob.tt.template
    return initial_root(mask, prob.camera, config.template_length,
                        config.template_length * float(np.ptp(tmpl.vertices[:, 1])))


def fit_start(prob: QuadrupedProblem, root0: np.ndarray, up_cam: np.ndarray, angle: float,
              config: QuadrupedFitConfig) -> tuple[float, Params]:
    """(loss, parameters) of the template at heading ``angle`` [rad] fitted to the first frame: rigid (root, scale,
    girth), then with its joints."""
    params = start_params(prob, heading_rotation(up_cam, angle), root0, config.template_length)
    run_steps(prob, np.arange(1), params, config, config.start_iterations // 2, free=RIGID)
    loss, _, iou = run_steps(prob, np.arange(1), params, config, config.start_iterations - config.start_iterations // 2)
    log.info("quadruped start (heading %.0f deg): loss %.4f, IoU %.3f", math.degrees(angle) % 360, loss, iou.mean())
    return loss, params


def first_frame_starts(prob: QuadrupedProblem, mask: np.ndarray, up_cam: np.ndarray, config: QuadrupedFitConfig
                       ) -> list[tuple[float, int, Params]]:
    """(loss, heading index, parameters) of every heading fitted to the first frame (rigid, then with joints)."""
    root0 = start_root(prob, mask, config)
    starts = []
    for k in range(config.starts):
        loss, params = fit_start(prob, root0, up_cam, 2 * math.pi * k / config.starts, config)
        starts.append((loss, k, params))
    return starts


def history_of(prob: QuadrupedProblem, frames: list[Params]) -> torch.Tensor | None:
    """(2, J + 1, 3) root-relative joints and root of the last two tracked frames (template units)."""
    if len(frames) < 2:
        return None
    with torch.no_grad():
        past = []
        for p in frames[-2:]:
            j, _ = pose_body(prob.tt, p)
            past.append(torch.cat([j - j[:, :1], j[:, :1]], 1) / p["log_scale"].exp())
    return torch.cat(past)


def track(prob: QuadrupedProblem, start: Params, config: QuadrupedFitConfig, n: int) -> Params:
    """Clip parameters from a first-frame fit: every later frame warm-started from the previous one (root
    extrapolated at constant velocity), smoothed against the two frames before it, its image motion from the
    frame before against the flow, its shape held near the start's (without the hold the tracked body grows
    and thins frame by frame: docs/results/people_animals.md)."""
    frames = [start]
    anchor = {k: start[k].detach().clone() for k in CLIP}
    for t in range(1, n):
        cur = frame_params(frames[-1], 0)
        if t >= 2:
            with torch.no_grad():
                cur["root_pos"] += frames[-1]["root_pos"].detach() - frames[-2]["root_pos"].detach()
        with torch.no_grad():
            prev = pose_body(prob.tt, frames[-1])[1]
        run_steps(prob, np.array([t]), cur, config, config.frame_iterations, history=history_of(prob, frames),
                  prev=prev, anchor=anchor)
        frames.append(cur)
    return {k: (torch.cat([p[k].detach() for p in frames]) if k not in CLIP else frames[-1][k].detach().clone()
                ).requires_grad_(True) for k in frames[0]}


def union_flow_residual(prob: QuadrupedProblem, params: Params) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(T-1, P) distance [grid cells] between the image motion ``params`` predicts and the video's flow, (T-1, P)
    the cells it counts: the union of the mask's and the body's cells where the flow is consistent, and (T-1, P)
    the body's occupancy. Where the body is, the body's motion; where it is not, the background's: the median
    flow of the consistent cells off both mask and body (0 under a still camera, the camera's motion under a
    moving one). So a body pays for the mask it leaves uncovered (the subject's motion there predicted as
    background) and for the cells it puts off the mask (its motion against the background's)."""
    assert prob.flow is not None and prob.flow_consistent is not None
    with torch.no_grad():
        _, verts = pose_body(prob.tt, params)
        flow, occ = predicted_flow(prob, verts, params["log_scale"].exp())
        body, mask = occ > 0.5, prob.target[:-1] > 0.5
        off = prob.flow_consistent & ~body & ~mask
        background = torch.stack([prob.flow[t, off[t]].median(0).values if off[t].any() else flow.new_zeros(2)
                                  for t in range(len(flow))])
        pred = torch.where(body[..., None], flow, background[:, None])
        err = (pred - prob.flow).norm(dim=-1) / (2 * prob.tau)
    return err, (body | mask) & prob.flow_consistent, body


def misplaced_cells(prob: QuadrupedProblem, body: torch.Tensor) -> torch.Tensor:
    """(T', P) how far [cells] each cell of the mask the ``body`` (T', P) bool leaves uncovered lies from the body,
    and each cell of the body off the mask from the mask (0 elsewhere): the silhouette's error as a displacement,
    in the flow residual's units."""
    mask = (prob.target[: len(body)] > 0.5).numpy()
    grid = body.numpy().reshape(len(body), prob.gh, prob.gw).astype(np.float64)
    to_body = outside_distance(grid).reshape(len(body), -1)
    to_mask = prob.outside[: len(body)].reshape(len(body), -1).numpy()
    out = np.where(mask & ~body.numpy(), to_body, 0.0) + np.where(body.numpy() & ~mask, to_mask, 0.0)
    return torch.tensor(out, dtype=DTYPE)


def hypothesis_score(prob: QuadrupedProblem, params: Params, config: QuadrupedFitConfig, n: int) -> float:
    """A hypothesis' rank (lower is better): per cell of the union of mask and body, its flow residual
    (:func:`union_flow_residual`; Cauchy at ``flow_robust_cells`` with ``rank_by_loss``, then beside the clip loss
    without the flow term) plus how far the cell lies beyond the outline's first cell from the silhouette it
    misses (:func:`misplaced_cells`: a misplaced cell is a displacement too; the template's outline differs from
    the animal's by about a cell, so the first cell is the shape's, not the placement's). Without the video's
    frames the clip loss. Scored over the body's cells alone, a leg swap that crosses the silhouette can explain
    the flow best (the real cat clip: docs/results/people_animals.md)."""
    if prob.flow is None:
        with torch.no_grad():
            return float(clip_loss(prob, np.arange(n), params, config)[0])
    err, keep, body = union_flow_residual(prob, params)
    if not keep.any():
        return 0.0
    beyond = (misplaced_cells(prob, body) - 1.0).clamp_min(0.0)[keep]
    if not config.rank_by_loss:
        return float((err[keep] + beyond).mean())
    with torch.no_grad():
        loss = float(clip_loss(prob, np.arange(n), params, replace(config, flow_in_clip=False))[0])
    robust = torch.log1p((err[keep] / config.flow_robust_cells) ** 2)
    return loss + float((config.flow_weight * robust + beyond).mean())


def mask_travel(prob: QuadrupedProblem, masks: np.ndarray, up_cam: np.ndarray, config: QuadrupedFitConfig
                ) -> np.ndarray:
    """(3,) the subject's displacement over the clip on the ground plane [body lengths, first camera frame], read
    from the masks alone: the first frame's root guess (:func:`start_root`: the mask's centroid at the depth its
    height implies) in the last frame against the first, a moving camera's motion taken out. No hypothesis is
    needed, so a head-on walk (the masks grow) is read the same whichever way the body is fitted to face."""
    up = up_cam / np.linalg.norm(up_cam)
    ends = []
    for t in (0, len(masks) - 1):
        root = start_root(prob, masks[t], config)
        if prob.cams is not None:  # frame t's camera -> the first's
            back = np.linalg.inv(prob.cams[t].numpy().astype(np.float64))
            root = back[:3, :3] @ root + back[:3, 3]
        ends.append(root)
    disp = ends[1] - ends[0]
    return (disp - (disp @ up) * up) / config.template_length


def tracked_hypotheses(prob: QuadrupedProblem, starts: list[tuple[float, int, Params]], config: QuadrupedFitConfig,
                       up_cam: np.ndarray, masks: np.ndarray, walk: np.ndarray | None) -> list[tuple[float, Params]]:
    """(heading [deg], clip parameters) of the ``tracks`` lowest-loss starts, tracked and refined on the clip, and,
    with ``travel_start`` and a ``walk`` (3,) (the masks' travel, :func:`mask_travel`) that no tracked body faces
    (every one's heading more than 90 degrees from it), of a start heading along the walk: animals walk head
    first, and a head-on dog's silhouette fits the wrong headings best (docs/results/people_animals.md). When a
    tracked body already faces the walk no start is added: a second one near it only re-draws the fit's spread
    (dog side: a start at 21 deg beside the track at 45 won by 0.005 and ended 30.7 % against 24.8)."""
    n = len(masks)
    out = []
    for _, k, params in sorted(starts, key=lambda x: x[0])[: config.tracks]:
        full = track(prob, params, config, n)
        run_steps(prob, np.arange(n), full, config, config.iterations)
        out.append((360.0 * k / config.starts, full))
    if config.travel_start and walk is not None and all(ground_heading(p, up_cam) @ walk <= 0 for _, p in out):
        angle = travel_heading(walk, up_cam)
        full = track(prob, fit_start(prob, start_root(prob, masks[0], config), up_cam, angle, config)[1], config, n)
        run_steps(prob, np.arange(n), full, config, config.iterations)
        out.append((math.degrees(angle) % 360, full))
    return out


def best_hypothesis(prob: QuadrupedProblem, starts: list[tuple[float, int, Params]], config: QuadrupedFitConfig,
                    up_cam: np.ndarray, masks: np.ndarray) -> Params:
    """The best tracked hypothesis (:func:`tracked_hypotheses`), each with and without its fore and/or hind legs
    swapped, by :func:`hypothesis_score`. When the masks travel at least one body length (:func:`mask_travel`: a
    walk, not a survey in place), with ``travel_rank`` each is also charged its backward travel (:func:`travel`, in
    body lengths): animals walk head first. Below a body length a hypothesis' own travel is noise (shiba export:
    the better hypothesis' root drifted 0.39 body lengths backward, the worse one's 0.13), so the cue is silent."""
    best: tuple[float, Params] | None = None
    swaps = ((), ("f",), ("h",), ("f", "h")) if prob.flow is not None else ((),)
    n = len(masks)
    travelled = mask_travel(prob, masks, up_cam, config)
    log.info("quadruped travel read from the masks: %.2f body lengths", float(np.linalg.norm(travelled)))
    walk = travelled if float(np.linalg.norm(travelled)) >= WALK_BODY_LENGTHS else None
    for heading, full in tracked_hypotheses(prob, starts, config, up_cam, masks, walk):
        backward = max(0.0, -travel(prob, full, up_cam)[1]) if config.travel_rank and walk is not None else 0.0
        for pairs in swaps:
            trial = {**full, "local": swap_legs(prob.tt, full["local"].detach(), pairs)}
            score = hypothesis_score(prob, trial, config, n) + backward
            log.info("quadruped hypothesis heading %.0f deg, legs swapped: %s: score %.4f (backward travel %.3f)",
                     heading, "+".join(pairs) or "none", score, backward)
            if best is None or score < best[0]:
                best = (score, trial)
    assert best is not None
    return {k: v.detach().clone().requires_grad_(True) for k, v in best[1].items()}


def flow_gate(prob: QuadrupedProblem, config: QuadrupedFitConfig, source: str) -> QuadrupedFitConfig:
    """``config`` without the flow term, the shape hold and the loss ranking when the video's flow explains less
    than ``flow_min_explained`` of the masks' change (``config`` itself otherwise, or without frames)."""
    if prob.flow_explained is None:
        return config
    trusted = prob.flow_explained >= config.flow_min_explained
    log.info("quadruped fit of %s: the flow explains %.3f of the masks' change: %s", source, prob.flow_explained,
             "flow term, shape hold and loss ranking on" if trusted else "the fit without them")
    return config if trusted else replace(config, flow_weight=0.0, shape_hold_weight=0.0, rank_by_loss=False)


def check_masks(masks: np.ndarray, source: str, extrinsics: np.ndarray | None) -> None:
    """InputError naming the video when a frame's mask is empty or the extrinsics do not match the frames."""
    empty = np.flatnonzero(~masks.any((1, 2)))
    if len(empty):
        raise InputError(
            f"{source}: the subject's mask is empty in {len(empty)} frame(s) (first: {empty[0]}); "
            "give masks (reference.masks) or a video with a static camera and a moving subject")
    if extrinsics is not None and (np.shape(extrinsics) != (len(masks), 4, 4) or not np.isfinite(extrinsics).all()):
        raise InputError(f"{source}: the camera extrinsics must be finite (T, 4, 4) with T = {len(masks)} frames, "
                         f"got shape {np.shape(extrinsics)}")


def fit_quadruped(masks: np.ndarray, camera: Camera, config: QuadrupedFitConfig, *, source: str,
                  world_up: np.ndarray | None = None, frames: np.ndarray | None = None, fps: float = SMOOTH_FPS,
                  extrinsics: np.ndarray | None = None) -> QuadrupedFit:
    """Fit the body template to (T, H, W) bool masks.

    1. first frame: ``starts`` root headings about the up axis, each fitted rigidly (root, scale, girth) and
       then with its joints;
    2. the ``tracks`` lowest-loss starts tracked frame by frame (warm start, root at constant velocity,
       smoothed against the two frames before, the flow from the frame before, the shape held near the
       start's), then refined on the whole clip (silhouette and priors);
    3. each track with the fore and/or hind legs swapped left for right (mirrored): the hypothesis with the
       lowest clip loss with the flow term wins and is refined.

    When the flow explains less than ``flow_min_explained`` of the masks' change (:func:`flow_gate`), step 2
    runs without the flow and the hold and step 3 ranks by the raw flow error (the fit before the flow term).

    Args:
        masks: (T, H, W) bool subject masks.
        camera: the camera (intrinsics; ``world_to_cam`` is frame 0's pose when ``extrinsics`` is given).
        config: template, weights, schedule, starts.
        source: the video's name, for messages.
        world_up: (3,) world up direction (orients the starts); None = the camera's -y.
        frames: (T, H, W, 3) uint8 video frames for the optical flow; None = no flow (the clip loss ranks).
        fps: the video's frame rate [1/s]; the smoothness acts on accelerations.
        extrinsics: (T, 4, 4) world-to-camera per frame (a moving camera), or None (static).

    Returns:
        The fit, in the first frame's camera frame.

    Raises:
        InputError: a frame's mask is empty, or the extrinsics do not match the frames.
    """
    check_masks(masks, source, extrinsics)
    n = len(masks)
    prob = QuadrupedProblem(masks, camera, config, frames=frames, extrinsics=extrinsics, fps=fps)
    config = flow_gate(prob, config, source)
    w2c0 = camera.world_to_cam if extrinsics is None else np.asarray(extrinsics[0], dtype=np.float64)
    up_cam = np.array([0.0, -1.0, 0.0]) if world_up is None else w2c0[:3, :3] @ np.asarray(world_up, dtype=np.float64)
    starts = first_frame_starts(prob, masks[0], up_cam, config)
    full = best_hypothesis(prob, starts, config, up_cam, masks)
    loss, joints, iou = run_steps(prob, np.arange(n), full, config, config.swap_iterations if prob.flow is not None else 0)
    log.info("quadruped fit of %s: %d frames, silhouette IoU %.3f (min %.3f), loss %.4f", source, n, iou.mean(),
             iou.min(), loss)
    return finish_fit(prob, full, masks.shape[1:], joints, iou)


def finish_fit(prob: QuadrupedProblem, params: Params, size: tuple[int, int], joints: np.ndarray, iou: np.ndarray
               ) -> QuadrupedFit:
    """The :class:`QuadrupedFit` of ``params``: posed mesh and its full-size silhouettes per frame."""
    with torch.no_grad():
        _, verts = pose_body(prob.tt, params)
        cam_verts = to_cameras(verts, prob.cams).numpy().astype(np.float64)
    faces = prob.tt.template.faces
    sil = np.stack([rasterise(v, faces, prob.camera.K, size[1], size[0]) for v in cam_verts])
    tmpl = prob.tt.template
    return QuadrupedFit(joints=joints, names=tmpl.names, parents=tmpl.parents.copy(),
                        vertices=verts.numpy().astype(np.float64), faces=faces.copy(), silhouettes=sil, iou=iou)
