"""What the viewer shows of a run folder, read lazily: Gaussian frames, the input video, particles.

A finished run leaves (see :mod:`sync4d.run.exports`) ``sequence.s4d`` (the target's Gaussians with
part labels), ``reference.s4d`` (the reconstructed reference's), ``input.mp4`` (the input video, when
the reference came from one) and ``trajectory.npz`` (the simulated points). A run without
``sequence.s4d`` (an older or interrupted run) is read from ``frames/*.ply`` instead, one file per frame.
Frames are decoded when asked for, so a long or large run costs one frame (or one ``.s4d`` chunk) of
memory, not the whole sequence.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from sync4d.errors import InputError
from sync4d.io.seq4d import Sequence4D

#: Part colours (matplotlib's tab10): target part b and the reference bone b it is matched to share one.
PALETTE = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
                    [140, 86, 75], [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207]]) / 255.0


def part_colors(parts: np.ndarray) -> np.ndarray:
    """(N,) integer labels -> (N, 3) RGB in [0, 1] (the palette repeats after 10 parts)."""
    return PALETTE[np.asarray(parts, dtype=np.int64) % len(PALETTE)]


@dataclass(frozen=True)
class SplatFrame:
    """One frame of Gaussians.

    Attributes:
        means: (N, 3) centres [m].
        covariances: (N, 3, 3) [m^2].
        colors: (N, 3) RGB in [0, 1].
        opacities: (N,) in [0, 1].
        parts: (N,) part labels, or None.
    """

    means: np.ndarray
    covariances: np.ndarray
    colors: np.ndarray
    opacities: np.ndarray
    parts: np.ndarray | None


class FrameSource(Protocol):
    """A Gaussian sequence read frame by frame."""

    num_frames: int

    num: int

    fps: float | None  # frames per second, when the sequence records it

    def frame(self, t: int) -> SplatFrame: ...

    def all_means(self, index: np.ndarray | None = None) -> np.ndarray: ...


class Seq4DSource:
    """Frames of a ``.s4d`` file (one decoded chunk held at a time)."""

    def __init__(self, path: Path) -> None:
        self.seq = Sequence4D(path)
        self.num_frames, self.num = self.seq.num_frames, self.seq.num
        self.fps = float(self.seq.fps) if self.seq.fps > 0 else None

    def frame(self, t: int) -> SplatFrame:
        means, covs = self.seq.frame(t)
        return SplatFrame(means, covs, self.seq.colors, self.seq.opacities, self.seq.parts)

    def all_means(self, index: np.ndarray | None = None) -> np.ndarray:
        return self.seq.means(index)


class PlySource:
    """Frames of a ``frames/%06d.ply`` folder, one file read per frame."""

    def __init__(self, folder: Path, parts: np.ndarray | None) -> None:
        self.files = sorted(folder.glob("*.ply"))
        if not self.files:
            raise InputError(f"{folder}: no .ply frames; pass a run folder of train.py")
        self.num_frames = len(self.files)
        self.parts = parts
        self.fps: float | None = None  # .ply frames record no frame rate
        from sync4d.io.ply import read_gaussians_ply

        self.num = read_gaussians_ply(self.files[0]).num

    def frame(self, t: int) -> SplatFrame:
        from sync4d.io.ply import read_gaussians_ply

        g = read_gaussians_ply(self.files[t])
        parts = self.parts if self.parts is not None and len(self.parts) == g.num else None
        return SplatFrame(g.means.astype(np.float64), g.covariances(), g.colors(), g.opacities, parts)

    def all_means(self, index: np.ndarray | None = None) -> np.ndarray:
        # Framing needs only a few frames' extent: first, middle, last.
        picks = sorted({0, self.num_frames // 2, self.num_frames - 1})
        return np.stack([self.frame(t).means if index is None else self.frame(t).means[index] for t in picks])


class CachedFrames:
    """The last ``capacity`` frames of a source, by index (the viewer revisits frames while scrubbing)."""

    def __init__(self, source: FrameSource, capacity: int) -> None:
        self.source, self.capacity = source, max(int(capacity), 1)
        self._frames: OrderedDict[int, SplatFrame] = OrderedDict()

    def __call__(self, t: int) -> SplatFrame:
        if t in self._frames:
            self._frames.move_to_end(t)
            return self._frames[t]
        frame = self.source.frame(t)
        self._frames[t] = frame
        while len(self._frames) > self.capacity:
            self._frames.popitem(last=False)
        return frame


@dataclass(frozen=True)
class Placement:
    """A similarity that puts an object in its panel: ``x' = scale * R (x - center) + offset``.

    Attributes:
        center: (3,) [m]; rotation: (3, 3) about the viewer's up (+y), turning the object's motion plane
            to face +z; scale: [1/m] so the object's extent is about one viewer unit; offset: (3,) viewer units.
    """

    center: np.ndarray
    rotation: np.ndarray
    scale: float
    offset: np.ndarray

    def points(self, x: np.ndarray) -> np.ndarray:
        """(N, 3) [m] -> (N, 3) viewer units."""
        return self.scale * (np.asarray(x, dtype=np.float64) - self.center) @ self.rotation.T + self.offset

    def covariances(self, cov: np.ndarray) -> np.ndarray:
        """(N, 3, 3) [m^2] -> (N, 3, 3) viewer units^2."""
        return self.scale**2 * (self.rotation @ np.asarray(cov, dtype=np.float64) @ self.rotation.T)


def place(sequence: np.ndarray, offset: np.ndarray, *, up: np.ndarray) -> Placement:
    """The placement of a (T, N, 3) sequence [m] in a panel at ``offset``: upright, its motion seen side-on.

    The object is turned about ``up`` (the run's scene up, mapped to the viewer's +y) so the horizontal
    normal of its motion's principal plane (:func:`sync4d.render.camera.motion_view_direction`) faces +z,
    the viewer's default camera side, and scaled so its bounding sphere has radius 0.5.
    """
    from sync4d.render.camera import SIDE_ON, bounding_sphere, motion_view_direction

    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    normal = motion_view_direction(sequence, SIDE_ON, up=up,
                                   prefer=np.array([0.0, 0.0, 1.0]) if abs(up[2]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    side = np.cross(up, normal)
    # Rows: where the object's (side, up, normal) go in the viewer: x, y, z.
    rotation = np.stack([side, up, normal])
    center, radius = bounding_sphere(sequence)
    return Placement(center=center, rotation=rotation, scale=0.5 / radius, offset=np.asarray(offset, float))


def splat_buffer(means: np.ndarray, covariances: np.ndarray, colors: np.ndarray, opacities: np.ndarray) -> np.ndarray:
    """The (N, 8) uint32 buffer viser's Gaussian splats take (its ``add_gaussian_splats`` layout): centres
    float32, the covariance's upper triangle float16, RGBA uint8."""
    n = len(means)
    cov_triu = np.asarray(covariances).reshape(n, 9)[:, [0, 1, 2, 4, 5, 8]]
    rgba = np.concatenate([colors, np.asarray(opacities).reshape(n, 1)], axis=1)
    return np.concatenate([
        np.ascontiguousarray(means, dtype=np.float32).view(np.uint8),
        np.zeros((n, 4), dtype=np.uint8),
        np.ascontiguousarray(cov_triu, dtype=np.float16).view(np.uint8),
        np.clip(np.rint(rgba * 255.0), 0, 255).astype(np.uint8),
    ], axis=1).view(np.uint32)


