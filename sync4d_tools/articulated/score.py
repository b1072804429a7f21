"""Scores of an articulated reconstruction against a case's exact truth: every joint as a line, and labels.

Per gt joint (the part it moves is matched to the bone that renders most of it):
    * ``kind``: the fit's joint kind for that bone (``hinge``, ``slide``; ``none`` when no bone renders
      the part or the bone is the base) against the truth's;
    * ``axis_deg``: the angle between the recovered and the true axis (hinge) or direction (slide),
      either sign; a hinge read with no rotation has no axis (90);
    * ``pivot_pct`` (hinges): the distance from the true hinge line's point nearest the part (its frame-0
      visible surface's centroid projected on the line) to the recovered hinge line, in % of the object's
      size (its frame-0 visible surface's bounding-box diagonal); the recovered line is first scaled about
      the camera centre by the one scale a single view cannot see (gt / recovered mean camera depth of the
      part's frame-0 surface);
    * ``motion``: mean |recovered - true| joint value over the frames, signed about the true axis [deg], or
      along it, scaled as above, in % of the travel's range (slides);
    * ``pass``: right kind, axis <= 3 deg, pivot <= 3 % (hinges), motion <= 3 deg or 3 %.

The recovered joint is read from the reference's bone motion (rest = frame 0) relative to the base bone,
so any method's output is scored the same way.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from sync4d.types import Camera
from sync4d_tools.articulated.truth import CaseTruth

BAR = 3.0  # degrees, % of the object's size, % of travel


def hinge_line(rel: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(unit axis (3,), a point on it (3,) [m], signed angle per frame (T,) [rad]) of rigid motions rel
    (T, 4, 4) since frame 0 about one line (least squares over the frames turned more than 2 deg)."""
    rotvec = Rotation.from_matrix(rel[:, :3, :3]).as_rotvec()
    angle = np.linalg.norm(rotvec, axis=1)
    if angle.max() < 1e-6:
        return np.zeros(3), np.zeros(3), np.zeros(len(rel))
    ref = rotvec[np.argmax(angle)] / angle.max()
    axis = (rotvec * np.sign(rotvec @ ref)[:, None]).sum(0)
    axis /= np.linalg.norm(axis)
    use = angle > np.radians(2.0)
    if not use.any():
        use = angle >= angle.max()
    lhs = np.concatenate([np.eye(3) - rel[t, :3, :3] for t in np.flatnonzero(use)])
    rhs = np.concatenate([rel[t, :3, 3] for t in np.flatnonzero(use)])
    point = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    return axis, point, rotvec @ axis


def line_distance(point: np.ndarray, origin: np.ndarray, direction: np.ndarray) -> float:
    """Distance [m] of ``point`` from the line through ``origin`` along the unit ``direction``."""
    d = point - origin
    return float(np.linalg.norm(d - (d @ direction) * direction))


def axis_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle [deg] between two lines' directions, either sign (90 when ``a`` is zero)."""
    na = np.linalg.norm(a)
    if na < 1e-12:
        return 90.0
    return float(np.degrees(np.arccos(np.clip(abs(a @ b) / na / np.linalg.norm(b), 0.0, 1.0))))


def joint_row(rel: np.ndarray, found: str, j: int, truth: CaseTruth, camera: Camera, part_points: np.ndarray) -> dict[str, Any]:
    """The scores of gt joint ``j`` given the recovered motion ``rel`` (T, 4, 4) of the bone that carries its
    part, relative to the base since frame 0, the fit's kind for that bone and the bone's frame-0 surface
    points (M, 3) [m]."""
    kind, true_axis, value = truth.kinds[j], truth.axes[j], truth.values[:, j]
    centre = np.linalg.inv(camera.world_to_cam)[:3, 3]
    depth = part_points @ camera.world_to_cam[2, :3] + camera.world_to_cam[2, 3]
    scale = truth.part_depth(camera, j + 2) / float(depth.mean()) if len(part_points) else 1.0
    row: dict[str, Any] = {"joint": kind, "found": found, "scale": round(scale, 3)}
    if kind == "hinge":
        axis, point, angle = hinge_line(rel)
        flip = -1.0 if axis @ true_axis < 0 else 1.0
        row["axis_deg"] = axis_angle_deg(axis, true_axis)
        anchor = truth.pivots[j] + ((truth.points(camera, j + 2).mean(0) - truth.pivots[j]) @ true_axis) * true_axis
        scaled = centre + scale * (point - centre)
        row["pivot_pct"] = (100.0 * line_distance(anchor, scaled, axis) / truth.size(camera)
                            if np.linalg.norm(axis) > 0 else float("inf"))
        row["motion"] = float(np.degrees(np.abs(flip * angle - value).mean()))
    else:
        centroid = part_points.mean(0) if len(part_points) else np.zeros(3)
        disp = np.einsum("tij,j->ti", rel[:, :3, :3], centroid) + rel[:, :3, 3] - centroid
        direction = np.linalg.svd(disp, full_matrices=False)[2][0] if np.abs(disp).max() > 1e-12 else np.zeros(3)
        direction = direction * (-1.0 if direction @ true_axis < 0 else 1.0)
        row["axis_deg"] = axis_angle_deg(direction, true_axis)
        row["pivot_pct"] = None
        row["motion"] = float(np.abs(scale * disp @ direction - value).mean() / max(float(np.ptp(value)), 1e-9) * 100.0)
    row["pass"] = joint_passes(row)
    return row


def joint_passes(row: dict[str, Any]) -> bool:
    """Right kind, axis <= 3 deg, pivot <= 3 % of the size (hinges), motion <= 3 deg or 3 % of travel."""
    pivot_ok = row["pivot_pct"] is None or row["pivot_pct"] <= BAR
    return bool(row["found"] == row["joint"] and row["axis_deg"] <= BAR and pivot_ok and row["motion"] <= BAR)


def missing_row(j: int, truth: CaseTruth) -> dict[str, Any]:
    """A gt joint with no recovered joint (no bone for its part, or the static floor): the true motion is the
    error."""
    value = truth.values[:, j]
    hinge = truth.kinds[j] == "hinge"
    motion = float(np.degrees(np.abs(value).mean())) if hinge else float(np.abs(value).mean() / max(float(np.ptp(value)), 1e-9) * 100)
    return {"joint": truth.kinds[j], "found": "none", "axis_deg": 90.0, "pivot_pct": float("inf") if hinge else None,
            "motion": motion, "pass": False, "scale": None}


def label_scores(correct: list[np.ndarray], seen: np.ndarray, labels: np.ndarray) -> dict[str, float]:
    """Agreement over all gt object pixels, over those showing surface frame 0 sees and over the revealed
    rest; ``correct`` per frame (M_t,) bool in the order of ``np.nonzero(labels[t] > 0)``."""
    flags = np.concatenate(correct) if correct else np.zeros(0, bool)
    first = np.concatenate([seen[t][labels[t] > 0] for t in range(len(correct))]) if correct else np.zeros(0, bool)
    return {"all": round(float(flags.mean()) if len(flags) else 0.0, 4),
            "first": round(float(flags[first].mean()) if first.any() else float("nan"), 4),
            "revealed": round(float(flags[~first].mean()) if (~first).any() else float("nan"), 4)}


def constant_labels(labels: np.ndarray, seen: np.ndarray) -> dict[str, float]:
    """The floor of the labels: every pixel given the part that covers most object pixels over the clip."""
    part = int(np.argmax(np.bincount(labels[labels > 0])))
    return label_scores([labels[t][labels[t] > 0] == part for t in range(len(labels))], seen, labels)
