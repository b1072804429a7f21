"""Body templates of the quadruped fit: a skinned mesh with a skeleton, in one canonical frame.

A template is data (:class:`BodyTemplate`): rest joints, parents, a triangle mesh with linear-blend skinning
weights, and which joints are the legs, their left/right twins and the ``recon_joints`` vocabulary. Templates
are registered by name (:func:`register_template`; ``recon.quadruped.template``), so another animal's mesh
(a plugin in ``plugins/`` calling :func:`register_template`) can replace the built-in one.

Built in: ``fox``, the Khronos glTF sample fox (``../shared/data/skinned/fox/Fox.gltf``: low poly fox by
PixelMannen, CC0; rigging and animation by @tomkranis, CC-BY 4.0; glTF conversion by @AsoboStudio and
@scurest), its bind pose and skin. Only the mesh, skeleton and weights are used: none of its animations.

Canonical frame (every template): y up, the animal facing -x, +z its left, the root joint at the origin,
body length (head joint to tail-base joint) 1.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sync4d.errors import ConfigError, InputError
from sync4d.paths import PROJECT_ROOT

SHARED = PROJECT_ROOT.parent / "shared" / "data"
FOX_FILE = SHARED / "skinned" / "fox" / "Fox.gltf"
LEG_PREFIXES = ("fl_", "fr_", "hl_", "hr_")


@dataclass(frozen=True)
class BodyTemplate:
    """A skinned body in the canonical frame (template units: body length 1).

    Attributes:
        name: the template's registered name.
        names: (J,) joint names; leg joints start with ``fl_``, ``fr_``, ``hl_``, ``hr_``.
        parents: (J,) parent per joint, -1 for the root (index 0); parents precede children.
        joints: (J, 3) rest joint positions.
        vertices: (V, 3) rest surface vertices.
        faces: (F, 3) int64 triangles.
        weights: (V, J) skinning weights, rows sum to 1.
        vocabulary: (vocabulary name, joint name) pairs for ``recon_joints``.
        head: index of the head joint; tail: index of the tail-base joint (they define the body length).
    """

    name: str
    names: tuple[str, ...]
    parents: np.ndarray
    joints: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray
    weights: np.ndarray
    vocabulary: tuple[tuple[str, str], ...]
    head: int
    tail: int

    @property
    def twin(self) -> np.ndarray:
        """(J,) index of each joint's left/right twin (itself for midline joints)."""
        swap = {"fl_": "fr_", "fr_": "fl_", "hl_": "hr_", "hr_": "hl_"}
        return np.array([self.names.index(swap[n[:3]] + n[3:]) if n[:3] in swap else j
                         for j, n in enumerate(self.names)])

    def leg(self, prefix: str) -> np.ndarray:
        """Indices of the joints of one leg (``fl_``, ``fr_``, ``hl_``, ``hr_``)."""
        return np.array([j for j, n in enumerate(self.names) if n.startswith(prefix)], dtype=np.int64)

    @property
    def leg_joints(self) -> np.ndarray:
        return np.concatenate([self.leg(p) for p in LEG_PREFIXES])

    def validate(self) -> BodyTemplate:
        j, v = len(self.names), len(self.vertices)
        ok = (self.parents.shape == (j,) and self.joints.shape == (j, 3) and self.weights.shape == (v, j)
              and self.parents[0] == -1 and all(0 <= p < i for i, p in enumerate(self.parents) if i > 0)
              and np.allclose(self.weights.sum(1), 1.0, atol=1e-4) and self.faces.max() < v)
        if not ok:
            raise InputError(f"body template '{self.name}': inconsistent shapes, parents or weights")
        if any(len(self.leg(p)) == 0 for p in LEG_PREFIXES) or not np.array_equal(self.twin[self.twin], np.arange(j)):
            raise InputError(f"body template '{self.name}': needs four legs whose joints pair up left/right")
        return self


TEMPLATES: dict[str, Callable[[], BodyTemplate]] = {}


def register_template(name: str) -> Callable[[Callable[[], BodyTemplate]], Callable[[], BodyTemplate]]:
    """Decorator registering a function that builds a :class:`BodyTemplate` under ``name``."""

    def decorator(fn: Callable[[], BodyTemplate]) -> Callable[[], BodyTemplate]:
        if name in TEMPLATES and TEMPLATES[name] is not fn:
            raise ConfigError(f"body template '{name}' is registered twice")
        TEMPLATES[name] = fn
        return fn

    return decorator


_BUILT: dict[str, BodyTemplate] = {}