def part_boxes(points: np.ndarray, parts: np.ndarray, num_parts: int) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned boxes of each part's points: centres (B, 3) and sizes (B, 3) (zero for empty parts)."""
    centers, sizes = np.zeros((num_parts, 3)), np.zeros((num_parts, 3))
    for b in range(num_parts):
        sel = points[parts == b]
        if len(sel):
            lo, hi = sel.min(axis=0), sel.max(axis=0)
            centers[b], sizes[b] = 0.5 * (lo + hi), hi - lo
    return centers, sizes


class VideoFrames:
    """Frames of ``input.mp4``, read once (a run's input video is small: low resolution, tens of frames)."""

    def __init__(self, path: Path) -> None:
        from sync4d.render.video import read_video

        self.frames = read_video(path)
        self.num_frames = len(self.frames)

    def __call__(self, t: int) -> np.ndarray:
        return self.frames[t % self.num_frames]


@dataclass
class RunData:
    """Everything the viewer shows of one run folder (each part None when the run did not write it).

    Attributes:
        folder: the run folder; name: its label.
        target: the target's Gaussian frames; reference: the reconstructed reference's, or None.
        video: the input video, or None.
        masks: the subject's masks over the input video (``recon/masks.mp4``), or None.
        particles: (T, P, 3) simulated points after the global transform [m], or None.
        particle_parts: (P,) their part labels, or None.
        up: (3,) the scene's up axis.
    """

    folder: Path
    name: str
    target: FrameSource
    reference: FrameSource | None
    video: VideoFrames | None
    particles: np.ndarray | None
    particle_parts: np.ndarray | None
    up: np.ndarray
    masks: VideoFrames | None = None

    @property
    def num_frames(self) -> int:
        return self.target.num_frames


