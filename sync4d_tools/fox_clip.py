"""Rendered quadruped clips with exact joints: the Khronos glTF fox playing its own animations.

``../shared/data/skinned/fox/Fox.gltf`` (KhronosGroup/glTF-Sample-Models; low poly fox by PixelMannen, CC0;
rigging and animation by @tomkranis, CC-BY 4.0; glTF conversion by @AsoboStudio and @scurest) is posed by
one of its clips (``Walk``, ``Run``, ``Survey``; the rig's own linear-blend skinning, :mod:`sync4d.io.gltf`),
sampled into small Gaussians coloured by its texture and splatted by ``render=splat_torch``
(:func:`sync4d_tools.shiba_clip.render_mesh_frames`). File units are centimetre-like: scaled by 0.01.

Views: ``side``, ``oblique``, ``front`` (static look-at cameras as in :mod:`sync4d_tools.body_clips`) and
``orbit`` (a moving camera: it turns ``ORBIT_DEG`` about the fox over the clip, from the oblique view, and
dollies in by ``DOLLY`` of its distance). Written: ``rgb.mp4``, ``masks/%05d.png`` (opacity > 0.5),
``camera.npz`` (``K``, ``world_to_cam`` (T, 4, 4) per frame) and ``gt.npz`` (``joints`` (T, J, 3) [m] in the
world frame, ``names`` in the ``recon_joints`` quadruped vocabulary, ``fps``, ``K``, ``world_to_cam``).

Joint truth: the rig's own joints (:data:`sync4d.recon.pose.templates.FOX_JOINTS`: hip, neck, head, first
tail joint, shoulder / elbow / wrist of the fore legs, hip / stifle / toe joint of the hind legs), exact.

    python -m sync4d_tools.fox_clip --out outputs/body_suite/fox_walk_side --clip Walk --view side
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

FOX = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "skinned" / "fox" / "Fox.gltf"
METRES_PER_UNIT = 0.01
SIZE = (480, 320)
ORBIT_DEG = 50.0
DOLLY = 0.2
#: frames per second each clip is sampled at (about 20 frames a clip)
CLIP_FPS = {"Walk": 24.0, "Run": 18.0, "Survey": 6.0}


def fox_frames(clip: str, fps: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray, tuple[str, ...]]:
    """Posed vertices (T, V, 3) [m], faces, vertex colours (V, 3), truth joints (T, J, 3) [m] and their names
    over one loop of ``clip`` sampled at ``fps``."""
    from sync4d.io.gltf import joint_matrices, joint_world, read_gltf, skin_vertices, vertex_colours
    from sync4d.recon.pose.templates import FOX_JOINTS, VOCABULARY

    mesh = read_gltf(FOX)
    anim = mesh.animation(clip)
    times = np.arange(int(np.floor(anim.duration * fps))) / fps
    verts = np.stack([skin_vertices(mesh, joint_matrices(mesh, anim, t)) for t in times]) * METRES_PER_UNIT
    rig = dict((name, rig_name) for rig_name, name in FOX_JOINTS)
    names = tuple(v for v, _ in VOCABULARY)
    ids = [mesh.joint_names.index(rig[n]) for n in names]
    joints = np.stack([joint_world(mesh, anim, t)[ids, :3, 3] for t in times]) * METRES_PER_UNIT
    return verts, mesh.faces, vertex_colours(mesh), joints, names


def view_cameras(verts: np.ndarray, view: str) -> tuple[list, np.ndarray, np.ndarray]:
    """Cameras per frame, their K and (T, 4, 4) world-to-camera matrices for ``view``."""
    from sync4d.sources.references import camera_from_look
    from sync4d_tools.body_clips import clip_camera

    tracks = {"head": verts[:, :, :].max(1) * [0, 0, 1], "tail_base": verts.min(1) * [0, 0, 1],
              "all": np.concatenate([verts.min(1), verts.max(1)])}
    camera, K, pos, fwd, up = clip_camera(tracks, "oblique" if view == "orbit" else view, SIZE[0], SIZE[1], 50.0)
    if view != "orbit":
        return [camera] * len(verts), K, np.repeat(camera.world_to_cam[None], len(verts), 0)
    centre = pos + fwd  # clip_camera looks from pos at the clip's centre
    cams = []
    for t in range(len(verts)):
        s = t / max(len(verts) - 1, 1)
        a = np.radians(ORBIT_DEG * s)
        rot = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        offset = rot @ (pos - centre) * (1 - DOLLY * s)
        cams.append(camera_from_look(K, centre + offset, -offset, up, SIZE[0], SIZE[1]))
    return cams, K, np.stack([c.world_to_cam for c in cams])


def write_clip(out: Path, clip: str, view: str) -> dict:
    """Render the fox playing ``clip`` seen from ``view`` into ``out``."""
    import imageio.v2 as imageio

    from sync4d.io.video import write_video
    from sync4d_tools.shiba_clip import render_mesh_frames

    fps = CLIP_FPS[clip]
    verts, faces, colours, joints, names = fox_frames(clip, fps)
    cameras, K, w2c = view_cameras(verts, view)
    rgb, masks = render_mesh_frames(verts, faces, colours, cameras, samples=40000)
    out.mkdir(parents=True, exist_ok=True)
    write_video(out / "rgb.mp4", rgb, fps)
    (out / "masks").mkdir(exist_ok=True)
    for t, m in enumerate(masks):
        imageio.imwrite(out / "masks" / f"{t:05d}.png", (m * 255).astype(np.uint8))
    static = view != "orbit"
    world_to_cam = w2c[0] if static else w2c
    np.savez(out / "camera.npz", K=K, world_to_cam=world_to_cam)
    np.savez(out / "gt.npz", joints=joints, names=np.array(names), fps=fps, K=K, world_to_cam=world_to_cam)
    return {"clip": f"fox_{clip.lower()}", "view": view, "frames": len(rgb), "fps": fps, "out": str(out)}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--clip", default="Walk", choices=sorted(CLIP_FPS))
    parser.add_argument("--view", default="side", choices=["side", "oblique", "front", "orbit"])
    args = parser.parse_args(argv)
    result = write_clip(Path(args.out), args.clip, args.view)
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
