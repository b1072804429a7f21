"""Label files of the matching benchmark: which target area should receive which reference parts.

A label file is JSON::

    {
      "name": "dog_to_spot",                       # the pair's key in the report
      "reference": "dog",                          # a built-in reference body of match_gt: "human" | "dog" | "laptop"
      "target": "targets/meshes/spot_low_resolution.obj",   # a mesh under ../shared/data, an absolute
                                                   # path, or "procedural:chair|table|lamp|cross|shell"
      "kind": "same_structure",                    # or "cross" (other category)
      "up_axis": "y",                              # the target's up axis ("y" if absent)
      "labels": [
        {"name": "leg_front_left",
         "where": {"x": [0.0, 0.5], "y": [0.0, 0.3], "z": [0.0, 0.6]},   # a box in bounding-box fractions
         "expect": ["leg_a_upper", "leg_a_lower"]},                       # reference part names
        {"name": "leg", "where": {"part": ["leg_fl", "leg_fr"]}, "expect": [...]},  # procedural part names
        {"name": "body", "where": {...}, "expect": ["torso"], "trunk": true}        # the trunk is scored too
      ]
    }

``where`` is one box or a list of boxes (a vertex matching any of them); box bounds are fractions of
the target's axis-aligned bounding box (0 = min, 1 = max, per axis, in the file's own axes); a
``"part"`` entry selects the named parts of a procedural target. A vertex takes the first label whose
``where`` it matches; vertices matching none are not scored. Limb accuracy is the fraction of the
labelled surface area (one third of each face's area per vertex) whose matched reference part is in
its label's ``expect`` list; every file labels its trunk (``"trunk": true``) as well as its limbs.

Beside a method's accuracy, :func:`score` gives what no matching at all reaches: the best constant
assignment (every point one reference part) and a uniformly random one (each point any part with equal
probability: its expected accuracy), and the accuracy corrected for the better of the two,
``(acc - chance) / (1 - chance)`` (1 = every labelled point right, 0 = no better than chance, < 0 worse).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sync4d.errors import InputError

HERE = Path(__file__).resolve().parent
KINDS = ("same_structure", "cross")


@dataclass(frozen=True)
class LabelSpec:
    """One label: its name, the vertices it covers (rule), the reference parts it expects."""

    name: str
    where: list[dict[str, list]]
    expect: tuple[str, ...]
    trunk: bool = False


@dataclass(frozen=True)
class LabelFile:
    """A parsed label file (see the module docstring)."""

    path: Path
    name: str
    reference: str
    target: str
    kind: str
    up_axis: str
    labels: tuple[LabelSpec, ...]


def read_label_file(path: str | Path) -> LabelFile:
    """Parse and check a label file; raises InputError naming the file and the bad entry."""
    path = Path(path)
    try:
        raw = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise InputError(f"--labels {path}: not a readable JSON file ({err})") from err
    for key in ("name", "reference", "target", "kind", "labels"):
        if key not in raw:
            raise InputError(f"--labels {path}: missing key '{key}' (see sync4d_tools/match_labels/labels.py)")
    if raw["kind"] not in KINDS:
        raise InputError(f"--labels {path}: kind={raw['kind']!r}, use one of {', '.join(KINDS)}")
    specs = []
    for i, lab in enumerate(raw["labels"]):
        if not {"name", "where", "expect"} <= set(lab):
            raise InputError(f"--labels {path}: labels[{i}] needs name, where and expect")
        where = lab["where"] if isinstance(lab["where"], list) else [lab["where"]]
        specs.append(LabelSpec(str(lab["name"]), where, tuple(lab["expect"]), bool(lab.get("trunk", False))))
    return LabelFile(path, str(raw["name"]), str(raw["reference"]), str(raw["target"]), str(raw["kind"]),
                     str(raw.get("up_axis", "y")), tuple(specs))


def default_label_files() -> list[Path]:
    """The benchmark's label files, sorted."""
    return sorted(HERE.glob("*.json"))


def _matches(where: dict[str, list], frac: np.ndarray, part_names: np.ndarray | None) -> np.ndarray:
    sel = np.ones(len(frac), dtype=bool)
    for key, bounds in where.items():
        if key == "part":
            if part_names is None:
                raise InputError("label 'where': 'part' needs a procedural target")
            sel &= np.isin(part_names, bounds)
        elif key in ("x", "y", "z"):
            col = frac[:, "xyz".index(key)]
            sel &= (col >= bounds[0]) & (col <= bounds[1])
        else:
            raise InputError(f"label 'where': unknown key {key!r} (use x, y, z or part)")
    return sel


