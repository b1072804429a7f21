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
