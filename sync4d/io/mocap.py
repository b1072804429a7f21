"""Motion-capture readers: BVH with forward kinematics, and joint-position text files.

Both produce a :class:`SkeletonMotion`: joint world positions and rotations per frame plus a parent
table, which :mod:`sync4d.recon.mocap` turns into bones, a capsule body and skinning.

Data this was written against (keep the attribution where the files are used):
    * ``motion/cmu_bvh/131_01.bvh``: CMU Graphics Lab Motion Capture Database (mocap.cs.cmu.edu), via
      ``yuki-koyama/bvh11``. "The data used in this project was obtained from mocap.cs.cmu.edu. The
      database was created with funding from NSF EIA-0196217." CMU units: x 0.0564 = metres.
    * ``motion/dog_mocap/dog_trot_joint_pos.txt``: AI4Animation (MANN) dog mocap via
      ``erwincoumans/motion_imitation``, CC BY-NC 4.0 (non-commercial, attribute).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree
from scipy.spatial.transform import Rotation

from sync4d.errors import DataMissingError, InputError

CMU_UNIT_SCALE = 0.056444  # CMU BVH length unit in metres (1 / (0.45 * 39.37), mocap.cs.cmu.edu FAQ)


@dataclass(frozen=True)
class SkeletonMotion:
    """Joint motion of a skeleton.

    Attributes:
        names: (J,) joint names.
        parents: (J,) int64 parent index, -1 for the root (parents precede children).
        positions: (T, J, 3) joint world positions [m].
        rotations: (T, J, 3, 3) joint world rotations, or None when only positions are known.
        fps: frames per second [1/s].
        up_axis: index of the vertical axis (1 = Y-up, 2 = Z-up).
        source: the file read.
    """

    names: tuple[str, ...]
    parents: np.ndarray
    positions: np.ndarray
    rotations: np.ndarray | None
    fps: float
    up_axis: int = 1
    source: str = ""

    @property
    def num_frames(self) -> int:
        return int(self.positions.shape[0])

    def subsample(self, step: int) -> SkeletonMotion:
        """Every ``step``-th frame (fps divided by ``step``)."""
        if step <= 1:
            return self
        return SkeletonMotion(
            self.names, self.parents, self.positions[::step],
            None if self.rotations is None else self.rotations[::step], self.fps / step, self.up_axis, self.source,
        )


# --------------------------------------------------------------------------------------------------
# BVH
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BVHSkeleton:
    """The HIERARCHY part of a BVH file.

    Attributes:
        names: joint names; end sites are named ``<parent>_End``.
        parents: (J,) parent index, -1 for the root.
        offsets: (J, 3) offset from the parent [file units].
        channels: per joint, the channel names in file order (empty for end sites).
    """

    names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    channels: tuple[tuple[str, ...], ...]


def parse_bvh(text: str, *, source: str = "<bvh>") -> tuple[BVHSkeleton, np.ndarray, float]:
    """Parse BVH text.

    Args:
        text: the file contents.
        source: name used in error messages.

    Returns:
        (skeleton, motion (T, C) channel values in file order [file units, degrees], frame time [s]).

    Raises:
        InputError: malformed hierarchy or motion section.
    """
    tokens = text.split()
    if not tokens or tokens[0] != "HIERARCHY":
        raise InputError(f"{source}: not a BVH file (must start with HIERARCHY)")
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: list[tuple[str, ...]] = []
    stack: list[int] = []
    i = 1
    pending: int | None = None
    try:
        while i < len(tokens) and tokens[i] != "MOTION":
            tok = tokens[i]
            if tok in ("ROOT", "JOINT"):
                name = tokens[i + 1]
                i += 2
                pending = len(names)
                names.append(name)
                parents.append(stack[-1] if stack else -1)
                offsets.append([0.0, 0.0, 0.0])
                channels.append(())
            elif tok == "End":  # "End Site"
                i += 2
                pending = len(names)
                names.append(f"{names[stack[-1]]}_End")
                parents.append(stack[-1])
                offsets.append([0.0, 0.0, 0.0])
                channels.append(())
            elif tok == "{":
                if pending is None:
                    raise InputError(f"{source}: '{{' without a joint")
                stack.append(pending)
                pending = None
                i += 1
            elif tok == "}":
                stack.pop()
                i += 1
            elif tok == "OFFSET":
                offsets[stack[-1]] = [float(x) for x in tokens[i + 1 : i + 4]]
                i += 4
            elif tok == "CHANNELS":
                n = int(tokens[i + 1])
                channels[stack[-1]] = tuple(tokens[i + 2 : i + 2 + n])
                i += 2 + n
            else:
                raise InputError(f"{source}: unexpected token '{tok}' in HIERARCHY")
        if i >= len(tokens):
            raise InputError(f"{source}: no MOTION section")
        if tokens[i + 1] != "Frames:" or tokens[i + 3] != "Frame" or tokens[i + 4] != "Time:":
            raise InputError(f"{source}: MOTION must be followed by 'Frames: N' and 'Frame Time: dt'")
        n_frames = int(tokens[i + 2])
        frame_time = float(tokens[i + 5])
        values = np.asarray(tokens[i + 6 :], dtype=np.float64)
    except (IndexError, ValueError) as err:
        raise InputError(f"{source}: malformed BVH ({err})") from None
    n_channels = sum(len(c) for c in channels)
    if n_frames < 1 or values.size != n_frames * n_channels:
        raise InputError(
            f"{source}: MOTION holds {values.size} numbers, expected Frames ({n_frames}) x channels ({n_channels})"
        )
    if frame_time <= 0:
        raise InputError(f"{source}: Frame Time must be > 0, got {frame_time}")
    skel = BVHSkeleton(tuple(names), np.asarray(parents, dtype=np.int64), np.asarray(offsets), tuple(channels))
    return skel, values.reshape(n_frames, n_channels), frame_time


def bvh_forward_kinematics(
    skeleton: BVHSkeleton, motion: np.ndarray, *, unit_scale: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """Forward kinematics of every frame.

    Rotation channels compose in the order listed (``Zrotation Yrotation Xrotation`` means
    ``R = Rz Ry Rx``, intrinsic); position channels add to the joint's offset.

    Args:
        skeleton: the hierarchy.
        motion: (T, C) channel values [file units, degrees].
        unit_scale: metres per file unit.

    Returns:
        (positions (T, J, 3) [m], rotations (T, J, 3, 3) world rotations).
    """
    n_frames = motion.shape[0]
    n_joints = len(skeleton.names)
    pos = np.zeros((n_frames, n_joints, 3))
    rot = np.zeros((n_frames, n_joints, 3, 3))
    col = 0
    for j in range(n_joints):
        chans = skeleton.channels[j]
        values = motion[:, col : col + len(chans)]
        col += len(chans)
        local_t = np.broadcast_to(skeleton.offsets[j], (n_frames, 3)).copy()
        axes = ""
        angles = []
        for k, ch in enumerate(chans):
            kind, axis = ch[1:], ch[0].upper()
            if kind == "position":
                local_t[:, "XYZ".index(axis)] += values[:, k]
            elif kind == "rotation":
                axes += axis
                angles.append(values[:, k])
            else:
                raise InputError(f"BVH channel '{ch}' of joint {skeleton.names[j]} is not a position/rotation")
        local_r = (
            Rotation.from_euler(axes, np.stack(angles, 1), degrees=True).as_matrix()
            if axes
            else np.tile(np.eye(3), (n_frames, 1, 1))
        )
        local_t *= unit_scale
        p = skeleton.parents[j]
        if p < 0:
            rot[:, j] = local_r
            pos[:, j] = local_t
        else:
            rot[:, j] = rot[:, p] @ local_r
            pos[:, j] = pos[:, p] + np.einsum("tij,tj->ti", rot[:, p], local_t)
    return pos, rot


def read_bvh(path: str | Path, *, unit_scale: float = CMU_UNIT_SCALE) -> SkeletonMotion:
    """Read a BVH file and run forward kinematics (Y-up assumed, as BVH files are).

    Args:
        path: the .bvh file.
        unit_scale: metres per file unit (CMU files: 0.0564).

    Raises:
        DataMissingError: the file does not exist.
        InputError: the file is malformed.
    """
    path = Path(path)
    if not path.is_file():
        raise DataMissingError(f"BVH file not found: {path}")
    skel, motion, frame_time = parse_bvh(path.read_text(errors="replace"), source=str(path))
    pos, rot = bvh_forward_kinematics(skel, motion, unit_scale=unit_scale)
    return SkeletonMotion(skel.names, skel.parents, pos, rot, 1.0 / frame_time, 1, str(path))


# --------------------------------------------------------------------------------------------------
# Joint positions
# --------------------------------------------------------------------------------------------------


def read_joint_positions(path: str | Path, *, num_joints: int | None = None) -> np.ndarray:
    """Read a text file with one frame per line of ``x y z`` per joint (commas and/or whitespace).

    Args:
        path: the text file.
        num_joints: expected joints per frame, or None to accept any multiple of 3.

    Returns:
        (T, J, 3) positions [file units].

    Raises:
        DataMissingError: the file does not exist.
        InputError: ragged rows or a row length not divisible by 3 (or not 3 * num_joints).
    """
    path = Path(path)
    if not path.is_file():
        raise DataMissingError(f"joint-position file not found: {path}")
    rows = []
    for n, line in enumerate(path.read_text().splitlines()):
        parts = [p for p in line.replace(",", " ").split() if p]
        if not parts:
            continue
        try:
            rows.append([float(p) for p in parts])
        except ValueError:
            raise InputError(f"{path}:{n + 1}: not a list of numbers") from None
    if not rows:
        raise InputError(f"{path}: no frames")
    widths = {len(r) for r in rows}
    if len(widths) != 1:
        raise InputError(f"{path}: rows have different lengths {sorted(widths)}")
    width = widths.pop()
    if width % 3 or (num_joints is not None and width != 3 * num_joints):
        want = f"3 x {num_joints}" if num_joints else "a multiple of 3"
        raise InputError(f"{path}: {width} numbers per frame, expected {want}")
    arr = np.asarray(rows, dtype=np.float64).reshape(len(rows), -1, 3)
    if not np.isfinite(arr).all():
        raise InputError(f"{path}: NaN/inf in the joint positions")
    return arr


def infer_skeleton(positions: np.ndarray, *, root: int = 0, std_weight: float = 5.0) -> np.ndarray:
    """Infer a parent table from joint trajectories by a minimum spanning tree.

    Edge cost = mean distance + ``std_weight`` x its standard deviation over frames: joints joined by a
    bone keep a constant distance, so the variation term rejects short but non-rigid pairs (e.g. two
    feet passing each other). Coincident joints (zero distance) are joined to each other.

    Args:
        positions: (T, J, 3) joint positions [m].
        root: the root joint.
        std_weight: weight of the distance variation.

    Returns:
        (J,) int64 parents, -1 at ``root``; each joint's parent precedes it in a breadth-first order
        from ``root`` but indices are the file's.
    """
    n_joints = positions.shape[1]
    dist = np.linalg.norm(positions[:, :, None] - positions[:, None], axis=-1)  # (T, J, J)
    cost = dist.mean(0) + std_weight * dist.std(0)
    # csgraph treats 0 as "no edge": keep coincident joints connected with a tiny positive cost.
    cost = np.where(np.eye(n_joints, dtype=bool), 0.0, np.maximum(cost, 1e-9))
    tree = minimum_spanning_tree(cost)
    sym = tree + tree.T
    _, preds = breadth_first_order(sym, root, directed=False, return_predecessors=True)
    parents = np.where(preds < 0, -1, preds).astype(np.int64)
    parents[root] = -1
    if (parents < 0).sum() != 1:
        raise InputError("infer_skeleton: the joints do not form one connected tree")
    return parents


def topological_order(parents: np.ndarray) -> np.ndarray:
    """(J,) joint indices ordered so that every parent comes before its children."""
    order: list[int] = []
    children: dict[int, list[int]] = {}
    for j, p in enumerate(parents):
        children.setdefault(int(p), []).append(j)
    queue = list(children.get(-1, []))
    while queue:
        j = queue.pop(0)
        order.append(j)
        queue.extend(children.get(j, []))
    if len(order) != len(parents):
        raise InputError("parent table has a cycle or dangling index")
    return np.asarray(order, dtype=np.int64)


def read_joint_position_motion(
    path: str | Path, *, fps: float, unit_scale: float = 1.0, root: int = 0, parents: np.ndarray | None = None,
    up_axis: int = 1,
) -> SkeletonMotion:
    """Read joint-position mocap and attach a skeleton (given, or inferred by :func:`infer_skeleton`).

    Args:
        path: text file, one frame per line.
        fps: frames per second of the file [1/s] (the format does not store it).
        unit_scale: metres per file unit.
        root: root joint index (used when inferring).
        parents: (J,) parent table, or None to infer one.
        up_axis: vertical axis of the data.
    """
    pos = read_joint_positions(path) * unit_scale
    if parents is None:
        parents = infer_skeleton(pos, root=root)
    else:
        parents = np.asarray(parents, dtype=np.int64)
        if parents.shape != (pos.shape[1],):
            raise InputError(f"{path}: parent table has {len(parents)} entries for {pos.shape[1]} joints")
    names = tuple(f"joint{j}" for j in range(pos.shape[1]))
    return SkeletonMotion(names, parents, pos, None, float(fps), up_axis, str(path))


# --------------------------------------------------------------------------------------------------
# Rotations from positions
# --------------------------------------------------------------------------------------------------


def minimal_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(..., 3, 3) the smallest rotation taking direction ``a`` onto direction ``b`` (both (..., 3)).

    Antiparallel inputs rotate by pi about an axis perpendicular to ``a``.
    """
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    v = np.cross(a, b)
    c = (a * b).sum(-1)
    s2 = (v * v).sum(-1)
    k = np.zeros(a.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    k[..., 1, 0], k[..., 2, 0], k[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    factor = np.where(s2 > 1e-12, (1 - c) / np.maximum(s2, 1e-12), 0.5)
    out = np.eye(3) + k + (k @ k) * factor[..., None, None]
    # Antiparallel: rotate by pi about any axis perpendicular to a.
    anti = (c < -1 + 1e-9) & (s2 <= 1e-12)
    if np.any(anti):
        helper = np.where(np.abs(a[..., :1]) < 0.9, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
        axis = np.cross(a, helper)
        axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
        flip = 2 * axis[..., :, None] * axis[..., None, :] - np.eye(3)
        out = np.where(anti[..., None, None], flip, out)
    return out


def rotations_from_positions(positions: np.ndarray, parents: np.ndarray, *, rest_frame: int = 0) -> np.ndarray:
    """Per-joint world rotations (relative to the rest frame) from joint positions alone.

    The root's rotation is the Kabsch fit of its neighbourhood (root, children, grandchildren). Every
    other joint with one child turns by the minimal rotation taking its parent-carried rest direction
    onto its current direction, composed with its parent's rotation: the twist about the segment is
    inherited from the parent (parallel transport), which keeps it consistent over time. A joint with
    several children is Kabsch-fitted to them, with the parent's rotation as the fallback; a leaf keeps
    its parent's rotation.

    Args:
        positions: (T, J, 3) joint positions [m].
        parents: (J,) parent table.
        rest_frame: frame whose pose has identity rotations.

    Returns:
        (T, J, 3, 3) rotations mapping rest-frame directions to frame t.
    """
    from sync4d.geometry import rigid_fit

    n_frames, n_joints, _ = positions.shape
    parents = np.asarray(parents)
    children = [np.flatnonzero(parents == j) for j in range(n_joints)]
    rot = np.tile(np.eye(3), (n_frames, n_joints, 1, 1))
    rest = positions[rest_frame]

    def moving(j: int) -> np.ndarray:
        """Children of j at a distance; a coincident child (zero-length helper) is looked through."""
        out: list[int] = []
        for c in children[j]:
            if np.linalg.norm(rest[c] - rest[j]) > 1e-6:
                out.append(int(c))
            else:
                out.extend(int(g) for g in moving(int(c)))
        return np.asarray(out, dtype=np.int64)

    for j in topological_order(parents):
        kids = moving(j)
        p = parents[j]
        base = rot[:, p] if p >= 0 else np.tile(np.eye(3), (n_frames, 1, 1))
        if p < 0 or len(kids) >= 2:
            group = list(kids) + [g for k in kids for g in moving(int(k))] if p < 0 else list(kids)
            if len(group) >= 2:
                # The joint itself is one of the points: with two children, centring two points alone
                # would leave the rotation about their line undetermined.
                group = [j] + group
                src = rest[group] - rest[j]
                dst = positions[:, group] - positions[:, j : j + 1]
                rot[:, j] = rigid_fit(np.broadcast_to(src, dst.shape), dst)[..., :3, :3]
                continue
        if len(kids) == 1:
            c = int(kids[0])
            carried = np.einsum("tij,j->ti", base, rest[c] - rest[j])
            now = positions[:, c] - positions[:, j]
            rot[:, j] = minimal_rotation(carried, now) @ base
        else:
            rot[:, j] = base
    return rot
