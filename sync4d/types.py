"""Typed objects passed between pipeline stages.

All arrays are NumPy arrays in SI units (metres, seconds, kilograms, pascals). Every class is a frozen
dataclass with ``validate()``, which checks shapes, dtypes and finiteness and raises
:class:`~sync4d.errors.InputError` naming the field, the expected and the actual shape.

Conventions:
    * Rigid transforms are (4, 4) homogeneous matrices acting on column vectors: ``x' = T @ [x, 1]``.
    * Quaternions are (w, x, y, z), unit length.
    * Frames are indexed ``t = 0 .. T-1``; bone transforms map the rest (canonical) pose to frame t.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sync4d.geometry import SH_C0, gaussian_covariances

from sync4d.errors import InputError

Dim = int | str  # a fixed size, or a symbol bound to the first size seen for it


def check_array(
    owner: str,
    name: str,
    value: Any,
    shape: tuple[Dim, ...],
    dims: dict[str, int],
    *,
    kind: str = "f",
    finite: bool = True,
) -> None:
    """Check one array field; symbols in ``shape`` must agree across fields through ``dims``.

    Args:
        owner: class name used in messages.
        name: field name used in messages.
        value: the array.
        shape: expected shape, ints or symbol names (e.g. ``("N", 3)``).
        dims: symbol bindings shared by the fields of one object (updated in place).
        kind: NumPy dtype kind expected: ``"f"`` float, ``"i"`` integer (signed or unsigned), ``"b"`` bool,
            ``"u8"`` uint8.
        finite: reject NaN/inf (floats only).
    """
    where = f"{owner}.{name}"
    if not isinstance(value, np.ndarray):
        raise InputError(f"{where}: expected a numpy array of shape {_fmt(shape)}, got {type(value).__name__}")
    if value.ndim != len(shape):
        raise InputError(f"{where}: expected shape {_fmt(shape)}, got {value.shape}")
    for axis, (want, got) in enumerate(zip(shape, value.shape)):
        if isinstance(want, str):
            bound = dims.setdefault(want, got)
            if bound != got:
                raise InputError(
                    f"{where}: expected shape {_fmt(shape)} with {want}={bound} (from other fields), got {value.shape}"
                )
        elif want != got:
            raise InputError(f"{where}: expected shape {_fmt(shape)}, got {value.shape} (axis {axis})")
    dtype_ok = {
        "f": value.dtype.kind == "f",
        "i": value.dtype.kind in "iu",
        "b": value.dtype.kind == "b",
        "u8": value.dtype == np.uint8,
    }[kind]
    if not dtype_ok:
        raise InputError(f"{where}: expected dtype kind '{kind}', got {value.dtype}")
    if finite and value.dtype.kind == "f" and value.size and not np.isfinite(value).all():
        bad = int((~np.isfinite(value)).sum())
        raise InputError(f"{where}: contains {bad} NaN/inf value(s); clean the input or regenerate it")


def _fmt(shape: tuple[Dim, ...]) -> str:
    return "(" + ", ".join(str(s) for s in shape) + ")"


def _require(cond: bool, message: str) -> None:
    if not cond:
        raise InputError(message)


@dataclass(frozen=True)
class VideoClip:
    """A reference video with foreground masks.

    Attributes:
        frames: (T, H, W, 3) uint8 RGB.
        masks: (T, H, W) bool, True on the object.
        fps: frames per second [1/s].
        intrinsics: (3, 3) pinhole K in pixels, or None if unknown.
        extrinsics: (T, 4, 4) world-to-camera per frame, or None (static camera assumed).
        source: where the clip came from (for logs).
    """

    frames: np.ndarray
    masks: np.ndarray
    fps: float
    intrinsics: np.ndarray | None = None
    extrinsics: np.ndarray | None = None
    source: str = ""

    @property
    def num_frames(self) -> int:
        return int(self.frames.shape[0])

    def validate(self) -> VideoClip:
        dims: dict[str, int] = {}
        check_array("VideoClip", "frames", self.frames, ("T", "H", "W", 3), dims, kind="u8")
        check_array("VideoClip", "masks", self.masks, ("T", "H", "W"), dims, kind="b")
        _require(dims["T"] > 0, f"VideoClip.frames: the video '{self.source}' has no frames")
        _require(np.isfinite(self.fps) and self.fps > 0, f"VideoClip.fps: must be > 0, got {self.fps}")
        if self.intrinsics is not None:
            check_array("VideoClip", "intrinsics", self.intrinsics, (3, 3), dims)
        if self.extrinsics is not None:
            check_array("VideoClip", "extrinsics", self.extrinsics, ("T", 4, 4), dims)
        return self


@dataclass(frozen=True)
class Reference:
    """A reconstructed (or given) articulated reference: rest shape, Gaussian bones, skinning, motion.

    A rest point x* moves to frame t as ``x_t = G_t @ sum_b W_b(x*) J_{t,b} @ x*`` (linear blend skinning,
    then the global transform).

    Attributes:
        rest_vertices: (V, 3) canonical surface vertices [m].
        rest_faces: (F, 3) int triangle indices into rest_vertices, or None for a point set.
        bone_centers: (B, 3) canonical bone centres B* [m].
        bone_covariances: (B, 3, 3) Gaussian bone shapes (covariance) [m^2], symmetric positive definite.
        skinning: (V, B) blend-skinning weights of rest_vertices, rows sum to 1.
        bone_transforms: (T, B, 4, 4) J_{t,b}, rest -> frame t in the object frame (before G_t).
        global_transforms: (T, 4, 4) G_t, object frame -> world at frame t.
        fps: frames per second of the motion [1/s].
        vertex_colors: (V, 3) float RGB in [0, 1], or None.
        bone_names: optional names of the bones (e.g. skeleton joints).
        name: a label for logs and pictures.
        bone_parents: (B,) int parent bone of each bone (-1 for roots) when the bones form a known tree
            (mocap skeletons), or None; structure-aware matching uses it to find the limbs.
    """

    rest_vertices: np.ndarray
    rest_faces: np.ndarray | None
    bone_centers: np.ndarray
    bone_covariances: np.ndarray
    skinning: np.ndarray
    bone_transforms: np.ndarray
    global_transforms: np.ndarray
    fps: float
    vertex_colors: np.ndarray | None = None
    bone_names: tuple[str, ...] | None = None
    name: str = "reference"
    bone_parents: np.ndarray | None = None

    @property
    def num_bones(self) -> int:
        return int(self.bone_centers.shape[0])

    @property
    def num_frames(self) -> int:
        return int(self.bone_transforms.shape[0])

    def validate(self) -> Reference:
        dims: dict[str, int] = {}
        check_array("Reference", "rest_vertices", self.rest_vertices, ("V", 3), dims)
        if self.rest_faces is not None:
            check_array("Reference", "rest_faces", self.rest_faces, ("F", 3), dims, kind="i")
            if self.rest_faces.size:
                _require(
                    0 <= int(self.rest_faces.min()) and int(self.rest_faces.max()) < dims["V"],
                    f"Reference.rest_faces: indices must lie in [0, {dims['V']}), got "
                    f"[{self.rest_faces.min()}, {self.rest_faces.max()}]",
                )
        check_array("Reference", "bone_centers", self.bone_centers, ("B", 3), dims)
        check_array("Reference", "bone_covariances", self.bone_covariances, ("B", 3, 3), dims)
        check_array("Reference", "skinning", self.skinning, ("V", "B"), dims)
        check_array("Reference", "bone_transforms", self.bone_transforms, ("T", "B", 4, 4), dims)
        check_array("Reference", "global_transforms", self.global_transforms, ("T", 4, 4), dims)
        _require(dims["V"] > 0, "Reference.rest_vertices: needs at least one vertex")
        _require(dims["B"] > 0, "Reference.bone_centers: needs at least one bone (recon.bones >= 1)")
        _require(dims["T"] > 0, "Reference.bone_transforms: needs at least one frame")
        row_sums = self.skinning.sum(axis=1)
        _require(
            bool(np.all(self.skinning >= -1e-6)) and np.allclose(row_sums, 1.0, atol=1e-4),
            f"Reference.skinning: rows must be non-negative and sum to 1 (sums in [{row_sums.min():.4g}, "
            f"{row_sums.max():.4g}])",
        )
        eig = np.linalg.eigvalsh(0.5 * (self.bone_covariances + np.swapaxes(self.bone_covariances, 1, 2)))
        _require(bool(np.all(eig > 0)), "Reference.bone_covariances: every bone covariance must be positive definite")
        _require(np.isfinite(self.fps) and self.fps > 0, f"Reference.fps: must be > 0, got {self.fps}")
        if self.vertex_colors is not None:
            check_array("Reference", "vertex_colors", self.vertex_colors, ("V", 3), dims)
        if self.bone_names is not None:
            _require(len(self.bone_names) == dims["B"], "Reference.bone_names: one name per bone expected")
        if self.bone_parents is not None:
            check_array("Reference", "bone_parents", self.bone_parents, ("B",), dims, kind="i")
            _require(bool(np.all((self.bone_parents >= -1) & (self.bone_parents < dims["B"]))),
                     "Reference.bone_parents: entries must be -1 or a bone index")
        return self

    def bone_centers_at(self) -> np.ndarray:
        """(T, B, 3) bone centres b_t = J_{t,b} B*_b in the object frame (before G_t) [m]."""
        homo = np.concatenate([self.bone_centers, np.ones((self.num_bones, 1))], axis=1)
        return np.einsum("tbij,bj->tbi", self.bone_transforms, homo)[..., :3]

    def posed_vertices(self, t: int, *, apply_global: bool = False) -> np.ndarray:
        """(V, 3) rest vertices posed at frame t by linear blend skinning [m]."""
        blended = np.einsum("vb,bij->vij", self.skinning, self.bone_transforms[t])
        homo = np.concatenate([self.rest_vertices, np.ones((len(self.rest_vertices), 1))], axis=1)
        posed = np.einsum("vij,vj->vi", blended, homo)
        if apply_global:
            posed = posed @ self.global_transforms[t].T
        return posed[:, :3]

    def part_labels(self) -> np.ndarray:
        """(V,) int part of each rest vertex: argmax of its skinning weights (paper Sec. 3.3)."""
        return np.argmax(self.skinning, axis=1).astype(np.int64)


@dataclass(frozen=True)
class TargetGaussians:
    """A static 3D Gaussian object, in the Inria 3DGS parameterisation.

    Attributes:
        means: (N, 3) centres [m].
        quats: (N, 4) unit rotations, (w, x, y, z).
        log_scales: (N, 3) natural log of the per-axis standard deviations [log m].
        opacity_logits: (N,) logit of opacity.
        sh: (N, K, 3) spherical-harmonic colour coefficients, K = (degree + 1)^2 in {1, 4, 9, 16};
            sh[:, 0] is the DC term (``f_dc``).
        normals: (N, 3) or None; carried through files, unused by the method.
        name: a label for logs.
    """

    means: np.ndarray
    quats: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    sh: np.ndarray
    normals: np.ndarray | None = None
    name: str = "target"

    @property
    def num(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return int(round(np.sqrt(self.sh.shape[1]))) - 1

    @property
    def scales(self) -> np.ndarray:
        """(N, 3) per-axis standard deviations [m]."""
        return np.exp(self.log_scales.astype(np.float64))

    @property
    def opacities(self) -> np.ndarray:
        """(N,) opacity in (0, 1)."""
        return 1.0 / (1.0 + np.exp(-self.opacity_logits.astype(np.float64)))

    def covariances(self) -> np.ndarray:
        """(N, 3, 3) world covariances R S S R^T [m^2]."""
        return gaussian_covariances(self.scales, self.quats)

    def colors(self) -> np.ndarray:
        """(N, 3) view-independent RGB in [0, 1] from the DC term."""
        return np.clip(0.5 + SH_C0 * self.sh[:, 0, :], 0.0, 1.0)

    def replace(self, **changes: Any) -> TargetGaussians:
        return dataclasses.replace(self, **changes)

    def subset(self, index: np.ndarray) -> TargetGaussians:
        """A new object holding the Gaussians selected by ``index`` (bool mask or integer indices)."""
        return self.replace(
            means=self.means[index],
            quats=self.quats[index],
            log_scales=self.log_scales[index],
            opacity_logits=self.opacity_logits[index],
            sh=self.sh[index],
            normals=None if self.normals is None else self.normals[index],
        )

    def validate(self) -> TargetGaussians:
        dims: dict[str, int] = {}
        check_array("TargetGaussians", "means", self.means, ("N", 3), dims)
        check_array("TargetGaussians", "quats", self.quats, ("N", 4), dims)
        check_array("TargetGaussians", "log_scales", self.log_scales, ("N", 3), dims)
        check_array("TargetGaussians", "opacity_logits", self.opacity_logits, ("N",), dims)
        check_array("TargetGaussians", "sh", self.sh, ("N", "K", 3), dims)
        if self.normals is not None:
            check_array("TargetGaussians", "normals", self.normals, ("N", 3), dims)
        _require(dims["N"] > 0, f"TargetGaussians.means: '{self.name}' has zero Gaussians")
        _require(
            dims["K"] in (1, 4, 9, 16),
            f"TargetGaussians.sh: expected K in (1, 4, 9, 16) coefficients (SH degree 0-3), got {dims['K']}",
        )
        norms = np.linalg.norm(self.quats, axis=1)
        _require(bool(np.all(norms > 1e-8)), "TargetGaussians.quats: zero-length quaternion(s)")
        return self


@dataclass(frozen=True)
class PartMap:
    """Correspondence between reference parts and the target's Gaussians.

    Attributes:
        ref_part: (V,) int part of each reference vertex, in [0, B).
        tgt_part: (N,) int part of each target Gaussian, in [0, B).
        confidence: (N,) float in [0, 1]: cosine-similarity margin of the assignment (0 for orphans).
        num_parts: B.
        alignment_rotation: (3, 3) rotation matching used to turn the target into the reference's frame
            (its transpose turns the reference's motion into the target's), or None when not recorded.
    """

    ref_part: np.ndarray
    tgt_part: np.ndarray
    confidence: np.ndarray
    num_parts: int
    alignment_rotation: np.ndarray | None = None

    def validate(self) -> PartMap:
        dims: dict[str, int] = {}
        check_array("PartMap", "ref_part", self.ref_part, ("V",), dims, kind="i")
        check_array("PartMap", "tgt_part", self.tgt_part, ("N",), dims, kind="i")
        check_array("PartMap", "confidence", self.confidence, ("N",), dims)
        if self.alignment_rotation is not None:
            check_array("PartMap", "alignment_rotation", self.alignment_rotation, (3, 3), dims)
        for name in ("ref_part", "tgt_part"):
            arr = getattr(self, name)
            _require(
                arr.size == 0 or (arr.min() >= 0 and arr.max() < self.num_parts),
                f"PartMap.{name}: labels must lie in [0, {self.num_parts})",
            )
        return self


@dataclass(frozen=True)
class DrivingMotion:
    """Reference part motion expressed in the target's space, ready to drive the simulation.

    Attributes:
        part_transforms: (T, B, 4, 4) rigid motion of each part, rest -> frame t, in target space
            (bone transforms conjugated by the reference->target similarity, translations scaled).
        part_displacements: (T-1, B, 3) scaled reference displacement of each part's bone centre
            between consecutive frames, (s_t / s_o) (b_{t+1} - b_t) [m].
        global_transforms: (T, 4, 4) G_t in target space, applied to the output after simulation.
        coverage_ratio: s_t / s_o, the target's size over the reference's (dimensionless).
        fps: frames per second [1/s].
        part_parent: (B,) the part each part is joined to by the drive (-1 for a root), or None when the
            parts are driven independently (``pivot`` other than ``joint``).
    """

    part_transforms: np.ndarray
    part_displacements: np.ndarray
    global_transforms: np.ndarray
    coverage_ratio: float
    fps: float
    part_parent: np.ndarray | None = None

    @property
    def num_frames(self) -> int:
        return int(self.part_transforms.shape[0])

    def validate(self) -> DrivingMotion:
        dims: dict[str, int] = {}
        check_array("DrivingMotion", "part_transforms", self.part_transforms, ("T", "B", 4, 4), dims)
        check_array("DrivingMotion", "global_transforms", self.global_transforms, ("T", 4, 4), dims)
        _require(
            self.part_displacements.shape == (max(dims["T"] - 1, 0), dims["B"], 3),
            f"DrivingMotion.part_displacements: expected ({dims['T'] - 1}, {dims['B']}, 3), "
            f"got {self.part_displacements.shape}",
        )
        _require(
            np.isfinite(self.coverage_ratio) and self.coverage_ratio > 0,
            f"DrivingMotion.coverage_ratio: must be > 0, got {self.coverage_ratio}",
        )
        _require(
            self.part_parent is None or (self.part_parent.shape == (dims["B"],)
                                         and bool(np.all(self.part_parent < dims["B"]))),
            f"DrivingMotion.part_parent: expected ({dims['B']},) parts or -1",
        )
        return self


def validate_material(E: float, nu: float, density: float, *, where: str = "sim") -> None:
    """Refuse physically meaningless materials before any kernel runs.

    Raises:
        ConfigError: E <= 0, nu outside [0, 0.5), or density <= 0, naming the key and the fix.
    """
    from sync4d.errors import ConfigError

    if not (np.isfinite(E) and E > 0):
        raise ConfigError(f"{where}.E={E}: Young's modulus must be > 0 Pa (the paper uses 1e3..1e5)")
    if not (np.isfinite(nu) and 0.0 <= nu < 0.5):
        raise ConfigError(
            f"{where}.nu={nu}: Poisson's ratio must be in [0, 0.5); nu=0.5 makes lambda infinite (use <= 0.49)"
        )
    if not (np.isfinite(density) and density > 0):
        raise ConfigError(f"{where}.density={density}: density must be > 0 kg/m^3")


@dataclass(frozen=True)
class Trajectory:
    """Simulated motion of the target, one entry per output frame.

    Attributes:
        x: (T, P, 3) particle positions per frame [m] (before the global transform).
        frame_dt: time between output frames [s].
        F: (T, P, 3, 3) deformation gradients, or None.
        v: (T, P, 3) velocities [m/s], or None.
        global_transforms: (T, 4, 4) G_t applied for output, or None (identity).
        extras: free-form per-run arrays (e.g. per-frame losses) kept with the trajectory.
    """

    x: np.ndarray
    frame_dt: float
    F: np.ndarray | None = None
    v: np.ndarray | None = None
    global_transforms: np.ndarray | None = None
    extras: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return int(self.x.shape[0])

    def validate(self) -> Trajectory:
        dims: dict[str, int] = {}
        check_array("Trajectory", "x", self.x, ("T", "P", 3), dims)
        if self.F is not None:
            check_array("Trajectory", "F", self.F, ("T", "P", 3, 3), dims)
        if self.v is not None:
            check_array("Trajectory", "v", self.v, ("T", "P", 3), dims)
        if self.global_transforms is not None:
            check_array("Trajectory", "global_transforms", self.global_transforms, ("T", 4, 4), dims)
        _require(self.frame_dt > 0, f"Trajectory.frame_dt: must be > 0, got {self.frame_dt}")
        return self


@dataclass(frozen=True)
class Camera:
    """A pinhole camera.

    Attributes:
        K: (3, 3) intrinsics in pixels (fx, fy on the diagonal, principal point cx, cy).
        world_to_cam: (4, 4) extrinsics in OpenCV convention (x right, y down, z forward) [m].
        width: image width [px].
        height: image height [px].
    """

    K: np.ndarray
    world_to_cam: np.ndarray
    width: int
    height: int

    def validate(self) -> Camera:
        dims: dict[str, int] = {}
        check_array("Camera", "K", self.K, (3, 3), dims)
        check_array("Camera", "world_to_cam", self.world_to_cam, (4, 4), dims)
        _require(self.width > 0 and self.height > 0, f"Camera: image size must be positive, got {self.width}x{self.height}")
        return self


@dataclass(frozen=True)
class ReferenceInput:
    """What a ``reference`` source hands to a reconstructor; any subset of the fields may be present.

    Attributes:
        name: a label for logs.
        video: the reference video, if any.
        camera: the camera of ``video`` if known.
        mesh_sequence: (T, V, 3) posed vertices with fixed topology [m], if any.
        faces: (F, 3) faces of ``mesh_sequence``, if any.
        path: a file or folder the reconstructor reads itself (BVH, Lab4D export), if any.
        ground_truth: the exact articulated reference when the source is synthetic, else None.
        fps: frames per second [1/s].
        world_up: (3,) unit up direction of the world frame of ``camera``, when the source knows it (a
            scene it filmed itself), else None.
    """

    name: str
    fps: float
    video: VideoClip | None = None
    camera: Camera | None = None
    mesh_sequence: np.ndarray | None = None
    faces: np.ndarray | None = None
    path: str | None = None
    ground_truth: Reference | None = None
    world_up: np.ndarray | None = None


@dataclass(frozen=True)
class FramePose:
    """The driving motion over one frame pair, in the target's frame: what a simulator may follow.

    Attributes:
        start: (B, 4, 4) each part's rest -> frame t transform.
        end: (B, 4, 4) each part's rest -> frame t+1 transform.
    """

    start: np.ndarray
    end: np.ndarray

    @property
    def num_parts(self) -> int:
        return int(self.start.shape[0])

    def validate(self) -> FramePose:
        dims: dict[str, int] = {}
        check_array("FramePose", "start", self.start, ("B", 4, 4), dims)
        check_array("FramePose", "end", self.end, ("B", 4, 4), dims)
        return self


@dataclass(frozen=True)
class FloaterReport:
    """What floater removal did (logged and written to the run's metrics).

    Attributes:
        total: Gaussians given.
        removed_far: removed by the distance test.
        removed_sparse: removed by the density test.
        removed_clusters: removed as small disconnected pieces.
        cell: voxel side of the density and connectivity tests [m].
        kept_box: (2, 3) bounding box of the kept centres [m] (the robust extent).
        removed_box: (2, 3) bounding box of the removed centres [m], or None when none was removed.
    """

    total: int
    removed_far: int
    removed_sparse: int
    removed_clusters: int
    cell: float
    kept_box: np.ndarray
    removed_box: np.ndarray | None

    @property
    def removed(self) -> int:
        return self.removed_far + self.removed_sparse + self.removed_clusters

    def as_dict(self) -> dict[str, object]:
        """JSON-ready summary."""
        return {
            "total": self.total, "removed": self.removed, "removed_far": self.removed_far,
            "removed_sparse": self.removed_sparse, "removed_clusters": self.removed_clusters, "cell_m": self.cell,
            "kept_box_m": self.kept_box.tolist(),
            "removed_box_m": None if self.removed_box is None else self.removed_box.tolist(),
        }  # fmt: skip
