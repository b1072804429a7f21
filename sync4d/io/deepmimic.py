"""DeepMimic motion clips: a URDF skeleton plus a JSON ``Frames`` array of joint rotations.

A clip (e.g. ``humanoid3d_walk.txt`` from DeepMimic, shipped with pybullet) is JSON with ``Frames``: one
row per frame, ``[duration, root position (3), root rotation (w, x, y, z), then one entry per movable
URDF joint in file order: a quaternion (w, x, y, z) for a spherical joint, an angle [rad] about the
joint axis for a revolute joint]``. Fixed joints take no values. Positions are in metres, Y up.

The skeleton comes from the URDF: each joint's origin (xyz, rpy) in its parent link's frame, times
``urdf_scale`` (pybullet loads DeepMimic's humanoid with ``globalScaling=0.25``). Links without child
joints (head, feet, hands) get an *end site* on the far side of their collision shape, so that the
body built around the skeleton has a head, feet and hands.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from sync4d.errors import InputError
from sync4d.geometry import quat_to_matrix, rotation_about_axis
from sync4d.io.mocap import SkeletonMotion

# pybullet's DeepMimic humanoid environment loads humanoid.urdf with globalScaling=0.25.
DEEPMIMIC_URDF_SCALE = 0.25
JOINT_WIDTH = {"spherical": 4, "revolute": 1, "continuous": 1, "prismatic": 1, "fixed": 0}


@dataclass(frozen=True)
class UrdfSkeleton:
    """A URDF kinematic tree as joints (root first, parents before children).

    Attributes:
        names: (J,) joint names; the root is the root link's name, end sites end in ``_end``.
        parents: (J,) parent joint index, -1 for the root.
        offsets: (J, 3) joint origin in the parent's frame [m] (already scaled).
        origin_rotations: (J, 3, 3) fixed rotation of the joint origin (URDF rpy).
        types: (J,) ``root``, ``spherical``, ``revolute``, ``prismatic``, ``fixed`` or ``end``.
        axes: (J, 3) unit joint axis (revolute/prismatic), zero otherwise.
    """

    names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    origin_rotations: np.ndarray
    types: tuple[str, ...]
    axes: np.ndarray

    @property
    def motion_width(self) -> int:
        """Values per frame row: duration + root position + root quaternion + the joints' values."""
        return 8 + sum(JOINT_WIDTH.get(t, 0) for t in self.types[1:] if t != "end")


