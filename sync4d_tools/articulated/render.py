"""Render the articulated suite with MuJoCo (kinematic playback, EGL): clips in the laptop renders' layout.

    python -m sync4d_tools.articulated.render [--out outputs/cache/articulated] [--frames 24] [--size 240 180]

Each clip folder holds ``rgb.mp4``, ``masks/%05d.png`` (255 = object, from the exact labels) and ``gt.npz``:
``part_labels`` (T, H, W) uint8 (0 background, 1 the static base, j + 2 the part moved by joint j),
``part_names``, ``joint_type`` (J,) ``hinge``/``slide``, ``joint_value`` (T, J) [rad or m], ``joint_axis``
(J, 3) world, ``joint_pos`` (J, 3) a world point on each joint's axis in frame 0 [m], ``depth_m`` (H, W)
frame-0 camera depth of the object's pixels [m] (0 elsewhere; for diagnostics only), ``part_depth_m`` (P,) mean camera depth of each part's visible pixels in frame 0 [m]
(label 1 first), ``fps``, ``K``, ``cam_pos``, ``cam_forward``, ``cam_up`` (the projection convention of
``rendered/metaworld_laptop_hinge``), and for one-hinge objects ``hinge_angle_rad`` (T,) as that render has.

Meta-World assets: ``metaworld==3.1.1`` (MIT). Requires ``mujoco`` (Apache-2.0); ``MUJOCO_GL=egl``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sync4d_tools.articulated.objects import SuiteObject, suite_objects

os.environ.setdefault("MUJOCO_GL", "egl")


@dataclass(frozen=True)
class View:
    """A static camera around the object: azimuth and elevation [deg] (MuJoCo free-camera convention)."""

    name: str
    azimuth: float
    elevation: float


VIEWS = (View("left", 55.0, -28.0), View("right", 125.0, -38.0))


def _assets_dir(cache: Path) -> Path:
    """A private copy of Meta-World's assets (wrapper files are written next to its object files)."""
    import metaworld

    dst = cache / "mw_assets"
    if not dst.exists():
        shutil.copytree(Path(metaworld.__file__).parent / "assets", dst)
    return dst / "objects"


def scene_xml(obj: SuiteObject) -> str:
    """A standalone MJCF scene: the object on a plain floor, lit, no gravity (kinematic playback)."""
    return (f'<mujoco model="{obj.name}"><compiler angle="radian"/><option gravity="0 0 0"/>{obj.dependencies}'
            '<visual><headlight ambient="0.45 0.45 0.45" diffuse="0.5 0.5 0.5"/></visual>'
            '<asset><material name="suite_floor" rgba=".42 .44 .46 1"/></asset>'
            '<worldbody><light directional="true" diffuse=".5 .5 .5" pos="0 0 3" dir="-0.3 0.2 -1"/>'
            '<geom name="suite_floor" type="plane" size="3 3 .05" material="suite_floor"/>'
            f"{obj.body_xml}</worldbody></mujoco>")


def _part_of_bodies(model: object, joint_ids: list[int]) -> np.ndarray:
    """(nbody,) part label of each body: 0 world, 1 base, j + 2 for the subtree moved by joint j."""
    nb = model.nbody  # type: ignore[attr-defined]
    part = np.ones(nb, dtype=np.int64)
    part[0] = 0
    moving = {int(model.jnt_bodyid[j]): k + 2 for k, j in enumerate(joint_ids)}  # type: ignore[attr-defined]
    for b in range(1, nb):
        a = b
        while a > 0 and a not in moving:
            a = int(model.body_parentid[a])  # type: ignore[attr-defined]
        if a in moving:
            part[b] = moving[a]
    return part


def _camera(model: object, data: object, view: View) -> object:
    """A free camera looking at the object's bounding box centre, framing its motion."""
    import mujoco

    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for g in range(model.ngeom):  # type: ignore[attr-defined]
        if model.geom_bodyid[g] == 0 or model.geom_group[g] > 2:  # type: ignore[attr-defined]
            continue
        centre, radius = data.geom_xpos[g], model.geom_rbound[g]  # type: ignore[attr-defined]
        lo, hi = np.minimum(lo, centre - radius * 0.7), np.maximum(hi, centre + radius * 0.7)
    cam = mujoco.MjvCamera()
    cam.lookat[:] = (lo + hi) / 2
    fovy = np.radians(model.vis.global_.fovy)  # type: ignore[attr-defined]
    cam.distance = 0.8 * np.linalg.norm(hi - lo) / 2 / np.tan(fovy / 2)
    cam.azimuth, cam.elevation = view.azimuth, view.elevation
    return cam


