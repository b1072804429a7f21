"""``transfer_gt``'s pairs: a reference and a target of other proportions built from the SAME joint motion,
and the target's two truths (its own skinning model, and an elastic solid held by its bone cores).

* ``laptop``: the procedural laptop (34 x 24 cm, 2 cm base, 12 mm lid) drives a laptop of 42 x 18 cm with
  a 3 cm base and an 8 mm lid; its hinge sits at its own back edge and height.
* ``cmu_walk``: CMU 131_01 (start walk stop) drives a body with 20% longer legs, 20% shorter arms and
  capsules 35% thicker.
* ``deepmimic_walk``, ``deepmimic_run``, ``deepmimic_spinkick``, ``deepmimic_cartwheel``: the DeepMimic humanoid
  clips (30 fps; the 60 fps clips taken every second frame) drive the same kind of body change. The walk
  starts at its first frame; the other clips at the window of the pair's length with the largest mean joint
  speed (the fastest stretch of the clip: fixed by the clip alone, never by a method's result).
* ``dog_trot``: the AI4Animation dog trot drives a quadruped with 30% shorter legs, a 25% longer body and
  neck, and 45% thicker capsules (cow-like).

Data (attribution): CMU Graphics Lab Motion Capture Database (mocap.cs.cmu.edu; "The database was created
with funding from NSF EIA-0196217"), via yuki-koyama/bvh11 (../shared); DeepMimic clips and humanoid URDF
(DeepMimic, MIT) from the pybullet 3.2.7 wheel (zlib), kept in the project's data/motion/deepmimic/;
AI4Animation dog mocap via erwincoumans/motion_imitation (CC BY-NC 4.0, ../shared).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from sync4d.errors import ConfigError
from sync4d.io.mesh import mesh_to_gaussians
from sync4d.io.mocap import SkeletonMotion
from sync4d.geometry import skinned_positions
from sync4d.types import PartMap, Reference, TargetGaussians
from sync4d_tools.truth import elastic

SHARED = "../shared/data/motion"
DEEPMIMIC = "data/motion/deepmimic"
#: the DeepMimic clips beyond the walk (file stem humanoid3d_<name>.txt)
DEEPMIMIC_CLIPS = ("run", "spinkick", "cartwheel")
PAIRS = ("laptop", "cmu_walk", "deepmimic_walk", *(f"deepmimic_{c}" for c in DEEPMIMIC_CLIPS), "dog_trot")
TRUTHS = ("skinning", "elastic")


@dataclass(frozen=True)
class GTPair:
    """A reference, a target of other proportions, and the target's true motions.

    Attributes:
        name: pair name.
        reference: the driving reference (its articulation in ``bone_transforms``).
        target: the target's rest Gaussians (N).
        target_vertices, target_faces: the target's rest surface [m].
        part_map: reference bone -> the target's own bone labels (argmax of its skinning).
        truths: ``skinning``: (T, N, 3) the Gaussians posed by the target's own bones and skinning; ``elastic``:
            (T, N, 3) the target as an ARAP solid whose bone cores follow the same bones
            (:mod:`sync4d_tools.truth.elastic`) [m]; articulation only (no G_t).
        core: (N,) the bone whose core holds each Gaussian in the elastic truth, or -1.
    """

    name: str
    reference: Reference
    target: TargetGaussians
    target_vertices: np.ndarray
    target_faces: np.ndarray
    part_map: PartMap
    truths: dict[str, np.ndarray]
    core: np.ndarray


def own_weights(model: Reference, points: np.ndarray) -> np.ndarray:
    """(N, B) skinning weights of points: those of each point's nearest rest vertex of ``model``."""
    _, nearest = cKDTree(model.rest_vertices).query(points)
    return model.skinning[nearest]


def own_bone_motion(model: Reference, num_frames: int) -> np.ndarray:
    """(T, B, 4, 4) rest -> frame t motion of the model's bones, relative to frame 0."""
    return model.bone_transforms[:num_frames] @ np.linalg.inv(model.bone_transforms[0])[None]


def posed_by_own_model(model: Reference, points: np.ndarray, num_frames: int) -> np.ndarray:
    """(T, N, 3) points posed by a kinematic model's own bones and skinning [m]."""
    weights, bones = own_weights(model, points), own_bone_motion(model, num_frames)
    return np.stack([skinned_positions(points, weights, bones[t]) for t in range(num_frames)])