def rpy_matrix(rpy: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of URDF roll-pitch-yaw (fixed axes X, then Y, then Z): Rz(y) Ry(p) Rx(r)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _floats(text: str | None, count: int, what: str, source: str) -> np.ndarray:
    try:
        values = np.array([float(v) for v in (text or "").split()], dtype=np.float64)
    except ValueError:
        values = np.zeros(0)
    if len(values) != count:
        raise InputError(f"{source}: {what} must have {count} numbers, got {text!r}")
    return values


def _end_site(link: ET.Element | None, incoming: np.ndarray, scale: float, source: str) -> np.ndarray | None:
    """Offset [m] of a leaf link's end site: the far side of its collision shape, or None without one.

    The direction is the collision shape's centre offset if it has one, else the incoming segment's
    direction (a hand sphere centred on the wrist); the distance is the shape's support along it.
    """
    collision = None if link is None else link.find("collision")
    if collision is None:
        return None
    origin = collision.find("origin")
    centre = np.zeros(3) if origin is None else _floats(origin.get("xyz", "0 0 0"), 3, "collision origin xyz", source)
    geometry = collision.find("geometry")
    shape = None if geometry is None or len(geometry) == 0 else geometry[0]
    direction = centre if np.linalg.norm(centre) > 1e-9 else incoming
    norm = np.linalg.norm(direction)
    if shape is None or norm < 1e-9:
        return None
    d = direction / norm
    if shape.tag == "sphere":
        support = float(shape.get("radius", "0"))
    elif shape.tag == "box":
        size = _floats(shape.get("size"), 3, "box size", source)
        rpy = np.zeros(3) if origin is None else _floats(origin.get("rpy", "0 0 0"), 3, "collision rpy", source)
        support = float(np.abs(rpy_matrix(rpy).T @ d) @ (size / 2))
    elif shape.tag in ("capsule", "cylinder"):
        # Axis along the shape's local z, turned by the collision rpy.
        rpy = np.zeros(3) if origin is None else _floats(origin.get("rpy", "0 0 0"), 3, "collision rpy", source)
        axis = rpy_matrix(rpy)[:, 2]
        half = float(shape.get("length", "0")) / 2
        radius = float(shape.get("radius", "0"))
        along = abs(float(axis @ d))
        support = half * along + radius * np.sqrt(max(0.0, 1 - along**2)) + (radius if shape.tag == "capsule" else 0.0) * along
    else:
        return None
    return scale * (centre + support * d)


class JointRow(NamedTuple):
    """One joint of a :class:`UrdfSkeleton` while the tree is being read (fields as there)."""

    name: str
    parent: int
    offset: np.ndarray
    rotation: np.ndarray
    kind: str
    axis: np.ndarray


def read_urdf_skeleton(path: str | Path, *, scale: float = DEEPMIMIC_URDF_SCALE) -> UrdfSkeleton:
    """The joint tree of a URDF, with end sites on leaf links (see module docstring).

    Args:
        path: the .urdf file.
        scale: metres per URDF unit.

    Raises:
        InputError: unreadable XML, a joint without parent/child, a link with two parents, or a cycle.
    """
    source = str(path)
    links, joints, base = parse_urdf_tree(path, source)
    rows = joints_in_motion_order(joints, base, scale, source)
    rows += end_site_rows(rows, links, scale, source)
    return UrdfSkeleton(
        names=tuple(r.name for r in rows), parents=np.asarray([r.parent for r in rows], dtype=np.int64),
        offsets=np.asarray([r.offset for r in rows]), origin_rotations=np.asarray([r.rotation for r in rows]),
        types=tuple(r.kind for r in rows), axes=np.asarray([r.axis for r in rows]),
    )


def parse_urdf_tree(path: str | Path, source: str) -> tuple[dict[str | None, ET.Element], list[ET.Element], str]:
    """The links by name, the joints in file order and the one root (base) link of a URDF file.

    Raises:
        InputError: unreadable XML, no joint, a joint without parent/child, a link with two parents, or not
            exactly one root link.
    """
    raw = Path(path).read_bytes().replace(b"\x00", b"")  # pybullet's humanoid.urdf ends in NUL padding
    try:
        root_el = ET.fromstring(raw.decode("utf-8", errors="replace"))
    except ET.ParseError as err:
        raise InputError(f"{source}: not valid URDF XML ({err})") from None
    links = {el.get("name"): el for el in root_el.findall("link")}
    joints = root_el.findall("joint")
    if not joints:
        raise InputError(f"{source}: the URDF has no <joint>")
    child_of: dict[str, ET.Element] = {}
    for j in joints:
        parent, child = j.find("parent"), j.find("child")
        if parent is None or child is None:
            raise InputError(f"{source}: joint {j.get('name')!r} lacks <parent> or <child>")
        if child.get("link") in child_of:
            raise InputError(f"{source}: link {child.get('link')!r} has two parent joints")
        child_of[str(child.get("link"))] = j
    roots = [name for name in links if name not in child_of]
    if len(roots) != 1:
        raise InputError(f"{source}: expected one root link, found {roots}")
    return links, joints, str(roots[0])


def joint_frame(j: ET.Element, source: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """A URDF joint's origin xyz (3,) and rpy (3,) [URDF units, rad], its raw axis (3,) and its type.

    Raises:
        InputError: a malformed number list or an unsupported joint type.
    """
    origin = j.find("origin")
    xyz = np.zeros(3) if origin is None else _floats(origin.get("xyz", "0 0 0"), 3, "joint origin xyz", source)
    rpy = np.zeros(3) if origin is None else _floats(origin.get("rpy", "0 0 0"), 3, "joint origin rpy", source)
    axis_el = j.find("axis")
    axis = np.array([1.0, 0.0, 0.0]) if axis_el is None else _floats(axis_el.get("xyz"), 3, "joint axis", source)
    kind = str(j.get("type"))
    if kind not in JOINT_WIDTH:
        raise InputError(f"{source}: joint {j.get('name')!r} has unsupported type {kind!r}")
    return xyz, rpy, axis, kind


def joints_in_motion_order(joints: list[ET.Element], base: str, scale: float, source: str) -> list[JointRow]:
    """The joints in file order (the order of the motion's values), each placed after its parent link's
    joint; the first joint hanging from the ``base`` link is the motion's root.

    Raises:
        InputError: several joints hang from the base link, or some joints are not connected to it.
    """
    rows: list[JointRow] = []
    index_of_link: dict[str, int] = {}
    pending = list(joints)
    while pending:
        placed = False
        for j in list(pending):
            parent_link = str(j.find("parent").get("link"))  # type: ignore[union-attr]
            child_link = str(j.find("child").get("link"))  # type: ignore[union-attr]
            if parent_link != base and parent_link not in index_of_link:
                continue
            xyz, rpy, axis, kind = joint_frame(j, source)
            if parent_link == base and not rows:
                # The first joint hanging from the base link is the root of the motion (root position
                # and rotation come from the clip), whatever its URDF type.
                kind = "root"
            elif parent_link == base:
                raise InputError(f"{source}: several joints hang from the base link {base!r}; expected one root")
            moving = kind in ("revolute", "continuous", "prismatic")
            rows.append(JointRow(
                name=child_link, parent=-1 if parent_link == base else index_of_link[parent_link],
                offset=scale * xyz, rotation=rpy_matrix(rpy), kind=kind,
                axis=axis / max(np.linalg.norm(axis), 1e-12) if moving else np.zeros(3),
            ))
            index_of_link[child_link] = len(rows) - 1
            pending.remove(j)
            placed = True
        if not placed:
            raise InputError(f"{source}: joints {[j.get('name') for j in pending]} are not connected to the root")
    return rows


def end_site_rows(rows: list[JointRow], links: dict[str | None, ET.Element], scale: float,
                  source: str) -> list[JointRow]:
    """The end sites of the leaf joints' links (:func:`_end_site`), indexed after ``rows``."""
    has_child = {r.parent for r in rows}
    ends: list[JointRow] = []
    for i, row in enumerate(rows):
        if i in has_child:
            continue
        end = _end_site(links.get(row.name), row.offset / max(scale, 1e-12), scale, source)
        if end is not None:
            ends.append(JointRow(f"{row.name}_end", i, end, np.eye(3), "end", np.zeros(3)))
    return ends


def parse_deepmimic_frames(text: str, *, source: str = "<clip>") -> np.ndarray:
    """(T, W) float64 rows of a DeepMimic clip's ``Frames`` (duration first).

    Raises:
        InputError: not JSON, no ``Frames``, ragged rows, non-finite values or non-positive durations.
    """
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        raise InputError(f"{source}: not a DeepMimic clip (JSON with 'Frames'): {err}") from None
    frames = data.get("Frames") if isinstance(data, dict) else None
    if not isinstance(frames, list) or not frames:
        raise InputError(f"{source}: no 'Frames' list; a DeepMimic clip is JSON {{\"Frames\": [[dt, ...], ...]}}")
    widths = {len(row) if isinstance(row, list) else -1 for row in frames}
    if len(widths) != 1 or -1 in widths:
        raise InputError(f"{source}: 'Frames' rows differ in length ({sorted(widths)}); every frame needs the same values")
    rows = np.asarray(frames, dtype=np.float64)
    if not np.isfinite(rows).all():
        raise InputError(f"{source}: 'Frames' holds NaN or inf")
    if (rows[:-1, 0] <= 0).any():
        raise InputError(f"{source}: frame durations (first value of each row) must be > 0")
    return rows


def deepmimic_forward_kinematics(skeleton: UrdfSkeleton, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World joint positions (T, J, 3) [m] and rotations (T, J, 3, 3) of every frame row.

    ``R_j = R_parent R_origin,j R_local,j`` and ``p_j = p_parent + R_parent offset_j``, with the root's
    position and rotation taken from the row.
    """
    num = len(rows)
    joints = len(skeleton.names)
    pos = np.zeros((num, joints, 3))
    rot = np.tile(np.eye(3), (num, joints, 1, 1))
    col = 8
    for j, kind in enumerate(skeleton.types):
        p = skeleton.parents[j]
        if kind == "root":
            pos[:, j] = rows[:, 1:4]
            rot[:, j] = quat_to_matrix(rows[:, 4:8])
            continue
        local = np.tile(np.eye(3), (num, 1, 1))
        shift = np.zeros((num, 3))
        if kind == "spherical":
            local = quat_to_matrix(rows[:, col : col + 4])
            col += 4
        elif kind in ("revolute", "continuous"):
            local = rotation_about_axis(skeleton.axes[j], rows[:, col])
            col += 1
        elif kind == "prismatic":
            shift = rows[:, col, None] * skeleton.axes[j]
            col += 1
        frame = rot[:, p] @ skeleton.origin_rotations[j]
        pos[:, j] = pos[:, p] + np.einsum("tij,j->ti", rot[:, p], skeleton.offsets[j]) + np.einsum("tij,tj->ti", frame, shift)
        rot[:, j] = frame @ local
    return pos, rot


def read_deepmimic(
    clip_path: str | Path, urdf_path: str | Path, *, urdf_scale: float = DEEPMIMIC_URDF_SCALE
) -> SkeletonMotion:
    """A DeepMimic clip as a :class:`SkeletonMotion` (Y up; fps from the first frame's duration).

    Raises:
        InputError: malformed clip or URDF, or a row width that does not fit the URDF's joints.
    """
    skeleton = read_urdf_skeleton(urdf_path, scale=urdf_scale)
    rows = parse_deepmimic_frames(Path(clip_path).read_text(errors="replace"), source=str(clip_path))
    if rows.shape[1] != skeleton.motion_width:
        raise InputError(
            f"{clip_path}: frames have {rows.shape[1]} values but {urdf_path} needs {skeleton.motion_width} "
            "(duration, root position, root quaternion, 4 per spherical and 1 per revolute joint); "
            "is this the clip's own URDF?"
        )
    positions, rotations = deepmimic_forward_kinematics(skeleton, rows)
    return SkeletonMotion(
        names=skeleton.names, parents=skeleton.parents, positions=positions, rotations=rotations,
        fps=1.0 / float(rows[0, 0]), up_axis=1, source=str(clip_path),
    )
