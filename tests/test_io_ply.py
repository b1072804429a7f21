"""3DGS .ply: bit-identical round trips for SH degree 0-3, the shared real file, and one-line errors."""

from __future__ import annotations

import numpy as np
import pytest

from sync4d.errors import InputError
from sync4d.io.ply import read_gaussians_ply, write_gaussians_ply
from sync4d.types import TargetGaussians


def random_gaussians(n: int, degree: int, normals: bool, seed: int = 0) -> TargetGaussians:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return TargetGaussians(
        means=rng.normal(size=(n, 3)).astype(np.float32),
        quats=(q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
        log_scales=rng.normal(-4, 1, size=(n, 3)).astype(np.float32),
        opacity_logits=rng.normal(size=n).astype(np.float32),
        sh=rng.normal(size=(n, (degree + 1) ** 2, 3)).astype(np.float32),
        normals=rng.normal(size=(n, 3)).astype(np.float32) if normals else None,
    )


FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh", "normals")


def assert_bit_identical(a: TargetGaussians, b: TargetGaussians) -> None:
    for name in FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        if x is None or y is None:
            assert x is None and y is None, name
            continue
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert x.tobytes() == y.tobytes(), f"{name} differs after the round trip"


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("normals", [False, True])
def test_round_trip_is_bit_identical(tmp_path, degree, normals):
    g = random_gaussians(257, degree, normals)
    path = write_gaussians_ply(tmp_path / "g.ply", g)
    back = read_gaussians_ply(path)
    assert back.sh_degree == degree
    assert_bit_identical(g, back)


def test_sh_rest_is_channel_major(tmp_path):
    """Inria stores f_rest as all R coefficients, then G, then B."""
    g = random_gaussians(3, 1, False)
    path = write_gaussians_ply(tmp_path / "g.ply", g)
    raw = path.read_bytes()
    header_end = raw.index(b"end_header\n") + len(b"end_header\n")
    names = [line.split()[-1] for line in raw[:header_end].decode().splitlines() if line.startswith("property")]
    row0 = np.frombuffer(raw[header_end:], dtype="<f4", count=len(names))
    values = dict(zip(names, row0))
    # f_rest_0..2 are the R channel of SH coefficients 1..3.
    np.testing.assert_array_equal([values[f"f_rest_{i}"] for i in range(3)], g.sh[0, 1:, 0])
    np.testing.assert_array_equal([values[f"f_rest_{i}"] for i in range(3, 6)], g.sh[0, 1:, 1])


def test_unnormalised_quaternions_are_normalised(tmp_path):
    g = random_gaussians(10, 0, False)
    g = g.replace(quats=(g.quats * 3.0).astype(np.float32))
    back = read_gaussians_ply(write_gaussians_ply(tmp_path / "g.ply", g))
    np.testing.assert_allclose(np.linalg.norm(back.quats, axis=1), 1.0, atol=1e-6)


def test_shared_real_splat_round_trips(shared_data, tmp_path):
    path = shared_data / "targets/gaussians/sunflowers_lod3_tile_0.ply"
    g = read_gaussians_ply(path)
    assert g.num == 1971 and g.sh_degree == 3 and g.normals is not None
    assert np.all(np.isfinite(g.scales)) and 0 < g.opacities.mean() < 1
    back = read_gaussians_ply(write_gaussians_ply(tmp_path / "copy.ply", g))
    assert_bit_identical(g, back)


def _header(props: list[str], count: int) -> bytes:
    return ("ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % count
            + "".join(f"property float {p}\n" for p in props) + "end_header\n").encode()


def test_errors_name_the_file_and_problem(tmp_path):
    not_ply = tmp_path / "a.ply"
    not_ply.write_text("hello")
    with pytest.raises(InputError, match=r"a\.ply: not a PLY file"):
        read_gaussians_ply(not_ply)

    good = write_gaussians_ply(tmp_path / "good.ply", random_gaussians(5, 0, False))
    truncated = tmp_path / "truncated.ply"
    truncated.write_bytes(good.read_bytes()[:-10])
    with pytest.raises(InputError, match=r"truncated\.ply: truncated"):
        read_gaussians_ply(truncated)

    missing = tmp_path / "missing.ply"
    missing.write_bytes(_header(["x", "y", "z"], 1) + np.zeros(3, "<f4").tobytes())
    with pytest.raises(InputError, match=r"missing\.ply: missing 3DGS property\(ies\) f_dc_0"):
        read_gaussians_ply(missing)

    nan = random_gaussians(4, 0, False)
    nan.means[2, 1] = np.nan
    nan_path = tmp_path / "nan.ply"
    from sync4d.io.ply import _ply_columns  # write around validate() to produce the bad file

    cols = _ply_columns(nan)
    data = np.empty(4, dtype=[(n, "<f4") for n, _ in cols])
    for n, v in cols:
        data[n] = v
    nan_path.write_bytes(_header([n for n, _ in cols], 4) + data.tobytes())
    with pytest.raises(InputError, match=r"nan\.ply: property 'y' holds 1 NaN"):
        read_gaussians_ply(nan_path)

    empty = tmp_path / "empty.ply"
    empty.write_bytes(_header([n for n, _ in cols], 0))
    with pytest.raises(InputError, match=r"empty\.ply: contains zero Gaussians"):
        read_gaussians_ply(empty)


def _write_raw(path, g: TargetGaussians) -> None:
    """Write ``g`` without validation (to produce files holding bad values)."""
    from sync4d.io.ply import gaussians_table

    data = gaussians_table(g)
    path.write_bytes(_header(list(data.dtype.names), g.num) + data.tobytes())


@pytest.mark.parametrize(
    ("field", "index", "value", "prop"),
    [
        ("log_scales", (3, 1), 200.0, "scale_1"),      # exp(200) overflows float32 to inf
        ("log_scales", (0, 0), -120.0, "scale_0"),     # exp(-120) underflows to zero
        ("opacity_logits", (2,), 1e9, "opacity"),
        ("means", (4, 2), 3e9, "z"),                   # 3 million km away
    ],
)
def test_absurd_values_are_refused_naming_file_property_and_gaussian(tmp_path, field, index, value, prop):
    g = random_gaussians(6, 1, False)
    getattr(g, field)[index] = value
    path = tmp_path / "absurd.ply"
    _write_raw(path, g)
    with pytest.raises(InputError, match=rf"absurd\.ply: property '{prop}' of Gaussian {index[0]} is ") as info:
        read_gaussians_ply(path)
    assert "\n" not in str(info.value)


def test_inf_scale_is_refused(tmp_path):
    g = random_gaussians(6, 0, False)
    g.log_scales[5, 2] = np.inf
    path = tmp_path / "inf.ply"
    _write_raw(path, g)
    with pytest.raises(InputError, match=r"inf\.ply: property 'scale_2' holds 1 inf value\(s\) \(first at Gaussian 5\)"):
        read_gaussians_ply(path)


def test_ascii_and_other_layouts_read_like_binary(tmp_path):
    """plyfile reads ASCII, big-endian and files whose vertex element is not first."""
    import plyfile

    from sync4d.io.ply import gaussians_table

    g = random_gaussians(7, 2, True)
    table = gaussians_table(g)
    faces = np.empty(1, dtype=[("vertex_indices", "O")])
    faces["vertex_indices"][0] = np.array([0, 1, 2], dtype=np.int32)
    elements = [plyfile.PlyElement.describe(faces, "face"), plyfile.PlyElement.describe(table, "vertex")]
    for text, order in ((True, "="), (False, ">")):
        path = tmp_path / f"layout_{text}.ply"
        plyfile.PlyData(elements, text=text, byte_order=order).write(str(path))
        back = read_gaussians_ply(path)
        assert back.sh_degree == 2
        np.testing.assert_allclose(back.sh, g.sh, rtol=1e-6)
        np.testing.assert_allclose(back.means, g.means, rtol=1e-6)


def test_list_property_and_bad_header_are_one_line_errors(tmp_path):
    path = tmp_path / "list.ply"
    path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar int idx\nend_header\n1 0\n")
    with pytest.raises(InputError, match=r"list\.ply: list property 'idx'"):
        read_gaussians_ply(path)
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty flot x\nend_header\n")
    with pytest.raises(InputError, match=r"bad\.ply: malformed PLY header"):
        read_gaussians_ply(bad)
