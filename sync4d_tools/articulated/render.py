"""Render the articulated suite with MuJoCo (kinematic playback, EGL): clips in the laptop renders' layout.

    python -m sync4d_tools.articulated.render [--out outputs/cache/articulated] [--seeds 0 1 2] [--frames 24] [--size 240 180]
        [--camera static|handheld]

Seed 0 renders every object as it is defined, from the two views; another seed samples what a new clip of
the same object would change (:func:`variant`): the camera's azimuth (+-15 deg) and elevation (+-8 deg), the
start state (up to 15 % of the motion in) and far end (up to 10 % short), the checker colours and scale of
the textured objects, the plain objects' colours, the floor's colour and the light. A clip's folder is
``clips/<object>-<view>`` at seed 0 and ``clips/<object>-<view>-s<seed>`` otherwise.

``--camera handheld`` films the same clips (the same object, start view, look and motion) as a phone user
would: the camera moves per frame along the default scene's hand-held arc
(:func:`sync4d.scenes.reference_video.handheld_path`: 30 deg of azimuth about the world's up over the clip,
elevation +-3 deg, distance +-5 %, aim jitter of 2 % of the object's radius, ~1 deg of roll; seeded by the
clip's seed and name), starting at the static view. Its folders end in ``-hh`` and its ``cam_pos``,
``cam_forward``, ``cam_up`` are (T, 3), one pose per frame (the joints stay in the fixed world).

Each clip folder holds ``rgb.mp4``, ``masks/%05d.png`` (255 = object, from the exact labels) and ``gt.npz``:
``part_labels`` (T, H, W) uint8 (0 background, 1 the static base, j + 2 the part moved by joint j),
``part_names``, ``joint_type`` (J,) ``hinge``/``slide``, ``joint_value`` (T, J) [rad or m], ``joint_axis``
(J, 3) world, ``joint_pos`` (J, 3) a world point on each joint's axis in frame 0 [m], ``depth_m`` (H, W)
frame-0 camera depth of the object's pixels [m] (0 elsewhere), ``depth_t`` (T, H, W) the same for every
frame (float16), ``part_depth_m`` (P,) mean camera depth of each part's visible pixels in frame 0 [m]
(label 1 first), ``fps``, ``K``, ``cam_pos``, ``cam_forward``, ``cam_up`` (the projection convention of
``rendered/metaworld_laptop_hinge``), and for one-hinge objects ``hinge_angle_rad`` (T,) as that render has.

Meta-World assets: ``metaworld==3.1.1`` (MIT). Requires ``mujoco`` (Apache-2.0); ``MUJOCO_GL=egl``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import zlib
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from sync4d.scenes.reference_video import FilmSettings, handheld_path
from sync4d_tools.articulated.objects import SuiteObject, suite_objects

os.environ.setdefault("MUJOCO_GL", "egl")


@dataclass(frozen=True)
class View:
    """A static camera around the object: azimuth and elevation [deg] (MuJoCo free-camera convention)."""

    name: str
    azimuth: float
    elevation: float


VIEWS = (View("left", 55.0, -28.0), View("right", 125.0, -38.0))
CAMERAS = ("static", "handheld")
HANDHELD = "suite_handheld"  # the model camera a hand-held clip is filmed with (MuJoCo's free camera cannot roll)


@dataclass(frozen=True)
class Look:
    """What a clip's surroundings look like: floor colour (RGB in [0, 1]) and light direction (world)."""

    floor: tuple[float, float, float] = (0.42, 0.44, 0.46)
    light: tuple[float, float, float] = (-0.3, 0.2, -1.0)


def _jitter_colours(text: str, rng: np.random.Generator) -> str:
    """Every ``rgb1``/``rgb2``/``rgba`` colour in MJCF ``text`` scaled by 0.8-1.2 per channel, every
    ``texrepeat`` set to 5-9 cells (per metre)."""

    def colour(m: re.Match) -> str:
        values = [float(v) for v in m.group(2).split()]
        rgb = np.clip(np.array(values[:3]) * rng.uniform(0.8, 1.2, 3), 0.05, 0.95)
        return f'{m.group(1)}="{" ".join(f"{v:.3f}" for v in rgb)}{"" if len(values) == 3 else " " + str(values[3])}"'

    text = re.sub(r'(rgb1|rgb2|rgba)="([^"]+)"', colour, text)
    cells = int(rng.integers(5, 10))
    return re.sub(r'texrepeat="[^"]+"', f'texrepeat="{cells} {cells}"', text)


