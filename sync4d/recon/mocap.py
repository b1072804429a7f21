"""``recon=mocap``: an articulated reference from motion capture (BVH or joint positions).

Bones are skeleton segments (bone centre = segment midpoint, Gaussian elongated along the segment),
optionally merged greedily into fewer bones; the reference body is a set of capsules around the rest
skeleton (:func:`sync4d.recon.body.capsule_body`); skinning is the softmax of the negative squared distance to
the segments in units of their radii (a Mahalanobis distance around each segment's line). Per-frame bone transforms are rigid: from
the joint rotations (BVH forward kinematics) or, for joint positions, from segment direction changes
(minimal rotation, twist carried from the parent; :func:`sync4d.io.mocap.rotations_from_positions`).
Root motion goes into G_t, articulation into J_{t,b}.

Data used in tests and evaluation (attribution): CMU Graphics Lab Motion Capture Database
(mocap.cs.cmu.edu; "The database was created with funding from NSF EIA-0196217"), via yuki-koyama/bvh11;
AI4Animation dog mocap via erwincoumans/motion_imitation (CC BY-NC 4.0); DeepMimic humanoid walk
clip and URDF (DeepMimic, MIT) from the pybullet 3.2.7 wheel's pybullet_data (zlib).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from sync4d.errors import ConfigError, DataMissingError, InputError
from sync4d.geometry import rigid_fit
from sync4d.io.mocap import (
    CMU_UNIT_SCALE,
    SkeletonMotion,
    read_bvh,
    read_joint_position_motion,
    minimal_rotation,
    rotations_from_positions,
)
from sync4d.io.deepmimic import read_deepmimic
from sync4d.recon import skinning as sk
from sync4d.recon.body import (
    capsule_body,
    segment_gaussians,
    segment_radii,
    segment_skinning,
    skeleton_segments,
)
from sync4d.registry import register
from sync4d.types import Reference, ReferenceInput

log = logging.getLogger(__name__)


def detect_motion_format(path: Path) -> Literal["bvh", "joint_positions", "deepmimic"]:
    """``bvh`` for .bvh, ``deepmimic`` for a JSON clip (first non-blank character '{'), else ``joint_positions``."""
    if path.suffix.lower() == ".bvh":
        return "bvh"
    with open(path, "rb") as fh:
        head = fh.read(256).lstrip()
    return "deepmimic" if head.startswith(b"{") else "joint_positions"


def clip_urdf(clip: Path, urdf: str) -> Path:
    """The URDF of a DeepMimic clip: ``urdf`` if given, else the only .urdf next to the clip."""
    if urdf:
        path = Path(urdf)
        if not path.is_file():
            raise DataMissingError(f"recon.urdf={urdf}: file not found")
        return path
    found = sorted(clip.parent.glob("*.urdf"))
    if len(found) != 1:
        raise ConfigError(
            f"recon.urdf: {clip.name} is a DeepMimic clip and its folder holds {len(found)} .urdf files; "
            "set recon.urdf=<the clip's skeleton .urdf>"
        )
    return found[0]


def relative_rotations(motion: SkeletonMotion, rest_frame: int) -> np.ndarray:
    """(T, J, 3, 3) joint rotations relative to the rest frame: R_t R_rest^T (or from positions)."""
    if motion.rotations is not None:
        return motion.rotations @ np.swapaxes(motion.rotations[rest_frame], -1, -2)[None]
    return rotations_from_positions(motion.positions, motion.parents, rest_frame=rest_frame)


def segment_transforms(
    positions: np.ndarray, rel_rot: np.ndarray, parents: np.ndarray, segments: np.ndarray, rest_frame: int,
    *, align_ends: bool = False,
) -> np.ndarray:
    """(T, S, 4, 4) world rigid motion rest -> t of each segment, carried by its parent joint's frame.

    A point x of segment (p -> j) moves as ``R_p(t) (x - P_p(rest)) + P_p(t)``; with ``align_ends``
    (joint-position data) R_p is corrected per segment so the segment's end lands on joint j.
    """
    p = np.asarray(parents)[segments]
    out = np.tile(np.eye(4), (positions.shape[0], len(segments), 1, 1))
    rot = rel_rot[:, p]
    if align_ends:
        # Joint rotations fitted to several children are a compromise; turn each segment by the
        # minimal extra rotation that puts its own end on the measured joint (twist still from the parent).
        rest_dir = positions[rest_frame, segments] - positions[rest_frame, p]
        carried = np.einsum("tsij,sj->tsi", rot, rest_dir)
        rot = minimal_rotation(carried, positions[:, segments] - positions[:, p]) @ rot
    out[..., :3, :3] = rot
    out[..., :3, 3] = positions[:, p] - np.einsum("tsij,sj->tsi", rot, positions[rest_frame, p])
    return out


def merge_segments(
    joint_positions: np.ndarray, parents: np.ndarray, segments: np.ndarray, bones: int
) -> np.ndarray:
    """Group skeleton segments into ``bones`` bones by greedily merging the shortest group into its parent.

    Args:
        joint_positions: (J, 3) rest joint positions [m].
        parents: (J,).
        segments: (S,) child joint per segment.
        bones: wanted number of groups, 1 <= bones <= S.

    Returns:
        (S,) int64 group label in [0, bones) per segment (labels ordered by first segment).
    """
    parents = np.asarray(parents)
    seg_of_joint = {int(j): i for i, j in enumerate(segments)}
    lengths = np.linalg.norm(joint_positions[segments] - joint_positions[parents[segments]], axis=1)

    def parent_segment(i: int) -> int:
        j = int(parents[segments[i]])
        while j >= 0:
            if j in seg_of_joint:
                return seg_of_joint[j]
            j = int(parents[j])
        return -1

    group = np.arange(len(segments))
    glen = {i: float(lengths[i]) for i in range(len(segments))}
    while len(glen) > bones:
        g = min(glen, key=lambda k: (glen[k], k))
        members = np.flatnonzero(group == g)
        # Merge into the group of the parent segment of the group's top member, else the nearest group.
        target = -1
        for m in members:
            ps = parent_segment(int(m))
            if ps >= 0 and group[ps] != g:
                target = int(group[ps])
                break
        if target < 0:
            mids = 0.5 * (joint_positions[segments] + joint_positions[parents[segments]])
            here = mids[members].mean(0)
            others = [k for k in glen if k != g]
            target = min(others, key=lambda k: np.linalg.norm(mids[group == k].mean(0) - here))
        group[members] = target
        glen[target] += glen.pop(g)
    _, labels = np.unique(group, return_inverse=True)
    return labels.astype(np.int64)


def heading_transform(rot: np.ndarray, up_axis: int) -> np.ndarray:
    """(T, 3, 3) rotation about the up axis matching the heading (yaw) of the given (T, 3, 3) rotations."""
    horiz = [a for a in range(3) if a != up_axis]
    fwd = np.zeros(3)
    fwd[horiz[0]] = 1.0
    turned = rot @ fwd
    angle = np.arctan2(turned[:, horiz[1]], turned[:, horiz[0]])
    c, s = np.cos(angle), np.sin(angle)
    out = np.tile(np.eye(3), (len(rot), 1, 1))
    a, b = horiz
    out[:, a, a], out[:, a, b], out[:, b, a], out[:, b, b] = c, -s, s, c
    return out


def root_travel(positions: np.ndarray, root: int, up_axis: int) -> tuple[float, float]:
    """(straight-line, path length) horizontal travel of the root joint over the clip [m]."""
    horiz = [a for a in range(3) if a != up_axis]
    path = positions[:, root][:, horiz]
    straight = float(np.linalg.norm(path[-1] - path[0]))
    along = float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())
    return straight, along


def bone_length_deviation(positions: np.ndarray, parents: np.ndarray) -> float:
    """Max over segments and frames of |length_t - length_0| [m] (0 for rigid-skeleton motion)."""
    child = np.flatnonzero(np.asarray(parents) >= 0)
    lengths = np.linalg.norm(positions[:, child] - positions[:, np.asarray(parents)[child]], axis=-1)
    return float(np.abs(lengths - lengths[:1]).max()) if len(child) else 0.0


def segment_group_parents(parents: np.ndarray, segments: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """(B,) parent bone of each bone (group of segments), -1 for a root bone.

    A bone's parent is the bone of the nearest kept segment above its top segment (skipped zero-length
    helper segments are walked through); segments hanging from the root joint have no parent bone.
    """
    parents = np.asarray(parents)
    seg_of_joint = {int(j): i for i, j in enumerate(segments)}
    n_bones = int(groups.max()) + 1
    out = np.full(n_bones, -1, dtype=np.int64)
    for i, j in enumerate(segments):
        a = int(parents[int(j)])
        while a >= 0 and a not in seg_of_joint:
            a = int(parents[a])
        if a >= 0 and groups[seg_of_joint[a]] != groups[i] and out[groups[i]] < 0:
            out[groups[i]] = groups[seg_of_joint[a]]
    return out


@register("recon", "mocap")
class MocapReconstructor:
    """Bones, capsule body and skinning from a BVH or joint-position file (``ReferenceInput.path``)."""

    @dataclass
    class Config:
        """``recon=mocap`` options.

        Attributes:
            bones: ``"skeleton"`` (one bone per segment) or an int B: segments merged greedily (shortest
                into its parent) down to B bones.
            format: ``auto`` (.bvh -> bvh; a JSON file -> deepmimic; else joint positions), ``bvh``,
                ``joint_positions`` or ``deepmimic`` (:mod:`sync4d.io.deepmimic`).
            urdf: the URDF skeleton of a DeepMimic clip; empty = the only .urdf in the clip's folder.
            urdf_scale: metres per URDF unit (pybullet loads DeepMimic's humanoid at 0.25).
            bvh_unit_scale: metres per BVH unit (CMU: 0.056444).
            joint_unit_scale: metres per unit of joint-position files.
            parents: parent table for joint-position files (-1 = root), or empty to infer it (MST).
            root: root joint for skeleton inference.
            target_fps: keep every round(fps / target_fps)-th frame; 0 keeps all frames [1/s].
            rest_frame: frame (after subsampling) whose pose is the rest pose of the body.
            global_motion: what goes into G_t: ``root`` (root joint's full rigid motion), ``heading``
                (root translation + yaw about the up axis) or ``none`` (all motion in J).
            radius_scale: capsule radius as a fraction of its segment length.
            min_radius: smallest capsule radius [m].
            min_segment_length: shorter segments are not bones [m] (e.g. BVH zero-offset helpers).
            along_factor: bone std-dev along its segment as a fraction of the segment length.
            skin_temperature: softness of the skinning blend, in squared capsule-radius units
                (:func:`sync4d.recon.body.segment_skinning`).
            capsule_rings: latitude rings per capsule hemisphere.
            capsule_sectors: longitude divisions per capsule.
            capsule_band: largest ring spacing along each capsule's cylinder [m], so the body has surface
                vertices along its limbs and not only at the joints (matching and features use the
                vertices); <= 0 = one band (vertices at the end caps only).
        """

        bones: Any = "skeleton"
        format: Literal["auto", "bvh", "joint_positions", "deepmimic"] = "auto"
        urdf: str = ""
        urdf_scale: float = 0.25
        bvh_unit_scale: float = CMU_UNIT_SCALE
        joint_unit_scale: float = 1.0
        parents: list[int] = field(default_factory=list)
        root: int = 0
        target_fps: float = 30.0
        rest_frame: int = 0
        global_motion: Literal["root", "heading", "none"] = "root"
        radius_scale: float = 0.18
        min_radius: float = 0.03
        min_segment_length: float = 1e-3
        along_factor: float = 0.5
        skin_temperature: float = 0.25
        capsule_rings: int = 4
        capsule_sectors: int = 10
        capsule_band: float = 0.03

        def validate(self) -> None:
            if isinstance(self.bones, str) and self.bones.strip().isdigit():
                self.bones = int(self.bones)
            if not (self.bones == "skeleton" or (isinstance(self.bones, int) and not isinstance(self.bones, bool)
                                                 and self.bones >= 1)):
                raise ConfigError(f"recon.bones={self.bones!r}: use 'skeleton' or a positive integer for recon=mocap")
            if self.urdf_scale <= 0:
                raise ConfigError(f"recon.urdf_scale={self.urdf_scale}: must be > 0 (metres per URDF unit)")
            if self.target_fps < 0:
                raise ConfigError(f"recon.target_fps={self.target_fps}: must be >= 0 (0 keeps every frame)")
            if self.radius_scale <= 0 and self.min_radius <= 0:
                raise ConfigError("recon.radius_scale and recon.min_radius: at least one must be > 0")

    def __init__(self, config: Config, *, device: str = "cpu") -> None:
        config.validate()
        self.config = config
        self.device = device
        self.last_fit_report: dict[str, Any] = {}
        self.last_motion: SkeletonMotion | None = None

    def load_motion(self, source: ReferenceInput) -> SkeletonMotion:
        """Read the skeleton motion named by ``source.path`` and subsample it to ``target_fps``."""
        if not source.path:
            raise InputError(
                f"recon=mocap needs a motion file, but reference '{source.name}' has no path; "
                "use reference=bvh or reference=joint_positions"
            )
        path = Path(source.path)
        if not path.is_file():
            raise DataMissingError(f"motion file not found: {path}")
        fmt = self.config.format
        if fmt == "auto":
            fmt = detect_motion_format(path)
        if fmt == "bvh":
            motion = read_bvh(path, unit_scale=self.config.bvh_unit_scale)
        elif fmt == "deepmimic":
            motion = read_deepmimic(path, clip_urdf(path, self.config.urdf), urdf_scale=self.config.urdf_scale)
        else:
            motion = read_joint_position_motion(
                path, fps=source.fps, unit_scale=self.config.joint_unit_scale, root=self.config.root,
                parents=np.asarray(self.config.parents) if self.config.parents else None,
            )
        if self.config.target_fps > 0:
            step = max(1, int(round(motion.fps / self.config.target_fps)))
            motion = motion.subsample(step)
        if not 0 <= self.config.rest_frame < motion.num_frames:
            raise ConfigError(f"recon.rest_frame={self.config.rest_frame}: the motion has {motion.num_frames} frames")
        return motion

    def reconstruct(self, source: ReferenceInput) -> Reference:
        """Build the reference from the mocap file of ``source`` (validated)."""
        motion = self.load_motion(source)
        self.last_motion = motion
        return self.from_motion(motion, name=source.name)

    def from_motion(self, motion: SkeletonMotion, *, name: str = "mocap") -> Reference:
        """Build the reference from an already-read :class:`SkeletonMotion`."""
        config = self.config
        r = config.rest_frame
        pos = motion.positions
        parents = motion.parents
        rest_joints = pos[r]
        segments = skeleton_segments(rest_joints, parents, min_length=config.min_segment_length)
        if len(segments) == 0:
            raise InputError(f"{motion.source}: the skeleton has no segment longer than {config.min_segment_length} m")
        n_seg = len(segments)
        if config.bones == "skeleton":
            groups = np.arange(n_seg)
        else:
            if config.bones > n_seg:
                raise ConfigError(f"recon.bones={config.bones}: the skeleton has only {n_seg} segments")
            groups = merge_segments(rest_joints, parents, segments, int(config.bones))
        n_bones = int(groups.max()) + 1

        rel = relative_rotations(motion, r)
        seg_world = segment_transforms(pos, rel, parents, segments, r, align_ends=motion.rotations is None)  # (T, S, 4, 4)

        radii = segment_radii(rest_joints, parents, segments, config.radius_scale, min_radius=config.min_radius)
        full_radii = np.zeros(len(parents))
        full_radii[segments] = radii
        verts, faces, owner_joint = capsule_body(
            rest_joints, parents, radii=full_radii, min_radius=config.min_radius, min_length=config.min_segment_length,
            rings=config.capsule_rings, sectors=config.capsule_sectors, band_spacing=config.capsule_band,
        )
        seg_index = {int(j): i for i, j in enumerate(segments)}
        owner_seg = np.array([seg_index[int(j)] for j in owner_joint])
        owner_bone = groups[owner_seg]

        seg_centers, seg_covs = segment_gaussians(rest_joints, parents, segments, radii, along_factor=config.along_factor)
        centers, covs, bone_world, names = merged_bones(
            motion, segments, groups, seg_centers, seg_covs, seg_world, verts, owner_bone, r
        )
        bone_parents = segment_group_parents(parents, segments, groups)
        weights = segment_skinning(
            verts, rest_joints, parents, segments, radii, groups, temperature=config.skin_temperature
        )

        glob = self.global_transforms(pos, rel, parents, r, motion.up_axis)
        bones_local = np.einsum("tij,tbjk->tbik", sk.rigid_inverse(glob), bone_world)

        straight, along = root_travel(pos, int(np.flatnonzero(parents < 0)[0]), motion.up_axis)
        posed_joints_err = self._joint_check(pos, parents, segments, groups, bone_world, r)
        self.last_fit_report = {
            "bones": n_bones,
            "segments": n_seg,
            "frames": int(pos.shape[0]),
            "fps": motion.fps,
            "bone_length_max_dev": bone_length_deviation(pos, parents),
            "root_travel_m": straight,
            "root_path_m": along,
            "joint_error_m": posed_joints_err,
        }
        log.info("mocap %s: %s", Path(motion.source).name, self.last_fit_report)
        return Reference(
            rest_vertices=verts,
            rest_faces=faces,
            bone_centers=centers,
            bone_covariances=covs,
            skinning=weights,
            bone_transforms=bones_local,
            global_transforms=glob,
            fps=float(motion.fps),
            bone_names=tuple(names),
            name=name,
            bone_parents=bone_parents,
        ).validate()

    def global_transforms(
        self, pos: np.ndarray, rel: np.ndarray, parents: np.ndarray, rest_frame: int, up_axis: int
    ) -> np.ndarray:
        """(T, 4, 4) G_t per ``global_motion``; G at the rest frame is the identity."""
        n_frames = pos.shape[0]
        glob = np.tile(np.eye(4), (n_frames, 1, 1))
        if self.config.global_motion == "none":
            return glob
        root = int(np.flatnonzero(np.asarray(parents) < 0)[0])
        rot = rel[:, root] if self.config.global_motion == "root" else heading_transform(rel[:, root], up_axis)
        glob[:, :3, :3] = rot
        glob[:, :3, 3] = pos[:, root] - rot @ pos[rest_frame, root]
        return glob

    @staticmethod
    def _joint_check(
        pos: np.ndarray, parents: np.ndarray, segments: np.ndarray, groups: np.ndarray, bone_world: np.ndarray,
        rest_frame: int,
    ) -> float:
        """Max distance [m] between each segment's child joint carried by its bone and the mocap joint."""
        per_seg = bone_world[:, groups]
        carried = np.einsum("tsij,sj->tsi", per_seg[..., :3, :3], pos[rest_frame, segments])
        carried += per_seg[..., :3, 3]
        return float(np.linalg.norm(carried - pos[:, segments], axis=-1).max())


def merged_bones(
    motion: SkeletonMotion, segments: np.ndarray, groups: np.ndarray, seg_centers: np.ndarray, seg_covs: np.ndarray,
    seg_world: np.ndarray, verts: np.ndarray, owner_bone: np.ndarray, rest_frame: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Bone centres (B, 3), covariances (B, 3, 3), world motion (T, B, 4, 4) and names of the segment groups: a
    one-segment bone keeps its segment's Gaussian and motion; a merged bone takes the Gaussian of its body
    vertices and moves rigidly with the best fit of its member joints."""
    pos, parents = motion.positions, motion.parents
    n_bones = int(groups.max()) + 1
    centers = np.zeros((n_bones, 3))
    covs = np.zeros((n_bones, 3, 3))
    bone_world = np.tile(np.eye(4), (pos.shape[0], n_bones, 1, 1))
    names = []
    for b in range(n_bones):
        members = np.flatnonzero(groups == b)
        top = members[0]  # segments are in joint order, so the first member is nearest the root
        names.append(motion.names[int(segments[top])])
        if len(members) == 1:
            centers[b], covs[b] = seg_centers[top], seg_covs[top]
            bone_world[:, b] = seg_world[:, top]
        else:
            pts = verts[owner_bone == b]
            centers[b] = pts.mean(0)
            covs[b] = np.cov(pts.T) + 1e-8 * np.eye(3)
            js = np.unique(np.concatenate([segments[members], parents[segments[members]]]))
            bone_world[:, b] = rigid_fit(np.broadcast_to(pos[rest_frame, js], pos[:, js].shape), pos[:, js])
    return centers, covs, bone_world, names
