"""``render=splat_torch``: a pure-torch, differentiable EWA Gaussian splatting renderer for the CPU.

The maths is the one of 3D Gaussian Splatting (Kerbl et al. 2023, as in gsplat):

1. Project: mean ``x`` -> camera ``x_c = R x + t``; pixel ``u = fx x_c/z + cx``; covariance
   ``Sigma_2d = J R Sigma R^T J^T + eps2d I`` with the perspective Jacobian ``J`` at ``x_c`` (x/z and y/z
   clamped a little outside the image, as 3DGS does, so Gaussians far off-screen do not explode) and the
   0.3 px^2 low-pass dilation of 3DGS.
2. Footprint: the axis-aligned box of the k-sigma ellipse, ``k = min(sigma_cutoff, sqrt(2 ln(o / alpha_min)))``
   so a faint Gaussian only touches tiles where it is at least ``alpha_min`` opaque.
3. Composite front to back: ``alpha_i = min(0.99, o_i exp(-0.5 d^T Sigma_2d^-1 d))`` for pixels inside
   the footprint ellipse ``d^T Sigma_2d^-1 d <= k^2`` (hence never below ``alpha_min``, as in 3DGS),
   ``C = sum_i c_i alpha_i T_i + T_final * background``, ``T_i = prod_{j<i} (1 - alpha_j)``.

Rasterisation follows the tile scheme of the CUDA rasterisers, with small tiles and no per-tile loop:
each Gaussian's footprint box is binned into ``tile_size``-pixel square tiles (4 by default, not 16:
on a CPU every evaluated pixel costs, and a Gaussian a few pixels wide touches few 4x4 tiles); the
(Gaussian, tile) pairs are generated in depth order and stable-sorted by tile (a radix sort of int32
keys), so each tile's pairs are contiguous and front to back. Every pair evaluates its Gaussian on
the tile's pixels as one dense (pairs, tile_size^2) block, and the transmittance is an exclusive
segmented cumulative sum of ``log(1 - alpha)`` down the pair axis (accumulated in float64 so that
subtracting each tile's start loses nothing). Everything is plain autograd (gradients for means,
covariances, colours and opacities). The image is processed in bands of tile rows holding at most
``max_pairs`` (Gaussian, pixel) evaluations: this bounds memory, and small bands are also much faster
here (the working set stays in cache and freed buffers are reused instead of page-faulted afresh).

Pixel convention: pixel (row r, column c) has its centre at image coordinates (c + 0.5, r + 0.5), as in
gsplat, so ``cx = width / 2`` is the image centre.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from sync4d.errors import ConfigError, InputError
from sync4d.registry import register
from sync4d.render.sh import sh_degree_from_count, sh_to_rgb
from sync4d.types import Camera

_DTYPES = {"float32": torch.float32, "float64": torch.float64}
LOG_ALPHA_MAX = math.log(0.99)  # 3DGS caps a Gaussian's alpha at 0.99


@dataclass
class Projection:
    """Screen-space Gaussians that survived culling, sorted front to back.

    Attributes:
        index: (M,) long indices into the input arrays.
        means2d: (M, 2) pixel coordinates (u, v) of the projected means [px].
        cov2d: (M, 2, 2) dilated screen covariances [px^2].
        conics: (M, 3) upper triangle (a, b, c) of ``cov2d^-1`` [1/px^2].
        depths: (M,) camera-space z of the means [m].
        opacities: (M,) opacity in (0, 1].
        boxes: (M, 4) int64 inclusive pixel ranges (x0, x1, y0, y1) of the footprints, inside the image.
        cutoff2: (M,) squared footprint radius k^2 in standard deviations: a pixel is drawn when its
            squared Mahalanobis distance ``d^T cov2d^-1 d <= k^2``.
    """

    index: torch.Tensor
    means2d: torch.Tensor
    cov2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    opacities: torch.Tensor
    boxes: torch.Tensor
    cutoff2: torch.Tensor


def camera_tensors(camera: Camera, dtype: torch.dtype, device: torch.device | str) -> dict[str, torch.Tensor]:
    """Camera matrices as tensors: ``R`` (3,3), ``t`` (3,), ``K`` (3,3), ``center`` (3,) world position [m]."""
    w2c = torch.as_tensor(np.asarray(camera.world_to_cam, dtype=np.float64), device=device)
    K = torch.as_tensor(np.asarray(camera.K, dtype=np.float64), device=device)
    R, t = w2c[:3, :3], w2c[:3, 3]
    center = -R.T @ t
    return {"R": R.to(dtype), "t": t.to(dtype), "K": K.to(dtype), "center": center.to(dtype)}


def project_gaussians(
    means: torch.Tensor,
    covariances: torch.Tensor,
    camera: Camera,
    *,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """EWA projection of 3D Gaussians (differentiable).

    Args:
        means: (N, 3) world positions [m].
        covariances: (N, 3, 3) world covariances [m^2].
        camera: pinhole camera (OpenCV axes).
        near: Gaussians with camera z <= near are invalid [m].
        far: Gaussians with camera z >= far are invalid [m].
        eps2d: isotropic low-pass dilation added to the screen covariance [px^2] (3DGS: 0.3).

    Returns:
        means2d (N, 2) [px], cov2d (N, 2, 2) [px^2], depths (N,) [m], valid (N,) bool. Entries of invalid
        Gaussians are finite but meaningless.
    """
    cam = camera_tensors(camera, means.dtype, means.device)
    R, t, K = cam["R"], cam["t"], cam["K"]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    xc = means @ R.T + t
    z = xc[:, 2]
    valid = (z > near) & (z < far)
    # Invalid depths are replaced by 1 so that no inf/NaN enters the graph (their outputs are discarded).
    zs = torch.where(valid, z, torch.ones_like(z))
    x_over_z, y_over_z = xc[:, 0] / zs, xc[:, 1] / zs
    means2d = torch.stack([fx * x_over_z + cx, fy * y_over_z + cy], dim=-1)
    # 3DGS clamps the tangent used by the Jacobian to 1.3x the half field of view (from the image bounds,
    # as gsplat does for off-centre principal points): the linearisation is meaningless far off-screen.
    tan_x, tan_y = 0.5 * camera.width / float(fx), 0.5 * camera.height / float(fy)
    lim_xp, lim_xn = (camera.width - float(cx)) / float(fx) + 0.3 * tan_x, float(cx) / float(fx) + 0.3 * tan_x
    lim_yp, lim_yn = (camera.height - float(cy)) / float(fy) + 0.3 * tan_y, float(cy) / float(fy) + 0.3 * tan_y
    tx = torch.clamp(x_over_z, -lim_xn, lim_xp)
    ty = torch.clamp(y_over_z, -lim_yn, lim_yp)
    zero = torch.zeros_like(zs)
    J = torch.stack(
        [
            torch.stack([fx / zs, zero, -fx * tx / zs], dim=-1),
            torch.stack([zero, fy / zs, -fy * ty / zs], dim=-1),
        ],
        dim=-2,
    )  # (N, 2, 3)
    M = J @ R  # world -> screen linear map
    cov2d = M @ covariances @ M.transpose(1, 2)
    cov2d = cov2d + eps2d * torch.eye(2, dtype=means.dtype, device=means.device)
    return means2d, cov2d, z, valid


def conics_from_cov2d(cov2d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse of symmetric 2x2 covariances.

    Args:
        cov2d: (M, 2, 2) [px^2].

    Returns:
        conics (M, 3) as (a, b, c) with ``cov2d^-1 = [[a, b], [b, c]]`` [1/px^2], and det (M,) [px^4].
    """
    a, b, c = cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]
    det = a * c - b * b
    inv = 1.0 / det
    return torch.stack([c * inv, -b * inv, a * inv], dim=-1), det