def read_particles(path: Path) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(T, P, 3) world positions [m] (global transforms applied) and (P,) part labels from ``trajectory.npz``."""
    if not path.is_file():
        return None, None
    with np.load(path) as data:
        x = np.asarray(data["x"], dtype=np.float64)
        parts = np.asarray(data["part"]) if "part" in data.files else None
        g = np.asarray(data["global_transforms"]) if "global_transforms" in data.files else None
    if g is not None and len(g) == len(x):
        x = np.einsum("tij,tnj->tni", g[:, :3, :3], x) + g[:, None, :3, 3]
    return x, parts


def gaussian_parts(path: Path, particle_parts: np.ndarray | None) -> np.ndarray | None:
    """(N,) part label of every Gaussian of the frames: ``gaussian_part`` of a control-point run (whose
    ``part`` labels the P simulated points), else the particles' own labels (N = P)."""
    if path.is_file():
        with np.load(path) as data:
            if "gaussian_part" in data.files:
                return np.asarray(data["gaussian_part"])
    return particle_parts


def scene_up(folder: Path) -> np.ndarray:
    """The run's up axis from its saved config (``render.up``), else +y (the project's scenes)."""
    config = folder / ".hydra" / "config.yaml"
    if config.is_file():
        from omegaconf import OmegaConf

        up = OmegaConf.select(OmegaConf.load(config), "render.up")
        if up is not None and len(up) == 3 and math.isfinite(float(np.linalg.norm(up))) and np.linalg.norm(up) > 0:
            return np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    return np.array([0.0, 1.0, 0.0])


def load_run(folder: str | Path) -> RunData:
    """Open a run folder of ``train.py`` (nothing is decoded yet but the particles).

    Raises:
        InputError: the folder does not exist or holds neither ``sequence.s4d`` nor ``frames/*.ply``.
    """
    folder = Path(folder).expanduser()
    if not folder.is_dir():
        raise InputError(f"{folder}: no such run folder; pass outputs/<name>/<timestamp> of a run")
    particles, particle_parts = read_particles(folder / "trajectory.npz")
    if (folder / "sequence.s4d").is_file():
        target: FrameSource = Seq4DSource(folder / "sequence.s4d")
    elif (folder / "frames").is_dir():
        target = PlySource(folder / "frames", gaussian_parts(folder / "trajectory.npz", particle_parts))
    else:
        raise InputError(f"{folder}: neither sequence.s4d nor frames/*.ply; pass the folder of a train.py run")
    reference = Seq4DSource(folder / "reference.s4d") if (folder / "reference.s4d").is_file() else None
    video = VideoFrames(folder / "input.mp4") if (folder / "input.mp4").is_file() else None
    masks = VideoFrames(folder / "recon" / "masks.mp4") if (folder / "recon" / "masks.mp4").is_file() else None
    name = f"{folder.parent.name}/{folder.name}" if folder.parent.name else folder.name
    return RunData(folder=folder, name=name, target=target, reference=reference, video=video,
                   particles=particles, particle_parts=particle_parts, up=scene_up(folder), masks=masks)
