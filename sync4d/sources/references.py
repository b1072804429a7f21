"""Reference sources for files on disk (group ``reference``): mesh sequences, Lab4D exports, BVH,
joint-position mocap and videos (masks and camera given, or found by the video front end).

Relative paths are tried against the working directory first, then against the project root (so
``../shared/data/...`` works from the project folder and from tests). A missing file stops with
:class:`~sync4d.errors.DataMissingError` naming the path.

Shared data these default to (attribution, see ``../shared/data/README.md``):
    * ``lab4d_export/shiba-haru-1002``: ``gengshan-y/ppr-diffphys`` (MIT).
    * ``motion/cmu_bvh/131_01.bvh``: CMU Graphics Lab Motion Capture Database (mocap.cs.cmu.edu; created
      with funding from NSF EIA-0196217), via ``yuki-koyama/bvh11``.
    * ``motion/dog_mocap/dog_trot_joint_pos.txt``: AI4Animation via ``erwincoumans/motion_imitation``,
      CC BY-NC 4.0.
    * ``rendered/metaworld_laptop_hinge``: rendered with MuJoCo from the Meta-World laptop model (MIT).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sync4d.errors import InputError
from sync4d.frontend import FrontEndConfig, Prompt, complete_video
from sync4d.io.lab4d import find_mesh_files, read_mesh_sequence
from sync4d.io.video import read_video_clip
from sync4d.paths import PROJECT_ROOT, resolve_path
from sync4d.registry import register
from sync4d.types import Camera, ReferenceInput

def camera_from_look(
    K: np.ndarray, position: np.ndarray, forward: np.ndarray, up: np.ndarray, width: int, height: int
) -> Camera:
    """A :class:`Camera` (OpenCV axes: x right, y down, z forward) from a look-at description.

    A world point p projects as ``x = (p-c).r, y = (p-c).up, z = (p-c).fwd`` with ``r = fwd x up``, then
    ``u = cx + fx x / z, v = cy - fy y / z`` (the convention of the laptop renders' ``gt.npz``); in OpenCV
    axes that is the rotation with rows ``r, -up, fwd``.
    """
    fwd = np.asarray(forward, dtype=np.float64)
    fwd = fwd / np.linalg.norm(fwd)
    upv = np.asarray(up, dtype=np.float64)
    upv = upv - fwd * (upv @ fwd)
    upv = upv / np.linalg.norm(upv)
    right = np.cross(fwd, upv)
    rot = np.stack([right, -upv, fwd])
    w2c = np.eye(4)
    w2c[:3, :3] = rot
    w2c[:3, 3] = -rot @ np.asarray(position, dtype=np.float64)
    return Camera(K=np.asarray(K, dtype=np.float64), world_to_cam=w2c, width=int(width), height=int(height)).validate()


@register("reference", "meshseq")
class MeshSequenceSource:
    """Posed meshes with fixed topology: a folder of .obj files (sorted by frame number) or a glob."""

    @dataclass
    class Config:
        """Attributes:
        path: folder of .obj files or a glob pattern (e.g. ``.../*-mesh-*.obj``).
        fps: frame rate of the sequence [1/s].
        unit_scale: metres per file unit.
        max_frames: keep at most this many frames (0 = all).
        """

        path: str = "../shared/data/lab4d_export/shiba-haru-1002/*-mesh-*.obj"
        fps: float = 10.0
        unit_scale: float = 1.0
        max_frames: int = 0

    def __init__(self, config: Config, *, device: str = "cpu", seed: int = 0) -> None:
        self.config = config

    def load(self) -> ReferenceInput:
        path = self.config.path
        if not any(ch in path for ch in "*?["):
            path = str(resolve_path(path, what="mesh sequence"))
        elif not Path(path).is_absolute() and not list(Path().glob(path)):
            path = str(PROJECT_ROOT / path)
        files = find_mesh_files(path)
        if self.config.max_frames > 0:
            files = files[: self.config.max_frames]
        verts, faces, _ = read_mesh_sequence(files)
        return ReferenceInput(
            name=Path(files[0]).parent.name, fps=self.config.fps, mesh_sequence=verts * self.config.unit_scale,
            faces=faces, path=str(Path(files[0]).parent),
        )


@register("reference", "lab4d")
class Lab4DSource:
    """A Lab4D export folder, read by ``recon=lab4d`` (its posed meshes are loaded here too, if any)."""

    @dataclass
    class Config:
        """Attributes:
        path: the export folder.
        fps: frame rate of the export [1/s] (Lab4D exports do not store it).
        """

        path: str = "../shared/data/lab4d_export/shiba-haru-1002"
        fps: float = 10.0

    def __init__(self, config: Config, *, device: str = "cpu", seed: int = 0) -> None:
        self.config = config

    def load(self) -> ReferenceInput:
        from sync4d.io.lab4d import read_lab4d_export

        root = resolve_path(self.config.path, what="Lab4D export folder")
        export = read_lab4d_export(root)
        return ReferenceInput(
            name=root.name, fps=self.config.fps, mesh_sequence=export.posed_vertices, faces=export.faces, path=str(root)
        )


@register("reference", "bvh")
class BVHSource:
    """A BVH motion file, read by ``recon=mocap``."""

    @dataclass
    class Config:
        """Attributes:
        path: the .bvh file.
        """

        path: str = "../shared/data/motion/cmu_bvh/131_01.bvh"

    def __init__(self, config: Config, *, device: str = "cpu", seed: int = 0) -> None:
        self.config = config

    def load(self) -> ReferenceInput:
        from sync4d.io.mocap import parse_bvh

        path = resolve_path(self.config.path, what="BVH file")
        _, _, frame_time = parse_bvh(path.read_text(errors="replace"), source=str(path))
        return ReferenceInput(name=path.stem, fps=1.0 / frame_time, path=str(path))


@register("reference", "joint_positions")
class JointPositionsSource:
    """A joint-position mocap text file (one frame per line, x y z per joint), read by ``recon=mocap``."""

    @dataclass
    class Config:
        """Attributes:
        path: the text file.
        fps: frame rate of the file [1/s] (the format does not store it; the dog trot is 60 fps).
        """

        path: str = "../shared/data/motion/dog_mocap/dog_trot_joint_pos.txt"
        fps: float = 60.0

    def __init__(self, config: Config, *, device: str = "cpu", seed: int = 0) -> None:
        self.config = config

    def load(self) -> ReferenceInput:
        from sync4d.io.mocap import read_joint_positions

        path = resolve_path(self.config.path, what="joint-position file")
        read_joint_positions(path)  # fail here, at load, on a malformed file
        return ReferenceInput(name=path.stem, fps=self.config.fps, path=str(path))


@register("reference", "deepmimic")
class DeepMimicSource:
    """A DeepMimic clip (JSON ``Frames``) with its URDF skeleton, read by ``recon=mocap``."""

    @dataclass
    class Config:
        """Attributes:
        path: the clip (.txt JSON); the frame rate comes from its frame durations.
        """

        path: str = "../shared/data/motion/deepmimic/humanoid3d_walk.txt"

    def __init__(self, config: Config, *, device: str = "cpu", seed: int = 0) -> None:
        self.config = config

    def load(self) -> ReferenceInput:
        from sync4d.io.deepmimic import parse_deepmimic_frames

        path = resolve_path(self.config.path, what="DeepMimic clip")
        rows = parse_deepmimic_frames(path.read_text(errors="replace"), source=str(path))  # fail early
        return ReferenceInput(name=path.stem, fps=1.0 / float(rows[0, 0]), path=str(path))


@register("reference", "gltf")
class GltfSource:
    """A skinned, animated glTF 2.0 file playing one of its clips: the posed meshes, and the exact articulated
    reference (its skin's bones and weights) for ``recon=ground_truth``. Default: the Khronos fox (low poly fox
    by PixelMannen, CC0; rigging and animation by @tomkranis, CC-BY 4.0; glTF conversion by @AsoboStudio and
    @scurest)."""

    @dataclass
    class Config:
        """Attributes:
        path: the .gltf file.
        animation: the clip to play.
        fps: sampling rate [1/s].
        unit_scale: metres per file unit (the fox's units are centimetre-like).
        max_frames: frames to sample (0 = one loop of the clip).
        """

        path: str = "../shared/data/skinned/fox/Fox.gltf"
        animation: str = "Walk"
        fps: float = 24.0
        unit_scale: float = 0.01
        max_frames: int = 0

    def __init__(self, config: Config, *, device: str = "cpu", seed: int = 0) -> None:
        self.config = config

    def load(self) -> ReferenceInput:
        from sync4d.io.gltf import read_gltf, skinned_reference

        path = resolve_path(self.config.path, what="glTF file")
        mesh = read_gltf(path)
        truth = skinned_reference(mesh, mesh.animation(self.config.animation), self.config.fps,
                                  unit_scale=self.config.unit_scale, frames=self.config.max_frames, name=path.stem)
        homo = np.concatenate([truth.rest_vertices, np.ones((len(truth.rest_vertices), 1))], axis=1)
        posed = np.einsum("vb,tbij,vj->tvi", truth.skinning, truth.bone_transforms[..., :3, :], homo)
        return ReferenceInput(name=path.stem, fps=self.config.fps, mesh_sequence=posed, faces=mesh.faces, path=str(path),
                              ground_truth=truth)


@register("reference", "video")
class VideoSource:
    """A reference video; the subject's masks and the camera are read when given, else found by the video
    front end (:mod:`sync4d.frontend`)."""

    @dataclass
    class Config:
        """Attributes:
        video: video file or folder of frames.
        masks: folder of mask PNGs or a mask video; empty = found by the front end; ``auto`` = the ``masks``
            folder beside the video if there is one, else found (so ``reference.video=<another video>``
            does not pick up the default's masks).
        camera: ``.npz`` with ``K`` and ``cam_pos``/``cam_forward``/``cam_up`` (laptop renders' layout),
            or with ``K`` and ``world_to_cam`` (4x4): a known static camera; with a frame axis (``cam_*``
            (T, 3), ``world_to_cam`` (T, 4, 4)) a known moving one (:func:`load_camera`); empty = found by the front end
            (intrinsics from a field-of-view guess refined when the camera moves, per-frame extrinsics,
            world = the first frame's camera); ``auto`` = ``gt.npz`` beside the video if there is one.
        prompt: where the subject is when the clip is ambiguous: a point ``[x, y]`` or a box
            ``[x0, y0, x1, y1]`` [px] on frame ``prompt_frame``; empty = found automatically.
        prompt_frame: the frame (after ``stride`` / ``max_frames``) the prompt is on.
        fps: frame rate [1/s]; 0 = from the video file.
        max_frames: keep at most this many frames (0 = all).
        stride: keep every ``stride``-th frame.
        frontend: the front end's options (:class:`~sync4d.frontend.FrontEndConfig`).
        """

        video: str = "../shared/data/rendered/metaworld_laptop_hinge/rgb.mp4"
        masks: str = "auto"
        camera: str = "auto"
        prompt: list[float] = field(default_factory=list)
        prompt_frame: int = 0
        fps: float = 0.0
        max_frames: int = 0
        stride: int = 1
        frontend: FrontEndConfig = field(default_factory=FrontEndConfig)

    def __init__(self, config: Config, *, device: str = "cpu", seed: int = 0) -> None:
        config.frontend.validate()
        self.config = config

    def load(self) -> ReferenceInput:
        video = resolve_path(self.config.video, what="reference video")
        masks = beside(video, self.config.masks, "masks", what="mask folder")
        camera_file = beside(video, self.config.camera, "gt.npz", what="camera file")
        clip = read_video_clip(
            video, masks, fps=self.config.fps or None, max_frames=self.config.max_frames or None, stride=self.config.stride
        )
        camera = None
        if camera_file is not None:
            select = np.arange(clip.num_frames) * max(1, int(self.config.stride))
            camera, per_frame = load_camera(camera_file, clip.frames.shape[2], clip.frames.shape[1], clip.num_frames,
                                            select)
            clip = type(clip)(clip.frames, clip.masks, clip.fps, camera.K, per_frame, clip.source).validate()
        prompt = Prompt(tuple(float(v) for v in self.config.prompt), int(self.config.prompt_frame)) if self.config.prompt else None
        # the front end's world is Y up when the phone is held upright (its first camera turned to Y up)
        up = None if camera is not None else np.array([0.0, 1.0, 0.0])
        if masks is None or camera is None or prompt is not None:
            clip, camera = complete_video(clip, camera, self.config.frontend, masks_given=masks is not None and prompt is None,
                                          prompt=prompt)
        return ReferenceInput(name=video.parent.name if video.is_file() else video.name, fps=clip.fps, video=clip,
                              camera=camera, path=str(video), world_up=up)


def beside(video: Path, value: str, name: str, *, what: str) -> Path | None:
    """A companion file of a video: ``value`` resolved, None when empty; ``auto`` = ``name`` in the video's
    folder if it exists, else None."""
    if value == "auto":
        found = (video.parent if video.is_file() else video) / name
        return found if found.exists() else None
    return resolve_path(value, what=what) if value else None


CAMERA_SHAPES = ("'K' (3, 3) with 'world_to_cam' (4, 4) or (T, 4, 4), or with 'cam_pos', 'cam_forward', 'cam_up' "
                 "each (3,) or (T, 3)")


def load_camera(path: Path, width: int, height: int, frames: int | None = None,
                select: np.ndarray | None = None) -> tuple[Camera, np.ndarray | None]:
    """A camera from an .npz: ``K`` (3, 3) and either ``world_to_cam`` (4, 4), or ``cam_pos`` / ``cam_forward`` /
    ``cam_up`` (3,) each (the laptop renders' layout): one static camera; or the same with a leading frame
    axis, ``world_to_cam`` (T, 4, 4) or ``cam_*`` (T, 3) (a (3,) ``cam_up`` is shared by every frame): a camera
    that moves.

    Args:
        path: the file.
        width, height: the video's size [px].
        frames: the clip's frame count; a per-frame camera must have this many poses, or as many as the
            video before ``select`` picked its frames.
        select: indices of the video's frames the clip kept (stride, max_frames), applied to a longer pose list.

    Returns:
        (the first frame's :class:`Camera`, (T, 4, 4) world-to-camera per frame or None when static).

    Raises:
        InputError: a key is missing or has another shape; one line naming the file and the shapes expected.
    """
    data = np.load(path)
    got = ", ".join(f"'{k}' {tuple(data[k].shape)}" for k in data.files)

    def refuse(why: str) -> InputError:
        return InputError(f"{path}: {why}; a camera file holds {CAMERA_SHAPES} (T = the video's frames, "
                          f"{frames}); this one has {got or 'nothing'}")

    if "K" not in data or data["K"].shape != (3, 3):
        raise refuse("'K' must be the (3, 3) intrinsics")
    K = data["K"].astype(np.float64)
    if "world_to_cam" in data:
        w2c = data["world_to_cam"].astype(np.float64)
        if w2c.shape == (4, 4):
            return Camera(K=K, world_to_cam=w2c, width=width, height=height).validate(), None
        if w2c.ndim != 3 or w2c.shape[1:] != (4, 4):
            raise refuse("'world_to_cam' must be (4, 4) or (T, 4, 4)")
        per_frame = _frames_of(w2c, frames, select, refuse)
    elif all(k in data for k in ("cam_pos", "cam_forward", "cam_up")):
        look = [data[k].astype(np.float64) for k in ("cam_pos", "cam_forward", "cam_up")]
        if any(a.shape not in ((3,),) and (a.ndim != 2 or a.shape[1] != 3) for a in look):
            raise refuse("'cam_pos', 'cam_forward', 'cam_up' must each be (3,) or (T, 3)")
        if all(a.shape == (3,) for a in look):
            return camera_from_look(K, look[0], look[1], look[2], width, height), None
        counts = {len(a) for a in look if a.ndim == 2}
        if len(counts) > 1:
            raise refuse("'cam_pos', 'cam_forward', 'cam_up' have different frame counts")
        n = counts.pop()
        if n < 1:
            raise refuse("its pose list is empty")
        look = [a if a.ndim == 2 else np.tile(a, (n, 1)) for a in look]
        w2c = np.stack([camera_from_look(K, p, f, u, width, height).world_to_cam for p, f, u in zip(*look)])
        per_frame = _frames_of(w2c, frames, select, refuse)
    else:
        raise refuse("it needs 'world_to_cam' or 'cam_pos', 'cam_forward', 'cam_up'")
    if not np.isfinite(per_frame).all():
        raise refuse("its poses hold NaN or inf")
    first = Camera(K=K, world_to_cam=per_frame[0], width=width, height=height).validate()
    return first, per_frame


def _frames_of(w2c: np.ndarray, frames: int | None, select: np.ndarray | None,
               refuse: Callable[[str], InputError]) -> np.ndarray:
    """The (T, 4, 4) poses of the clip's frames: all of ``w2c`` when it has ``frames`` poses, else the
    ``select``-ed ones of the video's whole pose list."""
    if frames is None or len(w2c) == frames:
        return w2c
    if select is not None and len(select) == frames and len(w2c) > int(np.max(select)):
        return w2c[select]
    raise refuse(f"it has {len(w2c)} poses but the clip has {frames} frames")
