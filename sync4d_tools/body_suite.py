"""The ``recon_joints`` suite: render every clip/view with truth, fit it with one configuration, tabulate.

    python -m sync4d_tools.body_suite --out outputs/body_suite [--only cmu,deepmimic,dog,shiba,fox_walk,fox_walk_orbit]
    python -m sync4d_tools.body_suite --held-out --out outputs/body_suite   # quadruped rows nothing was tuned on

Humans are scored twice: with the renders' camera (``--camera``) and with the camera unknown (the fit's
assumed field of view), through ``recon_joints``. The people clips are also filmed hand-held in a textured
room (:data:`HANDHELD`: each clip and view at two seeds, ``<clip>_<view>_handheld<seed>``; ``--only handheld``
runs these alone) and scored by :func:`score_handheld`: from the mp4 alone (the video front end's masks and
camera), with the true per-frame camera, with the camera taken as static, and the do-nothing floor. Quadrupeds are fitted with their true masks and true camera
(per frame when it moves: :func:`load_quadruped_clip` hands ``VideoClip.extrinsics`` to the fit) and scored
here (:func:`score_quadruped`), the floor beside (:func:`floor_joints`: the template's rest pose at each
mask's centroid): the dog trot (capsules around the AI4Animation trot), the Lab4D shiba-haru-1002 export
(:mod:`sync4d_tools.shiba_clip`; ``export`` is its handheld camera turned into object motion) and the glTF
fox's own clips (:mod:`sync4d_tools.fox_clip`; ``orbit`` is a moving camera). Prints a Markdown table and
writes ``suite.json``; every clip is reported, failures included.

``--split`` (quadruped clips already in ``--out``) splits each clip's error instead of fitting from scratch:
``A1`` the template's joints fitted to the truth joints directly (forward kinematics, per-frame pose, lengths
and scale free, no priors: the floor of the joint definitions), ``A2`` the same under the fit's priors (limb
lengths, girths, joint limits: the ceiling of the template), ``B`` the silhouette clip fit started at A2
(girth first, then the clip schedule: where the objective's minimum lies). The defaults' own row (the
search from scratch) minus B is the search's share, B minus A2 the objective's and body shape's.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from sync4d.errors import Sync4DError
from sync4d.recon.body_video import BodyVideoFit
from sync4d.types import Camera, ReferenceInput, VideoClip
from sync4d_tools import camera_of, video_of
from sync4d_tools.body_clips import write_clip
from sync4d_tools.evaluate.recon_joints import fit_silhouettes, joint_errors, mask_iou
from sync4d_tools.evaluate.recon_joints import main as recon_joints
from sync4d_tools.fox_clip import write_clip as write_fox
from sync4d_tools.shiba_clip import write_clip as write_shiba

if TYPE_CHECKING:
    import torch

    from sync4d.recon.pose.quadruped_fit import Params, QuadrupedFitConfig, QuadrupedProblem

CLIPS = (
    ("cmu", "front", 30, 12),
    ("cmu", "side", 30, 12),
    ("cmu", "oblique", 30, 12),
    ("deepmimic", "front", 39, 1),
    ("deepmimic", "oblique", 39, 1),
    ("deepmimic", "side", 39, 1),
    ("dog", "side", 17, 2),
    ("dog", "oblique", 17, 2),
    ("dog", "front", 17, 2),
    ("shiba", "side", 21, 1),
    ("shiba", "oblique", 21, 1),
    ("shiba", "front", 21, 1),
    ("shiba", "export", 21, 1),
    ("fox_walk", "side", 0, 1),
    ("fox_walk", "front", 0, 1),
    ("fox_walk", "orbit", 0, 1),
    ("fox_run", "oblique", 0, 1),
    ("fox_run", "orbit", 0, 1),
    ("fox_survey", "oblique", 0, 1),
)
QUADRUPEDS = ("dog", "shiba", "fox_walk", "fox_run", "fox_survey")
# quadruped rows no setting was chosen on (``--held-out``): other views, the dog filmed hand-held (seed), the fox's
# other clips; clip, view, hand-held seed or None
QUADRUPED_HELDOUT = (
    ("dog", "back", None),
    ("dog", "side", 0),
    ("dog", "oblique", 1),
    ("fox_run", "side", None),
    ("fox_run", "front", None),
    ("fox_survey", "side", None),
    ("fox_survey", "front", None),
    ("fox_walk", "oblique", None),
)
# people filmed hand-held in a textured room (sync4d_tools.body_clips.handheld_cameras): clip, view, seed
HANDHELD = tuple((clip, view, seed + 6 * rep) for rep in range(2) for seed, (clip, view) in enumerate(
    (c, v) for c in ("cmu", "deepmimic") for v in ("front", "oblique", "side")))


def row_name(clip: str, view: str, handheld: int | None = None) -> str:
    """A row's folder name: ``<clip>_<view>``, or ``<clip>_<view>_handheld<seed>`` when filmed hand-held."""
    return f"{clip}_{view}" if handheld is None else f"{clip}_{view}_handheld{handheld}"


