"""Rendered clips with exact joint truth for ``recon_joints``: a mannequin posed by motion capture.

A body of shaded capsules (skin, shirt, trousers, shoes; a sphere for the head) is posed per frame by a
mocap clip (CMU BVH, DeepMimic) and splatted by the project's renderer (``render=splat_torch``) from a
static look-at camera on a plain backdrop, or (``--handheld SEED``) from a hand-held one in a textured
room (:func:`handheld_cameras`: a slow pan after the walker, an arc, drift and shake, seeded). Written per
clip: ``rgb.mp4``, ``masks/%05d.png`` (rendered opacity > 0.5), ``camera.npz`` (``K, cam_pos, cam_forward,
cam_up``, the laptop renders' layout; hand-held: ``K, world_to_cam`` (T, 4, 4)) and ``gt.npz`` (``joints``
(T, J, 3) [m] in the world frame, ``names`` (J,) from the ``recon_joints`` vocabulary, and the camera again,
so that ``reference=video`` finds it beside the video).

    python -m sync4d_tools.body_clips --out outputs/body_clips --clip cmu --view front [--handheld 0]

Data (attribution): CMU Graphics Lab Motion Capture Database (mocap.cs.cmu.edu; created with funding from
NSF EIA-0196217) via yuki-koyama/bvh11; DeepMimic humanoid walk (MIT) from pybullet_data (zlib).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sync4d.types import Camera

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "motion"
SKIN, SHIRT, TROUSERS, SHOE = (0.87, 0.68, 0.55), (0.18, 0.33, 0.62), (0.32, 0.27, 0.22), (0.12, 0.12, 0.12)

# truth vocabulary -> joint name in each clip's skeleton ("head" is the head sphere's centre)
CLIP_JOINTS = {
    "cmu": {
        "l_shoulder": "LeftShoulder",
        "r_shoulder": "RightShoulder",
        "l_elbow": "LeftElbow",
        "r_elbow": "RightElbow",
        "l_wrist": "LeftWrist",
        "r_wrist": "RightWrist",
        "l_hip": "LeftHip",
        "r_hip": "RightHip",
        "l_knee": "LeftKnee",
        "r_knee": "RightKnee",
        "l_ankle": "LeftAnkle",
        "r_ankle": "RightAnkle",
        "pelvis": "Hips",
        "neck": "lowerneck",
        "l_toe": "LeftToe",
        "r_toe": "RightToe",
        "l_hand": "lhand",
        "r_hand": "rhand",
        "head_base": "Head",
        "head_top": "Head_End",
    },
    "deepmimic": {
        "l_shoulder": "left_shoulder",
        "r_shoulder": "right_shoulder",
        "l_elbow": "left_elbow",
        "r_elbow": "right_elbow",
        "l_wrist": "left_wrist",
        "r_wrist": "right_wrist",
        "l_hip": "left_hip",
        "r_hip": "right_hip",
        "l_knee": "left_knee",
        "r_knee": "right_knee",
        "l_ankle": "left_ankle",
        "r_ankle": "right_ankle",
        "pelvis": "root",
        "neck": "neck",
        "l_toe": "left_ankle_end",
        "r_toe": "right_ankle_end",
        "l_hand": "left_wrist_end",
        "r_hand": "right_wrist_end",
        "head_base": "neck",
        "head_top": "neck_end",
    },
}


@dataclass(frozen=True)
class Capsule:
    """One body part: from joint ``a`` to joint ``b`` (same name = a sphere), radius [m], RGB colour."""

    a: str
    b: str
    radius: float
    colour: tuple[float, float, float]


MANNEQUIN = (
    Capsule("pelvis", "neck", 0.12, SHIRT),
    Capsule("l_hip", "r_hip", 0.09, TROUSERS),
    Capsule("l_shoulder", "r_shoulder", 0.06, SHIRT),
    Capsule("neck", "head_base", 0.045, SKIN),
    Capsule("head", "head", 0.095, SKIN),
    Capsule("hair", "hair", 0.092, (0.2, 0.12, 0.06)),
    Capsule("l_eye", "l_eye", 0.016, (0.05, 0.05, 0.05)),
    Capsule("r_eye", "r_eye", 0.016, (0.05, 0.05, 0.05)),
    Capsule("nose", "nose", 0.018, (0.8, 0.55, 0.45)),
    Capsule("mouth_l", "mouth_r", 0.01, (0.6, 0.2, 0.2)),
    Capsule("l_shoulder", "l_elbow", 0.048, SHIRT),
    Capsule("r_shoulder", "r_elbow", 0.048, SHIRT),
    Capsule("l_elbow", "l_wrist", 0.038, SKIN),
    Capsule("r_elbow", "r_wrist", 0.038, SKIN),
    Capsule("l_wrist", "l_hand", 0.035, SKIN),
    Capsule("r_wrist", "r_hand", 0.035, SKIN),
    Capsule("l_hip", "l_knee", 0.07, TROUSERS),
    Capsule("r_hip", "r_knee", 0.07, TROUSERS),
    Capsule("l_knee", "l_ankle", 0.052, TROUSERS),
    Capsule("r_knee", "r_ankle", 0.052, TROUSERS),
    Capsule("l_ankle", "l_toe", 0.04, SHOE),
    Capsule("r_ankle", "r_toe", 0.04, SHOE),
)


def load_clip(clip: str, frames: int, stride: int) -> tuple[dict[str, np.ndarray], float]:
    """Named joint tracks {name: (T, 3)} [m] (Y up) of a mocap clip and its frame rate [1/s]."""
    if clip == "cmu":
        from sync4d.io.mocap import read_bvh

        motion = read_bvh(DATA / "cmu_bvh" / "131_01.bvh")
    elif clip == "deepmimic":
        from sync4d.io.deepmimic import read_deepmimic

        motion = read_deepmimic(
            DATA / "deepmimic" / "humanoid3d_walk.txt", DATA / "deepmimic" / "humanoid.urdf", urdf_scale=0.25
        )
    elif clip == "dog":
        return load_dog(frames, stride)
    else:
        raise SystemExit(f"--clip {clip}: use cmu, deepmimic or dog")
    motion = motion.subsample(stride)
    pos = motion.positions[:frames]
    tracks = {key: pos[:, motion.names.index(name)] for key, name in CLIP_JOINTS[clip].items()}
    # the head sphere sits over the skull's base, a radius up towards its top
    up = tracks["head_top"] - tracks["head_base"]
    up /= np.linalg.norm(up, axis=-1, keepdims=True)
    tracks["head"] = tracks["head_base"] + 0.09 * up
    add_face(tracks)
    return tracks, motion.fps


def add_face(tracks: dict[str, np.ndarray]) -> None:
    """Eyes, nose and a hair cap on the head sphere (a faceless head leaves front and back ambiguous)."""
    unit = lambda v: v / np.linalg.norm(v, axis=-1, keepdims=True)  # noqa: E731
    left = unit(tracks["l_shoulder"] - tracks["r_shoulder"])
    up = unit(tracks["neck"] - tracks["pelvis"])
    fwd = unit(np.cross(left, up))
    h = tracks["head"]
    tracks["l_eye"] = h + 0.08 * fwd + 0.035 * left + 0.02 * up
    tracks["r_eye"] = h + 0.08 * fwd - 0.035 * left + 0.02 * up
    tracks["nose"] = h + 0.095 * fwd - 0.01 * up
    tracks["mouth_l"] = h + 0.085 * fwd - 0.045 * up + 0.02 * left
    tracks["mouth_r"] = h + 0.085 * fwd - 0.045 * up - 0.02 * left
    tracks["hair"] = h - 0.02 * fwd + 0.02 * up


DOG_TRUTH = (
    "pelvis",
    "neck",
    "head",
    "tail_base",
    "fl_upper",
    "fl_middle",
    "fl_paw",
    "fr_upper",
    "fr_middle",
    "fr_paw",
    "hl_upper",
    "hl_middle",
    "hl_paw",
    "hr_upper",
    "hr_middle",
    "hr_paw",
)


def load_dog(frames: int, stride: int) -> tuple[dict[str, np.ndarray], float]:
    """Named joint tracks of the AI4Animation dog trot (CC BY-NC 4.0; 60 fps), template joint names."""
    from sync4d.io.mocap import read_joint_positions
    from sync4d.recon.pose.dog import DOG_NAMES

    pos = read_joint_positions(DATA / "dog_mocap" / "dog_trot_joint_pos.txt")[::stride][:frames]
    return {n: pos[:, j] for j, n in enumerate(DOG_NAMES)}, 60.0 / stride


def dog_capsules(tracks: dict[str, np.ndarray]) -> tuple[Capsule, ...]:
    """The template's own capsules (radii as in the quadruped fit), one brown body with darker paws."""
    from sync4d.recon.pose.dog import DOG_NAMES, DOG_PARENTS, DOG_RADII

    length = float(np.linalg.norm(tracks["head"][0] - tracks["tail_base"][0]))
    fur, paw = (0.62, 0.42, 0.24), (0.25, 0.17, 0.1)
    return tuple(
        Capsule(DOG_NAMES[p], DOG_NAMES[j], float(DOG_RADII[j] * length), paw if DOG_NAMES[j].endswith("paw") else fur)
        for j, p in enumerate(DOG_PARENTS)
        if p >= 0
    )


