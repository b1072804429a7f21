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


# Shapes of capsules (name, end a, end b, radius [m]) and axis-aligned ellipsoids (name, centre, radii [m]):
# the hard cases of the benchmark, labelled by construction (each primitive's name is its label).
Capsule = tuple[str, tuple[float, float, float], tuple[float, float, float], float]
Ellipsoid = tuple[str, tuple[float, float, float], tuple[float, float, float]]


def capsule_mesh(a: np.ndarray, b: np.ndarray, radius: float) -> trimesh.Trimesh:
    """A closed capsule around the segment a -> b [m]."""
    axis = b - a
    length = float(np.linalg.norm(axis))
    mesh = trimesh.creation.capsule(height=length, radius=radius, count=[12, 12])
    z = np.array([0.0, 0.0, 1.0])
    direction = axis / max(length, 1e-12)
    rot = trimesh.geometry.align_vectors(z, direction)
    mesh.apply_transform(rot)
    mesh.apply_translation((a + b) / 2 - mesh.bounds.mean(axis=0))
    return mesh


def inside_capsule(points: np.ndarray, a: np.ndarray, b: np.ndarray, radius: float) -> np.ndarray:
    """(N,) bool: strictly inside the capsule a -> b of ``radius`` (by 1 %)."""
    ab = b - a
    t = np.clip((points - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * ab), axis=1) < 0.99 * radius


def primitive_union(capsules: list[Capsule], ellipsoids: list[Ellipsoid], *, max_edge: float = 0.03
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices, faces and part name per vertex of the outer surface of capsules and ellipsoids.

    Surface vertices inside another primitive are removed with their faces (as :func:`box_union`).
    """
    meshes, names = [], []
    for name, a, b, r in capsules:
        meshes.append(capsule_mesh(np.asarray(a, float), np.asarray(b, float), r))
        names.append(name)
    for name, centre, radii in ellipsoids:
        sphere = trimesh.creation.icosphere(subdivisions=3)
        meshes.append(trimesh.Trimesh(np.asarray(sphere.vertices) * np.asarray(radii) + np.asarray(centre), sphere.faces))
        names.append(name)
    verts, faces, labels, owner, offset = [], [], [], [], 0
    for i, (mesh, name) in enumerate(zip(meshes, names)):
        v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=max_edge)
        verts.append(np.asarray(v))
        faces.append(np.asarray(f) + offset)
        labels += [name] * len(v)
        owner += [i] * len(v)
        offset += len(v)
    vertices, faces_a, part, own = np.concatenate(verts), np.concatenate(faces), np.array(labels), np.array(owner)
    buried = np.zeros(len(vertices), dtype=bool)
    for i, (_, a, b, r) in enumerate(capsules):
        buried |= inside_capsule(vertices, np.asarray(a, float), np.asarray(b, float), r) & (own != i)
    for k, (_, centre, radii) in enumerate(ellipsoids):
        inside = (((vertices - np.asarray(centre)) / np.asarray(radii)) ** 2).sum(axis=1) < 0.98
        buried |= inside & (own != len(capsules) + k)
    keep_face = ~buried[faces_a].any(axis=1)
    used = np.unique(faces_a[keep_face])
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return vertices[used], remap[faces_a[keep_face]], part[used]


def long_tail() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A quadruped facing -x (left +z) whose tail hangs down and back, as long and nearly as thick as a leg."""
    legs: list[Capsule] = []
    for name, x, z in (("leg_fl", -0.25, 0.08), ("leg_fr", -0.25, -0.08), ("leg_hl", 0.25, 0.08), ("leg_hr", 0.25, -0.08)):
        legs.append((name, (x, 0.5, z), (x + 0.02, 0.25, z)))  # type: ignore[arg-type]
        legs.append((name, (x + 0.02, 0.25, z), (x, 0.03, z)))  # type: ignore[arg-type]
    caps: list[Capsule] = [(n, a, b, 0.045) for n, a, b in legs]  # type: ignore[misc]
    caps += [("head", (-0.3, 0.6, 0.0), (-0.45, 0.8, 0.0), 0.06), ("tail", (0.33, 0.58, 0.0), (0.6, 0.1, 0.0), 0.036)]
    return primitive_union(caps, [("body", (0.0, 0.55, 0.0), (0.36, 0.14, 0.13)),
                                  ("head", (-0.5, 0.83, 0.0), (0.12, 0.08, 0.08))])


def chibi() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A standing figure facing +z (left +x) whose head (with two round ears) is bigger than its body."""
    caps: list[Capsule] = [
        ("arm_l", (0.14, 0.55, 0.0), (0.36, 0.36, 0.02), 0.05), ("arm_r", (-0.14, 0.55, 0.0), (-0.36, 0.36, 0.02), 0.05),
        ("leg_l", (0.08, 0.28, 0.0), (0.1, 0.03, 0.02), 0.065), ("leg_r", (-0.08, 0.28, 0.0), (-0.1, 0.03, 0.02), 0.065),
    ]
    return primitive_union(caps, [("body", (0.0, 0.42, 0.0), (0.17, 0.2, 0.14)), ("head", (0.0, 0.86, 0.0), (0.28, 0.26, 0.25)),
                                  ("head", (0.22, 1.1, 0.0), (0.09, 0.09, 0.05)), ("head", (-0.22, 1.1, 0.0), (0.09, 0.09, 0.05))])


def flush_penguin() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A penguin facing +z (left +x): flippers lying along the body's sides, short feet under it."""
    def side(y: float) -> float:  # the body's half width at height y
        return 0.2 * float(np.sqrt(max(1.0 - ((y - 0.45) / 0.4) ** 2, 0.0)))

    caps: list[Capsule] = []
    for s, name in ((1.0, "arm_l"), (-1.0, "arm_r")):
        caps.append((name, (s * (side(0.62) + 0.025), 0.62, 0.0), (s * (side(0.25) + 0.03), 0.25, 0.0), 0.04))
    for s, name in ((1.0, "leg_l"), (-1.0, "leg_r")):
        caps.append((name, (s * 0.08, 0.08, 0.0), (s * 0.09, 0.03, 0.16), 0.035))
    caps.append(("head", (0.0, 0.92, 0.1), (0.0, 0.9, 0.22), 0.025))  # the beak
    return primitive_union(caps, [("body", (0.0, 0.45, 0.0), (0.2, 0.4, 0.17)), ("head", (0.0, 0.92, 0.0), (0.14, 0.14, 0.14))])


def stretch() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A quadruped stretching, facing -x (left +z): chest low, front legs along the floor, hind quarters
    high, head low, tail raised."""
    caps: list[Capsule] = [("body", (-0.25, 0.3, 0.0), (0.3, 0.5, 0.0), 0.13)]
    for s, side in ((1.0, "l"), (-1.0, "r")):
        caps.append((f"leg_f{side}", (-0.22, 0.22, s * 0.08), (-0.62, 0.04, s * 0.08), 0.04))
        caps.append((f"leg_h{side}", (0.3, 0.45, s * 0.08), (0.33, 0.03, s * 0.08), 0.045))
    caps += [("head", (-0.33, 0.33, 0.0), (-0.45, 0.3, 0.0), 0.06), ("tail", (0.4, 0.57, 0.0), (0.55, 0.97, 0.0), 0.03)]
    return primitive_union(caps, [("head", (-0.52, 0.28, 0.0), (0.1, 0.08, 0.08))])


SHAPES.update({"long_tail": long_tail, "chibi": chibi, "flush_penguin": flush_penguin, "stretch": stretch})
