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
        {"name": "leg", "where": {"part": ["leg_fl", "leg_fr"]}, "expect": [...]}   # procedural part names
      ]
    }

``where`` is one box or a list of boxes (a vertex matching any of them); box bounds are fractions of
the target's axis-aligned bounding box (0 = min, 1 = max, per axis, in the file's own axes); a
``"part"`` entry selects the named parts of a procedural target. A vertex takes the first label whose
``where`` it matches; vertices matching none are not scored. Limb accuracy is the fraction of the
labelled surface area (one third of each face's area per vertex) whose matched reference part is in
its label's ``expect`` list.
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
        specs.append(LabelSpec(str(lab["name"]), where, tuple(lab["expect"])))
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


def vertex_labels(spec: LabelFile, vertices: np.ndarray, part_names: np.ndarray | None = None) -> np.ndarray:
    """(V,) label index per vertex (first matching label), -1 where no label matches."""
    lo, span = vertices.min(axis=0), np.maximum(np.ptp(vertices, axis=0), 1e-12)
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
    unknown = {n for lab in spec.labels for n in lab.expect} - set(part_names)
    if unknown:
        raise InputError(f"--labels {spec.path}: expected parts {sorted(unknown)} are not parts of "
                         f"'{spec.reference}' ({', '.join(part_names)})")
    ok = np.zeros(len(labels), dtype=bool)
    per = {}
    for i, lab in enumerate(spec.labels):
        allowed = np.array([part_names.index(n) for n in lab.expect])
        sel = labels == i
        ok[sel] = np.isin(matched[sel], allowed)
        if sel.any():
            per[lab.name] = float((areas[sel] * ok[sel]).sum() / areas[sel].sum())
    scored = labels >= 0
    if not scored.any():
        raise InputError(f"--labels {spec.path}: no vertex matches any label")
    return float((areas[scored] * ok[scored]).sum() / areas[scored].sum()), per