def elastic_truth(model: Reference, points: np.ndarray, num_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """((T, N, 3) the points as an ARAP solid held by the model's bone cores [m], (N,) core bone or -1)."""
    assert model.rest_faces is not None  # the targets are meshes
    mesh = elastic.tetrahedralise(points, model.rest_vertices, model.rest_faces)
    core = elastic.bone_cores(points, own_weights(model, points), model.bone_centers, model.bone_covariances)
    return elastic.arap_frames(mesh, core, own_bone_motion(model, num_frames)), core


def make_pair(name: str, reference: Reference, model: Reference, *, num_frames: int, gaussians: int,
              seed: int = 0) -> GTPair:
    """Sample the target model's rest surface into Gaussians and pose them by both truths."""
    assert model.rest_faces is not None  # the targets are meshes
    target = mesh_to_gaussians(model.rest_vertices, model.rest_faces, num_surface=int(gaussians * 0.6),
                               num_interior=int(gaussians * 0.4), seed=seed, name=f"{name}_target")
    points = target.means.astype(np.float64)
    labels = own_weights(model, points).argmax(axis=1)
    part_map = PartMap(reference.part_labels(), labels, np.ones(target.num), reference.num_bones).validate()
    skin = posed_by_own_model(model, points, num_frames)
    solid, core = elastic_truth(model, points, num_frames)
    return GTPair(name, reference, target, model.rest_vertices, model.rest_faces, part_map,
                  {"skinning": skin, "elastic": solid}, core)


def laptop_pair(num_frames: int, gaussians: int) -> GTPair:
    """Laptop -> a wider, shallower laptop with a thicker base and a thinner lid (hinge at its own edge)."""
    from sync4d.scenes.laptop import laptop_reference

    kw: dict[str, Any] = dict(rest_angle_deg=110.0, min_angle_deg=40.0, period_frames=24, subdivisions=2)
    ref = laptop_reference(num_frames, **kw)
    model = laptop_reference(num_frames, width=0.42, depth=0.18, base_thickness=0.03, lid_thickness=0.008, **kw)
    return make_pair("laptop", ref, model, num_frames=num_frames, gaussians=gaussians)


def rescale_segments(motion: SkeletonMotion, factors: np.ndarray) -> SkeletonMotion:
    """The same joint motion on a skeleton whose segment ``parents[j] -> j`` is ``factors[j]`` times as long.

    Every segment keeps its direction in every frame (so every joint rotation is unchanged); the root
    keeps its path. Parents precede children in the joint order.
    """
    pos = motion.positions
    out = pos.copy()
    for j, p in enumerate(motion.parents):
        if p >= 0:
            out[:, j] = out[:, p] + factors[j] * (pos[:, j] - pos[:, p])
    return dataclasses.replace(motion, positions=out)


def limb_factors(names: tuple[str, ...], legs: float, arms: float) -> np.ndarray:
    """(J,) segment factors of a humanoid by the child joint's name: legs (knee/ankle/toe), arms (elbow/wrist/hand)."""
    out = np.ones(len(names))
    for j, n in enumerate(names):
        low = n.lower()
        if any(k in low for k in ("knee", "ankle", "toe")):
            out[j] = legs
        elif any(k in low for k in ("elbow", "wrist", "hand", "finger", "thumb")):
            out[j] = arms
    return out


def quadruped_factors(parents: np.ndarray, toes: tuple[int, ...], hips: tuple[int, ...], legs: float,
                      body: float) -> np.ndarray:
    """(J,) segment factors of a quadruped: the chain from each toe up to (not including) its hip is a leg."""
    out = np.full(len(parents), body)
    for toe in toes:
        j = toe
        while j >= 0 and j not in hips:
            out[j] = legs
            j = int(parents[j])
    return out


def window(motion: SkeletonMotion, start: int, num_frames: int) -> SkeletonMotion:
    """Frames start .. start + num_frames - 1 of a motion."""
    sl = slice(start, start + num_frames)
    return dataclasses.replace(motion, positions=motion.positions[sl],
                               rotations=None if motion.rotations is None else motion.rotations[sl])


def fastest_window(motion: SkeletonMotion, num_frames: int) -> int:
    """Start of the ``num_frames`` window with the largest mean joint speed (the clip's most vigorous stretch)."""
    if motion.num_frames <= num_frames:
        return 0
    speed = np.linalg.norm(np.diff(motion.positions, axis=0), axis=2).mean(axis=1)  # (T-1,)
    sums = np.convolve(speed, np.ones(num_frames - 1), mode="valid")
    return int(np.argmax(sums))


def mocap_pair(name: str, motion: SkeletonMotion, factors: np.ndarray, *, radius_scale: float, girth: float,
               num_frames: int, gaussians: int) -> GTPair:
    """Reference and target from one joint motion: target segments x ``factors``, capsules x ``girth``."""
    from sync4d.recon.mocap import MocapReconstructor

    cfg = MocapReconstructor.Config(radius_scale=radius_scale)
    ref = MocapReconstructor(cfg).from_motion(motion, name=name)
    tcfg = MocapReconstructor.Config(radius_scale=radius_scale * girth, min_radius=cfg.min_radius * girth)
    model = MocapReconstructor(tcfg).from_motion(rescale_segments(motion, factors), name=f"{name}_target")
    if model.num_bones != ref.num_bones:
        raise ConfigError(f"transfer_gt {name}: the rescaled skeleton has {model.num_bones} bones, not {ref.num_bones}")
    return make_pair(name, ref, model, num_frames=num_frames, gaussians=gaussians)


def data_path(rel: str) -> Path:
    """A motion file, relative to the working directory or the project root."""
    from sync4d.sources.references import resolve_path

    return resolve_path(rel, what="transfer_gt motion file")


def deepmimic_motion(clip: str, num_frames: int) -> SkeletonMotion:
    """A DeepMimic humanoid clip at 30 fps (every second frame of a 60 fps clip), windowed (module docstring)."""
    from sync4d.io.deepmimic import read_deepmimic

    urdf = data_path(f"{DEEPMIMIC}/humanoid.urdf")
    m = read_deepmimic(data_path(f"{DEEPMIMIC}/humanoid3d_{clip}.txt"), urdf, urdf_scale=0.25)
    step = max(1, round(m.fps / 30.0))
    if step > 1:
        m = m.subsample(step)
    return window(m, 0 if clip == "walk" else fastest_window(m, num_frames), num_frames)


def load_pair(name: str, num_frames: int, gaussians: int) -> GTPair:
    """Build one of :data:`PAIRS` with ``num_frames`` frames (30 fps for the mocap pairs)."""
    from sync4d.io.mocap import CMU_UNIT_SCALE, read_bvh, read_joint_position_motion

    body: dict[str, Any] = dict(radius_scale=0.18, girth=1.35, num_frames=num_frames, gaussians=gaussians)
    if name == "laptop":
        return laptop_pair(num_frames, gaussians)
    if name == "cmu_walk":
        m = read_bvh(data_path(f"{SHARED}/cmu_bvh/131_01.bvh"), unit_scale=CMU_UNIT_SCALE).subsample(4)  # 30 fps
        m = window(m, int(0.4 * m.num_frames), num_frames)  # mid-stride
        return mocap_pair(name, m, limb_factors(m.names, 1.2, 0.8), **body)
    if name.startswith("deepmimic_") and name[len("deepmimic_"):] in ("walk", *DEEPMIMIC_CLIPS):
        m = deepmimic_motion(name[len("deepmimic_"):], num_frames)
        return mocap_pair(name, m, limb_factors(m.names, 1.2, 0.8), **body)
    if name == "dog_trot":
        m = read_joint_position_motion(data_path(f"{SHARED}/dog_mocap/dog_trot_joint_pos.txt"), fps=60.0,
                                       unit_scale=1.0, root=0, parents=None).subsample(2)  # 60 -> 30 fps
        m = window(m, 0, num_frames)
        factors = quadruped_factors(m.parents, toes=(10, 19, 15, 23), hips=(6, 16, 11, 20), legs=0.7, body=1.25)
        return mocap_pair(name, m, factors, **{**body, "girth": 1.45})
    raise ConfigError(f"transfer_gt --pairs: unknown pair '{name}'; use {', '.join(PAIRS)}")
