"""A rendered quadruped clip with a real dog's shape and motion: the Lab4D shiba-haru-1002 export.

The export (``../shared/data/lab4d_export/shiba-haru-1002``; ``gengshan-y/ppr-diffphys``, MIT, Copyright (c)
2023 Gengshan Yang) holds 21 posed meshes with one topology and vertex colours, in an object frame with y up
and the dog facing +z, and a world-to-camera matrix and intrinsics per frame (a handheld camera). The meshes
are sampled into small Gaussians coloured by the vertex colours and splatted by ``render=splat_torch``:

* ``export``: the export's own cameras. The background is plain, so a moving camera is the same video as a
  static camera (frame 0's) watching the dog move by ``inv(W_0) W_t``; the clip is written that way (the fit
  assumes a static camera): ``camera.npz`` is frame 0's camera, the truth joints are moved by ``inv(W_0) W_t``;
* ``side``, ``oblique``, ``front``: static look-at cameras as in :mod:`sync4d_tools.body_clips`.

Joint truth (the ``recon_joints`` quadruped vocabulary) comes from the mesh by a fixed rule on frame 0
(:func:`joint_groups`): vertex groups picked once, then carried through the frames by vertex index (the
topology is fixed), each joint the centroid of its group. It uses nothing of the fit or its template.

    python -m sync4d_tools.shiba_clip --out outputs/body_suite/shiba_side --view side

The export's units are Lab4D's (the body is 0.1 long): everything is scaled by ``METRES_PER_UNIT`` so that the
dog is a shiba's size (0.6 m nose to tail); the metric is in % of the height, so the choice does not matter.
Its frame rate is not recorded; ``FPS`` is an assumption (the fit's smoothness is stated per second).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sync4d.errors import InputError
from sync4d.io.lab4d import Lab4DExport
from sync4d.types import Camera

EXPORT = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "lab4d_export" / "shiba-haru-1002"
METRES_PER_UNIT = 6.0
FPS = 10.0
SIZE = (480, 320)  # static views (width, height), as the dog trot clips
EXPORT_SCALE = 480 / 1256  # the export's intrinsics are for a 1256 x 710 image (2 cx, 2 cy)
EXPORT_MARGIN = 40  # [px] added on every side of the scaled image (the dog reaches 12 px beyond its top)


@dataclass(frozen=True)
class GroupRule:
    """The fractions of the truth rule (stated once, not fitted).

    Attributes:
        min_leg_share: a leg is a connected piece of the mesh below the split height holding at least this
            share of the vertices.
        ring: the paw ring is the lowest ``ring`` of a leg's height, the middle ring its top ``ring``.
        slab: half-width of a cross-section slab along the body (fraction of the body length).
        head: the head is the front ``head`` of the body length.
        tail: the tail base is the centroid of the rear ``tail`` of the body length.
    """

    min_leg_share: float = 0.01
    ring: float = 0.2
    slab: float = 0.04
    head: float = 0.15
    tail: float = 0.1


def _components(faces: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """(V,) connected-component label of each kept vertex over the mesh edges between kept vertices (-1 if not kept)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = e[keep[e[:, 0]] & keep[e[:, 1]]]
    n = len(keep)
    _, lab = connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)), directed=False)
    return np.where(keep, lab, -1)


def leg_split(rest: np.ndarray, faces: np.ndarray, rule: GroupRule) -> tuple[float, list[np.ndarray]]:
    """The highest height (y, on a 1/80 grid of the body height) below which the mesh falls into four pieces of
    at least ``min_leg_share`` of the vertices each, and those four pieces' vertex indices."""
    y = rest[:, 1]
    ground, height = y.min(), np.ptp(y)
    best = None
    for f in np.arange(0.1, 0.8, 1 / 80):
        lab = _components(faces, y < ground + f * height)
        sizes = np.bincount(lab[lab >= 0])
        big = np.flatnonzero(sizes >= rule.min_leg_share * len(rest))
        if len(big) == 4:
            best = (float(ground + f * height), [np.flatnonzero(lab == c) for c in big])
    if best is None:
        raise SystemExit("shiba_clip: no height separates the mesh into four legs")
    return best


