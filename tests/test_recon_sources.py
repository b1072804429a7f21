"""reference=meshseq|lab4d|bvh|joint_positions|video sources, recon=ground_truth, and the YAML files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from sync4d.errors import DataMissingError, InputError
from sync4d.io.lab4d import write_obj
from sync4d.sources.references import camera_from_look
from sync4d.registry import build, make_config
from sync4d.types import Reference, ReferenceInput

CONF = Path(__file__).resolve().parent.parent / "conf"


@pytest.mark.parametrize(
    "group, name",
    [("recon", "skinning_fit"), ("recon", "lab4d"), ("recon", "mocap"), ("recon", "ground_truth"), ("recon", "video"),
     ("reference", "meshseq"), ("reference", "lab4d"), ("reference", "bvh"), ("reference", "joint_positions"),
     ("reference", "video")],
)
def test_yaml_matches_config(group: str, name: str) -> None:
    values = OmegaConf.to_container(OmegaConf.load(CONF / group / f"{name}.yaml"))
    values.pop("defaults", None)  # the schema_<name> entry: the Config itself
    _, cfg = make_config(group, values)
    assert type(cfg).__name__ == "Config"


def test_mocap_dog_preset_composes() -> None:
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["recon=mocap_dog"])
    _, typed = make_config("recon", cfg.recon)
    assert typed.parents[:4] == [-1, 0, 1, 2] and typed.target_fps == 30.0


@pytest.mark.parametrize("name", ["meshseq", "lab4d", "bvh", "joint_positions"])
def test_missing_files_name_the_path(tmp_path: Path, name: str) -> None:
    key = "path"
    with pytest.raises(DataMissingError, match="absent"):
        build("reference", {"type": name, key: str(tmp_path / "absent")}).load()


def test_missing_video_names_the_path(tmp_path: Path) -> None:
    with pytest.raises(DataMissingError, match="absent.mp4"):
        build("reference", {"type": "video", "video": str(tmp_path / "absent.mp4"), "masks": "", "camera": ""}).load()


def test_meshseq_source_reads_a_glob(tmp_path: Path) -> None:
    tri = np.array([[0, 1, 2]])
    for t in range(3):
        write_obj(tmp_path / f"pose-{t}.obj", np.eye(3) + t, tri)
    write_obj(tmp_path / "other.obj", np.zeros((3, 3)), tri)
    src = build("reference", {"type": "meshseq", "path": str(tmp_path / "pose-*.obj"), "fps": 5.0}).load()
    assert src.mesh_sequence.shape == (3, 3, 3) and src.fps == 5.0 and src.faces.tolist() == [[0, 1, 2]]


def test_camera_from_look_matches_the_laptop_convention() -> None:
    K = np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])
    c = np.array([1.0, 2.0, 3.0])
    fwd = np.array([0.0, 1.0, 0.0])
    up = np.array([0.0, 0.0, 1.0])
    cam = camera_from_look(K, c, fwd, up, 100, 80)
    p = np.array([1.5, 5.0, 3.2])
    right = np.cross(fwd, up)
    x, y, z = (p - c) @ right, (p - c) @ up, (p - c) @ fwd
    u_ref, v_ref = 50 + 100 * x / z, 40 - 100 * y / z
    pc = cam.world_to_cam @ np.append(p, 1)
    uv = (K @ pc[:3])[:2] / pc[2]
    assert np.allclose(uv, [u_ref, v_ref])


def test_ground_truth_reconstructor() -> None:
    ref = Reference(
        rest_vertices=np.zeros((2, 3)), rest_faces=None, bone_centers=np.zeros((1, 3)),
        bone_covariances=np.eye(3)[None], skinning=np.ones((2, 1)), bone_transforms=np.tile(np.eye(4), (2, 1, 1, 1)),
        global_transforms=np.tile(np.eye(4), (2, 1, 1)), fps=10.0,
    )
    recon = build("recon", {"type": "ground_truth"}, device="cpu")
    assert recon.reconstruct(ReferenceInput(name="syn", fps=10.0, ground_truth=ref)) is ref
    with pytest.raises(InputError, match="carries no ground truth"):
        recon.reconstruct(ReferenceInput(name="real", fps=10.0))


def test_video_source_with_camera(shared_data: Path) -> None:
    """Meta-World laptop (MIT) rendered with MuJoCo; camera from gt.npz."""
    root = shared_data / "rendered" / "metaworld_laptop_hinge"
    src = build("reference", {"type": "video", "video": str(root / "rgb.mp4"), "masks": str(root / "masks"),
                              "camera": str(root / "gt.npz"), "max_frames": 4}).load()
    assert src.video.num_frames == 4 and src.camera.width == 320 and src.camera.height == 240
    assert np.allclose(src.video.intrinsics, src.camera.K)
    # the laptop (at the world origin) is in front of the camera and inside the image
    pc = src.camera.world_to_cam @ np.array([0.0, 0.0, 0.0, 1.0])
    u, v = (src.camera.K @ pc[:3])[:2] / pc[2]
    assert pc[2] > 0 and 0 <= u < 320 and 0 <= v < 240


def _frames_folder(root: Path, count: int = 6, size: tuple[int, int] = (40, 32)) -> Path:
    """A folder of ``count`` small PNG frames (a square moving right) and its masks folder beside them."""
    import cv2

    (root / "frames").mkdir(parents=True)
    (root / "masks").mkdir()
    for t in range(count):
        image = np.full((size[1], size[0], 3), 200, np.uint8)
        image[10:20, 5 + 2 * t:15 + 2 * t] = (40, 90, 160)
        cv2.imwrite(str(root / "frames" / f"{t:04d}.png"), image)
        cv2.imwrite(str(root / "masks" / f"{t:04d}.png"), (image[..., 0] < 100).astype(np.uint8) * 255)
    return root / "frames"


def _arc(count: int) -> dict[str, np.ndarray]:
    """A camera circling the origin: K (3, 3) and cam_pos / cam_forward (count, 3), cam_up (3,)."""
    angle = np.linspace(0.0, 0.4, count)
    pos = np.stack([2.0 * np.sin(angle), np.full(count, 0.5), 2.0 * np.cos(angle)], 1)
    K = np.array([[40.0, 0, 20], [0, 40.0, 16], [0, 0, 1]])
    return {"K": K, "cam_pos": pos, "cam_forward": -pos, "cam_up": np.array([0.0, 1.0, 0.0])}


def test_video_source_reads_a_moving_camera(tmp_path: Path) -> None:
    """cam_pos / cam_forward (T, 3) (and world_to_cam (T, 4, 4)) give a pose per frame; stride picks the
    clip's frames' poses from the video's; frame t's pose is the look-at of row t."""
    frames = _frames_folder(tmp_path)
    cam = _arc(6)
    np.savez(tmp_path / "look.npz", **cam)
    src = build("reference", {"type": "video", "video": str(frames), "masks": str(tmp_path / "masks"),
                              "camera": str(tmp_path / "look.npz"), "fps": 10.0, "stride": 2}).load()
    assert src.video.num_frames == 3 and src.video.extrinsics is not None and src.video.extrinsics.shape == (3, 4, 4)
    for i, t in enumerate((0, 2, 4)):
        want = camera_from_look(cam["K"], cam["cam_pos"][t], cam["cam_forward"][t], cam["cam_up"], 40, 32)
        assert np.allclose(src.video.extrinsics[i], want.world_to_cam)
    assert np.allclose(src.camera.world_to_cam, src.video.extrinsics[0])
    np.savez(tmp_path / "w2c.npz", K=cam["K"], world_to_cam=src.video.extrinsics)  # (T, 4, 4), T = the clip's
    again = build("reference", {"type": "video", "video": str(frames), "masks": str(tmp_path / "masks"),
                                "camera": str(tmp_path / "w2c.npz"), "fps": 10.0, "stride": 2}).load()
    assert np.allclose(again.video.extrinsics, src.video.extrinsics)


@pytest.mark.parametrize("bad", [
    {"cam_pos": np.zeros((6, 2))},                   # not (T, 3)
    {"cam_pos": np.zeros((5, 3)) + [0, 0, 2]},        # 5 poses for 6 frames
    {"world_to_cam": np.zeros((6, 3, 4))},           # not (T, 4, 4)
    {"K": np.eye(4)},                                # K not (3, 3)
    {"cam_forward": None},                           # a key missing
])
def test_a_camera_file_of_another_shape_is_refused_in_one_line(tmp_path: Path, bad: dict) -> None:
    frames = _frames_folder(tmp_path)
    cam = _arc(6)
    if "world_to_cam" in bad:
        cam = {"K": cam["K"], **bad}
    else:
        cam.update({k: v for k, v in bad.items() if v is not None})
        cam = {k: v for k, v in cam.items() if bad.get(k, 0) is not None}
    path = tmp_path / "bad.npz"
    np.savez(path, **cam)
    with pytest.raises(InputError) as err:
        build("reference", {"type": "video", "video": str(frames), "masks": str(tmp_path / "masks"),
                            "camera": str(path), "fps": 10.0}).load()
    line = str(err.value)
    assert "\n" not in line and str(path) in line and "(T, 3)" in line and "(T, 4, 4)" in line, line


def test_train_and_the_evaluation_tools_refuse_a_bad_camera_file_with_exit_code_2(tmp_path: Path) -> None:
    import subprocess
    import sys

    root = Path(__file__).resolve().parent.parent
    frames = _frames_folder(tmp_path)
    cam = _arc(6)
    cam["cam_pos"] = cam["cam_pos"][:, :2]
    np.savez(tmp_path / "bad.npz", **cam)
    proc = subprocess.run([sys.executable, str(root / "train.py"), "reference=video", f"reference.video={frames}",
                           f"reference.masks={tmp_path / 'masks'}", f"reference.camera={tmp_path / 'bad.npz'}",
                           "reference.fps=10", f"hydra.run.dir={tmp_path / 'run'}"],
                          capture_output=True, text=True, timeout=300, cwd=root)
    assert proc.returncode == 2, proc.stderr[-3000:]
    lines = proc.stderr.strip().splitlines()
    assert "bad.npz" in lines[-1] and "(T, 3)" in lines[-1], proc.stderr[-2000:]
    from sync4d_tools.evaluate.__main__ import main

    np.savez(tmp_path / "none.npz", joints=np.zeros((6, 1, 3)), names=np.array(["head"]))
    code = main(["recon_joints", "--video", str(frames), "--camera", str(tmp_path / "bad.npz"),
                 "--gt", str(tmp_path / "none.npz")])
    assert code == 2
