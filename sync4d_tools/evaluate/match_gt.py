"""``python -m sync4d.evaluate match_gt``: part matching on pairs whose answer is known.

Three ground-truth pairs (accuracy = fraction of target points whose part, as the pipeline assigns it
to the target's Gaussians through the part boxes, equals the true part):

* ``accuracy_self_copy``: the human capsule body (CMU BVH skeleton, 13 parts) against a copy of itself
  resampled as a new point set (area-uniform surface samples, so no vertex is shared), rescaled x1.7,
  rotated by a random rotation and jittered with Gaussian noise of 0.5% of its bounding-box diagonal.
* ``accuracy_laptop_proportions``: the default laptop (0.34 x 0.24 m, lid at 110 deg) against a laptop
  of other proportions (0.28 x 0.21 m, thicker base, thinner lid, lid at 100 deg), given as its mesh,
  also rotated and translated.
* ``accuracy_mocap_bodies``: two capsule bodies on the same CMU skeleton with different proportions:
  longer legs and neck, shorter arms, stockier torso, thinner limbs.

With ``--cross-category DIR`` (or ``--labels FILE``) also the labelled pairs of
:mod:`sync4d_tools.match_labels`: per pair the accuracy over every label (the trunk included), the limb
accuracy, the floors (best constant assignment, uniformly random assignment) and the chance-corrected
accuracy, printed as a table and a picture per pair written into DIR; the seed samples the target's
Gaussians on its surface and turns and stretches it.

The last line printed is one JSON object with the three accuracies (and details under ``details``).
``--figures DIR`` writes a picture per within-category pair.

Data: CMU Graphics Lab Motion Capture Database (mocap.cs.cmu.edu; "The database was created with
funding from NSF EIA-0196217"); dog mocap from AI4Animation (CC BY-NC 4.0) via motion_imitation;
meshes from odedstein/meshes (see ``../shared/data/targets/meshes/README_*.md``).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
from scipy.spatial.transform import Rotation

from sync4d.errors import DataMissingError, InputError
from sync4d.match import METHODS, MatchConfig, MatchResult, match_parts
from sync4d.registry import build
from sync4d.surface import area_points
from sync4d.types import Reference, TargetGaussians
from sync4d_tools.evaluate import dotlist, mapping

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[2]
SHARED_DATA = Path(os.environ.get("SYNC4D_SHARED_DATA", ROOT.parent / "shared" / "data"))
BVH_PATH = "motion/cmu_bvh/131_01.bvh"
DOG_PATH = "motion/dog_mocap/dog_trot_joint_pos.txt"

# 13 parts of the CMU skeleton (the paper's minimal human setting, B = 13). Each part lists the
# segments it owns, a segment being named by its child joint (parent -> child).
HUMAN_PARTS: dict[str, tuple[str, ...]] = {
    "pelvis": ("LeftHip", "RightHip", "Chest"),
    "chest": ("Chest2", "LeftShoulder", "RightShoulder"),
    "head": ("Neck", "Head", "Head_End"),
    "l_upper_arm": ("LeftElbow",),
    "l_forearm_hand": ("LeftWrist", "LFingers", "LFingers_End", "LThumb_End"),
    "r_upper_arm": ("RightElbow",),
    "r_forearm_hand": ("RightWrist", "RFingers", "RFingers_End", "RThumb_End"),
    "l_thigh": ("LeftKnee",),
    "l_shin": ("LeftAnkle",),
    "l_foot": ("LeftToe", "LeftToe_End"),
    "r_thigh": ("RightKnee",),
    "r_shin": ("RightAnkle",),
    "r_foot": ("RightToe", "RightToe_End"),
}
# Capsule radius [m] of each part's segments for body A (an adult of average build).
HUMAN_RADII: dict[str, float] = {
    "pelvis": 0.09, "chest": 0.10, "head": 0.085, "l_upper_arm": 0.045, "l_forearm_hand": 0.035,
    "r_upper_arm": 0.045, "r_forearm_hand": 0.035, "l_thigh": 0.07, "l_shin": 0.05, "l_foot": 0.035,
    "r_thigh": 0.07, "r_shin": 0.05, "r_foot": 0.035,
}
# Body B: segment length and radius factors per part (same skeleton, other proportions).
HUMAN_B_LENGTH = {"pelvis": 1.1, "chest": 1.15, "head": 1.2, "l_upper_arm": 0.85, "l_forearm_hand": 0.85,
                  "r_upper_arm": 0.85, "r_forearm_hand": 0.85, "l_thigh": 1.15, "l_shin": 1.15, "l_foot": 1.0,
                  "r_thigh": 1.15, "r_shin": 1.15, "r_foot": 1.0}
HUMAN_B_RADIUS = {"pelvis": 1.3, "chest": 1.25, "head": 1.1, "l_upper_arm": 0.8, "l_forearm_hand": 0.8,
                  "r_upper_arm": 0.8, "r_forearm_hand": 0.8, "l_thigh": 0.85, "l_shin": 0.85, "l_foot": 1.0,
                  "r_thigh": 0.85, "r_shin": 0.85, "r_foot": 1.0}

# 11 parts of the dog skeleton inferred from the joint trajectories (segments named by child joint index;
# the file documents pelvis 0, neck 3, hips 6/16/11/20 and toes 10/19/15/23, the rest is read off the
# positions: 24-26 run backwards and down from the pelvis, a tail).
DOG_PARTS: dict[str, tuple[int, ...]] = {
    "torso": (1, 2, 11, 24),
    "head_neck": (3, 4, 5),
    "leg_a_upper": (6, 7), "leg_a_lower": (8, 9, 10),
    "leg_b_upper": (12, 13), "leg_b_lower": (14, 15),
    "leg_c_upper": (16, 17), "leg_c_lower": (18, 19),
    "leg_d_upper": (20, 21), "leg_d_lower": (22, 23),
    "tail": (25, 26),
}
# The MANN dog skeleton's parent table (as conf/recon/mocap_dog.yaml: constant segment lengths on the clip).
DOG_PARENTS = (-1, 0, 1, 2, 3, 4, 2, 6, 7, 8, 9, 2, 11, 12, 13, 14, 0, 16, 17, 18, 0, 20, 21, 22, 0, 24, 25)
DOG_RADII = {"torso": 0.09, "head_neck": 0.05, "tail": 0.02}
DOG_LEG_RADIUS = 0.028


@dataclass(frozen=True)
class Body:
    """A capsule body with ground-truth parts.

    Attributes:
        vertices: (V, 3) [m]; faces: (F, 3); part: (V,) part index per vertex; names: part names;
        part_parents: (P,) parent part of each part in the skeleton (-1 for the root part), or None.
    """

    vertices: np.ndarray
    faces: np.ndarray
    part: np.ndarray
    names: tuple[str, ...]
    part_parents: np.ndarray | None = None


def data_path(relative: str) -> Path:
    path = SHARED_DATA / relative
    if not path.exists():
        raise DataMissingError(f"{path} not found: match_gt needs ../shared/data (set SYNC4D_SHARED_DATA)")
    return path


def segment_to_part(segment_names: list[str], groups: dict[str, tuple[Any, ...]]) -> np.ndarray:
    """(J,) part index per joint (segment named by child joint), -1 for joints in no group."""
    lookup = {member: i for i, members in enumerate(groups.values()) for member in members}
    return np.array([lookup.get(n, -1) for n in segment_names], dtype=np.int64)


def rescale_skeleton(joints: np.ndarray, parents: np.ndarray, factor: np.ndarray) -> np.ndarray:
    """(J, 3) joints with every segment parent -> j scaled by ``factor[j]``, children carried along."""
    out = joints.copy()
    from sync4d.io.mocap import topological_order

    for j in topological_order(parents):
        p = parents[j]
        if p >= 0:
            out[j] = out[p] + factor[j] * (joints[j] - joints[p])
    return out


def grouped_body(
    joints: np.ndarray,
    parents: np.ndarray,
    joint_part: np.ndarray,
    part_radius: np.ndarray,
    names: tuple[str, ...],
    *,
    rings: int = 6,
    sectors: int = 12,
    max_edge: float = 0.05,
) -> Body:
    """Capsule body (``sync4d.recon.body.capsule_body``) whose vertices carry the part of their segment.

    The capsules have vertices only on their end caps (the cylinder is one band of long triangles), so
    the mesh is subdivided to edges of at most ``max_edge`` [m]: the vertices then cover the surface
    evenly, as the per-part mean features of the paper assume. Faces buried inside another capsule are
    removed, leaving (approximately) the outer surface of the union.
    """
    import trimesh

    from sync4d.recon.body import capsule_body, skeleton_segments

    radii = np.where(joint_part >= 0, part_radius[np.maximum(joint_part, 0)], 0.01)
    vertices, faces, segment = capsule_body(joints, parents, radii=radii, min_length=1e-3, rings=rings, sectors=sectors)
    face_segment = segment[faces[:, 0]]
    if (joint_part[face_segment] < 0).any():
        missing = sorted({int(s) for s in face_segment[joint_part[face_segment] < 0]})
        raise ValueError(f"grouped_body: segments {missing} belong to no part")
    vertices, faces, index = trimesh.remesh.subdivide_to_size(vertices, faces, max_edge=max_edge, return_index=True)
    vertices, faces = np.asarray(vertices), np.asarray(faces, dtype=np.int64)
    vertex_segment = np.zeros(len(vertices), dtype=np.int64)
    vertex_segment[faces.reshape(-1)] = np.repeat(face_segment[index], 3)  # capsules share no vertex
    # Keep the outer surface of the union: capsule skin buried inside a neighbouring capsule is not
    # surface of a body (and its part would be ambiguous ground truth).
    segs = skeleton_segments(joints, parents, min_length=1e-3)
    buried = np.zeros(len(vertices), dtype=bool)
    for j in segs:
        a, b = joints[parents[j]], joints[j]
        t = np.clip((vertices - a) @ (b - a) / max(float((b - a) @ (b - a)), 1e-12), 0.0, 1.0)
        dist = np.linalg.norm(vertices - (a + t[:, None] * (b - a)), axis=1)
        buried |= (dist < 0.98 * radii[j]) & (vertex_segment != j)
    keep_face = ~buried[faces].any(axis=1)
    used = np.unique(faces[keep_face])
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    vertices, faces, part = vertices[used], remap[faces[keep_face]], joint_part[vertex_segment[used]]
    return Body(np.asarray(vertices), np.asarray(faces, dtype=np.int64), part, names,
                part_parents(parents, joint_part, len(names)))


def part_parents(parents: np.ndarray, joint_part: np.ndarray, num_parts: int) -> np.ndarray:
    """(P,) parent part of each part: the part of the segment its top segment hangs from (-1 for none).

    Segment j (parent joint -> j) hangs from segment parents[j]; a part whose segments all hang from its
    own segments or from the root joint has no parent.
    """
    out = np.full(num_parts, -1, dtype=np.int64)
    for j, p in enumerate(joint_part):
        q = parents[j]
        while q >= 0 and joint_part[q] < 0:  # helper joints of no part are skipped
            q = parents[q]
        if p >= 0 and q >= 0 and joint_part[q] >= 0 and joint_part[q] != p:
            out[p] = joint_part[q]
    return out


def body_reference(body: Body, *, name: str) -> Reference:
    """A one-frame Reference with hard skinning (one bone per part) for a labelled body."""
    b = len(body.names)
    skinning = np.eye(b)[body.part]
    centers = np.stack([body.vertices[body.part == i].mean(axis=0) for i in range(b)])
    covs = np.stack([np.cov(body.vertices[body.part == i].T) + 1e-6 * np.eye(3) for i in range(b)])
    return Reference(
        rest_vertices=body.vertices, rest_faces=body.faces, bone_centers=centers, bone_covariances=covs,
        skinning=skinning, bone_transforms=np.tile(np.eye(4), (1, b, 1, 1)), global_transforms=np.eye(4)[None],
        fps=30.0, bone_names=body.names, name=name, bone_parents=body.part_parents,
    ).validate()


def human_body(*, length: dict[str, float] | None = None, radius: dict[str, float] | None = None) -> Body:
    """The 13-part human capsule body on the first (standing) frame of CMU 131_01."""
    from sync4d.io.mocap import read_bvh

    motion = read_bvh(data_path(BVH_PATH))
    joints, parents = motion.positions[0], np.asarray(motion.parents)
    joint_part = segment_to_part(list(motion.names), HUMAN_PARTS)
    names = tuple(HUMAN_PARTS)
    if length is not None:
        factor = np.array([length[names[p]] if p >= 0 else 1.0 for p in joint_part])
        joints = rescale_skeleton(joints, parents, factor)
    radii = np.array([HUMAN_RADII[n] * (radius or {}).get(n, 1.0) for n in names])
    return grouped_body(joints, parents, joint_part, radii, names)


def dog_body() -> Body:
    """The 11-part dog capsule body on the first frame of the dog trot mocap."""
    from sync4d.io.mocap import read_joint_position_motion

    motion = read_joint_position_motion(data_path(DOG_PATH), fps=60.0, parents=np.array(DOG_PARENTS))
    joints, parents = motion.positions[0], np.asarray(motion.parents)
    names = tuple(DOG_PARTS)
    joint_part = np.full(len(joints), -1, dtype=np.int64)
    for i, members in enumerate(DOG_PARTS.values()):
        joint_part[list(members)] = i
    radii = np.array([DOG_RADII.get(n, DOG_LEG_RADIUS) for n in names])
    return grouped_body(joints, parents, joint_part, radii, names)


def laptop_body() -> Body:
    """The pipeline's default laptop (``reference=laptop``'s rest shape): base and lid."""
    from sync4d.scenes.laptop import laptop_mesh

    vertices, faces, part = laptop_mesh()
    return Body(vertices, faces, part, ("base", "lid"), np.array([-1, 0]))


def sample_labelled_surface(
    vertices: np.ndarray, faces: np.ndarray, part: np.ndarray, count: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform surface samples (count, 3) and the part of the face each came from (count,)."""
    tri = vertices[faces]
    sampled = area_points(tri, count, rng)
    if sampled is None:
        raise InputError("match_gt: a reference body has zero surface area")
    points, face = sampled
    return points, part[faces[face, 0]]