def variant(obj: SuiteObject, view: View, seed: int) -> tuple[SuiteObject, View, Look]:
    """The object, view and look of the clip ``seed`` (seed 0: as defined): camera azimuth +-15 deg and
    elevation +-8 deg, start state up to 15 % of the motion in, far end up to 10 % short, colours and
    checker scale of the procedural objects, floor colour and light direction."""
    if seed == 0:
        return obj, view, Look()
    rng = np.random.default_rng([seed, zlib.crc32(f"{obj.name}-{view.name}".encode())])
    view = View(view.name, view.azimuth + rng.uniform(-15, 15), float(np.clip(view.elevation + rng.uniform(-8, 8), -60, -15)))
    start, turn = np.asarray(obj.start), np.asarray(obj.turn)
    span = turn - start
    new_start = start + rng.uniform(0.0, 0.15, len(span)) * span
    new_turn = turn - rng.uniform(0.0, 0.1, len(span)) * span
    deps = obj.dependencies if obj.dependencies.startswith("<include") else _jitter_colours(obj.dependencies, rng)
    obj = replace(obj, start=tuple(float(v) for v in new_start), turn=tuple(float(v) for v in new_turn), dependencies=deps)
    floor = tuple(float(v) for v in np.clip(np.array(Look().floor) * rng.uniform(0.7, 1.3, 3), 0.1, 0.9))
    light = tuple(float(v) for v in np.array(Look().light) + np.append(rng.uniform(-0.4, 0.4, 2), 0.0))
    return obj, view, Look(floor=floor, light=light)  # type: ignore[arg-type]


def assets_dir(cache: Path) -> Path:
    """A private copy of Meta-World's assets (wrapper files are written next to its object files)."""
    import metaworld

    dst = cache / "mw_assets"
    if not dst.exists():
        shutil.copytree(Path(metaworld.__file__).parent / "assets", dst)
    return dst / "objects"


def scene_xml(obj: SuiteObject, look: Look = Look(), handheld: bool = False) -> str:
    """A standalone MJCF scene: the object on a plain floor, lit, no gravity (kinematic playback); with
    ``handheld`` a world camera (:data:`HANDHELD`) the hand-held path moves."""
    floor, light = " ".join(f"{v:.3f}" for v in look.floor), " ".join(f"{v:.3f}" for v in look.light)
    camera = f'<camera name="{HANDHELD}" mode="fixed" pos="0 0 1"/>' if handheld else ""
    return (f'<mujoco model="{obj.name}"><compiler angle="radian"/><option gravity="0 0 0"/>{obj.dependencies}'
            '<visual><headlight ambient="0.45 0.45 0.45" diffuse="0.5 0.5 0.5"/></visual>'
            f'<asset><material name="suite_floor" rgba="{floor} 1"/></asset>'
            f'<worldbody><light directional="true" diffuse=".5 .5 .5" pos="0 0 3" dir="{light}"/>'
            '<geom name="suite_floor" type="plane" size="3 3 .05" material="suite_floor"/>'
            f"{camera}{obj.body_xml}</worldbody></mujoco>")


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


def _frame_box(model: object, data: object) -> tuple[np.ndarray, np.ndarray]:
    """(lo (3,), hi (3,)) the box the camera frames: the object's geoms' bounding spheres, shrunk to 0.7."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for g in range(model.ngeom):  # type: ignore[attr-defined]
        if model.geom_bodyid[g] == 0 or model.geom_group[g] > 2:  # type: ignore[attr-defined]
            continue
        centre, radius = data.geom_xpos[g], model.geom_rbound[g]  # type: ignore[attr-defined]
        lo, hi = np.minimum(lo, centre - radius * 0.7), np.maximum(hi, centre + radius * 0.7)
    return lo, hi


def _camera(model: object, data: object, view: View) -> object:
    """A free camera looking at the object's bounding box centre, framing its motion."""
    import mujoco

    lo, hi = _frame_box(model, data)
    cam = mujoco.MjvCamera()
    cam.lookat[:] = (lo + hi) / 2
    fovy = np.radians(model.vis.global_.fovy)  # type: ignore[attr-defined]
    cam.distance = 0.8 * np.linalg.norm(hi - lo) / 2 / np.tan(fovy / 2)
    cam.azimuth, cam.elevation = view.azimuth, view.elevation
    return cam


