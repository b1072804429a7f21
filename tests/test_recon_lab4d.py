"""recon=lab4d: a small new-style export written here, mismatch handling, and the shiba folder."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sync4d.errors import InputError
from sync4d.io.lab4d import write_obj
from sync4d.registry import build
from sync4d.types import ReferenceInput


def rot_x(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def write_export(root: Path, *, with_skin: bool, skin_columns: int = 2, frames: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """A two-bone bar along y bending at y = 0 about x; returns (rest, posed object-frame meshes)."""
    rng = np.random.default_rng(0)
    y = np.linspace(-0.5, 0.5, 60)
    rest = np.stack([0.05 * np.cos(y * 40), y, 0.05 * np.sin(y * 40)], 1)
    faces = np.array([[i, i + 1, i + 2] for i in range(len(rest) - 2)])
    w1 = 1 / (1 + np.exp(-y / 0.05))
    weights = np.stack([1 - w1, w1], 1)
    art = np.tile(np.eye(4), (frames, 2, 1, 1))
    field2cam = np.tile(np.eye(4), (frames, 1, 1))
    for t in range(frames):
        art[t, 1, :3, :3] = rot_x(0.3 * t)
        field2cam[t, :3, :3] = rot_x(0.1 * t).T
        field2cam[t, :3, 3] = [0.0, 0.0, 2.0 + 0.1 * t]
    posed = np.einsum("vb,tbij,vj->tvi", weights, art[..., :3, :3], rest) + np.einsum("vb,tbi->tvi", weights, art[..., :3, 3])
    write_obj(root / "fg.obj", rest, faces)
    for t in range(frames):
        write_obj(root / f"fg-{t:05d}.obj", posed[t], faces)
    (root / "fg-motion.json").write_text(json.dumps({"field2cam": field2cam.tolist(), "t_articulation": art.tolist()}))
    if with_skin:
        skin = weights if skin_columns == 2 else np.full((len(rest), skin_columns), 1.0 / skin_columns)
        np.save(root / "fg-skin.npy", skin)
    del rng
    return rest, posed


def source_for(root: Path) -> ReferenceInput:
    return build("reference", {"type": "lab4d", "path": str(root), "fps": 12.0}).load()


def test_import_with_skinning_file_is_exact(tmp_path: Path) -> None:
    rest, posed = write_export(tmp_path, with_skin=True)
    recon = build("recon", {"type": "lab4d"}, device="cpu")
    ref = recon.reconstruct(source_for(tmp_path))
    assert ref.num_bones == 2 and ref.num_frames == 5
    assert np.allclose(ref.rest_vertices, rest, atol=1e-6)
    assert np.allclose(ref.posed_vertices(4), posed[4], atol=1e-6)
    # G_t is field2cam: the world of the reference is the camera of each frame
    assert np.allclose(ref.global_transforms[3, :3, 3], [0, 0, 2.3], atol=1e-6)
    assert recon.last_fit_report["mode"] == "import" and recon.last_fit_report["mean_error_pct"] < 1e-3


def test_import_without_skinning_fits_weights_to_posed_meshes(tmp_path: Path) -> None:
    rest, posed = write_export(tmp_path, with_skin=False)
    recon = build("recon", {"type": "lab4d"})
    ref = recon.reconstruct(source_for(tmp_path))
    err = np.abs(np.stack([ref.posed_vertices(t) for t in range(5)]) - posed).max()
    assert err < 1e-3
    assert (ref.part_labels() == (rest[:, 1] > 0)).mean() > 0.95


def test_bone_count_mismatch_is_named(tmp_path: Path) -> None:
    write_export(tmp_path, with_skin=True, skin_columns=3)
    with pytest.raises(InputError, match="hold 2 bones but the rest skinning has 3 columns"):
        build("recon", {"type": "lab4d"}).reconstruct(source_for(tmp_path))


def test_mismatch_refit_fits_new_bones(tmp_path: Path) -> None:
    _, posed = write_export(tmp_path, with_skin=True, skin_columns=3)
    recon = build("recon", {"type": "lab4d", "on_mismatch": "refit", "bones": 2, "iterations": 150, "fit_vertices": 0})
    ref = recon.reconstruct(source_for(tmp_path))
    assert ref.num_bones == 2
    assert recon.last_fit_report["mode"] == "refit" and "3 columns" in recon.last_fit_report["problem"]
    assert recon.last_fit_report["mean_error_pct"] < 1.0


def test_shiba_inconsistency_is_reported(shared_data: Path) -> None:
    """ppr-diffphys shiba-haru-1002 (MIT): 25 bone transforms vs 13 skinning columns."""
    src = build("reference", {"type": "lab4d", "path": str(shared_data / "lab4d_export" / "shiba-haru-1002")}).load()
    assert src.mesh_sequence.shape == (21, 10002, 3)
    with pytest.raises(InputError, match="25 bones but the rest skinning has 13 columns"):
        build("recon", {"type": "lab4d"}).reconstruct(src)