def points_to_gaussians(points: np.ndarray, *, name: str) -> TargetGaussians:
    """Minimal isotropic Gaussians at ``points`` (only their means matter for matching)."""
    n = len(points)
    spacing = float(np.cbrt(np.prod(np.ptp(points, axis=0) + 1e-9) / n))
    return TargetGaussians(
        means=points.astype(np.float64), quats=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
        log_scales=np.full((n, 3), np.log(0.5 * spacing)), opacity_logits=np.full(n, 3.0),
        sh=np.zeros((n, 1, 3)), name=name,
    ).validate()


def random_similarity(points: np.ndarray, rng: np.random.Generator, *, scale: float) -> np.ndarray:
    """``points`` rotated by a uniformly random rotation, scaled and translated."""
    rot = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
    return scale * points @ rot.T + rng.normal(0.0, 1.0, 3)


@dataclass
class PairResult:
    """Outcome of one ground-truth pair."""

    name: str
    accuracy: float             # on the Gaussians' final parts (boxes, ties, orphans)
    vertex_accuracy: float      # on the surface vertices' cosine-argmax parts, before outlier removal
    result: MatchResult
    reference: Reference
    truth: np.ndarray           # (N,) true part per Gaussian
    seconds: float

    def details(self) -> dict[str, Any]:
        out = {"accuracy": self.accuracy, "vertex_accuracy": self.vertex_accuracy, "seconds": self.seconds}
        out.update(self.result.diagnostics.summary())
        # the floors: every point the most common true part, and the expected accuracy of a uniformly random part
        num_parts = self.reference.num_bones
        out["constant"] = float(np.bincount(self.truth, minlength=num_parts).max() / max(len(self.truth), 1))
        out["random"] = 1.0 / num_parts
        out["corrected"] = (self.accuracy - out["constant"]) / (1.0 - out["constant"])
        auto = self.result.diagnostics.auto_residual
        return {**{k: round(float(v), 4) for k, v in out.items()}, "method": self.result.diagnostics.method,
                **({} if auto is None else {"auto_residual": round(auto, 4), "auto_scores": auto_scores(self.result)})}


