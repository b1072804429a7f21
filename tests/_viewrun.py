"""A small finished-run folder for the viewer tests, written with the run's own writers (no pipeline run)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

RED = (0.9, 0.1, 0.1)  # the target's colour: no part colour and no grey is near it


def lid_sequence(t: int, n: int, *, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A flat base (part 0) and a lid (part 1) swinging 90 degrees about the x axis over ``t`` frames.

    Returns:
        means (T, N, 3) [m], covariances (T, N, 3, 3) [m^2], parts (N,).
    """
    rng = np.random.default_rng(seed)
    half = n // 2
    base = np.c_[rng.uniform(-0.15, 0.15, half), rng.uniform(0, 0.01, half), rng.uniform(0, 0.2, half)]
    lid = np.c_[rng.uniform(-0.15, 0.15, n - half), rng.uniform(0, 0.2, n - half), rng.uniform(-0.005, 0.005, n - half)]
    parts = np.r_[np.zeros(half, int), np.ones(n - half, int)]
    means = []
    for a in np.linspace(0.0, np.pi / 2, t):
        rot = np.array([[1, 0, 0], [0, np.cos(a), np.sin(a)], [0, -np.sin(a), np.cos(a)]])
        means.append(np.r_[base, lid @ rot.T])
    covs = np.broadcast_to(np.eye(3) * 0.012**2, (t, n, 3, 3)).copy()
    return np.stack(means), covs, parts


def make_run(folder: Path, *, frames: int = 4, n: int = 1200, video: bool = True) -> Path:
    """Write ``sequence.s4d``, ``reference.s4d``, ``input.mp4``, ``trajectory.npz`` and ``.hydra/config.yaml``."""
    from sync4d.io.seq4d import Seq4DConfig, write_seq4d
    from sync4d.render.video import write_mp4

    folder.mkdir(parents=True, exist_ok=True)
    means, covs, parts = lid_sequence(frames, n, seed=0)
    write_seq4d(folder / "sequence.s4d", means, covs, np.tile(RED, (n, 1)), np.full(n, 0.95), fps=8.0,
                config=Seq4DConfig(), parts=parts)
    ref_means, ref_covs, ref_parts = lid_sequence(frames, n // 2, seed=1)
    write_seq4d(folder / "reference.s4d", ref_means, ref_covs, np.full((n // 2, 3), 0.35), np.full(n // 2, 0.95),
                fps=8.0, config=Seq4DConfig(), parts=ref_parts)
    if video:
        clip = np.full((frames, 48, 64, 3), 240, np.uint8)
        for k in range(frames):
            clip[k, 10:38, 5 + 12 * k : 20 + 12 * k] = (20, 20, 200)  # a blue square moving right
        write_mp4(folder / "input.mp4", clip, 8.0)
    np.savez(folder / "trajectory.npz", x=means.astype(np.float32), part=parts,
             global_transforms=np.tile(np.eye(4), (frames, 1, 1)))
    (folder / ".hydra").mkdir(exist_ok=True)
    (folder / ".hydra" / "config.yaml").write_text("render:\n  up: [0.0, 1.0, 0.0]\n")
    return folder