def body_template(name: str) -> BodyTemplate:
    """The registered template ``name`` (built once, then reused)."""
    if name not in TEMPLATES:
        raise ConfigError(f"recon.quadruped.template={name}: unknown; registered: {sorted(TEMPLATES)}")
    if name not in _BUILT:
        _BUILT[name] = TEMPLATES[name]().validate()
    return _BUILT[name]


# fox rig joint -> template joint name (legs: upper = shoulder / hip, middle = elbow / stifle, then the
# lower joints down to the paw)
FOX_JOINTS = (
    ("b_Hip_01", "pelvis"), ("b_Spine01_02", "spine0"), ("b_Spine02_03", "spine1"), ("b_Neck_04", "neck"),
    ("b_Head_05", "head"),
    ("b_LeftUpperArm_09", "fl_upper"), ("b_LeftForeArm_010", "fl_middle"), ("b_LeftHand_011", "fl_paw"),
    ("b_RightUpperArm_06", "fr_upper"), ("b_RightForeArm_07", "fr_middle"), ("b_RightHand_08", "fr_paw"),
    ("b_LeftLeg01_015", "hl_upper"), ("b_LeftLeg02_016", "hl_middle"), ("b_LeftFoot01_017", "hl_hock"),
    ("b_LeftFoot02_018", "hl_paw"),
    ("b_RightLeg01_019", "hr_upper"), ("b_RightLeg02_020", "hr_middle"), ("b_RightFoot01_021", "hr_hock"),
    ("b_RightFoot02_022", "hr_paw"),
    ("b_Tail01_012", "tail_base"), ("b_Tail02_013", "tail1"), ("b_Tail03_014", "tail2"),
)
VOCABULARY = tuple((n, n) for n in (
    "pelvis", "neck", "head", "tail_base", "fl_upper", "fl_middle", "fl_paw", "fr_upper", "fr_middle", "fr_paw",
    "hl_upper", "hl_middle", "hl_paw", "hr_upper", "hr_middle", "hr_paw"))
# glTF fox frame (y up, facing +z, +x its left) -> canonical (facing -x, +z left): a quarter turn about y
FOX_TO_CANONICAL = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])


def skinned_mesh_template(name: str, path: Path, rig: tuple[tuple[str, str], ...], to_canonical: np.ndarray,
                          vocabulary: tuple[tuple[str, str], ...]) -> BodyTemplate:
    """A template from a skinned glTF mesh in its bind pose: the ``rig`` joints renamed (rig name, template
    name; the first is the root), the skin weights of other joints moved to their nearest kept ancestor."""
    from sync4d.io.gltf import dense_weights, joint_world, read_gltf

    if not path.is_file():
        raise InputError(f"body template '{name}': {path} not found; it comes with ../shared/data")
    mesh = read_gltf(path)
    rig_names = [r for r, _ in rig]
    missing = [r for r in rig_names if r not in mesh.joint_names]
    if missing:
        raise InputError(f"body template '{name}': {path} has no joints {missing}")
    skin_parents = mesh.joint_parents
    keep = [mesh.joint_names.index(r) for r in rig_names]
    owner = np.zeros(len(skin_parents), dtype=np.int64)  # skin joint -> kept joint that takes its weight
    for j in range(len(skin_parents)):
        a = j
        while a >= 0 and a not in keep:
            a = int(skin_parents[a])
        owner[j] = keep.index(a) if a >= 0 else 0
    parents = np.full(len(keep), -1, dtype=np.int64)
    for i, j in enumerate(keep[1:], start=1):
        parents[i] = owner[int(skin_parents[j])]
    weights = np.zeros((len(mesh.positions), len(keep)))
    np.add.at(weights.T, owner, dense_weights(mesh).T)
    rest = joint_world(mesh, None, 0.0)[keep, :3, 3]
    root = rest[0]
    joints, verts = (rest - root) @ to_canonical.T, (mesh.positions - root) @ to_canonical.T
    names = tuple(t for _, t in rig)
    head, tail = names.index("head"), names.index("tail_base")
    length = float(np.linalg.norm(joints[head] - joints[tail]))
    return BodyTemplate(name, names, parents, joints / length, verts / length, mesh.faces.copy(), weights,
                        vocabulary, head, tail)


@register_template("fox")
def fox_template() -> BodyTemplate:
    """The Khronos glTF fox's bind pose, skeleton and skin (22 of its 24 joints: the two empty root joints
    dropped)."""
    return skinned_mesh_template("fox", FOX_FILE, FOX_JOINTS, FOX_TO_CANONICAL, VOCABULARY)