def footprint_boxes(
    means2d: torch.Tensor,
    cov2d: torch.Tensor,
    opacities: torch.Tensor,
    width: int,
    height: int,
    *,
    sigma_cutoff: float = 3.0,
    alpha_min: float = 1.0 / 255.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Inclusive pixel boxes of the k-sigma ellipses, clipped to the image (no gradient).

    The exact axis-aligned bounding box of ``{d : d^T cov2d^-1 d <= k^2}`` has half-sizes
    ``k sqrt(cov_xx)`` and ``k sqrt(cov_yy)``; ``k`` shrinks for faint Gaussians to where ``o e^{-k^2/2}``
    falls to ``alpha_min`` (beyond that a Gaussian adds less than one 8-bit level).

    Args:
        means2d: (M, 2) [px].
        cov2d: (M, 2, 2) [px^2].
        opacities: (M,) in (0, 1].
        width: image width [px].
        height: image height [px].
        sigma_cutoff: largest extent in standard deviations.
        alpha_min: smallest opacity worth drawing.

    Returns:
        boxes (M, 4) int64 (x0, x1, y0, y1), visible (M,) bool (a non-empty box inside the image) and
        k^2 (M,) float64, the squared footprint radius in standard deviations.
    """
    with torch.no_grad():
        o = opacities.detach().double()
        k = torch.sqrt(2.0 * torch.log(torch.clamp_min(o / alpha_min, 1.0)))
        k = torch.clamp_max(k, sigma_cutoff)
        rx = k * torch.sqrt(torch.clamp_min(cov2d[:, 0, 0].detach().double(), 0.0))
        ry = k * torch.sqrt(torch.clamp_min(cov2d[:, 1, 1].detach().double(), 0.0))
        u, v = means2d[:, 0].detach().double(), means2d[:, 1].detach().double()
        # Pixel c is covered when |c + 0.5 - u| <= rx; clip before casting so huge boxes stay in range.
        x0 = torch.ceil(torch.clamp(u - rx - 0.5, -1.0, width + 1.0)).long().clamp_min(0)
        x1 = torch.floor(torch.clamp(u + rx - 0.5, -2.0, width + 1.0)).long().clamp_max(width - 1)
        y0 = torch.ceil(torch.clamp(v - ry - 0.5, -1.0, height + 1.0)).long().clamp_min(0)
        y1 = torch.floor(torch.clamp(v + ry - 0.5, -2.0, height + 1.0)).long().clamp_max(height - 1)
        visible = (x0 <= x1) & (y0 <= y1) & (k > 0)
        return torch.stack([x0, x1, y0, y1], dim=-1), visible, k * k


def tile_row_bands(tile_boxes: torch.Tensor, tiles_y: int, budget_rows: int) -> list[tuple[int, int]]:
    """Split tile rows into bands [t0, t1) holding at most ``budget_rows`` (Gaussian, tile) pairs each.

    A single tile row is never split, so a band exceeds the budget only when one row alone does.

    Args:
        tile_boxes: (M, 4) inclusive tile ranges (tx0, tx1, ty0, ty1).
        tiles_y: number of tile rows.
        budget_rows: pair budget per band.

    Returns:
        Consecutive (t0, t1) covering [0, tiles_y).
    """
    widths = tile_boxes[:, 1] - tile_boxes[:, 0] + 1
    diff = torch.zeros(tiles_y + 1, dtype=torch.int64, device=tile_boxes.device)
    diff.index_add_(0, tile_boxes[:, 2], widths)
    diff.index_add_(0, tile_boxes[:, 3] + 1, -widths)
    per_row = torch.cumsum(diff, 0)[:tiles_y].tolist()
    bands: list[tuple[int, int]] = []
    start, acc = 0, 0
    for row, count in enumerate(per_row):
        if acc > 0 and acc + count > budget_rows:
            bands.append((start, row))
            start, acc = row, 0
        acc += count
    bands.append((start, tiles_y))
    return bands


def tile_pairs(tile_boxes: torch.Tensor, t0: int, t1: int, tiles_x: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(Gaussian, tile) pairs of the tile rows [t0, t1), grouped by tile, front to back within a tile.

    Args:
        tile_boxes: (M, 4) inclusive tile ranges (tx0, tx1, ty0, ty1) of depth-sorted Gaussians.
        t0: first tile row of the band.
        t1: end tile row of the band (exclusive).
        tiles_x: tiles per row.

    Returns:
        gid (P,) int64 Gaussian index and tile (P,) int64 band-local tile index
        ``(ty - t0) * tiles_x + tx``, sorted by tile (stable, so ties keep the depth order).
    """
    dev = tile_boxes.device
    inside = (tile_boxes[:, 2] < t1) & (tile_boxes[:, 3] >= t0)
    g = torch.nonzero(inside, as_tuple=False)[:, 0]  # ascending = front to back
    if g.numel() == 0:
        empty = torch.zeros(0, dtype=torch.int64, device=dev)
        return empty, empty
    b = tile_boxes.index_select(0, g)
    bx0 = b[:, 0]
    bw = b[:, 1] - bx0 + 1
    by0 = torch.clamp_min(b[:, 2], t0)
    bh = torch.clamp_max(b[:, 3], t1 - 1) - by0 + 1
    counts = bw * bh
    total = int(counts.sum())
    owner = torch.repeat_interleave(torch.arange(g.numel(), device=dev), counts, output_size=total)
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(total, device=dev) - first.index_select(0, owner)
    w_p = bw.index_select(0, owner)
    ly = torch.div(local, w_p, rounding_mode="floor")
    tx = bx0.index_select(0, owner) + (local - ly * w_p)
    ty = by0.index_select(0, owner) + ly - t0
    # int32 keys take torch's radix-sort path for stable CPU sorts (several times faster than int64).
    key = (ty * tiles_x + tx).to(torch.int32)
    key_sorted, order = torch.sort(key, stable=True)
    return g.index_select(0, owner.index_select(0, order)), key_sorted.long()


def composite_tiles(
    gid: torch.Tensor,
    tile: torch.Tensor,
    num_tiles: int,
    tiles_x: int,
    tile_size: int,
    row0: int,
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    cutoff2: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Front-to-back alpha compositing of tile-grouped pairs over each tile's pixels (differentiable).

    Every pair evaluates its Gaussian on all ``tile_size^2`` pixels of its tile; pixels outside the
    Gaussian's footprint ellipse (squared Mahalanobis distance > k^2) are dropped, so the image does
    not depend on the tile size, and alphas are capped at 0.99 (3DGS).

    Args:
        gid: (P,) Gaussian of each pair; pairs grouped by tile, front to back within a tile.
        tile: (P,) band-local tile index of each pair.
        num_tiles: tiles in the band.
        tiles_x: tiles per row.
        tile_size: tile side [px].
        row0: first pixel row of the band.
        means2d: (M, 2) [px]; conics: (M, 3) [1/px^2]; opacities: (M,).
        features: (M, C) per-Gaussian values to composite (colours, depth, ...).
        cutoff2: (M,) squared footprint radius k^2 [standard deviations^2] (see :func:`footprint_boxes`).

    Returns:
        (num_tiles, tile_size^2, C) sums ``f_i alpha_i T_i`` and (num_tiles, tile_size^2) accumulated
        alpha ``1 - T_final``; pixel k of a tile is at (row k // tile_size, column k % tile_size).
    """
    n_px, C = tile_size * tile_size, features.shape[1]
    if gid.numel() == 0:
        return means2d.new_zeros(num_tiles, n_px, C), means2d.new_zeros(num_tiles, n_px)
    alpha = pair_alphas(gid, tile, tiles_x, tile_size, row0, means2d, conics, opacities, cutoff2)
    log_t = torch.log1p(-alpha).double()
    # Exclusive cumulative log-transmittance down the pair axis, restarted at each tile's first pair.
    excl = torch.cumsum(log_t, 0) - log_t
    counts = torch.bincount(tile, minlength=num_tiles)
    starts = torch.cumsum(counts, 0) - counts
    trans = torch.exp(excl - excl.index_select(0, starts.index_select(0, tile))).to(means2d.dtype)
    weight = alpha * trans  # (P, n_px)
    feats = features.index_select(0, gid)  # (P, C)
    out = means2d.new_zeros(num_tiles, n_px, C).index_add(0, tile, weight[:, :, None] * feats[:, None, :])
    acc = means2d.new_zeros(num_tiles, n_px).index_add(0, tile, weight)
    return out, acc


def pair_alphas(
    gid: torch.Tensor,
    tile: torch.Tensor,
    tiles_x: int,
    tile_size: int,
    row0: int,
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    cutoff2: torch.Tensor,
) -> torch.Tensor:
    """(P, tile_size^2) alpha of each pair's Gaussian at every pixel of its tile (0 outside the footprint,
    capped at 0.99); arguments as :func:`composite_tiles`'s.

    The log-alpha of a pair is a quadratic in the pixel's offset (ox, oy) inside the tile, so it is one small
    matmul of per-pair coefficients with a fixed basis [1, ox, oy, ox^2, ox oy, oy^2] instead of a dozen
    full-size elementwise passes: log(o) - 0.5 (a dx^2 + 2 b dx dy + c dy^2) with dx = dx0 + ox,
    dy = dy0 + oy and (dx0, dy0) the offset of the tile's first pixel centre.
    """
    dtype, dev = means2d.dtype, means2d.device
    k = torch.arange(tile_size * tile_size, device=dev)
    ox = (k % tile_size).to(dtype)
    oy = torch.div(k, tile_size, rounding_mode="floor").to(dtype)
    basis = torch.stack([torch.ones_like(ox), ox, oy, ox * ox, ox * oy, oy * oy])  # (6, n_px)
    tile_x = ((tile % tiles_x) * tile_size).to(dtype) + 0.5
    tile_y = (torch.div(tile, tiles_x, rounding_mode="floor") * tile_size).to(dtype) + (row0 + 0.5)
    # 1-D gathers of each parameter are several times faster than one gather of a (M, k) table.
    dx0 = tile_x - means2d[:, 0].index_select(0, gid)
    dy0 = tile_y - means2d[:, 1].index_select(0, gid)
    ca = conics[:, 0].index_select(0, gid)
    cb = conics[:, 1].index_select(0, gid)
    cc = conics[:, 2].index_select(0, gid)
    log_o = torch.log(opacities).index_select(0, gid)
    coeffs = torch.stack(
        [
            log_o - 0.5 * (ca * dx0 * dx0 + cc * dy0 * dy0) - cb * dx0 * dy0,
            -(ca * dx0 + cb * dy0),
            -(cc * dy0 + cb * dx0),
            -0.5 * ca,
            -cb,
            -0.5 * cc,
        ],
        dim=1,
    )  # (P, 6)
    log_alpha = coeffs @ basis  # (P, n_px)
    # Footprint test: d^T Sigma^-1 d <= k^2  <=>  log_alpha >= log(o) - k^2 / 2 (so alpha >= alpha_min).
    threshold = (log_o - 0.5 * cutoff2.to(dtype).index_select(0, gid))[:, None]
    # 0.99 cap as in 3DGS keeps log(1 - alpha) finite and the backward pass well conditioned.
    log_alpha = torch.clamp_max(log_alpha, LOG_ALPHA_MAX)
    return torch.where(log_alpha >= threshold, torch.exp(log_alpha), torch.zeros((), dtype=dtype, device=dev))


def untile(x: torch.Tensor, tiles_y: int, tiles_x: int, tile_size: int, height: int, width: int) -> torch.Tensor:
    """(tiles_y * tiles_x, tile_size^2, ...) per-tile pixels -> (height, width, ...) image (cropped)."""
    rest = x.shape[2:]
    img = x.reshape(tiles_y, tiles_x, tile_size, tile_size, *rest).transpose(1, 2)
    return img.reshape(tiles_y * tile_size, tiles_x * tile_size, *rest)[:height, :width]


@register("render", "splat_torch")
class SplatTorch:
    """Pure-torch EWA splatting renderer (CPU or CUDA through torch), differentiable.

    Also holds the render-stage settings the pipeline uses to make its camera and videos (image size,
    field of view, viewing direction); the renderer itself always draws at ``camera.width x camera.height``.
    """

    @dataclass
    class Config:
        width: int = 256  # image width of the run's videos [px]
        height: int = 256  # image height of the run's videos [px]
        fov_deg: float = 40.0  # vertical field of view of the framing camera [deg]
        view_direction: list[float] = field(default_factory=lambda: [0.9, 1.1, 1.6])  # object -> camera
        up: list[float] = field(default_factory=lambda: [0.0, 1.0, 0.0])  # world up (the scenes are Y up)
        margin: float = 1.15  # framing: the object's bounding sphere fills 1/margin of the smaller image side
        background: list[float] = field(default_factory=lambda: [1.0, 1.0, 1.0])  # RGB in [0, 1]
        near: float = 0.01  # near plane [m]
        far: float = 1e10  # far plane [m]
        eps2d: float = 0.3  # low-pass dilation of screen covariances [px^2] (3DGS)
        sigma_cutoff: float = 3.0  # footprint extent [standard deviations]
        alpha_min: float = 0.00392156862745098  # 1/255: faint Gaussians get smaller footprints
        sh_degree: int | None = None  # highest SH degree used for (N, K, 3) colours; None = all given
        tile_size: int = 4  # pixels per tile side: each (Gaussian, tile) pair evaluates tile_size^2 pixels
        max_pairs: int = 1_000_000  # (Gaussian, pixel) evaluations per band: bounds memory (~60 B each), speed
        dtype: str = "float32"  # compute dtype for numpy inputs (torch inputs keep theirs)
        num_threads: int = 1  # torch CPU threads while rendering; 0 = torch's setting (1: contended cores stall 2 threads)
        fps: float = 0.0  # video frame rate [1/s]; 0 = the reference's
        turntable_frames: int = 0  # frames of an optional turntable of the last frame (0 = none)

        def validate(self) -> None:
            if self.width <= 0 or self.height <= 0:
                raise ConfigError(f"render.width/height: must be positive, got {self.width}x{self.height}")
            if len(self.background) != 3:
                raise ConfigError(f"render.background: expected [r, g, b], got {self.background}")
            if not 0.0 < self.fov_deg < 180.0:
                raise ConfigError(f"render.fov_deg={self.fov_deg}: must be in (0, 180) degrees")
            if self.dtype not in _DTYPES:
                raise ConfigError(f"render.dtype={self.dtype}: one of {', '.join(_DTYPES)}")
            if self.near <= 0 or self.far <= self.near:
                raise ConfigError(f"render.near/far: need 0 < near < far, got {self.near}, {self.far}")
            if self.sigma_cutoff <= 0 or not 0 < self.alpha_min < 1:
                raise ConfigError("render.sigma_cutoff must be > 0 and render.alpha_min in (0, 1)")
            if self.sh_degree is not None and not 0 <= self.sh_degree <= 3:
                raise ConfigError(f"render.sh_degree={self.sh_degree}: must be 0..3 or null")
            if not 1 <= self.tile_size <= 64:
                raise ConfigError(f"render.tile_size={self.tile_size}: must be in 1..64 pixels")
            if self.num_threads < 0:
                raise ConfigError(f"render.num_threads={self.num_threads}: must be >= 0 (0 = torch's setting)")
            if self.max_pairs < 1:
                raise ConfigError(f"render.max_pairs={self.max_pairs}: must be >= 1")

    def __init__(self, config: Config | None = None, *, device: str = "cpu") -> None:
        from sync4d.device import torch_device

        self.config = config if config is not None else self.Config()
        self.config.validate()
        self.device = torch.device(torch_device(device))

    # -- public API -------------------------------------------------------------------------------

    def render(self, means: Any, covariances: Any, colors: Any, opacities: Any, camera: Camera) -> Any:
        """Render an RGB image.

        Args:
            means: (N, 3) world positions [m], numpy or torch.
            covariances: (N, 3, 3) world covariances [m^2].
            colors: (N, 3) RGB in [0, 1], (N, K, 3) SH coefficients (K = 1, 4, 9, 16), or (N, C) any
                per-Gaussian features (composited over a zero background when C != 3).
            opacities: (N,) or (N, 1) in [0, 1].
            camera: the camera; the image is ``camera.height x camera.width``.

        Returns:
            (H, W, 3) RGB (or (H, W, C)): a torch tensor (with gradients) when ``means`` is a tensor,
            otherwise a float32 numpy array.
        """
        return self.render_full(means, covariances, colors, opacities, camera)["rgb"]

    def render_full(
        self,
        means: Any,
        covariances: Any,
        colors: Any,
        opacities: Any,
        camera: Camera,
        *,
        background: Any | None = None,
    ) -> dict[str, Any]:
        """Render colour, accumulated opacity and expected depth.

        Args:
            means, covariances, colors, opacities, camera: as in :meth:`render`.
            background: (C,) colour behind the Gaussians; None uses ``config.background`` for RGB, zeros
                otherwise.

        Returns:
            ``rgb`` (H, W, C) composited over the background; ``alpha`` (H, W) accumulated opacity
            ``1 - prod(1 - alpha_i)`` (a soft silhouette); ``depth`` (H, W) alpha-normalised expected
            camera depth ``sum w_i z_i / alpha`` [m] (0 where nothing is drawn). Torch tensors when
            ``means`` is a tensor, else float32 numpy arrays.
        """
        as_numpy = not isinstance(means, torch.Tensor)
        with _torch_threads(self.config.num_threads):
            if as_numpy:
                with torch.no_grad():
                    out = self._render(means, covariances, colors, opacities, camera, background)
                return {k: v.detach().cpu().float().numpy() for k, v in out.items()}
            return self._render(means, covariances, colors, opacities, camera, background)

    # -- implementation ---------------------------------------------------------------------------

    def _tensor(self, value: Any, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
        if isinstance(value, torch.Tensor):
            return value.to(device=device, dtype=dtype)
        return torch.as_tensor(np.ascontiguousarray(value), device=device).to(dtype)

    def _render(
        self, means: Any, covariances: Any, colors: Any, opacities: Any, camera: Camera, background: Any | None
    ) -> dict[str, torch.Tensor]:
        config = self.config
        if isinstance(means, torch.Tensor) and means.is_floating_point():
            dtype, device = means.dtype, means.device
        else:
            dtype, device = _DTYPES[config.dtype], self.device
        means_t = self._tensor(means, dtype, device)
        covs_t = self._tensor(covariances, dtype, device)
        cols_t = self._tensor(colors, dtype, device)
        opac_t = self._tensor(opacities, dtype, device).reshape(-1)
        check_inputs(means_t, covs_t, cols_t, opac_t)
        width, height = int(camera.width), int(camera.height)
        channels = 3 if cols_t.ndim == 3 else cols_t.shape[1]
        if background is None:
            bg = config.background if channels == 3 else [0.0] * channels
        else:
            bg = background
        bg_t = self._tensor(bg, dtype, device).reshape(-1)
        if bg_t.numel() != channels:
            raise InputError(f"render: background has {bg_t.numel()} values for {channels}-channel colours")

        proj = self.project(means_t, covs_t, opac_t, camera)
        feats = self._colors(cols_t, means_t, proj.index, camera)
        # Depth rides along as one more composited channel.
        table = torch.cat([feats, proj.depths[:, None]], dim=1)
        ts = config.tile_size
        tiles_x, tiles_y = -(-width // ts), -(-height // ts)
        tile_boxes = torch.div(proj.boxes, ts, rounding_mode="floor")
        if proj.index.numel():
            bands = tile_row_bands(tile_boxes, tiles_y, max(config.max_pairs // (ts * ts), 1))
        else:
            bands = [(0, tiles_y)]
        out_parts, acc_parts = [], []
        for t0, t1 in bands:
            gid, tile = tile_pairs(tile_boxes, t0, t1, tiles_x)
            out_b, acc_b = composite_tiles(
                gid, tile, (t1 - t0) * tiles_x, tiles_x, ts, t0 * ts,
                proj.means2d, proj.conics, proj.opacities, table, proj.cutoff2,
            )
            out_parts.append(out_b)
            acc_parts.append(acc_b)
        out = untile(torch.cat(out_parts, 0), tiles_y, tiles_x, ts, height, width)
        acc = untile(torch.cat(acc_parts, 0), tiles_y, tiles_x, ts, height, width)
        rgb = out[..., :channels] + (1.0 - acc)[..., None] * bg_t
        depth = out[..., channels] / torch.clamp_min(acc, 1e-10)
        depth = torch.where(acc > 1e-10, depth, torch.zeros_like(depth))
        return {"rgb": rgb, "alpha": acc, "depth": depth}

    def project(
        self, means: torch.Tensor, covariances: torch.Tensor, opacities: torch.Tensor, camera: Camera
    ) -> Projection:
        """Project, cull and depth-sort Gaussians (differentiable w.r.t. means, covariances, opacities).

        Args:
            means: (N, 3) [m]; covariances: (N, 3, 3) [m^2]; opacities: (N,).
            camera: the camera.

        Returns:
            The visible Gaussians in front-to-back order (see :class:`Projection`).
        """
        config = self.config
        means2d, cov2d, depths, valid = project_gaussians(
            means, covariances, camera, near=config.near, far=config.far, eps2d=config.eps2d
        )
        conics, det = conics_from_cov2d(cov2d)
        boxes, visible, cutoff2 = footprint_boxes(
            means2d, cov2d, opacities, camera.width, camera.height,
            sigma_cutoff=config.sigma_cutoff, alpha_min=config.alpha_min,
        )
        keep = valid & visible & (det > 0) & torch.isfinite(det)
        idx = torch.nonzero(keep, as_tuple=False)[:, 0]
        order = torch.argsort(depths.detach().index_select(0, idx), stable=True)
        idx = idx.index_select(0, order)
        return Projection(
            index=idx,
            means2d=means2d.index_select(0, idx),
            cov2d=cov2d.index_select(0, idx),
            conics=conics.index_select(0, idx),
            depths=depths.index_select(0, idx),
            opacities=opacities.index_select(0, idx),
            boxes=boxes.index_select(0, idx),
            cutoff2=cutoff2.index_select(0, idx),
        )

    def _colors(self, colors: torch.Tensor, means: torch.Tensor, index: torch.Tensor, camera: Camera) -> torch.Tensor:
        """(M, C) colours of the visible Gaussians: given RGB/features, or SH evaluated for the view."""
        picked = colors.index_select(0, index)
        if colors.ndim == 2:
            return picked
        center = camera_tensors(camera, means.dtype, means.device)["center"]
        dirs = means.index_select(0, index) - center
        dirs = dirs / torch.clamp_min(torch.linalg.norm(dirs, dim=-1, keepdim=True), 1e-12)
        return sh_to_rgb(picked, dirs, self.config.sh_degree)


@contextlib.contextmanager
def _torch_threads(num: int) -> Iterator[None]:
    """Run with ``num`` torch CPU threads (0: unchanged), restoring the previous count afterwards.

    On an oversubscribed machine one thread can be several times faster than two, because every
    parallel op waits at a barrier for a thread that another process has descheduled.
    """
    if num <= 0 or num == torch.get_num_threads():
        yield
        return
    previous = torch.get_num_threads()
    torch.set_num_threads(num)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def check_inputs(means: torch.Tensor, covs: torch.Tensor, colors: torch.Tensor, opacities: torch.Tensor) -> None:
    n = means.shape[0]
    if means.ndim != 2 or means.shape[1] != 3:
        raise InputError(f"render: means must be (N, 3), got {tuple(means.shape)}")
    if covs.shape != (n, 3, 3):
        raise InputError(f"render: covariances must be ({n}, 3, 3), got {tuple(covs.shape)}")
    if colors.shape[0] != n or colors.ndim not in (2, 3) or (colors.ndim == 3 and colors.shape[2] != 3):
        raise InputError(f"render: colors must be ({n}, 3) RGB or ({n}, K, 3) SH, got {tuple(colors.shape)}")
    if colors.ndim == 3:
        try:
            sh_degree_from_count(colors.shape[1])
        except ValueError as err:
            raise InputError(f"render: colors: {err}") from None
    if opacities.shape != (n,):
        raise InputError(f"render: opacities must be ({n},), got {tuple(opacities.shape)}")



def deform_covariances(covariances: Any, deformation: Any) -> Any:
    """Covariances carried by a deformation gradient, ``F Sigma F^T`` (PhysGaussian's kinematics).

    Args:
        covariances: (N, 3, 3) rest covariances [m^2] (numpy or torch).
        deformation: (N, 3, 3) or (T, N, 3, 3) deformation gradients F (dimensionless).

    Returns:
        (N, 3, 3) or (T, N, 3, 3) deformed covariances [m^2], of the inputs' array type.
    """
    if isinstance(covariances, torch.Tensor) or isinstance(deformation, torch.Tensor):
        F = torch.as_tensor(deformation)
        S = torch.as_tensor(covariances, dtype=F.dtype, device=F.device)
        return F @ S @ F.transpose(-1, -2)
    F_np = np.asarray(deformation)
    return F_np @ np.asarray(covariances) @ np.swapaxes(F_np, -1, -2)