def free_camera_eye(lookat: np.ndarray, distance: float, azimuth: float, elevation: float) -> np.ndarray:
    """(3,) the eye of MuJoCo's free camera (angles [deg]; it looks along (cos el cos az, cos el sin az, sin el))."""
    az, el = np.radians(azimuth), np.radians(elevation)
    forward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    return np.asarray(lookat, np.float64) - distance * forward


def handheld_poses(lookat: np.ndarray, eye: np.ndarray, radius: float, frames: int, rng: np.random.Generator
                   ) -> np.ndarray:
    """(T, 3, 3) per frame (eye, unit forward, unit up) of the default scene's hand-held arc
    (:func:`~sync4d.scenes.reference_video.handheld_path`, its ``arc_deg``) about the world's up (+z), starting
    at ``eye`` aimed at ``lookat``; ``radius`` [m] the object's (the aim's jitter scales with it)."""
    path = handheld_path(np.asarray(eye, np.float64), np.asarray(lookat, np.float64), radius, (0.0, 0.0, 1.0),
                         FilmSettings().arc_deg, frames, rng)
    out = np.zeros((frames, 3, 3))
    for t, (pos, aim, tilt) in enumerate(path):
        fwd = (aim - pos) / np.linalg.norm(aim - pos)
        up = tilt - fwd * (tilt @ fwd)
        out[t] = pos, fwd, up / np.linalg.norm(up)
    return out


def camera_quaternions(poses: np.ndarray) -> np.ndarray:
    """(T, 7) MuJoCo camera position and quaternion (its frame: x right, y up, z backwards) of poses (T, 3, 3)."""
    import mujoco

    out = np.zeros((len(poses), 7))
    for t, (pos, fwd, up) in enumerate(poses):
        mat = np.stack([np.cross(fwd, up), up, -fwd], axis=1)
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, mat.ravel())
        out[t] = np.concatenate([pos, quat])
    return out


def _union_box_pose(model: object, data: object, joint_ids: list[int], values: np.ndarray) -> None:
    """Pose the scene at the motion's midpoint so the camera frames the whole sweep."""
    import mujoco

    for k, j in enumerate(joint_ids):
        data.qpos[model.jnt_qposadr[j]] = values[len(values) // 2, k]  # type: ignore[attr-defined]
    mujoco.mj_forward(model, data)


def _segment(renderer: object, data: object, cam: object, model: object, part_of_body: np.ndarray) -> np.ndarray:
    """(H, W) uint8 part label of every pixel (0: background and floor)."""
    import mujoco

    renderer.enable_segmentation_rendering()  # type: ignore[attr-defined]
    renderer.update_scene(data, camera=cam)  # type: ignore[attr-defined]
    seg = renderer.render().copy()  # type: ignore[attr-defined]
    renderer.disable_segmentation_rendering()  # type: ignore[attr-defined]
    geom = np.where(seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), seg[..., 0], -1)
    body = model.geom_bodyid[np.maximum(geom, 0)]  # type: ignore[attr-defined]
    lab = np.where(geom >= 0, part_of_body[body], 0).astype(np.uint8)
    lab[(geom >= 0) & (body == 0)] = 0  # the floor
    return lab


def _depth(renderer: object, data: object, cam: object) -> np.ndarray:
    """(H, W) distance along the view axis [m] (MuJoCo's depth buffer, as our z = (p - c).fwd)."""
    renderer.enable_depth_rendering()  # type: ignore[attr-defined]
    renderer.update_scene(data, camera=cam)  # type: ignore[attr-defined]
    depth = renderer.render().copy()  # type: ignore[attr-defined]
    renderer.disable_depth_rendering()  # type: ignore[attr-defined]
    return depth