def _union_box_pose(model: object, data: object, joint_ids: list[int], values: np.ndarray) -> None:
    """Pose the scene at the motion's midpoint so the camera frames the whole sweep."""
    import mujoco

    for k, j in enumerate(joint_ids):
        data.qpos[model.jnt_qposadr[j]] = values[len(values) // 2, k]  # type: ignore[attr-defined]
    mujoco.mj_forward(model, data)


def render_clip(obj: SuiteObject, view: View, out: Path, *, frames: int, width: int, height: int, cache: Path) -> dict:
    """Render one object from one view into ``out`` (rgb.mp4, masks/, gt.npz); returns a summary."""
    import imageio.v2 as imageio
    import mujoco

    objects_dir = _assets_dir(cache)
    xml_path = objects_dir / f"suite_{obj.name}.xml"
    xml_path.write_text(scene_xml(obj))
    model = mujoco.MjModel.from_xml_path(str(xml_path))
    data = mujoco.MjData(model)
    joint_ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n) if n else k for k, n in enumerate(obj.joints)]
    values = obj.trajectory(frames)
    part_of_body = _part_of_bodies(model, joint_ids)
    _union_box_pose(model, data, joint_ids, values)
    cam = _camera(model, data, view)
    renderer = mujoco.Renderer(model, height, width)
    rgb, labels, depth0 = [], [], None
    for t in range(frames):
        for k, j in enumerate(joint_ids):
            data.qpos[model.jnt_qposadr[j]] = values[t, k]
        mujoco.mj_forward(model, data)
        renderer.update_scene(data, camera=cam)
        rgb.append(renderer.render().copy())
        renderer.enable_segmentation_rendering()
        renderer.update_scene(data, camera=cam)
        seg = renderer.render().copy()
        renderer.disable_segmentation_rendering()
        geom = np.where(seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), seg[..., 0], -1)
        lab = np.where(geom >= 0, part_of_body[model.geom_bodyid[np.maximum(geom, 0)]], 0).astype(np.uint8)
        lab[(geom >= 0) & (model.geom_bodyid[np.maximum(geom, 0)] == 0)] = 0  # the floor
        labels.append(lab)
        if t == 0:
            renderer.enable_depth_rendering()
            renderer.update_scene(data, camera=cam)
            depth0 = renderer.render().copy()
            renderer.disable_depth_rendering()
            axes = np.stack([data.xaxis[j] for j in joint_ids]).copy()
            anchors = np.stack([data.xanchor[j] for j in joint_ids]).copy()
    gl = renderer.scene.camera  # the two eyes of the GL camera: their mean is the view
    pos = np.mean([gl[i].pos for i in range(2)], 0)
    fwd = np.mean([gl[i].forward for i in range(2)], 0)
    up = np.mean([gl[i].up for i in range(2)], 0)
    renderer.close()
    fy = 0.5 * height / np.tan(np.radians(model.vis.global_.fovy) / 2)
    K = np.array([[fy, 0, width / 2], [0, fy, height / 2], [0, 0, 1.0]])
    labels_a = np.stack(labels)
    n_parts = len(joint_ids) + 1
    # MuJoCo's depth buffer holds distance along the view axis, as our z = (p - c).fwd
    part_depth = np.array([float(depth0[labels_a[0] == p + 1].mean()) if (labels_a[0] == p + 1).any() else np.nan
                           for p in range(n_parts)])
    kinds = np.array(["hinge" if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE else "slide" for j in joint_ids])
    gt = {"part_labels": labels_a, "part_names": np.array(["background", "base"] + [f"part{j + 1}" for j in range(len(joint_ids))]),
          "joint_type": kinds, "joint_value": values.astype(np.float64), "joint_axis": axes, "joint_pos": anchors, "part_depth_m": part_depth,
          "depth_m": np.where(labels_a[0] > 0, depth0, 0.0).astype(np.float32),
          "fps": np.int64(12), "K": K, "cam_pos": pos.astype(np.float32), "cam_forward": fwd.astype(np.float32),
          "cam_up": up.astype(np.float32)}
    if kinds.tolist() == ["hinge"]:
        gt["hinge_angle_rad"] = values[:, 0].astype(np.float32)
    out.mkdir(parents=True, exist_ok=True)
    (out / "masks").mkdir(exist_ok=True)
    for t, lab in enumerate(labels_a):
        imageio.imwrite(out / "masks" / f"{t:05d}.png", ((lab > 0) * 255).astype(np.uint8))
    imageio.mimwrite(out / "rgb.mp4", rgb, fps=12, quality=9, macro_block_size=1)
    np.savez_compressed(out / "gt.npz", **gt)
    return {"clip": out.name, "object": obj.name, "view": view.name, "joints": kinds.tolist(),
            "part_pixels_frame0": [int((labels_a[0] == p + 1).sum()) for p in range(n_parts)]}


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="outputs/cache/articulated")
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--size", type=int, nargs=2, default=(240, 180), metavar=("W", "H"))
    parser.add_argument("--only", nargs="*", default=[], help="object names to render (default: all)")
    args = parser.parse_args(argv)
    cache = Path(args.out)
    cache.mkdir(parents=True, exist_ok=True)
    rows = []
    for obj in suite_objects():
        if args.only and obj.name not in args.only:
            continue
        for view in VIEWS:
            clip = cache / "clips" / f"{obj.name}-{view.name}"
            rows.append(render_clip(obj, view, clip, frames=args.frames, width=args.size[0], height=args.size[1],
                                    cache=cache))
            print(json.dumps(rows[-1]))
    return rows


if __name__ == "__main__":
    main()
