"""Exports: animated USD read back with pxr, npz round trip."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sync4d.errors import InputError
from sync4d.io.export import (
    export_npz,
    export_usd,
    load_npz,
    read_usd_points,
    widths_from_covariances,
    widths_from_scales,
)


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