def run_pair(
    name: str,
    reference: Reference,
    target: TargetGaussians,
    truth: np.ndarray,
    extractor: Any,
    match_options: MatchConfig,
    *,
    target_vertices: np.ndarray | None = None,
    target_faces: np.ndarray | None = None,
    vertex_truth: np.ndarray | None = None,
) -> PairResult:
    """Match and score one pair; ``vertex_truth`` scores the surface vertices (default: ``truth``)."""
    start = time.perf_counter()
    result = match_parts(reference, target, extractor, match_options, target_vertices=target_vertices,
                         target_faces=target_faces, seed=SEED)
    accuracy = float((result.part_map.tgt_part == truth).mean())
    diag = result.diagnostics
    vt = vertex_truth if vertex_truth is not None else truth[diag.target_index] if diag.target_index is not None else truth
    # with method=structure the surface points are fresh samples without truth: report the final accuracy
    vertex_accuracy = float((diag.vertex_part == vt).mean()) if len(vt) == len(diag.vertex_part) else accuracy
    seconds = time.perf_counter() - start
    log.info("%s: accuracy %.4f (vertices %.4f) in %.1f s", name, accuracy, vertex_accuracy, seconds)
    return PairResult(name, accuracy, vertex_accuracy, result, reference, truth, seconds)


