"""The pictures and files a finished run leaves: ``render.mp4``, ``compare.mp4``, a GIF in TensorBoard,
an animated USD and a ``.npz`` of the Gaussian sequence."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig

from sync4d.io.mesh import mesh_to_gaussians
from sync4d.metrics import skinned_positions
from sync4d.registry import build, effective_config
from sync4d.types import DrivingMotion, Reference, TargetGaussians, Trajectory

log = logging.getLogger(__name__)


def sequence_gaussians(target: TargetGaussians, trajectory: Trajectory, globals_: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World means (T, N, 3) and covariances (T, N, 3, 3): F Sigma F^T, then the global transform G_t."""
    rest_cov = target.covariances()
    rot = globals_[:, :3, :3]
    means = np.einsum("tij,tnj->tni", rot, trajectory.x) + globals_[:, None, :3, 3]
    cov = rest_cov[None] if trajectory.F is None else trajectory.F @ rest_cov[None] @ np.swapaxes(trajectory.F, 2, 3)
    cov = np.einsum("tij,tnjk,tlk->tnil", rot, np.broadcast_to(cov, (len(rot), *rest_cov.shape)), rot)
    return means, cov


def reference_gaussians(reference: Reference, num_frames: int, *, count: int = 3000) -> tuple[TargetGaussians, np.ndarray, np.ndarray]:
    """The reference's rest surface as Gaussians, posed for every output frame (looped) by its own skinning.

    Returns:
        The rest Gaussians, world means (T, N, 3) and covariances (T, N, 3, 3).
    """
    from scipy.spatial import cKDTree

    if reference.rest_faces is not None and len(reference.rest_faces):
        rest = mesh_to_gaussians(reference.rest_vertices, reference.rest_faces, num_surface=count,
                                 vertex_colors=reference.vertex_colors, name=reference.name)
    else:
        from sync4d.types import matrix_to_quat

        n = len(reference.rest_vertices)
        size = 0.01 * np.linalg.norm(np.ptp(reference.rest_vertices, axis=0))
        colors = reference.vertex_colors if reference.vertex_colors is not None else np.full((n, 3), 0.6)
        rest = TargetGaussians(
            means=reference.rest_vertices.astype(np.float32), quats=matrix_to_quat(np.tile(np.eye(3), (n, 1, 1))).astype(np.float32),
            log_scales=np.full((n, 3), np.log(size), np.float32), opacity_logits=np.full(n, 2.0, np.float32),
            sh=((colors - 0.5) / 0.28209479177387814)[:, None, :].astype(np.float32),
        )
    _, nearest = cKDTree(reference.rest_vertices).query(rest.means)
    weights = reference.skinning[nearest]
    means, covs = [], []
    rest_cov = rest.covariances()
    for t in range(num_frames):
        i = t % reference.num_frames
        x = skinned_positions(rest.means.astype(np.float64), weights, reference.bone_transforms[i])
        blended = np.einsum("nb,bij->nij", weights, reference.bone_transforms[i][:, :3, :3])
        G = reference.global_transforms[i]
        means.append(x @ G[:3, :3].T + G[:3, 3])
        R = G[:3, :3] @ blended
        covs.append(R @ rest_cov @ np.swapaxes(R, 1, 2))
    return rest, np.stack(means), np.stack(covs)


def render_run_outputs(
    run_dir: Path,
    cfg: DictConfig,
    target: TargetGaussians,
    trajectory: Trajectory,
    motion: DrivingMotion,
    reference: Reference,
    *,
    logger: Any = None,
) -> dict[str, Path]:
    """Render and export a finished run. Returns the written files by name."""
    from sync4d.io.export import export_npz, export_usd
    from sync4d.render.camera import frame_object
    from sync4d.render.video import compare, log_gif_tensorboard, render_sequence, write_mp4

    shrink = (cfg.get("shrink") or {}).get("render")
    render_cfg = effective_config("render", cfg.render, shrink)
    renderer = build("render", render_cfg, device=cfg.device)
    rc = renderer.cfg
    fps = rc.fps or motion.fps
    globals_ = motion.global_transforms[: trajectory.num_frames]
    means, covs = sequence_gaussians(target, trajectory, globals_)
    opac = target.opacities
    camera = frame_object(means.reshape(-1, 3), direction=rc.view_direction, up=rc.up, fov_deg=rc.fov_deg,
                          width=rc.width, height=rc.height, margin=rc.margin)
    frames = render_sequence(renderer, means, covs, target.sh, opac, camera, desc="render target")
    files = {"render.mp4": write_mp4(run_dir / "render.mp4", frames, fps)}

    ref_rest, ref_means, ref_covs = reference_gaussians(reference, trajectory.num_frames)
    ref_camera = frame_object(ref_means.reshape(-1, 3), direction=rc.view_direction, up=rc.up, fov_deg=rc.fov_deg,
                              width=rc.width, height=rc.height, margin=rc.margin)
    ref_frames = render_sequence(renderer, ref_means, ref_covs, ref_rest.sh, ref_rest.opacities, ref_camera,
                                 desc="render reference")
    side = compare(ref_frames, frames, labels=("reference", "target"))
    files["compare.mp4"] = write_mp4(run_dir / "compare.mp4", side, fps)
    writer = getattr(logger, "writer", None)
    if writer is not None:
        log_gif_tensorboard(writer, "video/compare", side, 0, fps=fps, gif_path=run_dir / "compare.gif")
    files["sequence.usda"] = export_usd(
        run_dir / "sequence.usda", means, colors=target.colors(), widths=2.0 * target.scales.max(axis=1), fps=motion.fps,
        opacities=opac, up_axis="Y",
        mesh_vertices=np.stack([reference.posed_vertices(t % reference.num_frames, apply_global=True)
                                for t in range(trajectory.num_frames)]) if reference.rest_faces is not None else None,
        mesh_faces=reference.rest_faces,
    )
    files["sequence.npz"] = export_npz(run_dir / "sequence.npz", means, fps=motion.fps, covariances=covs,
                                       colors=target.colors(), sh=target.sh, opacities=opac,
                                       global_transforms=globals_)
    log.info("wrote %s", ", ".join(files))
    return files