def _play(model: object, data: object, cam: object, joint_ids: list[int], values: np.ndarray, size: tuple[int, int],
          part_of_body: np.ndarray, path: np.ndarray | None = None
          ) -> tuple[list[np.ndarray], np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Render every frame: (rgb list, labels (T, H, W), depths (T, H, W), frame-0 joint axes (J, 3) and
    anchors (J, 3), the GL camera's (pos, forward, up) (3, 3), or (3, T, 3) when ``path`` (T, 7) moves the
    model camera ``cam`` (its id) per frame)."""
    import mujoco

    width, height = size
    renderer = mujoco.Renderer(model, height, width)
    rgb, labels, depths, poses = [], [], [], []
    for t in range(len(values)):
        for k, j in enumerate(joint_ids):
            data.qpos[model.jnt_qposadr[j]] = values[t, k]  # type: ignore[attr-defined]
        if path is not None:
            model.cam_pos[cam], model.cam_quat[cam] = path[t, :3], path[t, 3:]  # type: ignore[attr-defined]
        mujoco.mj_forward(model, data)
        renderer.update_scene(data, camera=cam)
        rgb.append(renderer.render().copy())
        labels.append(_segment(renderer, data, cam, model, part_of_body))
        depths.append(np.where(labels[-1] > 0, _depth(renderer, data, cam), 0.0).astype(np.float32))
        if t == 0:
            axes = np.stack([data.xaxis[j] for j in joint_ids]).copy()  # type: ignore[attr-defined]
            anchors = np.stack([data.xanchor[j] for j in joint_ids]).copy()  # type: ignore[attr-defined]
        gl = renderer.scene.camera  # the two eyes of the GL camera: their mean is the view
        poses.append(np.stack([np.mean([getattr(gl[i], k) for i in range(2)], 0) for k in ("pos", "forward", "up")]))
    pose = poses[-1] if path is None else np.stack(poses, 1)
    renderer.close()
    return rgb, np.stack(labels), np.stack(depths), axes, anchors, pose


def _handheld(model: object, data: object, free: object, frames: int, seed: int, name: str) -> tuple[int, np.ndarray]:
    """(the model camera's id, its (T, 7) path): the hand-held arc starting at the free camera ``free``'s view,
    seeded by the clip's ``seed`` and ``name``; the camera's field of view set to the free camera's."""
    import mujoco

    cid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, HANDHELD)
    model.cam_fovy[cid] = model.vis.global_.fovy  # type: ignore[attr-defined]
    lo, hi = _frame_box(model, data)
    lookat = np.array(free.lookat, np.float64)  # type: ignore[attr-defined]
    eye = free_camera_eye(lookat, free.distance, free.azimuth, free.elevation)  # type: ignore[attr-defined]
    rng = np.random.default_rng([seed, zlib.crc32(f"{name}-handheld".encode())])
    return cid, camera_quaternions(handheld_poses(lookat, eye, float(np.linalg.norm(hi - lo)) / 2, frames, rng))


def render_clip(obj: SuiteObject, view: View, out: Path, *, frames: int, width: int, height: int, cache: Path,
                look: Look = Look(), camera: str = "static", seed: int = 0) -> dict:
    """Render one object from one view into ``out`` (rgb.mp4, masks/, gt.npz); returns a summary. ``camera``
    ``handheld``: the camera moves along the hand-held arc from the view (seeded by ``seed``)."""
    import imageio.v2 as imageio
    import mujoco

    xml_path = assets_dir(cache) / f"suite_{obj.name}.xml"
    xml_path.write_text(scene_xml(obj, look, handheld=camera == "handheld"))
    model = mujoco.MjModel.from_xml_path(str(xml_path))
    data = mujoco.MjData(model)
    joint_ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n) if n else k for k, n in enumerate(obj.joints)]
    values = obj.trajectory(frames)
    part_of_body = _part_of_bodies(model, joint_ids)
    _union_box_pose(model, data, joint_ids, values)
    cam, path = _camera(model, data, view), None
    if camera == "handheld":
        cam, path = _handheld(model, data, cam, frames, seed, f"{obj.name}-{view.name}")
    rgb, labels_a, depth, axes, anchors, pose = _play(model, data, cam, joint_ids, values, (width, height), part_of_body,
                                                      path)
    fy = 0.5 * height / np.tan(np.radians(model.vis.global_.fovy) / 2)
    K = np.array([[fy, 0, width / 2], [0, fy, height / 2], [0, 0, 1.0]])
    n_parts = len(joint_ids) + 1
    part_depth = np.array([float(depth[0][labels_a[0] == p + 1].mean()) if (labels_a[0] == p + 1).any() else np.nan
                           for p in range(n_parts)])
    kinds = np.array(["hinge" if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE else "slide" for j in joint_ids])
    gt = {"part_labels": labels_a, "part_names": np.array(["background", "base"] + [f"part{j + 1}" for j in range(len(joint_ids))]),
          "joint_type": kinds, "joint_value": values.astype(np.float64), "joint_axis": axes, "joint_pos": anchors,
          "part_depth_m": part_depth, "depth_m": depth[0], "depth_t": depth,
          "fps": np.int64(12), "K": K, "cam_pos": pose[0].astype(np.float32), "cam_forward": pose[1].astype(np.float32),
          "cam_up": pose[2].astype(np.float32),
          "variant": np.array(json.dumps({"azimuth": view.azimuth, "elevation": view.elevation, "start": obj.start,
                                          "turn": obj.turn, "floor": look.floor, "light": look.light,
                                          **({"camera": camera} if camera != "static" else {})}))}
    if kinds.tolist() == ["hinge"]:
        gt["hinge_angle_rad"] = values[:, 0].astype(np.float32)
    (out / "masks").mkdir(parents=True, exist_ok=True)
    for t, lab in enumerate(labels_a):
        imageio.imwrite(out / "masks" / f"{t:05d}.png", ((lab > 0) * 255).astype(np.uint8))
    images: list[ArrayLike] = [*rgb]
    imageio.mimwrite(out / "rgb.mp4", images, fps=12, quality=9, macro_block_size=1)
    np.savez_compressed(out / "gt.npz", **gt)
    return {"clip": out.name, "object": obj.name, "view": view.name, "camera": camera, "joints": kinds.tolist(),
            "part_pixels_frame0": [int((labels_a[0] == p + 1).sum()) for p in range(n_parts)]}