def joint_groups(rest: np.ndarray, faces: np.ndarray, rule: GroupRule = GroupRule()) -> dict[str, np.ndarray]:
    """Vertex indices of every truth joint, picked on ``rest`` (V, 3) (y up, facing +z, +x the dog's left).

    * legs: the four pieces below the split height (:func:`leg_split`); the two with the larger mean z are the
      fore legs, the one with the larger x at its top ring the left one of each pair;
    * ``<leg>_paw``: the leg's lowest ``ring`` of its height; ``<leg>_middle`` (elbow, stifle): its top ``ring``
      (the belly line, where the leg leaves the body);
    * ``<leg>_upper`` (shoulder, hip): the body's vertices (no leg) above the top ring (horizontally within
      twice the ring's RMS radius of its centre), between the split height and half-way to the body's top
      there (the body's lower half over the leg);
    * ``neck`` / ``pelvis``: the body's whole cross-section slab at the fore / hind legs' mean top-ring z;
    * ``head``: the front ``head`` of the body length; ``tail_base``: the rear ``tail`` of it.
    """
    split, legs = leg_split(rest, faces, rule)
    z = rest[:, 2]
    length = np.ptp(z)
    in_leg = np.zeros(len(rest), bool)
    for idx in legs:
        in_leg[idx] = True
    fore = sorted(legs, key=lambda i: -rest[i, 2].mean())
    groups: dict[str, np.ndarray] = {}
    tops = {}
    for pair, pieces in (("f", fore[:2]), ("h", fore[2:])):
        rings = []
        for idx in pieces:
            y = rest[idx, 1]
            span = split - y.min()
            rings.append((idx[y < y.min() + rule.ring * span], idx[y > split - rule.ring * span]))
        rings.sort(key=lambda r: -rest[r[1], 0].mean())
        for side, (paw, top) in zip("lr", rings):
            groups[f"{pair}{side}_paw"], groups[f"{pair}{side}_middle"] = paw, top
            tops[f"{pair}{side}"] = top
    body = ~in_leg
    for leg, top in tops.items():
        centre = rest[top].mean(0)
        reach = 2.0 * np.sqrt(((rest[top][:, [0, 2]] - centre[[0, 2]]) ** 2).sum(1).mean())
        near = body & (np.linalg.norm(rest[:, [0, 2]] - centre[[0, 2]], axis=1) < reach)
        mid_y = 0.5 * (split + rest[near, 1].max())
        groups[f"{leg}_upper"] = np.flatnonzero(near & (rest[:, 1] > split) & (rest[:, 1] < mid_y))
    for name, pair in (("neck", "f"), ("pelvis", "h")):
        zc = 0.5 * (rest[tops[pair + "l"], 2].mean() + rest[tops[pair + "r"], 2].mean())
        groups[name] = np.flatnonzero(body & (np.abs(z - zc) < rule.slab * length))
    groups["head"] = np.flatnonzero(z > z.max() - rule.head * length)
    groups["tail_base"] = np.flatnonzero(z < z.min() + rule.tail * length)
    empty = [k for k, v in groups.items() if len(v) == 0]
    if empty:
        raise SystemExit(f"shiba_clip: the truth rule found no vertices for {empty}")
    return groups


def truth_joints(vertices: np.ndarray, groups: dict[str, np.ndarray], names: tuple[str, ...]) -> np.ndarray:
    """(T, J, 3) centroids of each joint's vertex group in every frame of ``vertices`` (T, V, 3)."""
    return np.stack([vertices[:, groups[n]].mean(1) for n in names], axis=1)