def vertex_labels(spec: LabelFile, vertices: np.ndarray, part_names: np.ndarray | None = None, *,
                  box: np.ndarray | None = None) -> np.ndarray:
    """(V,) label index per vertex (first matching label), -1 where no label matches.

    ``box`` (2, 3): the bounding box the rules' fractions refer to (default: that of ``vertices``; give the
    mesh's own when labelling samples of its surface)."""
    lo = vertices.min(axis=0) if box is None else np.asarray(box[0])
    span = np.maximum((vertices.max(axis=0) if box is None else np.asarray(box[1])) - lo, 1e-12)
    frac = (vertices - lo) / span
    out = np.full(len(vertices), -1, dtype=np.int64)
    for i, lab in enumerate(spec.labels):
        hit = np.zeros(len(vertices), dtype=bool)
        for w in lab.where:
            hit |= _matches(w, frac, part_names)
        out[(out < 0) & hit] = i
    return out


def vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V,) one third of the area of the faces around each vertex [m^2]."""
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    out = np.zeros(len(vertices))
    np.add.at(out, faces.ravel(), np.repeat(area / 3.0, 3))
    return out


def limb_accuracy(spec: LabelFile, labels: np.ndarray, areas: np.ndarray, matched: np.ndarray,
                  part_names: tuple[str, ...]) -> tuple[float, dict[str, float]]:
    """Area-weighted fraction of labelled vertices whose matched part is expected, overall and per label.

    Args:
        spec: the label file.
        labels: (V,) label index per vertex (-1 unlabelled).
        areas: (V,) vertex areas.
        matched: (V,) matched reference part index per vertex.
        part_names: the reference's part names.
    """
    allowed = allowed_matrix(spec, part_names)
    scored = labels >= 0
    if not scored.any():
        raise InputError(f"--labels {spec.path}: no vertex matches any label")
    ok = np.zeros(len(labels), dtype=bool)
    ok[scored] = allowed[labels[scored], matched[scored]]
    per = {}
    for i, lab in enumerate(spec.labels):
        sel = labels == i
        if sel.any():
            per[lab.name] = float((areas[sel] * ok[sel]).sum() / areas[sel].sum())
    return float((areas[scored] * ok[scored]).sum() / areas[scored].sum()), per


def allowed_matrix(spec: LabelFile, part_names: tuple[str, ...]) -> np.ndarray:
    """(L, B) bool: label l accepts reference part b; InputError naming any expected part the reference lacks."""
    unknown = {n for lab in spec.labels for n in lab.expect} - set(part_names)
    if unknown:
        raise InputError(f"--labels {spec.path}: expected parts {sorted(unknown)} are not parts of "
                         f"'{spec.reference}' ({', '.join(part_names)})")
    out = np.zeros((len(spec.labels), len(part_names)), dtype=bool)
    for i, lab in enumerate(spec.labels):
        out[i, [part_names.index(n) for n in lab.expect]] = True
    return out


def chance_accuracies(spec: LabelFile, labels: np.ndarray, weights: np.ndarray,
                      part_names: tuple[str, ...]) -> tuple[float, float, str]:
    """Accuracy of the best constant assignment, the expected accuracy of a uniformly random one, and the
    constant's part name, over the labelled points (weighted by ``weights``)."""
    allowed = allowed_matrix(spec, part_names)
    scored = labels >= 0
    w = np.bincount(labels[scored], weights=weights[scored], minlength=len(spec.labels))
    w = w / max(w.sum(), 1e-300)
    constant = w @ allowed  # (B,) accuracy if every point took part b
    best = int(np.argmax(constant))
    random = float(w @ allowed.mean(axis=1))
    return float(constant[best]), random, part_names[best]


def chance_corrected(accuracy: float, chance: float) -> float:
    """``(accuracy - chance) / (1 - chance)``; NaN when chance is 1 (the labels cannot tell anything apart)."""
    return float("nan") if chance >= 1.0 - 1e-12 else (accuracy - chance) / (1.0 - chance)


def score(spec: LabelFile, labels: np.ndarray, weights: np.ndarray, matched: np.ndarray,
          part_names: tuple[str, ...]) -> dict[str, object]:
    """Every number of one labelled pair: accuracy over all labels, limb accuracy (trunk labels left out),
    per label, the constant and random floors, the chance-corrected accuracy (see the module docstring)."""
    acc, per = limb_accuracy(spec, labels, weights, matched, part_names)
    limb = np.array([not lab.trunk for lab in spec.labels])
    limb_labels = np.where((labels >= 0) & limb[np.maximum(labels, 0)], labels, -1)
    limb_acc = limb_accuracy(spec, limb_labels, weights, matched, part_names)[0] if (limb_labels >= 0).any() else acc
    constant, random, constant_part = chance_accuracies(spec, labels, weights, part_names)
    chance = max(constant, random)
    return {"accuracy": acc, "limb_accuracy": limb_acc, "per_label": per, "constant": constant,
            "constant_part": constant_part, "random": random, "chance": chance,
            "corrected": chance_corrected(acc, chance)}
