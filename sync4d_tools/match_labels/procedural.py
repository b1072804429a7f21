"""Procedural targets of the matching benchmark, built from boxes whose part names are their labels.

World frame: Y up, metres; every shape stands on y = 0. The boxes overlap at their joints; surface
vertices buried inside another box are removed with their faces, leaving (approximately) the outer
surface of the union, as for the capsule bodies of ``match_gt``.
"""

from __future__ import annotations

import numpy as np
import trimesh

Box = tuple[str, tuple[float, float, float], tuple[float, float, float]]  # name, lo corner, hi corner [m]


def box_union(boxes: list[Box], *, max_edge: float = 0.02) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices (V, 3), faces (F, 3) and part name per vertex (V,) of the outer surface of boxes."""
    verts, faces, names, offset = [], [], [], 0
    for name, lo, hi in boxes:
        lo_a, hi_a = np.asarray(lo, float), np.asarray(hi, float)
        box = trimesh.creation.box(extents=hi_a - lo_a)
        v, f = trimesh.remesh.subdivide_to_size(np.asarray(box.vertices) + (lo_a + hi_a) / 2, box.faces, max_edge=max_edge)
        verts.append(np.asarray(v))
        faces.append(np.asarray(f) + offset)
        names += [name] * len(v)
        offset += len(v)
    vertices, faces_a, labels = np.concatenate(verts), np.concatenate(faces), np.array(names)
    buried = np.zeros(len(vertices), dtype=bool)
    for name, lo, hi in boxes:
        inside = np.all((vertices > np.asarray(lo) + 1e-6) & (vertices < np.asarray(hi) - 1e-6), axis=1)
        buried |= inside & (labels != name)
    keep_face = ~buried[faces_a].any(axis=1)
    used = np.unique(faces_a[keep_face])
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return vertices[used], remap[faces_a[keep_face]], labels[used]


def chair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A chair 0.4 x 0.4 m, seat at 0.40-0.45 m, four legs, a back on the +x edge up to 0.85 m."""
    legs = [(f"leg_{fx}{fz}", (x, 0.0, z), (x + 0.05, 0.41, z + 0.05))
            for fx, x in (("f", -0.2), ("b", 0.15)) for fz, z in (("l", 0.15), ("r", -0.2))]
    return box_union([("seat", (-0.2, 0.40, -0.2), (0.2, 0.45, 0.2)), *legs,
                      ("back", (0.15, 0.44, -0.2), (0.2, 0.85, 0.2))])


def table() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A table 0.8 x 0.5 m, top at 0.70-0.75 m, four legs 0.05 m inset from the corners."""
    legs = [(f"leg_{fx}{fz}", (x, 0.0, z), (x + 0.05, 0.71, z + 0.05))
            for fx, x in (("f", -0.35), ("b", 0.30)) for fz, z in (("l", 0.15), ("r", -0.2))]
    return box_union([("top", (-0.4, 0.70, -0.25), (0.4, 0.75, 0.25)), *legs])


def lamp() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A desk lamp: base plate, vertical pole to 0.64 m, an arm along +x, a shade hanging from its end."""
    return box_union([
        ("base", (-0.15, 0.0, -0.15), (0.15, 0.04, 0.15)),
        ("pole", (-0.02, 0.03, -0.02), (0.02, 0.64, 0.02)),
        ("arm", (-0.02, 0.60, -0.02), (0.35, 0.64, 0.02)),
        ("shade", (0.27, 0.48, -0.06), (0.39, 0.62, 0.06)),
    ])


def cross() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pipeline's ``target=cross`` (its default sizes), labelled top / arm_left / arm_right / bottom / centre."""
    from sync4d.scenes.cross import cross_mesh

    v, f = cross_mesh()
    w, lo, hi = 0.06, 0.42 - 0.05, 0.42 + 0.05
    names = np.where(v[:, 1] > hi + 1e-6, "top", np.where(v[:, 1] < lo - 1e-6, "bottom",
                     np.where(v[:, 0] > w + 1e-6, "arm_px", np.where(v[:, 0] < -w - 1e-6, "arm_nx", "centre"))))
    return v, f, names


def shell() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pipeline's default ``target=shell`` (its default sizes), labelled bottom / top."""
    from sync4d.scenes.shell import shell_mesh

    v, f, part = shell_mesh()
    return v, f, np.where(part == 0, "bottom", "top")


SHAPES = {"chair": chair, "table": table, "lamp": lamp, "cross": cross, "shell": shell}