def require_mujoco(what: str) -> None:
    """Fail with one line when MuJoCo (``requirements-suite.txt``) is not installed; ``what`` names the need."""
    import importlib.util

    from sync4d.errors import DataMissingError

    if importlib.util.find_spec("mujoco") is None or importlib.util.find_spec("metaworld") is None:
        raise DataMissingError(f"{what} needs MuJoCo and Meta-World: pip install -r requirements-suite.txt")


def clip_name(obj: str, view: str, seed: int, camera: str = "static") -> str:
    """The folder name of a clip: ``<object>-<view>`` at seed 0, ``<object>-<view>-s<seed>`` otherwise; a
    hand-held clip's ends in ``-hh``."""
    name = f"{obj}-{view}" if seed == 0 else f"{obj}-{view}-s{seed}"
    return name + ("-hh" if camera == "handheld" else "")


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="outputs/cache/articulated")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--size", type=int, nargs=2, default=(240, 180), metavar=("W", "H"))
    parser.add_argument("--only", nargs="*", default=[], help="object names to render (default: all)")
    parser.add_argument("--camera", choices=CAMERAS, default="static",
                        help="static views, or a hand-held arc from each (clip folders end in -hh)")
    args = parser.parse_args(argv)
    require_mujoco("rendering the articulated suite")
    cache = Path(args.out)
    cache.mkdir(parents=True, exist_ok=True)
    rows = []
    for seed in args.seeds:
        for base in suite_objects():
            if args.only and base.name not in args.only:
                continue
            for base_view in VIEWS:
                obj, view, look = variant(base, base_view, seed)
                clip = cache / "clips" / clip_name(base.name, base_view.name, seed, args.camera)
                rows.append(render_clip(obj, view, clip, frames=args.frames, width=args.size[0], height=args.size[1],
                                        cache=cache, look=look, camera=args.camera, seed=seed))
                print(json.dumps(rows[-1]))
    return rows


if __name__ == "__main__":
    import sys

    from sync4d.errors import Sync4DError

    try:
        main()
    except Sync4DError as err:  # one line and exit code 2, as the evaluation commands end
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
