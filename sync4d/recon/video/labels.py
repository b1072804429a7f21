"""The final part labels of the tracked points: every frame's evidence under every part's fitted motion, plus
spatial coherence.

After the joint fit each part's motion is known. A point's label is then a choice between these motions: for
every part b the point is put on its frame-0 ray at the depth of b's surface (b's plane at that pixel) and
moved with b through the clip; its cost is what that predicts against the images, accumulated over all
frames: the chained track where trusted, the frame-to-frame flow where consistent and the point visible
(not behind the fitted surface), the distance outside the masks, and the colour at the predicted pixel
against the point's frame-0 colour where visible (under the wrong motion a point lands on other surface,
which tracks and flow on a plain face do not show). Parts are connected pieces of surface,
so the labels minimise these costs plus a Potts penalty on grid neighbours with different labels (iterated
conditional modes from the cheapest labels): a point whose evidence is ambiguous (a plain face whose tracks
stick, a point near the hinge that barely moves) follows its neighbours.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from sync4d.recon.video.joints import Articulation, Scene, project, sample_outside

COLOUR_SIGMA = 0.1  # colour difference (RGB in [0, 1], L2) of one unit of the colour cost
POTTS = 0.1  # cost [strides, Charbonnier] of each grid neighbour with another label
SWEEPS = 10  # iterated conditional modes sweeps (converges in 3-5 on the suite)


def _zbuffer(uv: torch.Tensor, depth: torch.Tensor, stride: float) -> list[dict[int, float]]:
    """Per frame, the nearest camera depth [m] of the posed points in each stride cell (key -> depth)."""
    cell = torch.floor(uv / stride).long()
    key = (cell[..., 0] * 100003 + cell[..., 1]).numpy()
    out = []
    for f in range(len(key)):
        order = np.argsort(-depth[f].numpy())  # later writes (nearer points) win
        out.append(dict(zip(key[f][order].tolist(), depth[f].numpy()[order].tolist())))
    return out


def _visible(uv: torch.Tensor, depth: torch.Tensor, zbuf: list[dict[int, float]], stride: float) -> torch.Tensor:
    """(F, N) bool: candidate points (pixels uv (F, N, 2), depths (F, N)) not behind the fitted surface."""
    cell = torch.floor(uv / stride).long()
    key = (cell[..., 0] * 100003 + cell[..., 1]).numpy()
    out = np.ones(key.shape, bool)
    for f in range(len(key)):
        near = np.array([zbuf[f].get(k, np.inf) for k in key[f].tolist()])
        out[f] = depth[f].numpy() <= near * 1.02
    return torch.as_tensor(out)


def part_costs(model: Articulation) -> np.ndarray:
    """(N, B) cost of every tracked point under every part's motion, summed over the clip's frames (mean per
    frame of each term, in strides)."""
    sc = model.scene
    n_parts = len(model.kinds)
    cost = np.full((len(model.labels), n_parts), np.inf)
    with torch.no_grad():
        trans = model.part_transforms()
        posed = model.posed()
        zbuf = _zbuffer(project(sc, posed), (posed @ sc.w2c[:3, :3].T + sc.w2c[:3, 3])[..., 2], sc.stride)
        ok = sc.trusted.double()
        for b in range(n_parts):
            if not (model.labels == b).any():
                continue
            inv = (model.plane[b][None] * model.coords).sum(1).clamp_min(1e-3)
            rest = sc.centre + (1.0 / inv)[:, None] * sc.rays
            x = torch.einsum("tij,nj->tni", trans[:, b, :, :3], rest) + trans[:, b, None, :, 3]
            uv = project(sc, x)
            err = torch.sqrt(((uv - sc.tracks) ** 2).sum(-1) / sc.stride**2 + 1.0) - 1.0
            track = (err * ok).sum(0) / ok.sum(0).clamp_min(1.0)
            inside = (sample_outside(sc, uv, 0) / sc.stride).clamp(max=10.0).mean(0)
            depth = (x @ sc.w2c[:3, :3].T + sc.w2c[:3, 3])[..., 2]
            vis = _visible(uv, depth, zbuf, sc.stride)
            cost[:, b] = (track + inside + _flow_cost(model, uv, vis) + _colour_cost(sc, uv, vis)).numpy()
    return cost


def _sample(images: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """(F, C, N) bilinear samples of images (F, C, H, W) at pixels uv (F, N, 2)."""
    _, _, h, w = images.shape
    grid = torch.stack([uv[..., 0] / w * 2 - 1, uv[..., 1] / h * 2 - 1], -1)[:, None].to(images.dtype)
    return torch.nn.functional.grid_sample(images, grid, align_corners=False)[:, :, 0].double()


def _colour_cost(sc: Scene, uv: torch.Tensor, vis: torch.Tensor) -> torch.Tensor:
    """(N,) mean truncated Charbonnier (units of COLOUR_SIGMA) of the colour at the predicted pixels uv
    (T, N, 2) against the point's frame-0 colour, over frames 1.. where the point is visible: under another
    part's motion a point lands on other surface (a lid held static sees the keyboard it uncovers), which
    tracks and flow on a plain face do not show; 0 without frames."""
    if sc.colour is None or len(uv) < 2:
        return torch.zeros(uv.shape[1], dtype=uv.dtype)
    ref = _sample(sc.colour[:1], uv[:1])
    now = _sample(sc.colour[1:], uv[1:])
    err = ((now - ref) ** 2).sum(1) / COLOUR_SIGMA**2
    use = vis[1:].double()
    return ((torch.sqrt(err + 1.0) - 1.0).clamp(max=3.0) * use).sum(0) / use.sum(0).clamp_min(1.0)


def _flow_cost(model: Articulation, uv: torch.Tensor, vis: torch.Tensor) -> torch.Tensor:
    """(N,) mean Charbonnier [strides] of the predicted frame-to-frame motion (pixels uv (T, N, 2)) against
    the flow, over the frames where it is consistent and the point visible (vis (T, N)); 0 without flow."""
    sc = model.scene
    if sc.flow is None or len(uv) < 2:
        return torch.zeros(uv.shape[1], dtype=uv.dtype)
    at = uv[:-1]
    fl = _sample(sc.flow, at)  # (T-1, 3, N)
    use = ((fl[:, 2] > 0.99) & vis[:-1]).double()
    err = ((uv[1:] - at - fl[:, :2].transpose(1, 2)) ** 2).sum(-1) / sc.stride**2
    return ((torch.sqrt(err + 1.0) - 1.0) * use).sum(0) / use.sum(0).clamp_min(1.0)


def potts_labels(cost: np.ndarray, uv0: np.ndarray, stride: float, start: np.ndarray) -> np.ndarray:
    """(N,) labels minimising sum cost[i, l_i] + POTTS x (grid neighbours with another label), by iterated
    conditional modes from ``start`` (N,); every part keeps at least 3 points, else ``start`` is returned."""
    pairs = np.array(sorted(cKDTree(uv0).query_pairs(1.5 * stride)), dtype=np.int64).reshape(-1, 2)
    n, n_parts = cost.shape
    finite = np.where(np.isfinite(cost), cost, 1e6)
    labels = start.copy()
    for _ in range(SWEEPS):
        onehot = np.eye(n_parts)[labels]
        agree = np.zeros((n, n_parts))
        np.add.at(agree, pairs[:, 0], onehot[pairs[:, 1]])
        np.add.at(agree, pairs[:, 1], onehot[pairs[:, 0]])
        degree = agree.sum(1, keepdims=True)
        new = np.argmin(finite + POTTS * (degree - agree), 1)
        if np.array_equal(new, labels):
            break
        labels = new
    return labels if all((labels == b).sum() >= 3 for b in range(n_parts)) else start