POINTS = 4000  # target points of a within-category pair


def pair_self_copy(extractor: Any, options: MatchConfig, *, seed: int = 0, n_points: int = POINTS) -> PairResult:
    """(a) the human body against a resampled, rescaled, rotated, jittered copy of itself."""
    rng = np.random.default_rng(seed)
    body = human_body()
    points, truth = sample_labelled_surface(body.vertices, body.faces, body.part, n_points, rng)
    points = random_similarity(points, rng, scale=1.7)
    points += rng.normal(0.0, 0.005 * np.linalg.norm(np.ptp(points, axis=0)), points.shape)
    target = points_to_gaussians(points, name="human_copy")
    return run_pair("self_copy", body_reference(body, name="human"), target, truth, extractor, options)


def pair_laptop_proportions(extractor: Any, options: MatchConfig, *, seed: int = 0, n_points: int = POINTS) -> PairResult:
    """(b) the default laptop against a laptop of other proportions (mesh given), rotated."""
    from sync4d.scenes.laptop import laptop_mesh, laptop_reference

    rng = np.random.default_rng(seed + 1)
    reference = laptop_reference(1)
    vertices, faces, part = laptop_mesh(
        width=0.28, depth=0.21, base_thickness=0.03, lid_thickness=0.008, lid_angle_deg=100.0, subdivisions=3
    )
    rot = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
    shift = rng.normal(0.0, 1.0, 3)
    vertices = vertices @ rot.T + shift
    points, truth = sample_labelled_surface(vertices, faces, part, n_points, rng)
    target = points_to_gaussians(points, name="laptop_b")
    return run_pair(
        "laptop_proportions", reference, target, truth, extractor, options,
        target_vertices=vertices, target_faces=faces, vertex_truth=part,
    )


