"""The pictures and files a finished run leaves.

* ``render.mp4``: the target; ``compare.mp4`` and ``compare.gif`` (also in TensorBoard): the input video
  (when the reference came from one) | the reconstructed reference | the target, frame-aligned. Both
  objects are framed upright (the renderer's ``up``) from the side their own motion is best seen
  (:func:`sync4d.render.camera.motion_view_direction`), so each is seen alike relative to its own motion.
* ``input.mp4``: the input video itself; ``sequence.s4d`` / ``reference.s4d``: the target's and the
  reconstructed reference's Gaussians over time with their part labels, compact (:mod:`sync4d.io.seq4d`);
  together with ``trajectory.npz`` these are what ``python -m sync4d.view`` shows.
* ``sequence.glb`` (animated glTF points), ``sequence.usda`` and ``sequence.npz`` (:mod:`sync4d.io.export`).

Renders and these files hold every frame of every Gaussian at once, so beyond ``RENDER_GAUSSIANS`` they
show that many, evenly by stride (a preview; every Gaussian of every frame is in ``frames/*.ply``).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from sync4d.render.reference import reference_gaussians, reference_nearest
from sync4d.interfaces import VideoLogger
from sync4d.registry import Component
from sync4d.sim.control import bounded_subset, gaussian_trajectory
from sync4d.types import Camera, DrivingMotion, PartMap, Reference, TargetGaussians, Trajectory, VideoClip

log = logging.getLogger(__name__)
#: Most target Gaussians rendered and exported per frame (evenly by stride beyond it).
RENDER_GAUSSIANS = 100_000


def sequence_gaussians(target: TargetGaussians, trajectory: Trajectory, globals_: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World means (T, N, 3) and covariances (T, N, 3, 3): F Sigma F^T, then the global transform G_t.

    ``trajectory`` is per Gaussian (see :func:`sync4d.sim.control.gaussian_trajectory`)."""
    rest_cov = target.covariances()
    rot = globals_[:, :3, :3]
    means = np.einsum("tij,tnj->tni", rot, trajectory.x) + globals_[:, None, :3, 3]
    cov = rest_cov[None] if trajectory.F is None else trajectory.F @ rest_cov[None] @ np.swapaxes(trajectory.F, 2, 3)
    cov = np.einsum("tij,tnjk,tlk->tnil", rot, np.broadcast_to(cov, (len(rot), *rest_cov.shape)), rot)
    return means, cov


def motion_camera(sequence: np.ndarray, rc: Any) -> Camera:
    """A fixed camera framing a (T, N, 3) sequence [m] upright from the side its motion is best seen.

    ``rc`` is the renderer's config (``up``, ``view_direction`` picking the side, ``fov_deg``, size, ``margin``).
    """
    from sync4d.render.camera import MotionView, frame_object, motion_view_direction

    direction = motion_view_direction(sequence, MotionView(), up=rc.up, prefer=rc.view_direction)
    return frame_object(sequence.reshape(-1, 3), direction=direction, up=rc.up, fov_deg=rc.fov_deg,
                        width=rc.width, height=rc.height, margin=rc.margin)


def write_videos(run_dir: Path, panels: list[tuple[str, np.ndarray]], fps: float, *, logger: Any) -> dict[str, Path]:
    """``render.mp4`` of the last panel, ``compare.mp4`` / ``compare.gif`` (and TensorBoard) of all of them."""
    from sync4d.render.video import side_by_side, write_gif, write_mp4

    files = {"render.mp4": write_mp4(run_dir / "render.mp4", panels[-1][1], fps)}
    side = side_by_side([frames for _, frames in panels], labels=[name for name, _ in panels])
    files["compare.mp4"] = write_mp4(run_dir / "compare.mp4", side, fps)
    if isinstance(logger, VideoLogger):
        logger.video("video/compare", side, fps, gif_path=run_dir / "compare.gif")
    else:
        write_gif(run_dir / "compare.gif", side, fps)
    files["compare.gif"] = run_dir / "compare.gif"
    return files