def render_clip(folder: Path, clip: str, view: str, frames: int, stride: int, handheld: int | None = None) -> None:
    """Render a clip into ``folder`` unless it is there already (hand-held with seed ``handheld``: people and
    the dog)."""
    if (folder / "gt.npz").is_file():
        return
    if clip == "shiba":
        write_shiba(folder, view)
    elif clip.startswith("fox_"):
        write_fox(folder, clip[4:].capitalize(), view)
    else:
        human = clip not in QUADRUPEDS
        width, height = (320, 480) if human else (480, 320)
        write_clip(folder, clip, view, frames=frames, stride=stride, width=width, height=height, fov_deg=50.0,
                   handheld=handheld)


def run_handheld(out: Path, clip: str, view: str, seed: int) -> dict:
    """Render (if absent) and score one hand-held people clip (:func:`score_handheld`)."""
    folder = out / row_name(clip, view, seed)
    if not (folder / "gt.npz").is_file():
        frames, stride = next((f, s) for c, v, f, s in CLIPS if c == clip and v == view)
        write_clip(folder, clip, view, frames=frames, stride=stride, width=320, height=480, fov_deg=50.0,
                   handheld=seed)
    return {"clip": clip, "view": view, "seed": seed, **score_handheld(folder)}


def score_handheld(folder: Path) -> dict:
    """One hand-held people clip fitted three ways from the same frames, scored as ``recon_joints`` does:
    ``alone`` (the mp4 only: masks, intrinsics and per-frame camera from the video front end), ``given`` (the
    true intrinsics and per-frame camera), ``identity`` (the front end's intrinsics, the camera taken as
    static: its motion read as the body's), and the do-nothing floor (:func:`human_floor`)."""
    from sync4d.frontend import FrontEndConfig, complete_video
    from sync4d.io.video import read_video_clip

    video = read_video_clip(folder / "rgb.mp4", folder / "masks")
    h, w = video.frames.shape[1:3]
    gt = np.load(folder / "gt.npz")
    truth, names = np.asarray(gt["joints"], dtype=np.float64), [str(n) for n in gt["names"]]
    cam = np.load(folder / "camera.npz")
    K, w2c = cam["K"].astype(np.float64), cam["world_to_cam"].astype(np.float64)
    bare = VideoClip(video.frames, np.zeros_like(video.masks), video.fps, source=str(folder)).validate()
    given = Camera(K=K, world_to_cam=w2c[0], width=w, height=h).validate()
    inputs = {"given": (VideoClip(video.frames, np.zeros_like(video.masks), video.fps, K, w2c, str(folder)).validate(),
                        given)}
    row: dict = {}
    cpu = time.process_time()
    try:
        found, first = complete_video(bare, None, FrontEndConfig(), masks_given=False)
    except Sync4DError as err:  # a refusal is a result: no mp4-alone row
        row["front_end_error"] = str(err)
    else:
        assert found.extrinsics is not None and found.intrinsics is not None  # the front end fills the camera
        still = Camera(K=found.intrinsics, world_to_cam=np.eye(4), width=w, height=h).validate()
        inputs["alone"] = (found, first)
        inputs["identity"] = (VideoClip(video.frames, found.masks, video.fps, found.intrinsics, None,
                                        str(folder)).validate(), still)
    front_cpu = time.process_time() - cpu
    for key, (clip, camera) in inputs.items():
        fit, cpu_s = human_fit(ReferenceInput(name=folder.name, fps=video.fps, video=clip, camera=camera))
        score = joint_score(fit.joints[:, [fit.names.index(n) for n in names]], truth[: len(fit.joints)])
        row[f"{key}_mpjpe_pct_height"], row[f"{key}_pck10"] = score["mpjpe_pct_height"], score["pck10"]
        row[f"{key}_cpu_seconds"] = round(cpu_s, 2)
        if key == "alone":
            row["mask_iou"] = round(mask_iou(fit.masks, video.masks), 4)
            row["front_end_mask_iou"] = round(mask_iou(found.masks, video.masks), 4)
    floor = joint_score(human_floor(video.masks, K, w2c, names), truth)
    rot = np.einsum("tij,kj->tik", w2c[:, :3, :3], w2c[0, :3, :3])  # each camera relative to the first
    turn = np.degrees(np.arccos(np.clip((np.trace(rot, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return {**row, "floor_mpjpe_pct_height": floor["mpjpe_pct_height"], "floor_pck10": floor["pck10"],
            "ratio_alone_given": (round(row["alone_mpjpe_pct_height"] / max(row["given_mpjpe_pct_height"], 1e-9), 3)
                                  if "alone_mpjpe_pct_height" in row else None),
            "camera_turn_max_deg": round(float(turn.max()), 2), "front_end_cpu_seconds": round(front_cpu, 2),
            "frames": len(truth), "height_m": floor["height_m"]}


def human_fit(source: ReferenceInput) -> tuple[BodyVideoFit, float]:
    """``recon=body_video`` (human, defaults) on ``source``: the fit and its CPU seconds."""
    from sync4d.recon.body_video import BodyVideoReconstructor

    cpu = time.process_time()
    fit = BodyVideoReconstructor(BodyVideoReconstructor.Config(subject="human", figures=False)).fit(source)
    return fit, time.process_time() - cpu


# a person standing, arms down, facing +z, y up, pelvis at the origin [m] (1.7 m tall; recon_joints' names)
STANDING = {
    "head": (0.0, 0.62, 0.0), "l_shoulder": (0.19, 0.46, 0.0), "r_shoulder": (-0.19, 0.46, 0.0),
    "l_elbow": (0.22, 0.17, 0.0), "r_elbow": (-0.22, 0.17, 0.0), "l_wrist": (0.23, -0.09, 0.03),
    "r_wrist": (-0.23, -0.09, 0.03), "l_hip": (0.1, -0.02, 0.0), "r_hip": (-0.1, -0.02, 0.0),
    "l_knee": (0.1, -0.46, 0.02), "r_knee": (-0.1, -0.46, 0.02), "l_ankle": (0.1, -0.88, 0.0),
    "r_ankle": (-0.1, -0.88, 0.0),
}


def human_floor(masks: np.ndarray, K: np.ndarray, w2c: np.ndarray, names: list[str]) -> np.ndarray:
    """The do-nothing baseline (T, J, 3) [m, world]: a person standing (:data:`STANDING`) facing each frame's
    camera, at its mask's centroid at the depth a 1.7 m person of the mask's height is at, taken to the
    world by the true camera of each frame."""
    out: list[np.ndarray] = []
    pose = np.array([STANDING[n] for n in names]) * np.array([1.0, -1.0, -1.0])  # y down, facing the camera
    for t, mask in enumerate(masks):
        ys, xs = np.nonzero(mask)
        if len(ys) == 0:
            out.append(out[-1] if out else np.zeros((len(names), 3)))
            continue
        depth = K[1, 1] * 1.7 / max(float(np.ptp(ys)), 1.0)
        centre = np.linalg.inv(K) @ np.array([xs.mean(), ys.mean(), 1.0]) * depth
        c2w = np.linalg.inv(w2c[t])
        out.append((pose + centre) @ c2w[:3, :3].T + c2w[:3, 3])
    return np.stack(out)


def run_clip(out: Path, clip: str, view: str, frames: int, stride: int, handheld: int | None = None) -> list[dict]:
    """Render (if absent) and score one clip; one row per camera setting (humans: known and assumed)."""
    folder = out / row_name(clip, view, handheld)
    render_clip(folder, clip, view, frames, stride, handheld)
    if clip in QUADRUPEDS:
        setting = "known" if handheld is None else f"known, hand-held {handheld}"
        return [{"clip": clip, "view": view, "camera": setting, **score_quadruped(folder)}]
    rows = []
    for camera in [True, False]:
        args = ["--video", str(folder / "rgb.mp4"), "--masks", str(folder / "masks"), "--gt", str(folder / "gt.npz"),
                "--subject", "human"]
        if camera:
            args += ["--camera", str(folder / "camera.npz")]
        with contextlib.redirect_stdout(io.StringIO()):
            result = recon_joints(args)
        rows.append({"clip": clip, "view": view, "camera": "known" if camera else "assumed fov", **result})
    return rows


def load_quadruped_clip(folder: Path) -> tuple[ReferenceInput, np.ndarray, list[str], np.ndarray]:
    """A rendered quadruped clip with its true masks and camera (per frame when it moves): the fit's input, the
    truth joints (T, J, 3) [m, world], their names and the (T, 4, 4) world-to-camera matrices."""
    from sync4d.io.video import read_video_clip
    from sync4d.sources.references import load_camera

    clip = read_video_clip(folder / "rgb.mp4", folder / "masks")
    h, w = clip.frames.shape[1:3]
    cam = np.load(folder / "camera.npz")
    moving = "world_to_cam" in cam and cam["world_to_cam"].ndim == 3
    if moving:
        w2c = cam["world_to_cam"].astype(np.float64)
        camera = Camera(K=cam["K"].astype(np.float64), world_to_cam=w2c[0], width=w, height=h).validate()
    else:
        camera, _ = load_camera(folder / "camera.npz", w, h)
        w2c = np.repeat(camera.world_to_cam[None], clip.num_frames, 0)
    clip = VideoClip(clip.frames, clip.masks, clip.fps, camera.K, w2c if moving else None, str(folder)).validate()
    gt = np.load(folder / "gt.npz")
    source = ReferenceInput(name=folder.name, fps=clip.fps, video=clip, camera=camera,
                            world_up=np.array([0.0, 1.0, 0.0]))
    return source, np.asarray(gt["joints"], dtype=np.float64), [str(n) for n in gt["names"]], w2c


def joint_score(pred_world: np.ndarray, truth: np.ndarray) -> dict:
    """mpjpe in % of the height and pck10 after one similarity for the clip (``recon_joints``' metric)."""
    height = float((truth[..., 1].max(1) - truth[..., 1].min(1)).max())
    err = joint_errors(pred_world, truth)
    return {"mpjpe_pct_height": round(100.0 * float(err.mean()) / height, 3),
            "pck10": round(float((err < 0.1 * height).mean()), 4), "height_m": round(height, 4)}


def floor_joints(source: ReferenceInput, names: list[str]) -> np.ndarray:
    """The do-nothing baseline (T, J, 3) [m, world]: the template's rest pose, heading 0, placed in every frame at
    its mask's centroid at the depth the mask's extent implies (first camera frame), then to the world."""
    from sync4d.recon.pose import quadruped_fit as qf
    from sync4d.recon.pose.templates import body_template

    cfg = qf.QuadrupedFitConfig()
    tmpl = body_template(cfg.template)
    ids = [tmpl.names.index(dict(tmpl.vocabulary)[n]) for n in names]
    clip, camera = video_of(source), camera_of(source)
    w2c0 = camera.world_to_cam
    rot = qf.heading_rotation(w2c0[:3, :3] @ source.world_up, 0.0)
    from scipy.spatial.transform import Rotation

    rest = tmpl.joints[ids] * cfg.template_length @ Rotation.from_rotvec(rot).as_matrix().T
    out = []
    for t, mask in enumerate(clip.masks):
        root = qf.initial_root(mask, camera, cfg.template_length, cfg.template_length * float(np.ptp(tmpl.vertices[:, 1])))
        ext = clip.extrinsics
        to_first = np.eye(4) if ext is None else ext[0] @ np.linalg.inv(ext[t])  # frame t camera -> first
        out.append((rest + root) @ to_first[:3, :3].T + to_first[:3, 3])
    return first_camera_to_world(np.stack(out), w2c0)


def first_camera_to_world(points: np.ndarray, w2c0: np.ndarray) -> np.ndarray:
    c2w = np.linalg.inv(w2c0)
    return points @ c2w[:3, :3].T + c2w[:3, 3]


def score_quadruped(folder: Path) -> dict:
    """Fit one rendered quadruped clip with the defaults (true masks and camera) and score it, the floor beside."""
    from sync4d.recon.body_video import BodyVideoReconstructor

    source, truth, names, _ = load_quadruped_clip(folder)
    start, cpu = time.perf_counter(), time.process_time()
    recon = BodyVideoReconstructor(BodyVideoReconstructor.Config(subject="quadruped", figures=False))
    fit = recon.fit(source)
    cpu_s = time.process_time() - cpu
    mapping = dict(recon_template_vocabulary())
    clip, camera = video_of(source), camera_of(source)
    pred = first_camera_to_world(fit.joints[:, [fit.names.index(mapping[n]) for n in names]], camera.world_to_cam)
    row = joint_score(pred, truth[: len(pred)])
    floor = joint_score(floor_joints(source, names), truth)
    return {**row, "floor_mpjpe_pct_height": floor["mpjpe_pct_height"], "floor_pck10": floor["pck10"],
            "mask_iou": round(mask_iou(fit_silhouettes(fit), clip.masks), 4), "frames": len(pred),
            "moving_camera": clip.extrinsics is not None, "seconds": round(time.perf_counter() - start, 2),
            "cpu_seconds": round(cpu_s, 2), "cpu_seconds_per_frame": round(cpu_s / len(pred), 2)}


def recon_template_vocabulary() -> tuple[tuple[str, str], ...]:
    from sync4d.recon.pose.quadruped_fit import QuadrupedFitConfig
    from sync4d.recon.pose.templates import body_template

    return body_template(QuadrupedFitConfig().template).vocabulary


def split_clip(folder: Path) -> dict:
    """The A1 / A2 / B split of one quadruped clip (see the module docstring); mpjpe in % of the height."""
    import torch

    from sync4d.recon.pose import quadruped_fit as qf

    source, truth, names, w2c = load_quadruped_clip(folder)
    truth_cam = np.einsum("ij,tkj->tki", w2c[0][:3, :3], truth) + w2c[0][:3, 3]  # the first camera's frame
    cfg = qf.QuadrupedFitConfig()
    clip = video_of(source)
    prob = qf.QuadrupedProblem(clip.masks, camera_of(source), cfg, frames=clip.frames, extrinsics=clip.extrinsics,
                               fps=source.fps)
    tmpl = prob.tt.template
    ids = [tmpl.names.index(dict(tmpl.vocabulary)[n]) for n in names]
    frames, up_cam = np.arange(len(truth)), w2c[0][:3, :3] @ np.array([0.0, 1.0, 0.0])
    row: dict = {"clip": folder.name}
    for key, priors in (("A1", False), ("A2", True)):
        params = truth_start(prob, truth_cam, names, up_cam)
        fit_to_truth(prob, params, torch.tensor(truth_cam, dtype=qf.DTYPE), ids, cfg, priors)
        joints = qf.pose_body(prob.tt, params)[0].detach().numpy().astype(np.float64)
        row[key] = joint_score(first_camera_to_world(joints[:, ids], w2c[0]), truth)["mpjpe_pct_height"]
    qf.run_steps(prob, frames, params, cfg, 60, free=("log_thick", "log_girth"))
    row["A2_loss"] = round(qf.run_steps(prob, frames, params, cfg, 0)[0], 4)
    loss, joints, iou = qf.run_steps(prob, frames, params, cfg, cfg.iterations + cfg.swap_iterations)
    row["B"] = joint_score(first_camera_to_world(joints[:, ids], w2c[0]), truth)["mpjpe_pct_height"]
    row["B_loss"], row["B_iou"] = round(loss, 4), round(float(iou.mean()), 3)
    return row


def truth_start(prob: QuadrupedProblem, truth_cam: np.ndarray, names: list[str], up_cam: np.ndarray) -> Params:
    """Fit parameters whose root follows the truth (pelvis position, heading from pelvis to neck, up)."""
    from scipy.spatial.transform import Rotation

    from sync4d.recon.pose import quadruped_fit as qf

    g = {nm: truth_cam[:, i] for i, nm in enumerate(names)}
    rots = []
    for fwd in g["neck"] - g["pelvis"]:
        up = up_cam - fwd * (up_cam @ fwd) / (fwd @ fwd)
        fwd, up = fwd / np.linalg.norm(fwd), up / np.linalg.norm(up)
        rots.append(Rotation.from_matrix(np.stack([-fwd, up, np.cross(-fwd, up)], 1)).as_rotvec())
    length = float(np.linalg.norm(g["head"] - g["tail_base"], axis=-1).mean())
    params = qf.start_params(prob, rots[0], g["pelvis"][0], length, frames=len(truth_cam))
    with torch_no_grad():
        params["root_rot"].copy_(qf.torch.tensor(np.array(rots), dtype=qf.DTYPE))
        params["root_pos"].copy_(qf.torch.tensor(g["pelvis"], dtype=qf.DTYPE))
    return params


def torch_no_grad() -> torch.no_grad:
    import torch

    return torch.no_grad()


def fit_to_truth(prob: QuadrupedProblem, params: Params, target: torch.Tensor, ids: list[int],
                 cfg: QuadrupedFitConfig, priors: bool, steps: int = 1500) -> None:
    """Adam on the template's joints ``ids`` against the truth (first camera frame), with or without the priors."""
    import torch

    from sync4d.recon.pose import quadruped_fit as qf

    opt = torch.optim.Adam([v for k, v in params.items() if k not in ("log_thick", "log_girth")], lr=0.02)
    for _ in range(steps):
        opt.zero_grad()
        joints, _ = qf.pose_body(prob.tt, params)
        loss = 100 * ((joints[:, ids] - target) / params["log_scale"].exp()).pow(2).sum(-1).mean()
        if priors:
            lengths, limit = qf.shape_priors(prob, params, cfg)
            loss = loss + cfg.length_weight * lengths + cfg.limit_weight * limit
        loss.backward()
        opt.step()


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="outputs/body_suite")
    parser.add_argument("--only", default="", help="comma-separated clip names (cmu, deepmimic, dog, shiba, fox_walk, "
                        "fox_run, fox_survey) or clip_view names (fox_walk_orbit)")
    parser.add_argument("--split", action="store_true", help="split the quadruped clips' error (module docstring)")
    parser.add_argument("--held-out", action="store_true", help="the held-out quadruped rows (QUADRUPED_HELDOUT) "
                        "instead of CLIPS; --only takes their folder names (dog_side_handheld0)")
    args = parser.parse_args(argv)
    out = Path(args.out)
    keep = set(args.only.split(",")) if args.only else None
    if args.held_out:
        return held_out_suite(out, keep)
    if args.split:
        rows = [split_clip(out / f"{c}_{v}") for c, v, _, _ in CLIPS
                if c in QUADRUPEDS and (keep is None or c in keep or f"{c}_{v}" in keep)]
        print(json.dumps(rows, indent=1))
        (out / "split.json").write_text(json.dumps(rows, indent=1))
        return {"rows": rows}
    rows = []
    for clip, view, frames, stride in CLIPS:
        if keep is None or clip in keep or f"{clip}_{view}" in keep:
            rows += run_clip(out, clip, view, frames, stride)
            print(json.dumps(rows[-1]), flush=True)
    print(rows_table(rows))
    handheld = []
    for clip, view, seed in HANDHELD:
        if keep is None or clip in keep or row_name(clip, view, seed) in keep or "handheld" in keep:
            handheld.append(run_handheld(out, clip, view, seed))
            print(json.dumps(handheld[-1]), flush=True)
    if handheld:
        print(handheld_table(handheld, rows))
    out.mkdir(parents=True, exist_ok=True)
    (out / "suite.json").write_text(json.dumps(rows + handheld, indent=1))
    return {"rows": rows, "handheld": handheld}


def held_out_suite(out: Path, keep: set[str] | None) -> dict:
    """Fit and score the held-out quadruped rows; writes ``held_out.json`` and prints the table."""
    rows = []
    for clip, view, seed in QUADRUPED_HELDOUT:
        if keep is None or clip in keep or row_name(clip, view, seed) in keep:
            frames, stride = next(((f, s) for c, _, f, s in CLIPS if c == clip), (0, 1))
            rows += run_clip(out, clip, view, frames, stride, seed)
            print(json.dumps(rows[-1]), flush=True)
    print(rows_table(rows))
    out.mkdir(parents=True, exist_ok=True)
    (out / "held_out.json").write_text(json.dumps(rows, indent=1))
    return {"rows": rows}


def rows_table(rows: list[dict]) -> str:
    """Markdown: one line per fitted row, the do-nothing floor beside (quadrupeds)."""
    lines = ["| clip | view | camera | mpjpe % height | pck10 | floor mpjpe % (pck10) | mask IoU | frames | CPU s |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        floor = f"{r['floor_mpjpe_pct_height']:.2f} ({r['floor_pck10']:.3f})" if "floor_pck10" in r else "-"
        lines.append(f"| {r['clip']} | {r['view']} | {r['camera']} | {r['mpjpe_pct_height']:.2f} | {r['pck10']:.3f} | "
                     f"{floor} | {r['mask_iou']:.3f} | {r['frames']} | {r['cpu_seconds']:.0f} |")
    return "\n".join(lines)


def handheld_table(handheld: list[dict], rows: list[dict]) -> str:
    """Markdown: each hand-held row beside the same clip and view filmed by the static camera (known)."""
    static = {(r["clip"], r["view"]): r for r in rows if r["camera"] == "known"}
    lines = ["| clip | view | seed | camera turn [deg] | mp4 alone % (pck10) | camera given % (pck10) | alone / given | "
             "camera as static % (pck10) | floor % (pck10) | static camera, known % (pck10) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in handheld:
        st = static.get((r["clip"], r["view"]))
        ref = f"{st['mpjpe_pct_height']:.2f} ({st['pck10']:.3f})" if st else "-"
        def cell(key: str, r: dict = r) -> str:
            if f"{key}_mpjpe_pct_height" not in r:
                return "front end refused"
            return f"{r[key + '_mpjpe_pct_height']:.2f} ({r[key + '_pck10']:.3f})"

        ratio = "-" if r["ratio_alone_given"] is None else f"{r['ratio_alone_given']:.2f}"
        lines.append(f"| {r['clip']} | {r['view']} | {r['seed']} | {r['camera_turn_max_deg']:.1f} | {cell('alone')} | "
                     f"{cell('given')} | {ratio} | {cell('identity')} | {cell('floor')} | {ref} |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