def pair_mocap_bodies(extractor: Any, options: MatchConfig, *, seed: int = 0, n_points: int = POINTS) -> PairResult:
    """(c) two capsule bodies of different proportions on the same CMU skeleton."""
    rng = np.random.default_rng(seed + 2)
    body_a = human_body()
    body_b = human_body(length=HUMAN_B_LENGTH, radius=HUMAN_B_RADIUS)
    points, truth = sample_labelled_surface(body_b.vertices, body_b.faces, body_b.part, n_points, rng)
    points = random_similarity(points, rng, scale=1.0)
    target = points_to_gaussians(points, name="human_b")
    return run_pair("mocap_bodies", body_reference(body_a, name="human_a"), target, truth, extractor, options)


#: the within-category pairs (``--pairs``)
PAIRS: dict[str, Callable[..., PairResult]] = {"self_copy": pair_self_copy, "laptop_proportions": pair_laptop_proportions,
                                               "mocap_bodies": pair_mocap_bodies}


def save_pair_figure(pair: PairResult, path: Path, *, views: tuple[tuple[float, float], ...] = ((0.0, 10.0), (90.0, 10.0))) -> None:
    """Reference vs target part colours of one pair (target drawn with its final Gaussian parts)."""
    from sync4d.match.pictures import save_match_figure

    save_match_figure(
        path, pair.result.diagnostics, pair.reference.num_bones,
        views=views, titles=(pair.reference.name, f"target ({pair.name})"),
        suptitle=f"{pair.name}: accuracy {pair.accuracy:.3f}; black = removed outliers",
    )


def load_target_mesh(relative: str) -> tuple[np.ndarray, np.ndarray]:
    """A shared target mesh with texture-seam duplicates merged (vertices, faces)."""
    import trimesh

    loaded = trimesh.load(data_path(relative), force="mesh", process=False)
    if not isinstance(loaded, trimesh.Trimesh):
        raise InputError(f"{relative}: not a triangle mesh ({type(loaded).__name__})")
    mesh = trimesh.Trimesh(np.asarray(loaded.vertices), np.asarray(loaded.faces), process=True)  # merges seams
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


SEED = 0