def surface_samples(
    vertices: np.ndarray, faces: np.ndarray, count: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """``count`` (face index, barycentric weights (count, 3)) samples uniform by area on the rest mesh; the same
    samples move with the mesh in every frame."""
    from sync4d.surface import area_samples

    sampled = area_samples(vertices[faces], count, rng)
    if sampled is None:
        raise ValueError("shiba_clip: the export's frame-0 mesh has zero area")
    return sampled


def render_mesh_frames(
    vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray | None, cameras: list[Camera], *,
    samples: int = 60000
) -> tuple[np.ndarray, np.ndarray]:
    """(T, H, W, 3) uint8 frames and (T, H, W) bool masks (opacity > 0.5) of the mesh sequence, frame t seen by
    ``cameras[t]``; Gaussians of radius ~ the sample spacing, shaded by the face normal (two-sided); ``colours``
    (V, 3) in [0, 1] per vertex, or None for a plain light grey."""
    from sync4d.render.splat_torch import SplatTorch

    renderer = SplatTorch(SplatTorch.Config(background=[0.78, 0.78, 0.76], num_threads=1))
    rng = np.random.default_rng(0)
    face, bary = surface_samples(vertices[0], faces, samples, rng)
    tri0 = vertices[0][faces]
    area = 0.5 * np.linalg.norm(np.cross(tri0[:, 1] - tri0[:, 0], tri0[:, 2] - tri0[:, 0]), axis=1).sum()
    sigma = 0.7 * np.sqrt(area / samples)
    if colours is None:
        colours = np.full((len(vertices[0]), 3), 0.8)
    cols = (colours[faces[face]] * bary[..., None]).sum(1)
    light = np.array([0.3, 0.8, 0.6]) / np.linalg.norm([0.3, 0.8, 0.6])
    frames, masks = [], []
    for t, camera in enumerate(cameras):
        tri = vertices[t][faces[face]]
        means = (tri * bary[..., None]).sum(1)
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
        shade = 0.4 + 0.6 * np.abs(normal @ light)
        covs = np.tile(np.eye(3) * sigma**2, (samples, 1, 1))
        out = renderer.render_full(means, covs, cols * shade[:, None], np.full(samples, 0.9), camera)
        frames.append((np.clip(out["rgb"], 0, 1) * 255).astype(np.uint8))
        masks.append(out["alpha"] > 0.5)
    return np.stack(frames), np.stack(masks)


def export_cameras(export: Lab4DExport) -> tuple[list[Camera], np.ndarray, dict[str, Any]]:
    """The export's cameras as one static camera (frame 0's) and the per-frame object motion ``inv(W_0) W_t``.

    Returns (cameras (T,), motion (T, 4, 4) object -> frame-0 object frame, camera.npz fields)."""
    from sync4d.sources.references import camera_from_look

    if export.object_to_camera is None or export.intrinsics is None:
        raise InputError(f"{EXPORT}: the export has no per-frame cameras (object_to_camera, intrinsics)")
    w2c = export.object_to_camera.copy()
    w2c[:, :3, 3] *= METRES_PER_UNIT
    fx, fy, cx, cy = export.intrinsics[0] * EXPORT_SCALE
    width, height = 2 * int(round(cx)) + 2 * EXPORT_MARGIN, 2 * int(round(cy)) + 2 * EXPORT_MARGIN  # even (x264)
    cx, cy = cx + EXPORT_MARGIN, cy + EXPORT_MARGIN  # the same camera on a larger image: the dog is not cut
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    rot, trans = w2c[0, :3, :3], w2c[0, :3, 3]
    pos, fwd, up = -rot.T @ trans, rot.T @ np.array([0.0, 0.0, 1.0]), rot.T @ np.array([0.0, -1.0, 0.0])
    camera = camera_from_look(K, pos, fwd, up, width, height)
    motion = np.linalg.inv(w2c[0])[None] @ w2c
    return [camera] * len(w2c), motion, {"K": K, "cam_pos": pos, "cam_forward": fwd, "cam_up": up}


def write_clip(out: Path, view: str) -> dict:
    """Render the shiba clip seen from ``view`` (``export``, ``side``, ``oblique``, ``front``) into ``out``."""
    import imageio.v2 as imageio

    from sync4d.io.lab4d import read_lab4d_export
    from sync4d.io.video import write_video
    from sync4d_tools.body_clips import DOG_TRUTH, clip_camera

    export = read_lab4d_export(EXPORT)
    if export.posed_vertices is None:
        raise InputError(f"{EXPORT}: the export has no posed meshes to render")
    verts = export.posed_vertices * METRES_PER_UNIT
    groups = joint_groups(verts[0], export.faces)
    if view == "export":
        cameras, motion, cam = export_cameras(export)
        verts = np.einsum("tij,tvj->tvi", motion[:, :3, :3], verts) + motion[:, None, :3, 3]
    else:
        tracks = {"head": verts[:, groups["head"]].mean(1), "tail_base": verts[:, groups["tail_base"]].mean(1)}
        tracks["all"] = np.concatenate([verts.min(1), verts.max(1)])
        camera, K, pos, fwd, up = clip_camera(tracks, view, SIZE[0], SIZE[1], 50.0)
        cameras, cam = [camera] * len(verts), {"K": K, "cam_pos": pos, "cam_forward": fwd, "cam_up": up}
    rgb, masks = render_mesh_frames(verts, export.faces, export.colors, cameras)
    joints = truth_joints(verts, groups, DOG_TRUTH)
    out.mkdir(parents=True, exist_ok=True)
    write_video(out / "rgb.mp4", rgb, FPS)
    (out / "masks").mkdir(exist_ok=True)
    for t, m in enumerate(masks):
        imageio.imwrite(out / "masks" / f"{t:05d}.png", (m * 255).astype(np.uint8))
    np.savez(out / "camera.npz", **cam)
    np.savez(out / "gt.npz", joints=joints, names=np.array(DOG_TRUTH), fps=FPS, **cam)
    return {"clip": "shiba", "view": view, "frames": len(rgb), "fps": FPS, "out": str(out)}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--view", default="side", choices=["export", "side", "oblique", "front"])
    args = parser.parse_args(argv)
    result = write_clip(Path(args.out), args.view)
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