def render_run_outputs(
    run_dir: Path,
    render: Component,
    device: str,
    target: TargetGaussians,
    trajectory: Trajectory,
    motion: DrivingMotion,
    reference: Reference,
    *,
    clip: VideoClip | None = None,
    part_map: PartMap | None = None,
    logger: Any = None,
) -> dict[str, Path]:
    """Render and export a finished run (files listed in the module docstring) with the ``render`` component;
    ``clip`` is the reference's input video when it had one. Returns the files by name."""
    from sync4d.io.seq4d import Seq4DConfig, write_seq4d
    from sync4d.render.video import render_sequence, write_mp4

    renderer = render.build(device=device)
    rc = renderer.config
    fps = rc.fps or motion.fps
    num = trajectory.num_frames
    globals_ = motion.global_transforms[:num]
    index = bounded_subset(target.num, RENDER_GAUSSIANS)
    shown = target if index is None else target.subset(index)
    if index is not None:
        log.info("renders and exports show %d of the %d Gaussians (every %d-th); frames/*.ply hold all",
                 shown.num, target.num, index[1] - index[0])
    means, covs = sequence_gaussians(shown, gaussian_trajectory(trajectory, target.means, index), globals_)
    frames = render_sequence(renderer, means, covs, shown.sh, shown.opacities, motion_camera(means, rc),
                             desc="render target")
    ref_rest, ref_means, ref_covs = reference_gaussians(reference, num)
    ref_frames = render_sequence(renderer, ref_means, ref_covs, ref_rest.sh, ref_rest.opacities,
                                 motion_camera(ref_means, rc), desc="render reference")
    panels = [("reference", ref_frames), ("target", frames)]
    files: dict[str, Path] = {}
    if clip is not None:
        panels.insert(0, ("video", clip.frames))
        files["input.mp4"] = write_mp4(run_dir / "input.mp4", clip.frames, clip.fps)
    files.update(write_videos(run_dir, panels, fps, logger=logger))
    if rc.turntable_frames:
        files["turntable.mp4"] = write_turntable(run_dir / "turntable.mp4", renderer, means[-1], covs[-1], shown, fps)
    store = Seq4DConfig()
    parts = None if part_map is None else part_map.tgt_part if index is None else part_map.tgt_part[index]
    files["sequence.s4d"] = write_seq4d(run_dir / "sequence.s4d", means, covs, shown.colors(), shown.opacities,
                                        fps=motion.fps, config=store, sh=shown.sh, parts=parts)
    files["reference.s4d"] = write_seq4d(
        run_dir / "reference.s4d", ref_means, ref_covs, ref_rest.colors(), ref_rest.opacities, fps=motion.fps,
        config=store, parts=reference.part_labels()[reference_nearest(reference, ref_rest.means)])
    files.update(write_exports(run_dir, means, covs, shown, reference, globals_, fps=motion.fps))
    log.info("wrote %s", ", ".join(files))
    return files


def write_turntable(path: Path, renderer: Any, means: np.ndarray, covs: np.ndarray, target: TargetGaussians,
                    fps: float) -> Path:
    """A turntable of one frame's (N, 3) means [m] and (N, 3, 3) covariances [m^2] about the renderer's ``up``."""
    from sync4d.render.camera import orbit
    from sync4d.render.video import render_sequence, write_mp4

    rc = renderer.config
    cams = orbit(means, int(rc.turntable_frames), up=rc.up, fov_deg=rc.fov_deg, width=rc.width, height=rc.height,
                 margin=rc.margin)
    spin = render_sequence(renderer, np.repeat(means[None], len(cams), 0), covs, target.sh, target.opacities, cams,
                           desc="turntable")
    return write_mp4(path, spin, fps)


def write_exports(run_dir: Path, means: np.ndarray, covs: np.ndarray, target: TargetGaussians, reference: Reference,
                  globals_: np.ndarray, *, fps: float) -> dict[str, Path]:
    """``sequence.glb``, ``sequence.usda`` and ``sequence.npz`` of (T, N, 3) means and (T, N, 3, 3) covariances."""
    from sync4d.io.export import export_glb, export_npz, export_usd

    num = len(means)
    files = {"sequence.glb": export_glb(run_dir / "sequence.glb", means, fps=fps, colors=target.colors())}
    files["sequence.usda"] = export_usd(
        run_dir / "sequence.usda", means, colors=target.colors(), widths=2.0 * target.scales.max(axis=1), fps=fps,
        opacities=target.opacities, up_axis="Y",
        mesh_vertices=np.stack([reference.posed_vertices(t % reference.num_frames, apply_global=True)
                                for t in range(num)]) if reference.rest_faces is not None else None,
        mesh_faces=reference.rest_faces,
    )
    files["sequence.npz"] = export_npz(run_dir / "sequence.npz", means, fps=fps, covariances=covs,
                                       colors=target.colors(), sh=target.sh, opacities=target.opacities,
                                       global_transforms=globals_)
    return files
