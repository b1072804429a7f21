"""Exports: animated USD read back with pxr, npz round trip, animated glTF (Khronos validator, three.js),
the compact 4D file (round trip within its stated bounds, >= 10x smaller than the .ply sequence)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sync4d.errors import InputError
from sync4d.io.export import (
    export_glb,
    export_npz,
    export_usd,
    load_npz,
    read_glb,
    read_usd_points,
    widths_from_covariances,
    widths_from_scales,
)
from tests._node import node_tool, run_node


@pytest.fixture()
def sequence() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    t, n = 6, 25
    base = rng.uniform(-0.5, 0.5, (n, 3))
    means = np.stack([base + [0.0, 0.0, 0.05 * k] for k in range(t)])
    return {"means": means, "colors": rng.uniform(0, 1, (n, 3)), "opacities": rng.uniform(0.1, 1, n),
            "scales": rng.uniform(0.01, 0.03, (n, 3))}


@pytest.mark.parametrize("suffix", [".usd", ".usda"])
def test_usd_round_trip(tmp_path: Path, sequence: dict[str, np.ndarray], suffix: str) -> None:
    from pxr import Usd, UsdGeom

    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
    faces = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
    mesh_seq = np.stack([verts * (1 + 0.1 * k) for k in range(4)])
    widths = widths_from_scales(sequence["scales"])
    path = export_usd(tmp_path / f"sequence{suffix}", sequence["means"], sequence["colors"], widths, 12.0,
                      opacities=sequence["opacities"], mesh_vertices=mesh_seq, mesh_faces=faces)
    assert not list(tmp_path.glob(".*tmp*"))
    frames, fps = read_usd_points(path)
    assert frames.shape == (6, 25, 3) and fps == 12.0
    np.testing.assert_allclose(frames, sequence["means"], atol=1e-6)

    stage = Usd.Stage.Open(str(path))
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, 5)
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    points = UsdGeom.Points(stage.GetPrimAtPath("/sync4d/gaussians"))
    np.testing.assert_allclose(np.asarray(points.GetPointsAttr().Get(Usd.TimeCode(3))), sequence["means"][3],
                               atol=1e-6)
    # Between samples USD interpolates linearly: half-way between frames 2 and 3.
    np.testing.assert_allclose(np.asarray(points.GetPointsAttr().Get(Usd.TimeCode(2.5))),
                               0.5 * (sequence["means"][2] + sequence["means"][3]), atol=1e-6)
    np.testing.assert_allclose(np.asarray(points.GetWidthsAttr().Get()), widths, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(points.GetDisplayColorPrimvar().Get()), sequence["colors"], atol=1e-6)
    np.testing.assert_allclose(np.asarray(points.GetDisplayOpacityPrimvar().Get()), sequence["opacities"], atol=1e-6)
    lo, hi = np.asarray(points.GetExtentAttr().Get(Usd.TimeCode(5)))
    assert np.all(lo <= sequence["means"][5].min(0)) and np.all(hi >= sequence["means"][5].max(0))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/sync4d/reference"))
    assert list(mesh.GetFaceVertexIndicesAttr().Get()) == faces.reshape(-1).tolist()
    assert len(mesh.GetPointsAttr().GetTimeSamples()) == 4
    np.testing.assert_allclose(np.asarray(mesh.GetPointsAttr().Get(Usd.TimeCode(3))), mesh_seq[3], atol=1e-6)


def test_usd_static_mesh_and_per_frame_widths(tmp_path: Path, sequence: dict[str, np.ndarray]) -> None:
    from pxr import Usd, UsdGeom

    widths = np.linspace(0.01, 0.02, 6)[:, None] * np.ones((1, 25))
    path = export_usd(tmp_path / "s.usdc", sequence["means"], widths=widths, fps=30.0,
                      mesh_vertices=np.eye(3), mesh_faces=np.array([[0, 1, 2]]))
    stage = Usd.Stage.Open(str(path))
    points = UsdGeom.Points(stage.GetPrimAtPath("/sync4d/gaussians"))
    np.testing.assert_allclose(np.asarray(points.GetWidthsAttr().Get(Usd.TimeCode(5))), 0.02, rtol=1e-6)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/sync4d/reference"))
    assert mesh.GetPointsAttr().GetTimeSamples() == []
    np.testing.assert_allclose(np.asarray(mesh.GetPointsAttr().Get()), np.eye(3))


def test_usd_rejects_bad_shapes(tmp_path: Path, sequence: dict[str, np.ndarray]) -> None:
    with pytest.raises(InputError, match="frames_means"):
        export_usd(tmp_path / "x.usd", sequence["means"][0])
    with pytest.raises(InputError, match="colors"):
        export_usd(tmp_path / "x.usd", sequence["means"], np.ones((3, 3)))
    bad = sequence["means"].copy()
    bad[2, 3, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        export_usd(tmp_path / "x.usd", bad)
    assert not (tmp_path / "x.usd").exists()


def test_npz_round_trip(tmp_path: Path, sequence: dict[str, np.ndarray]) -> None:
    t, n = sequence["means"].shape[:2]
    covs = np.repeat((np.diag([1e-4, 2e-4, 3e-4]))[None, None], t, 0).repeat(n, 1)
    sh = np.random.default_rng(1).normal(size=(n, 4, 3))
    path = export_npz(tmp_path / "sequence.npz", sequence["means"], fps=24.0, colors=sequence["colors"], sh=sh,
                      opacities=sequence["opacities"], covariances=covs, frame_loss=np.arange(t, dtype=float))
    data = load_npz(path)
    assert data["fps"] == 24.0 and data["format_version"] == 1
    np.testing.assert_allclose(data["means"], sequence["means"], atol=1e-6)
    np.testing.assert_allclose(data["covariances"], covs, rtol=1e-6)
    np.testing.assert_allclose(data["sh"], sh, rtol=1e-6)
    np.testing.assert_allclose(data["opacities"], sequence["opacities"], rtol=1e-6)
    np.testing.assert_array_equal(data["frame_loss"], np.arange(t))
    with pytest.raises(InputError, match="covariances"):
        export_npz(tmp_path / "bad.npz", sequence["means"], fps=24.0, covariances=np.zeros((n, 3)))


def test_widths_from_covariances_and_scales_agree() -> None:
    scales = np.array([[0.01, 0.02, 0.04]])
    covs = np.diag(scales[0] ** 2)[None]
    expected = 2.0 * (0.01 * 0.02 * 0.04) ** (1 / 3)
    assert widths_from_scales(scales)[0] == pytest.approx(expected)
    assert widths_from_covariances(covs)[0] == pytest.approx(expected)


def moving_points(t: int = 5, n: int = 40) -> np.ndarray:
    rng = np.random.default_rng(3)
    base = rng.uniform(-0.2, 0.2, (n, 3))
    angles = np.linspace(0.0, 1.0, t)
    rot = np.stack([[[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]] for a in angles])
    return np.einsum("tij,nj->tni", rot, base) + [0.0, 0.1, 0.0]


def test_glb_holds_one_morph_target_a_frame_and_a_weights_animation(tmp_path: Path) -> None:
    means = moving_points()
    gltf, binary = read_glb(export_glb(tmp_path / "sequence.glb", means, fps=10.0,
                                       colors=np.full((40, 3), 0.5)))
    prim = gltf["meshes"][0]["primitives"][0]
    assert prim["mode"] == 0 and len(prim["targets"]) == 4 and "COLOR_0" in prim["attributes"]
    sampler = gltf["animations"][0]["samplers"][0]
    times = gltf["accessors"][sampler["input"]]
    assert times["count"] == 5 and times["max"] == [pytest.approx(0.4)]
    view = gltf["bufferViews"][gltf["accessors"][prim["targets"][2]["POSITION"]]["bufferView"]]
    delta = np.frombuffer(binary[view["byteOffset"] : view["byteOffset"] + view["byteLength"]], np.float32)
    np.testing.assert_allclose(delta.reshape(-1, 3), means[3] - means[0], atol=1e-6)
    with pytest.raises(InputError, match="colors"):
        export_glb(tmp_path / "bad.glb", means, fps=10.0, colors=np.ones((3, 3)))
    with pytest.raises(InputError, match="NaN"):
        export_glb(tmp_path / "bad.glb", np.full((2, 3, 3), np.nan), fps=10.0)


@pytest.mark.skipif(not node_tool("gltf-validator"), reason="the Khronos glTF validator is not installed: make browser")
def test_glb_passes_the_khronos_validator(tmp_path: Path) -> None:
    path = export_glb(tmp_path / "sequence.glb", moving_points(), fps=12.0, colors=np.full((40, 3), 0.3))
    report = run_node("validate_gltf.mjs", str(path))
    assert report["errors"] == 0, report["messages"]
    assert report["warnings"] == 0, report["messages"]
    # The validator can fail: a file with a broken accessor is reported.
    gltf, binary = read_glb(path)
    gltf["accessors"][0]["count"] += 7
    from sync4d.io.export import _glb_bytes

    (tmp_path / "broken.glb").write_bytes(_glb_bytes(gltf, binary))
    assert run_node("validate_gltf.mjs", str(tmp_path / "broken.glb"))["errors"] > 0


@pytest.mark.skipif(not node_tool("three"), reason="three.js is not installed (make browser)")
def test_glb_plays_in_threejs_at_the_exported_positions(tmp_path: Path) -> None:
    means = moving_points()
    path = export_glb(tmp_path / "sequence.glb", means, fps=10.0)
    for t in (0, 3):
        shown = run_node("load_three.mjs", str(path), str(t / 10.0))
        assert shown["type"] == "Points" and shown["morphs"] == 4
        np.testing.assert_allclose(np.array(shown["positions"]), means[t], atol=1e-5)
    halfway = np.array(run_node("load_three.mjs", str(path), "0.15")["positions"])
    np.testing.assert_allclose(halfway, 0.5 * (means[1] + means[2]), atol=1e-5)  # linear between frames


def deforming_gaussians(t: int = 20, n: int = 600) -> tuple[np.ndarray, np.ndarray]:
    """A smoothly turning, stretching cloud: (T, N, 3) means [m] and (T, N, 3, 3) covariances [m^2]."""
    from sync4d.geometry import quat_to_matrix

    rng = np.random.default_rng(5)
    base = rng.uniform(-0.3, 0.3, (n, 3))
    q = rng.normal(size=(n, 4))
    rest_rot = quat_to_matrix(q / np.linalg.norm(q, axis=1, keepdims=True))
    scales = rng.uniform(0.003, 0.02, (n, 3))
    rest_cov = (rest_rot * scales[:, None, :] ** 2) @ np.swapaxes(rest_rot, 1, 2)
    means, covs = [], []
    for k in range(t):
        a = 0.05 * k
        turn = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
        F = turn @ np.diag([1 + 0.01 * k, 1, 1])
        means.append(base @ F.T + [0.01 * k, 0, 0])
        covs.append(F @ rest_cov @ F.T)
    return np.stack(means), np.stack(covs)


def test_seq4d_round_trip_within_its_stated_bounds(tmp_path: Path) -> None:
    from sync4d.io.seq4d import Seq4DConfig, Sequence4D, log_covariances, write_seq4d

    means, covs = deforming_gaussians()
    n = means.shape[1]
    rng = np.random.default_rng(1)
    colors, opac, parts = rng.uniform(0, 1, (n, 3)), rng.uniform(0, 1, n), rng.integers(0, 3, n)
    cfg = Seq4DConfig(chunk=7)  # several chunks, the last one short
    path = write_seq4d(tmp_path / "s.s4d", means, covs, colors, opac, fps=24.0, config=cfg, parts=parts,
                       sh=rng.normal(size=(n, 4, 3)))
    seq = Sequence4D(path)
    assert (seq.num_frames, seq.num, seq.fps) == (20, n, 24.0)
    diagonal = np.linalg.norm(np.ptp(means.reshape(-1, 3), axis=0))
    assert seq.position_error == pytest.approx(cfg.relative_error * diagonal)
    for t in (0, 6, 7, 13, 19, 2):  # out of order: chunks decode on their own
        m, c = seq.frame(t)
        assert np.abs(m - means[t]).max() <= seq.position_error * (1 + 1e-6)
        # The stated covariance bound: every entry of logm(Sigma) within log_cov_error, so each standard
        # deviation is within exp(1.5 * log_cov_error).
        assert np.abs(log_covariances(c) - log_covariances(covs[t])).max() <= seq.log_cov_error + 1e-9
        sd_ratio = np.sqrt(np.linalg.eigvalsh(c) / np.linalg.eigvalsh(covs[t]))
        assert np.abs(np.log(sd_ratio)).max() <= 1.5 * seq.log_cov_error + 1e-9
    np.testing.assert_array_equal(seq.parts, parts)
    assert np.abs(seq.colors - colors).max() <= 0.5 / 255 + 1e-12
    assert np.abs(seq.opacities - opac).max() <= 0.5 / 255 + 1e-12
    np.testing.assert_allclose(seq.means(), means, atol=seq.position_error * (1 + 1e-6))
    # A coarser bound gives a smaller file, and a wrong-length read fails loudly.
    coarse = write_seq4d(tmp_path / "c.s4d", means, covs, colors, opac, fps=24.0,
                         config=Seq4DConfig(relative_error=1e-3, log_cov_error=1 / 32))
    assert coarse.stat().st_size < path.stat().st_size
    with pytest.raises(InputError, match="frame 20"):
        seq.frame(20)


def test_seq4d_is_over_ten_times_smaller_than_the_ply_sequence(tmp_path: Path) -> None:
    from sync4d.io.ply import write_gaussians_ply
    from sync4d.io.seq4d import Seq4DConfig, write_seq4d
    from sync4d.types import TargetGaussians
    from sync4d.geometry import matrix_to_quat

    means, covs = deforming_gaussians(t=12, n=1500)
    n = means.shape[1]
    lam, vec = np.linalg.eigh(covs)
    vec = vec * np.sign(np.linalg.det(vec))[..., None, None]  # proper rotations for the quaternions
    ply_bytes = 0
    for t in range(len(means)):
        frame = TargetGaussians(means=means[t].astype(np.float32), quats=matrix_to_quat(vec[t]).astype(np.float32),
                                log_scales=(0.5 * np.log(lam[t])).astype(np.float32),
                                opacity_logits=np.zeros(n, np.float32), sh=np.zeros((n, 1, 3), np.float32))
        ply_bytes += write_gaussians_ply(tmp_path / f"{t:06d}.ply", frame).stat().st_size
    path = write_seq4d(tmp_path / "s.s4d", means, covs, np.full((n, 3), 0.5), np.full(n, 0.5), fps=12.0,
                       config=Seq4DConfig(), sh=np.zeros((n, 1, 3)))
    assert ply_bytes / path.stat().st_size >= 10.0


def test_seq4d_rejects_bad_input(tmp_path: Path) -> None:
    from sync4d.io.seq4d import Seq4DConfig, Sequence4D, write_seq4d

    means, covs = deforming_gaussians(t=3, n=10)
    ok = dict(colors=np.zeros((10, 3)), opacities=np.ones(10), fps=12.0, config=Seq4DConfig())
    with pytest.raises(InputError, match="covariances"):
        write_seq4d(tmp_path / "a.s4d", means, covs[:, :5], **ok)
    bad = means.copy()
    bad[1, 2, 0] = np.inf
    with pytest.raises(InputError, match="NaN/inf"):
        write_seq4d(tmp_path / "a.s4d", bad, covs, **ok)
    (tmp_path / "junk.s4d").write_bytes(b"not a file")
    with pytest.raises(InputError, match="not a sync4d .s4d"):
        Sequence4D(tmp_path / "junk.s4d")