def load_label_target(spec: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Vertices, faces and (procedural) part names of a label file's target, turned Y-up."""
    from sync4d_tools.match_labels.procedural import SHAPES

    if spec.target.startswith("procedural:"):
        kind = spec.target.split(":", 1)[1]
        if kind not in SHAPES:
            raise DataMissingError(f"--labels {spec.path}: unknown procedural target {kind!r} ({', '.join(SHAPES)})")
        return SHAPES[kind]()
    path = Path(spec.target)
    vertices, faces = load_target_mesh(str(path) if path.is_absolute() else spec.target)
    if spec.up_axis != "y":
        from sync4d.sources.targets import fit_to_size

        vertices = fit_to_size(vertices, None, spec.up_axis)
    return vertices, faces, None


#: Gaussians sampled on a labelled target's surface, and how far each seed turns (about the up axis) and
#: stretches (per axis) the target: the seed changes what the method sees, not only its own sampling.
LABEL_SAMPLES = 5000
MAX_YAW_DEG = 20.0
MAX_STRETCH = 0.1


def sampled_target(vertices: np.ndarray, faces: np.ndarray, names: np.ndarray | None, rng: np.random.Generator,
                   samples: int = LABEL_SAMPLES) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Area-uniform surface samples (S, 3) of a labelled target, their part names (or None) and face (S,)."""
    tri = vertices[faces]
    sampled = area_points(tri, samples, rng)
    if sampled is None:
        raise InputError("match_gt: a labelled target has zero surface area")
    points, face = sampled
    return points, None if names is None else names[faces[face, 0]], face


def seed_transform(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(3, 3) linear map of this seed: a turn about y within +/- MAX_YAW_DEG, a stretch per axis within
    +/- MAX_STRETCH (applied about the centroid of ``points``)."""
    yaw = np.deg2rad(rng.uniform(-MAX_YAW_DEG, MAX_YAW_DEG))
    c, s = np.cos(yaw), np.sin(yaw)
    turn = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return turn @ np.diag(rng.uniform(1.0 - MAX_STRETCH, 1.0 + MAX_STRETCH, 3))


def labelled_pair(spec: Any, bodies: dict[str, Body], extractor: Any, options: MatchConfig,
                  figures: Path | None, samples: int = LABEL_SAMPLES) -> dict[str, Any]:
    """Match one label file's target (Gaussians sampled on its surface, turned and stretched by the seed) to
    its reference body; accuracy, floors, chance-corrected accuracy, per label, and a picture."""
    if spec.reference not in bodies:
        raise DataMissingError(f"--labels {spec.path}: reference {spec.reference!r}: use one of {', '.join(bodies)}")
    body = bodies[spec.reference]
    reference = body_reference(body, name=spec.reference)
    result, numbers, seconds = labelled_match(spec, body, reference, extractor, options, samples)
    out = pair_summary(spec, numbers, result, body, seconds)
    if figures is not None:
        save_labelled_figure(figures, spec, options, result, reference, numbers)
    log.info("%s [%s]: accuracy %.3f limb %.3f corrected %.3f (chance %.3f) %s", spec.name, options.method,
             numbers["accuracy"], numbers["limb_accuracy"], numbers["corrected"], numbers["chance"], numbers["per_label"])
    return out


def labelled_match(spec: Any, body: Body, reference: Reference, extractor: Any, options: MatchConfig,
                   samples: int = LABEL_SAMPLES) -> tuple[MatchResult, dict[str, Any], float]:
    """The match of one label file's target (``samples`` surface points) at the seed (:func:`labelled_pair`), its
    scores and seconds."""
    import zlib

    from sync4d_tools.match_labels.labels import score, vertex_labels

    vertices, faces, names = load_label_target(spec)
    rng = np.random.default_rng([SEED, zlib.crc32(spec.name.encode())])
    points, point_names, _ = sampled_target(vertices, faces, names, rng, samples)
    labels = vertex_labels(spec, points, point_names, box=np.stack([vertices.min(axis=0), vertices.max(axis=0)]))
    centre, linear = vertices.mean(axis=0), seed_transform(vertices, rng)
    moved_vertices, moved_points = (vertices - centre) @ linear.T + centre, (points - centre) @ linear.T + centre
    start = time.perf_counter()
    result = match_parts(reference, points_to_gaussians(moved_points, name=spec.name), extractor, options,
                         target_vertices=moved_vertices, target_faces=faces, seed=SEED)
    seconds = time.perf_counter() - start
    return result, score(spec, labels, np.ones(len(points)), result.part_map.tgt_part, body.names), seconds


#: the bars of a labelled pair: chance-corrected accuracy, and limb accuracy by kind of pair
CORRECTED_BAR = 0.7
LIMB_BARS = {"same_structure": 0.85, "cross": 0.75}


def pair_summary(spec: Any, numbers: dict[str, Any], result: MatchResult, body: Body, seconds: float) -> dict[str, Any]:
    """The JSON entry of one labelled pair (numbers rounded; ``passes``: both bars met)."""
    diag = result.diagnostics
    passes = numbers["corrected"] >= CORRECTED_BAR and numbers["limb_accuracy"] >= LIMB_BARS[spec.kind]
    return {**{k: round(float(numbers[k]), 4) for k in ("accuracy", "limb_accuracy", "corrected", "constant",
                                                         "random", "chance")},
            "constant_part": numbers["constant_part"], "passes": bool(passes), "kind": spec.kind,
            "method": diag.method, "auto_residual": None if diag.auto_residual is None else round(diag.auto_residual, 4),
            "auto_scores": auto_scores(result),
            "per_label": {k: round(v, 3) for k, v in numbers["per_label"].items()},
            "left_over": [body.names[b] for b in result.leftover_parts], "seconds": round(seconds, 2)}


def auto_scores(result: MatchResult) -> dict[str, list[float]] | None:
    """With ``method=auto``: each method's [connected, contacts] (sync4d.match.consistency), else None."""
    scores = result.diagnostics.auto_scores
    if scores is None:
        return None
    return {m: [round(c.connected, 4), round(c.contacts, 4)] for m, c in scores.items()}


def save_labelled_figure(figures: Path, spec: Any, options: MatchConfig, result: MatchResult, reference: Reference,
                         numbers: dict[str, Any]) -> None:
    """``figures/matching_<pair>_<method>.png``: reference parts left, the target's parts right, three views."""
    from sync4d.match.pictures import save_match_figure

    credit = {"human": "CMU mocap (mocap.cs.cmu.edu, NSF EIA-0196217)", "dog": "dog mocap: AI4Animation, CC BY-NC 4.0",
              "laptop": "procedural laptop"}[spec.reference]
    chosen = f" -> {result.diagnostics.method}" if options.method == "auto" else ""
    save_match_figure(
        figures / f"matching_{spec.name}_{options.method}.png", result.diagnostics, reference.num_bones,
        views=((0.0, 10.0), (90.0, 10.0), (0.0, 80.0)),
        titles=(f"{spec.reference} body (reference)", f"{Path(spec.target).name} (target)"),
        suptitle=f"{spec.name} [{options.method}{chosen}]: accuracy {numbers['accuracy']:.2f}, limbs "
        f"{numbers['limb_accuracy']:.2f}, chance-corrected {numbers['corrected']:.2f} (chance {numbers['chance']:.2f})\n"
        + credit + ("" if spec.target.startswith("procedural:") else "; mesh: odedstein/meshes, lab4d-org/lab4d"),
    )


def cross_category(extractor: Any, options: MatchConfig, label_files: list[Path],
                   figures: Path | None, samples: int = LABEL_SAMPLES) -> dict[str, dict[str, Any]]:
    """Limb accuracy of every labelled pair (see :mod:`sync4d_tools.match_labels.labels`), ``samples``
    Gaussians on each target."""
    from sync4d_tools.match_labels.labels import read_label_file

    specs = [read_label_file(p) for p in label_files]  # all files checked before any matching
    builders = {"human": human_body, "dog": dog_body, "laptop": laptop_body}
    for spec in specs:
        if spec.reference not in builders:
            raise DataMissingError(f"--labels {spec.path}: reference {spec.reference!r}: use one of {', '.join(builders)}")
    bodies = {name: builders[name]() for name in sorted({spec.reference for spec in specs})}
    return {spec.name: labelled_pair(spec, bodies, extractor, options, figures, samples) for spec in specs}


def pair_table(pairs: dict[str, dict[str, Any]]) -> str:
    """A text table of the labelled pairs: the method's accuracy beside the floors, the corrected accuracy."""
    head = (f"{'pair':<24} {'kind':<14} {'method':<9} {'acc':>6} {'limbs':>6} {'const':>6} {'random':>6} "
            f"{'corr':>6}  bars")
    rows = [f"{name:<24} {p['kind']:<14} {p['method']:<9} {p['accuracy']:6.3f} {p['limb_accuracy']:6.3f} "
            f"{p['constant']:6.3f} {p['random']:6.3f} {p['corrected']:6.3f}  {'pass' if p['passes'] else 'FAIL'}"
            for name, p in pairs.items()]
    passed = sum(p["passes"] for p in pairs.values())
    return "\n".join([head, *rows, f"{passed} of {len(pairs)} pairs at both bars (corrected >= {CORRECTED_BAR}, "
                      f"limbs >= {LIMB_BARS['same_structure']} same structure / {LIMB_BARS['cross']} cross)"])


def load_features_config(spec: str) -> dict[str, Any]:
    """A features config: a name under ``conf/features/`` or a path to a YAML file."""
    from omegaconf import OmegaConf

    path = Path(spec)
    if not path.suffix:
        path = ROOT / "conf" / "features" / f"{spec}.yaml"
    cfg = mapping(OmegaConf.load(path), str(path))
    cfg.pop("defaults", None)  # the Hydra schema line of conf/features/*.yaml; defaults come from the Config
    return cfg


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m sync4d.evaluate match_gt", description=__doc__.split("\n")[0])
    p.add_argument("--features", default="geometric", help="conf/features/<name>.yaml or a YAML path")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="feature config overrides")
    p.add_argument("--method", default=MatchConfig.method, choices=METHODS,
                   help="match.method (default: MatchConfig's)")
    p.add_argument("--match", nargs="*", default=[], metavar="KEY=VALUE",
                   help="further MatchConfig overrides, e.g. structure.miss_cost=3")
    p.add_argument("--align", default="pca_icp", choices=("none", "pca", "pca_icp", "upright_icp"),
                   help="for the randomly rotated within-category pairs (the labelled pairs use upright_icp)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--pairs", default=",".join(PAIRS), help="comma-separated within-category pairs ('' = none)")
    p.add_argument("--points", type=int, default=0,
                   help=f"target points per pair (0: {POINTS} within a category, {LABEL_SAMPLES} for a labelled pair)")
    p.add_argument("--figures", default="", help="folder for one picture per pair")
    p.add_argument("--cross-category", nargs="?", const="docs", default="", metavar="DIR",
                   help="also score the labelled pairs (sync4d_tools/match_labels/*.json); pictures into DIR (docs)")
    p.add_argument("--labels", action="append", default=[], metavar="FILE",
                   help="a label file of your own (format: sync4d_tools/match_labels/labels.py); repeatable")
    return p.parse_args(argv)


