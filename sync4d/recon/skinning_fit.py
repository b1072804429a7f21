"""``recon=skinning_fit``: Gaussian bones + neural blend skinning fitted to a posed mesh sequence.

Given posed vertices with fixed correspondence (``ReferenceInput.mesh_sequence`` (T, V, 3)), find a rest
shape, B Gaussian bones (centre, covariance from a rotation and log-scales), per-frame bone SE(3)
transforms J_{t,b}, a global transform G_t, and an MLP skinning correction, such that
``x_t = G_t sum_b W_b(x*) J_{t,b} x*`` with ``W = softmax(-d_M(x*, bones) + W_delta(x*))``
(paper Sec. 3.2, Eq. 1 and 3) reproduces every frame.

Procedure (all on the CPU with torch):
    1. Rest shape = frame ``rest_frame``; G_t = rigid Kabsch fit of the whole shape rest -> frame t (so
       root motion lives in G_t, articulation in J).
    2. Bones by k-means (farthest-point seeded) of the rest shape, optionally augmented with each
       vertex's trajectory so parts that move differently separate; bone shape from each cluster's
       covariance; J_{t,b} initialised by Kabsch of each cluster.
    3. Adam on a farthest-point subsample of the vertices (fast), evaluated on all vertices.

The per-frame vertex error is logged and kept in :attr:`SkinningFit.last_fit_report`.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from sync4d.errors import ConfigError, InputError
from sync4d.geometry import rigid_fit
from sync4d.recon import skinning as sk
from sync4d.registry import register
from sync4d.rng import torch_generator
from sync4d.types import Reference, ReferenceInput

log = logging.getLogger(__name__)


@dataclass
class FitOptions:
    """Numerical options of :func:`fit_skinning` (the ``recon=skinning_fit`` config minus ``bones``).

    Attributes:
        rest_frame: index of the frame used as the rest (canonical) shape.
        iterations: Adam steps.
        lr: Adam learning rate (parameters live in units of the rest bounding-box diagonal).
        fit_vertices: vertices (farthest-point subsample) used in the loss; 0 = all.
        cluster_motion_weight: weight of the per-vertex trajectory in the k-means features (0 = cluster
            by rest position only); trajectories are in units of the bbox diagonal.
        init_scale_factor: initial bone std-devs as a multiple of the cluster's own spread.
        mlp_width: hidden width of the skinning-delta MLP (0 disables the MLP).
        mlp_layers: hidden layers of the MLP.
        mlp_frequencies: sin/cos octaves of the MLP's coordinate encoding.
        delta_weight: weight of the mean squared MLP logit (keeps W_delta a small correction). The data
            term is a mean squared error in squared bbox-diagonal units (~1e-5 at a 0.3% fit), so the
            weights are much smaller than Lab4D's 5e-3 / 5e-4, which sit next to photometric losses.
        entropy_weight: weight of the mean skinning entropy [nats]; favours crisp parts.
        global_from: ``kabsch`` (root motion = rigid fit of the whole shape) or ``identity``.
        seed: seed of the torch initialisation.
    """

    rest_frame: int = 0
    iterations: int = 600
    lr: float = 1e-2
    fit_vertices: int = 2000
    cluster_motion_weight: float = 1.0
    init_scale_factor: float = 1.0
    mlp_width: int = 64
    mlp_layers: int = 2
    mlp_frequencies: int = 4
    delta_weight: float = 1e-6
    entropy_weight: float = 1e-7
    global_from: str = "kabsch"
    seed: int = 0


@dataclass
class FitResult:
    """What :func:`fit_skinning` returns (object frame = the rest frame's frame, units [m]).

    Attributes:
        rest: (V, 3) rest vertices [m].
        centers: (B, 3) bone centres [m].
        covariances: (B, 3, 3) bone covariances [m^2].
        weights: (V, B) skinning weights of every rest vertex.
        bone_transforms: (T, B, 4, 4) J_{t,b} rest -> frame t (object frame).
        global_transforms: (T, 4, 4) G_t.
        frame_error_m: (T,) mean vertex error over all vertices per frame [m].
        bbox_diagonal: diagonal of the rest bounding box [m].
        seconds: wall time of the fit [s].
    """

    rest: np.ndarray
    centers: np.ndarray
    covariances: np.ndarray
    weights: np.ndarray
    bone_transforms: np.ndarray
    global_transforms: np.ndarray
    frame_error_m: np.ndarray
    bbox_diagonal: float
    seconds: float
    history: list[float] = field(default_factory=list)

    @property
    def frame_error_pct(self) -> np.ndarray:
        """(T,) per-frame mean vertex error as a percentage of the rest bounding-box diagonal."""
        return 100.0 * self.frame_error_m / self.bbox_diagonal

    @property
    def mean_error_pct(self) -> float:
        return float(self.frame_error_pct.mean())


def bbox_diagonal(points: np.ndarray) -> float:
    """Length of the axis-aligned bounding-box diagonal of (N, 3) points [m]."""
    return float(np.linalg.norm(points.max(0) - points.min(0)))


def lbs_error(sequence: np.ndarray, fit: FitResult) -> np.ndarray:
    """(T,) mean Euclidean vertex error [m] of the fit's G_t LBS(J_t) against the sequence."""
    posed = sk.linear_blend(fit.rest, fit.weights, fit.bone_transforms)
    posed = np.einsum("tij,tvj->tvi", fit.global_transforms[:, :3, :3], posed) + fit.global_transforms[:, None, :3, 3]
    return np.linalg.norm(posed - sequence, axis=-1).mean(-1)


def _cluster_init(rest: np.ndarray, local: np.ndarray, bones: int, opts: FitOptions) -> np.ndarray:
    """(V,) bone label of each vertex: k-means over rest position (+ weighted trajectory)."""
    feats = rest
    if opts.cluster_motion_weight > 0 and len(local) > 1:
        disp = (local - rest[None]).transpose(1, 0, 2).reshape(len(rest), -1)
        feats = np.concatenate([rest, opts.cluster_motion_weight * disp / math.sqrt(len(local))], axis=1)
    return sk.kmeans(rest, bones, features=feats)


def _bone_shapes(rest: np.ndarray, labels: np.ndarray, bones: int, floor: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres (B,3), rotations (B,3,3) and std-devs (B,3) of each cluster (std floored at ``floor``)."""
    centers = np.zeros((bones, 3))
    rots = np.tile(np.eye(3), (bones, 1, 1))
    scales = np.full((bones, 3), floor)
    for b in range(bones):
        pts = rest[labels == b]
        centers[b] = pts.mean(0)
        if len(pts) >= 4:
            evals, evecs = np.linalg.eigh(np.cov(pts.T))
            if np.linalg.det(evecs) < 0:
                evecs[:, 0] = -evecs[:, 0]
            rots[b] = evecs
            scales[b] = np.sqrt(np.maximum(evals, floor**2))
    return centers, rots, scales


def check_sequence(sequence: np.ndarray, bones: int, opts: FitOptions) -> np.ndarray:
    """The (T, V, 3) sequence as float64 after checking its shape, values, B and the options."""
    seq = np.asarray(sequence, dtype=np.float64)
    if seq.ndim != 3 or seq.shape[-1] != 3 or seq.shape[0] < 1 or seq.shape[1] < 1:
        raise InputError(f"skinning_fit: mesh_sequence must have shape (T, V, 3), got {seq.shape}")
    if not np.isfinite(seq).all():
        raise InputError("skinning_fit: mesh_sequence contains NaN/inf")
    n_frames, n_verts, _ = seq.shape
    if not 1 <= bones <= n_verts:
        raise ConfigError(f"recon.bones={bones}: must lie in [1, {n_verts}] (the number of vertices)")
    if not 0 <= opts.rest_frame < n_frames:
        raise ConfigError(f"recon.rest_frame={opts.rest_frame}: the sequence has {n_frames} frames")
    if opts.global_from not in ("kabsch", "identity"):
        raise ConfigError(f"recon.global_from={opts.global_from!r}: use 'kabsch' or 'identity'")
    return seq


def initial_bone_motion(rest_n: np.ndarray, local_n: np.ndarray, labels: np.ndarray, bones: int) -> np.ndarray:
    """(T, B, 4, 4) each cluster's best rigid motion from rest (translation only for 1-2 point clusters)."""
    init_j = np.tile(np.eye(4), (local_n.shape[0], bones, 1, 1))
    for b in range(bones):
        members = labels == b
        if members.sum() >= 3:
            init_j[:, b] = rigid_fit(np.broadcast_to(rest_n[members], local_n[:, members].shape), local_n[:, members])
        else:  # a 1-2 point cluster cannot fix a rotation: translate only
            init_j[:, b, :3, 3] = local_n[:, members].mean(1) - rest_n[members].mean(0)
    return init_j


class BoneModel(torch.nn.Module):
    """Gaussian bones (centres, orientations, log scales), per-frame rotations about fixed pivots with
    translations, and an optional skinning MLP delta, in normalised units (paper Eq. W = softmax(d_M + W_delta))."""

    pivots: torch.Tensor  # a registered buffer (moves with .to(), not trained)

    def __init__(self, centers0: np.ndarray, rots0: np.ndarray, scales0: np.ndarray, init_j: np.ndarray,
                 opts: FitOptions) -> None:
        super().__init__()
        dt = torch.float32
        bones = len(centers0)
        self.register_buffer("pivots", torch.as_tensor(centers0, dtype=dt))  # fixed pivots of the rotations
        self.centers = torch.nn.Parameter(torch.as_tensor(centers0, dtype=dt))
        self.bone_rot = torch.nn.Parameter(torch.as_tensor(sk.matrix_to_rot6d(rots0), dtype=dt))
        self.log_scales = torch.nn.Parameter(torch.as_tensor(np.log(scales0 * opts.init_scale_factor), dtype=dt))
        self.rot6 = torch.nn.Parameter(torch.as_tensor(sk.matrix_to_rot6d(init_j[..., :3, :3]), dtype=dt))
        # Translation of each bone's pivot: x' = R (x - p) + p + tau.
        tau0 = np.einsum("tbij,bj->tbi", init_j[..., :3, :3], centers0) + init_j[..., :3, 3] - centers0
        self.tau = torch.nn.Parameter(torch.as_tensor(tau0, dtype=dt))
        self.mlp = (
            sk.SkinningDelta(bones, center=np.zeros(3), scale=0.5, width=opts.mlp_width, layers=opts.mlp_layers,
                             frequencies=opts.mlp_frequencies, generator=torch_generator(opts.seed))
            if opts.mlp_width > 0 else None
        )  # fmt: skip

    def bone_parameters(self) -> list[torch.nn.Parameter]:
        return [self.centers, self.bone_rot, self.log_scales, self.rot6, self.tau]

    def transforms(self) -> torch.Tensor:
        """(T, B, 3, 4) per-frame bone transforms."""
        rot = sk.rot6d_to_matrix(self.rot6)  # (T, B, 3, 3)
        trans = self.pivots + self.tau - torch.einsum("tbij,bj->tbi", rot, self.pivots)
        return torch.cat([rot, trans[..., None]], dim=-1)

    def weights(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(N, B) skinning weights of (N, 3) points and the MLP's delta logits (or None)."""
        logits = -sk.mahalanobis_sq_torch(points, self.centers, sk.rot6d_to_matrix(self.bone_rot), self.log_scales)
        delta = self.mlp(points) if self.mlp is not None else None
        if delta is not None:
            logits = logits + delta
        return torch.softmax(logits, dim=-1), delta


def optimise_bones(model: BoneModel, x_rest: torch.Tensor, y: torch.Tensor, opts: FitOptions) -> list[float]:
    """Adam with a cosine schedule on the LBS data term plus the delta and entropy regularisers; returns the
    rms data error every 50 iterations (normalised units)."""
    groups: list[dict[str, Any]] = [{"params": model.bone_parameters(), "lr": opts.lr}]
    if model.mlp is not None:
        groups.append({"params": list(model.mlp.parameters()), "lr": opts.lr * 0.5})
    optim = torch.optim.Adam(groups)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(optim, T_max=max(opts.iterations, 1), eta_min=opts.lr * 0.05)
    history: list[float] = []
    for it in range(opts.iterations):
        optim.zero_grad(set_to_none=True)
        w, delta = model.weights(x_rest)
        pred = sk.linear_blend_torch(x_rest, w, model.transforms())
        data = ((pred - y) ** 2).sum(-1).mean()
        loss = data
        if delta is not None and opts.delta_weight > 0:
            loss = loss + opts.delta_weight * (delta**2).mean()
        if opts.entropy_weight > 0:
            loss = loss + opts.entropy_weight * (-(w * torch.log(w + 1e-8)).sum(-1).mean())
        loss.backward()
        optim.step()
        sched.step()
        if it % 50 == 0 or it == opts.iterations - 1:
            history.append(float(data.detach().sqrt()))
            log.debug("skinning_fit B=%d it %d rms %.5f (bbox-diag units)", len(model.pivots), it, history[-1])
    return history


def fit_skinning(sequence: np.ndarray, bones: int, opts: FitOptions | None = None) -> FitResult:
    """Fit Gaussian bones, per-frame bone transforms and neural skinning to a posed sequence.

    Args:
        sequence: (T, V, 3) posed vertices with fixed correspondence [m].
        bones: number of bones B, 1 <= B <= V.
        opts: numerical options.

    Returns:
        The fitted model and its per-frame error on all vertices.

    Raises:
        InputError: the sequence has the wrong shape or non-finite values.
        ConfigError: B is out of range or the rest frame does not exist.
    """
    opts = opts or FitOptions()
    start = time.perf_counter()
    seq = check_sequence(sequence, bones, opts)
    n_frames, n_verts, _ = seq.shape
    rest = seq[opts.rest_frame]
    diag = bbox_diagonal(rest)
    if diag <= 0:
        raise InputError("skinning_fit: the rest shape is degenerate (zero bounding box)")
    # Work in normalised units (rest centred, diagonal 1) so learning rates do not depend on the scene.
    centre = rest.mean(0)
    glob = rigid_fit(np.broadcast_to(rest, seq.shape), seq) if opts.global_from == "kabsch" \
        else np.tile(np.eye(4), (n_frames, 1, 1))
    local = np.einsum("tij,tvj->tvi", sk.rigid_inverse(glob)[:, :3, :3], seq) + sk.rigid_inverse(glob)[:, None, :3, 3]
    rest_n = (rest - centre) / diag
    local_n = (local - centre) / diag
    labels = _cluster_init(rest_n, local_n, bones, opts)
    centers0, rots0, scales0 = _bone_shapes(rest_n, labels, bones, 0.01)  # floor 1% of the diagonal
    model = BoneModel(centers0, rots0, scales0, initial_bone_motion(rest_n, local_n, labels, bones), opts)
    idx = np.sort(sk.farthest_point_sample(rest_n, opts.fit_vertices)) \
        if opts.fit_vertices and opts.fit_vertices < n_verts else np.arange(n_verts)
    history = optimise_bones(model, torch.as_tensor(rest_n[idx], dtype=torch.float32),
                             torch.as_tensor(local_n[:, idx], dtype=torch.float32), opts)
    fit = fit_result(model, rest, rest_n, glob, centre, diag, history)
    fit.frame_error_m = lbs_error(seq, fit)
    fit.seconds = time.perf_counter() - start
    log.info(
        "skinning_fit B=%d: mean vertex error %.3f%% of bbox diagonal (max frame %.3f%%) in %.1f s",
        bones, fit.mean_error_pct, float(fit.frame_error_pct.max()), fit.seconds,
    )
    log.debug("skinning_fit per-frame error [%% diag]: %s", np.array2string(fit.frame_error_pct, precision=3))
    return fit


def fit_result(model: BoneModel, rest: np.ndarray, rest_n: np.ndarray, glob: np.ndarray, centre: np.ndarray,
               diag: float, history: list[float]) -> FitResult:
    """The fitted model back in metres: x = diag * x_n + centre, so J = S^-1 J_n S with S the normalisation."""
    n_frames, bones = model.rot6.shape[:2]
    with torch.no_grad():
        w_all, _ = model.weights(torch.as_tensor(rest_n, dtype=torch.float32))
        w_np = w_all.double().numpy()
        w_np = w_np / w_np.sum(1, keepdims=True)
        j_n = np.tile(np.eye(4), (n_frames, bones, 1, 1))
        j_n[..., :3, :] = model.transforms().double().numpy()
        cov_n = sk.bone_covariances(sk.rot6d_to_matrix(model.bone_rot).double().numpy(),
                                    np.exp(model.log_scales.double().numpy()))
        centers_n = model.centers.double().numpy()
    j = j_n.copy()
    j[..., :3, 3] = diag * j_n[..., :3, 3] + centre - np.einsum("tbij,j->tbi", j_n[..., :3, :3], centre)
    return FitResult(rest=rest.copy(), centers=centers_n * diag + centre, covariances=cov_n * diag**2, weights=w_np,
                     bone_transforms=j, global_transforms=glob, frame_error_m=np.zeros(n_frames),
                     bbox_diagonal=diag, seconds=0.0, history=history)


def parse_bones(value: Any) -> int | str:
    """Validate a ``bones`` config value: a positive int or the string ``"auto"``.

    Raises:
        ConfigError: anything else (0, negative, a non-numeric string).
    """
    if isinstance(value, str):
        text = value.strip().lower()
        if text == "auto":
            return "auto"
        if text.lstrip("+").isdigit():
            value = int(text)
        else:
            raise ConfigError(f"recon.bones={value!r}: use a positive integer or 'auto'")
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ConfigError(f"recon.bones={value!r}: use a positive integer or 'auto'")
    if value < 1:
        raise ConfigError(f"recon.bones={value}: needs at least one bone (or 'auto')")
    return int(value)


def choose_bones(
    sequence: np.ndarray, candidates: list[int], tolerance_pct: float, opts: FitOptions
) -> tuple[FitResult, list[tuple[int, float]]]:
    """Fit increasing bone counts and keep the smallest whose mean error is within tolerance.

    Args:
        sequence: (T, V, 3) posed vertices [m].
        candidates: bone counts to try, ascending.
        tolerance_pct: accepted mean vertex error, % of the rest bounding-box diagonal.
        opts: fit options.

    Returns:
        (chosen fit, the error-vs-B curve as (B, mean error %) pairs for every B tried). If no
        candidate meets the tolerance, the fit with the smallest error is returned (and a warning logged).
    """
    curve: list[tuple[int, float]] = []
    best: FitResult | None = None
    for b in sorted(set(candidates)):
        if b > sequence.shape[1]:
            break
        fit = fit_skinning(sequence, b, opts)
        curve.append((b, fit.mean_error_pct))
        log.info("bones=auto: B=%d -> %.3f%% (tolerance %.3f%%)", b, fit.mean_error_pct, tolerance_pct)
        if best is None or fit.mean_error_pct < best.mean_error_pct:
            best = fit
        if fit.mean_error_pct <= tolerance_pct:
            best = fit
            break
    else:
        log.warning("bones=auto: no B in %s reached %.3f%%; using the best fit", candidates, tolerance_pct)
    assert best is not None
    log.info("bones=auto: error-vs-B curve %s; chose B=%d", curve, best.centers.shape[0])
    return best, curve


@register("recon", "skinning_fit")
class SkinningFit:
    """Fit Gaussian bones and neural blend skinning to ``ReferenceInput.mesh_sequence``."""

    @dataclass
    class Config(FitOptions):
        """``recon=skinning_fit`` options (see :class:`FitOptions` for the numerical ones).

        Attributes:
            bones: number of bones B (int >= 1), or ``"auto"`` to pick the smallest B of
                ``auto_candidates`` whose mean vertex error is within ``auto_tolerance_pct``.
            auto_tolerance_pct: accepted mean vertex error for ``bones=auto`` [% of bbox diagonal].
            auto_candidates: bone counts tried (ascending) by ``bones=auto``.
        """

        bones: Any = 13
        auto_tolerance_pct: float = 1.5
        auto_candidates: list[int] = field(default_factory=lambda: [2, 3, 4, 5, 6, 8, 10, 13, 16, 20, 25])

        def validate(self) -> None:
            self.bones = parse_bones(self.bones)
            if self.iterations < 0:
                raise ConfigError(f"recon.iterations={self.iterations}: must be >= 0")
            if self.lr <= 0:
                raise ConfigError(f"recon.lr={self.lr}: must be > 0")
            if self.auto_tolerance_pct <= 0:
                raise ConfigError(f"recon.auto_tolerance_pct={self.auto_tolerance_pct}: must be > 0")
            if any(int(b) < 1 for b in self.auto_candidates) or not self.auto_candidates:
                raise ConfigError(f"recon.auto_candidates={self.auto_candidates}: positive bone counts needed")

    def __init__(self, config: Config, *, device: str = "cpu") -> None:
        config.validate()
        self.config = config
        self.device = device  # the fit is small; it always runs on the CPU
        self.last_fit_report: dict[str, Any] = {}

    def fit(self, sequence: np.ndarray) -> FitResult:
        """Fit the configured (or automatically chosen) bone count to a (T, V, 3) sequence [m]."""
        opts = FitOptions(**{k: getattr(self.config, k) for k in FitOptions.__dataclass_fields__})
        curve: list[tuple[int, float]] = []
        if self.config.bones == "auto":
            fit, curve = choose_bones(sequence, [int(b) for b in self.config.auto_candidates],
                                      self.config.auto_tolerance_pct, opts)
        else:
            if int(self.config.bones) > sequence.shape[1]:
                raise ConfigError(
                    f"recon.bones={self.config.bones}: more bones than the {sequence.shape[1]} vertices of the input"
                )
            fit = fit_skinning(sequence, int(self.config.bones), opts)
        self.last_fit_report = {
            "bones": int(fit.centers.shape[0]),
            "frame_error_m": fit.frame_error_m.tolist(),
            "frame_error_pct": fit.frame_error_pct.tolist(),
            "mean_error_pct": fit.mean_error_pct,
            "max_frame_error_pct": float(fit.frame_error_pct.max()),
            "bbox_diagonal_m": fit.bbox_diagonal,
            "seconds": fit.seconds,
            "bones_curve": curve,
        }
        return fit

    def reconstruct(self, source: ReferenceInput) -> Reference:
        """Fit ``source.mesh_sequence`` and return the articulated reference (validated)."""
        if source.mesh_sequence is None:
            raise InputError(
                f"recon=skinning_fit needs a mesh sequence, but reference '{source.name}' has none; "
                "use reference=meshseq or reference=lab4d, or recon=video for videos"
            )
        fit = self.fit(source.mesh_sequence)
        return reference_from_fit(fit, faces=source.faces, fps=source.fps, name=source.name)


def reference_from_fit(
    fit: FitResult, *, faces: np.ndarray | None, fps: float, name: str, colors: np.ndarray | None = None
) -> Reference:
    """Wrap a :class:`FitResult` into a validated :class:`~sync4d.types.Reference`."""
    return Reference(
        rest_vertices=fit.rest.astype(np.float64),
        rest_faces=None if faces is None else np.asarray(faces, dtype=np.int64),
        bone_centers=fit.centers,
        bone_covariances=0.5 * (fit.covariances + np.swapaxes(fit.covariances, 1, 2)),
        skinning=fit.weights,
        bone_transforms=fit.bone_transforms,
        global_transforms=fit.global_transforms,
        fps=float(fps),
        vertex_colors=colors,
        name=name,
    ).validate()