def capsule_gaussians(
    a: np.ndarray, b: np.ndarray, radius: float, rng: np.random.Generator, *, density: float = 16000.0
) -> tuple[np.ndarray, np.ndarray]:
    """Points on a capsule's surface (uniform by area, ``density`` per m^2) and their outward normals."""
    axis = b - a
    length = float(np.linalg.norm(axis))
    area = 2 * np.pi * radius * length + 4 * np.pi * radius**2
    n = max(64, int(area * density))
    z = axis / length if length > 1e-9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    s = rng.uniform(0, 1, n)
    on_cyl = rng.uniform(0, area, n) < 2 * np.pi * radius * length
    local = normals.copy()
    local[on_cyl, 2] = 0.0
    local /= np.linalg.norm(local, axis=1, keepdims=True)
    centre = np.where(on_cyl[:, None], s[:, None] * length, (local[:, 2:3] > 0) * length)
    pts_local = local * radius + np.concatenate([np.zeros((n, 2)), centre], axis=1)[:, [0, 1, 2]]
    rot = np.stack([x, y, z], axis=1)
    return a + pts_local @ rot.T, local @ rot.T


def render_clip(tracks: dict[str, np.ndarray], camera: Camera | list[Camera], *, seed: int = 0,
                room: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(T, H, W, 3) uint8 frames and (T, H, W) bool masks of the mannequin posed by ``tracks``, seen by one
    camera or one per frame; ``room``: in a textured room (a background a moving camera can be found from)
    instead of the plain backdrop."""
    from sync4d.render.splat_torch import SplatTorch
    from sync4d.scenes.reference_video import room_image

    renderer = SplatTorch(SplatTorch.Config(background=[0.0] * 3 if room else [0.78, 0.78, 0.76], num_threads=1))
    allp = np.concatenate(list(tracks.values()))
    centre, floor_y = 0.5 * (allp.min(0) + allp.max(0)), float(allp[:, 1].min()) - 0.04
    half = 1.5 * float(np.ptp(allp, axis=0).max()) + 1.5
    light = np.array([0.3, 0.8, 0.6])
    light /= np.linalg.norm(light)
    rng = np.random.default_rng(seed)
    frames, masks = [], []
    for t in range(len(tracks["pelvis"])):
        pts, cols = [], []
        for part in dog_capsules(tracks) if "tail_base" in tracks else MANNEQUIN:
            p, n = capsule_gaussians(tracks[part.a][t], tracks[part.b][t], part.radius, rng)
            shade = 0.35 + 0.65 * np.clip(n @ light, 0, None)
            pts.append(p)
            cols.append(np.asarray(part.colour)[None] * shade[:, None])
        means = np.concatenate(pts)
        sigma = 0.008
        covs = np.tile(np.eye(3) * sigma**2, (len(means), 1, 1))
        cam = camera[t] if isinstance(camera, list) else camera
        out = renderer.render_full(means, covs, np.concatenate(cols), np.full(len(means), 0.9), cam)
        rgb, alpha = np.asarray(out["rgb"]), np.asarray(out["alpha"]).reshape(cam.height, cam.width)
        if room:
            rgb = rgb + (1.0 - alpha[..., None]) * room_image(cam, centre, floor_y, half)
        frames.append((np.clip(rgb, 0, 1) * 255).astype(np.uint8))
        masks.append(alpha > 0.5)
    return np.stack(frames), np.stack(masks)


def clip_camera(tracks: dict[str, np.ndarray], view: str, width: int, height: int, fov_deg: float
                ) -> tuple[Camera, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A static look-at camera framing the whole clip; returns (Camera, K, position, forward, up)."""
    from sync4d.sources.references import camera_from_look

    allp = np.concatenate([v for v in tracks.values()])
    centre = 0.5 * (allp.min(0) + allp.max(0))
    extent = allp.max(0) - allp.min(0)
    angle = {"front": 0.0, "side": 90.0, "oblique": 40.0, "back": 180.0}[view]
    # the clip's facing: from the pelvis towards the average of the toes, else +z
    if "tail_base" in tracks:  # a quadruped faces from its tail to its head
        facing = (tracks["head"] - tracks["tail_base"]).mean(0)
    else:
        facing = 0.5 * (tracks["l_toe"] + tracks["r_toe"] - tracks["l_ankle"] - tracks["r_ankle"]).mean(0)
    facing[1] = 0.0
    facing = facing / np.linalg.norm(facing) if np.linalg.norm(facing) > 1e-6 else np.array([0.0, 0.0, 1.0])
    c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
    to_cam = np.array([c * facing[0] + s * facing[2], 0.0, -s * facing[0] + c * facing[2]])
    f = 0.5 * height / np.tan(np.radians(fov_deg) / 2)
    dist = 1.25 * max(extent[1], 0.7 * max(extent[0], extent[2])) * f / height + 0.5 * max(extent[0], extent[2])
    pos = centre + to_cam * dist + np.array([0.0, 0.25, 0.0])
    fwd = centre - pos
    up = np.array([0.0, 1.0, 0.0])
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    return camera_from_look(K, pos, fwd, up, width, height), K, pos, fwd, up


def handheld_cameras(tracks: dict[str, np.ndarray], view: str, width: int, height: int, fov_deg: float,
                     seed: int) -> list[Camera]:
    """Per-frame cameras of a hand-held film of the clip, around :func:`clip_camera`'s static framing.

    Over the clip the camera walks a 20 deg arc around the clip's centre (smoothstep, direction by the seed)
    and bobs 5 cm; it pans after the walker (aims at the point halfway between the clip's centre and the
    pelvis), drifts (a seeded random walk of the aim, 3 cm a frame) and shakes (0.7 deg of aim and 1 deg of
    roll a frame, white).
    """
    from sync4d.sources.references import camera_from_look

    rng = np.random.default_rng(seed)
    _, K, pos, _, up = clip_camera(tracks, view, width, height, fov_deg)
    allp = np.concatenate(list(tracks.values()))
    centre = 0.5 * (allp.min(0) + allp.max(0))
    count = len(tracks["pelvis"])
    s = np.linspace(0.0, 1.0, count)
    sweep = np.radians(20.0) * (3 * s**2 - 2 * s**3 - 0.5) * (1 if rng.uniform() < 0.5 else -1)
    drift = np.cumsum(rng.normal(0.0, 0.03, (count, 3)), axis=0) * np.array([1.0, 0.5, 1.0])
    cams = []
    for t in range(count):
        c, sn = np.cos(sweep[t]), np.sin(sweep[t])
        arm = pos - centre
        p = centre + np.array([c * arm[0] + sn * arm[2], arm[1], -sn * arm[0] + c * arm[2]])
        p = p + np.array([0.0, 0.05 * np.sin(2 * np.pi * s[t]), 0.0])
        aim = centre + 0.5 * (tracks["pelvis"][t] - centre) + drift[t]
        fwd = aim - p
        dist = float(np.linalg.norm(fwd))
        fwd = fwd + rng.normal(0.0, np.radians(0.7) * dist, 3)
        roll = np.radians(rng.normal(0.0, 1.0))
        side = np.cross(fwd / np.linalg.norm(fwd), up)
        side /= np.linalg.norm(side)
        cams.append(camera_from_look(K, p, fwd, np.cos(roll) * up + np.sin(roll) * side, width, height))
    return cams


def write_clip(
    out: Path, clip: str, view: str, *, frames: int, stride: int, width: int, height: int, fov_deg: float,
    handheld: int | None = None,
) -> dict:
    """Render one clip into ``out`` (static camera, or hand-held with seed ``handheld``) and return a summary."""
    import imageio.v2 as imageio

    from sync4d.io.video import write_video

    tracks, fps = load_clip(clip, frames, stride)
    camera, K, pos, fwd, up = clip_camera(tracks, view, width, height, fov_deg)
    if handheld is not None:
        cameras = handheld_cameras(tracks, view, width, height, fov_deg, handheld)
        rgb, masks = render_clip(tracks, cameras, room=True)
    else:
        rgb, masks = render_clip(tracks, camera)
    out.mkdir(parents=True, exist_ok=True)
    write_video(out / "rgb.mp4", rgb, fps)
    (out / "masks").mkdir(exist_ok=True)
    for t, m in enumerate(masks):
        imageio.imwrite(out / "masks" / f"{t:05d}.png", (m * 255).astype(np.uint8))
    cam_fields: dict[str, Any] = ({"world_to_cam": np.stack([c.world_to_cam for c in cameras])} if handheld is not None else
                  {"cam_pos": pos, "cam_forward": fwd, "cam_up": up})
    np.savez(out / "camera.npz", K=K, **cam_fields)
    from sync4d_tools.evaluate.recon_joints import HUMAN_VOCABULARY

    names = DOG_TRUTH if clip == "dog" else HUMAN_VOCABULARY
    joints = np.stack([tracks[n] for n in names], axis=1)
    # the camera again in gt.npz: reference=video's camera 'auto' reads gt.npz beside the video (laptop layout)
    np.savez(out / "gt.npz", joints=joints, names=np.array(names), fps=fps, K=K, **cam_fields)
    return {"clip": clip, "view": view, "frames": len(rgb), "fps": fps, "out": str(out), "handheld": handheld}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--clip", default="cmu", choices=["cmu", "deepmimic", "dog"])
    parser.add_argument("--view", default="front", choices=["front", "side", "oblique", "back"])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--stride", type=int, default=8)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--fov", type=float, default=50.0, help="vertical field of view [deg]")
    parser.add_argument("--handheld", type=int, default=None, metavar="SEED",
                        help="film hand-held in a textured room with this seed (default: static camera, plain backdrop)")
    args = parser.parse_args(argv)
    result = write_clip(
        Path(args.out),
        args.clip,
        args.view,
        frames=args.frames,
        stride=args.stride,
        width=args.width,
        height=args.height,
        fov_deg=args.fov,
        handheld=args.handheld,
    )
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