def match_config(method: str, align: str, overrides: list[str]) -> MatchConfig:
    """A MatchConfig from its defaults, ``method``, ``align`` and KEY=VALUE overrides (checked like the pipeline's)."""
    from omegaconf import OmegaConf

    from sync4d.registry import typed_config

    values = mapping(OmegaConf.merge({"method": method, "align": align}, dotlist(overrides, option="--match")),
                     "match_gt --match")
    cfg = typed_config(MatchConfig, values, where="match", label="match_gt --match")
    return cfg.validate()


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run the pairs, print a JSON object on the last line and return it."""
    global SEED
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s", stream=sys.stderr)
    from dataclasses import replace

    from omegaconf import OmegaConf

    from sync4d_tools.match_labels.labels import default_label_files

    SEED = args.seed
    pairs = [n for n in args.pairs.split(",") if n]
    unknown = [n for n in pairs if n not in PAIRS]
    if unknown:
        raise InputError(f"--pairs {unknown[0]}: unknown pair; known: {', '.join(PAIRS)}")
    if args.points < 0 or 0 < args.points < 100:
        raise InputError(f"--points {args.points}: 0 (the defaults) or at least 100")
    options = match_config(args.method, args.align, args.match)
    extractor = None
    if options.method in ("features", "auto"):
        feat_cfg = mapping(OmegaConf.merge(load_features_config(args.features), dotlist(args.set, option="--set")),
                           "match_gt --features with --set")
        extractor = build("features", feat_cfg, device="cpu")
    out: dict[str, Any] = {}
    details: dict[str, Any] = {}
    for name in pairs:
        pair = PAIRS[name](extractor, options, seed=args.seed, n_points=args.points or POINTS)
        out[f"accuracy_{name}"] = round(pair.accuracy, 4)
        details[name] = pair.details()
        if args.figures:
            save_pair_figure(pair, Path(args.figures) / f"match_gt_{name}.png")
    label_files = [Path(p) for p in args.labels] + (default_label_files() if args.cross_category else [])
    if label_files:
        # the labelled targets are given upright (Y up), as the pipeline's experiments use them
        figures = Path(args.cross_category) if args.cross_category else None
        out["cross_category"] = cross_category(extractor, replace(options, align="upright_icp"), label_files, figures,
                                               args.points or LABEL_SAMPLES)
        print(pair_table(out["cross_category"]))
    out["method"] = options.method
    out["features"] = args.features if options.method in ("features", "auto") else None
    out["details"] = details
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
