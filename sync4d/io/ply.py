"""3D Gaussian Splatting ``.ply`` files in the Inria layout, read and written with ``plyfile``.

Properties (binary little-endian float32, one vertex element)::

    x y z [nx ny nz] f_dc_0..2 [f_rest_0..3*(K-1)-1] opacity scale_0..2 rot_0..3

``opacity`` is a logit, ``scale_*`` are natural logs of standard deviations, ``rot_*`` is a wxyz
quaternion. ``f_rest`` is stored channel-major (all R coefficients, then G, then B), as the Inria code
writes it. Reading normalises quaternions that are not already unit length (to float32 precision), so a
file written by :func:`write_gaussians_ply` and read back gives bit-identical arrays.

Parsing is ``plyfile``'s (the library the field uses: any PLY layout, element order, ASCII or binary of
either byte order; binary data is memory-mapped). This module adds the 3DGS checks on top, each a
one-line :class:`~sync4d.errors.InputError` naming the file, the property and the first offending
Gaussian: NaN/inf, and values no trained splat holds (:data:`LIMITS`: log-scales whose exponential
overflows or underflows float32, opacity logits beyond +-100, positions beyond 1000 km).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import plyfile

from sync4d.errors import InputError
from sync4d.types import TargetGaussians

REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3"]  # fmt: skip

#: Inclusive (low, high) bounds of values a real splat can hold, per property prefix, and why.
#: exp(+-80) is near the float32 range (exp(88.7) overflows, exp(-87) is subnormal); a logit of 100 is
#: an opacity of 1 - 4e-44; 1e6 m is 1000 km (a floater farther than that is a corrupt file, and nearer
#: ones are found by :mod:`sync4d.sources.floaters`).
LIMITS: dict[str, tuple[float, float, str]] = {
    "scale_": (-80.0, 80.0, "a log standard deviation: exp() of it leaves the float32 range"),
    "opacity": (-100.0, 100.0, "an opacity logit"),
    "x": (-1e6, 1e6, "a position [m] farther than 1000 km"),
    "y": (-1e6, 1e6, "a position [m] farther than 1000 km"),
    "z": (-1e6, 1e6, "a position [m] farther than 1000 km"),
}


def _vertex_table(path: Path) -> tuple[list[str], np.ndarray]:
    """Property names and the (N, P) float32 matrix of a PLY's ``vertex`` element (one-line InputError otherwise).

    plyfile memory-maps binary data (its ``mmap=False`` path parses row by row in Python: 18 s for 50 k
    Gaussians); the table is then copied into memory in one sequential pass and viewed as one float32
    matrix when every property is little-endian float32 (the 3DGS case), so the checks below run once
    over a contiguous array instead of once per strided column of the map.
    """
    try:
        data = plyfile.PlyData.read(str(path))
    except plyfile.PlyHeaderParseError as err:
        if "expected 'ply'" in str(err):
            raise InputError(f"{path}: not a PLY file (it does not start with 'ply'); give a 3DGS .ply, "
                             "or target=mesh for a triangle mesh") from None
        raise InputError(f"{path}: malformed PLY header ({err})") from None
    except plyfile.PlyElementParseError as err:
        raise InputError(f"{path}: truncated or malformed data ({err}); the file was cut short, copy or "
                         "export it again") from None
    except (plyfile.PlyParseError, ValueError) as err:  # e.g. a count that is not a number
        raise InputError(f"{path}: malformed PLY ({err})") from None
    if "vertex" not in data:
        raise InputError(f"{path}: PLY has no 'vertex' element")
    vertex = data["vertex"]
    lists = [p.name for p in vertex.properties if isinstance(p, plyfile.PlyListProperty)]
    if lists:
        raise InputError(f"{path}: list property '{lists[0]}' in the vertex element is not supported")
    names = [p.name for p in vertex.properties]
    missing = [p for p in REQUIRED if p not in names]
    if missing:
        raise InputError(f"{path}: missing 3DGS property(ies) {', '.join(missing)}; is this a Gaussian splat .ply?")
    if vertex.count == 0:
        raise InputError(f"{path}: contains zero Gaussians ('element vertex 0'); export the trained splat again")
    table = np.array(vertex.data)  # one sequential copy out of the map
    if all(table.dtype[n] == np.dtype("<f4") for n in names) and table.dtype.itemsize == 4 * len(names):
        return names, table.view("<f4").reshape(len(table), len(names))
    return names, np.stack([np.asarray(table[n], dtype=np.float32) for n in names], axis=1)


def read_gaussians_ply(path: str | os.PathLike[str], *, name: str | None = None) -> TargetGaussians:
    """Read a 3DGS ``.ply`` (Inria layout, SH degree 0-3, with or without normals).

    Raises:
        InputError: not a PLY, truncated, missing a required property, NaN/inf, a value outside
            :data:`LIMITS`, zero Gaussians; one line naming the file, the property and the Gaussian.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    names, matrix = _vertex_table(path)
    count = len(matrix)
    check_finite_matrix(path, names, matrix)
    col = {n: i for i, n in enumerate(names)}
    check_value_ranges(path, {n: matrix[:, i] for n, i in col.items() if _limit_of(n) is not None})
    rest_names = sorted((n for n in names if n.startswith("f_rest_")), key=lambda n: int(n.split("_")[-1]))
    n_rest = len(rest_names)
    if n_rest % 3 or (n_rest // 3 + 1) not in (1, 4, 9, 16):
        raise InputError(f"{path}: {n_rest} f_rest properties do not form SH degree 0-3 (expected 0, 9, 24 or 45)")
    k = n_rest // 3 + 1
    # channel-major f_rest: coefficient j >= 1 of channel c is f_rest_{c (K-1) + j - 1}
    order = [[col[f"f_dc_{c}"]] + [col[rest_names[c * (k - 1) + j - 1]] for j in range(1, k)] for c in range(3)]
    sh = np.ascontiguousarray(matrix[:, np.asarray(order).T.reshape(-1)].reshape(count, k, 3))

    def cols(*keys: str) -> np.ndarray:
        return np.ascontiguousarray(matrix[:, [col[key] for key in keys]])

    gaussians = TargetGaussians(
        means=cols("x", "y", "z"),
        quats=normalize_quats(cols("rot_0", "rot_1", "rot_2", "rot_3"), path),
        log_scales=cols("scale_0", "scale_1", "scale_2"),
        opacity_logits=cols("opacity")[:, 0].copy(),
        sh=sh,
        normals=cols("nx", "ny", "nz") if "nx" in col else None,
        name=name or path.stem,
    )
    try:
        return gaussians.validate()
    except InputError as err:
        raise InputError(f"{path}: {err}") from None


def check_finite_matrix(path: Path, names: list[str], matrix: np.ndarray) -> None:
    """:func:`check_finite_columns` over the (N, P) property matrix in one pass."""
    finite = np.isfinite(matrix)
    if not finite.all():
        first = int(np.flatnonzero(~finite.all(axis=0))[0])
        check_finite_columns(path, {names[first]: matrix[:, first]})


def _limit_of(name: str) -> str | None:
    """The :data:`LIMITS` key that applies to property ``name``, or None."""
    return next((k for k in LIMITS if name == k or (k.endswith("_") and name.startswith(k))), None)


def check_finite_columns(path: Path, columns: dict[str, np.ndarray]) -> None:
    """Raise :class:`InputError` naming the first property holding NaN or inf, how many, and the first row."""
    for name, values in columns.items():
        bad = ~np.isfinite(values)
        if bad.any():
            kinds = "/".join(k for k, m in (("NaN", np.isnan(values)), ("inf", np.isinf(values))) if m.any())
            raise InputError(
                f"{path}: property '{name}' holds {int(bad.sum())} {kinds} value(s) (first at Gaussian "
                f"{int(np.flatnonzero(bad)[0])}); remove those Gaussians or export the splat again"
            )


def check_value_ranges(path: Path, columns: dict[str, np.ndarray]) -> None:
    """Raise :class:`InputError` naming the first property with a value outside :data:`LIMITS`.

    Args:
        path: the file (for the message).
        columns: property name -> (N,) finite values.
    """
    for name, values in columns.items():
        key = _limit_of(name)
        if key is None:
            continue
        low, high, meaning = LIMITS[key]
        bad = (values < low) | (values > high)
        if bad.any():
            first = int(np.flatnonzero(bad)[0])
            raise InputError(
                f"{path}: property '{name}' of Gaussian {first} is {float(values[first]):.6g}, outside "
                f"[{low:g}, {high:g}] for {meaning} ({int(bad.sum())} such Gaussian(s)); the file is corrupt "
                "or not in the Inria layout: remove those Gaussians or export the splat again"
            )


def normalize_quats(quats: np.ndarray, source: object = "quats") -> np.ndarray:
    """Unit-normalise (N, 4) float32 quaternions; rows already unit to float32 precision are kept as is.

    Keeping near-unit rows untouched makes write -> read bit-identical (renormalising a unit float32
    quaternion can change its last bit).
    """
    norms = np.linalg.norm(quats.astype(np.float64), axis=1, keepdims=True)
    if np.any(norms < 1e-12):
        first = int(np.flatnonzero(norms[:, 0] < 1e-12)[0])
        raise InputError(f"{source}: {int((norms < 1e-12).sum())} zero-length rotation quaternion(s) "
                         f"(rot_0..3, first at Gaussian {first})")
    needs = np.abs(norms - 1.0) > 4e-7
    out = quats.astype(np.float32, copy=True)
    out[needs[:, 0]] = (quats[needs[:, 0]] / norms[needs[:, 0]]).astype(np.float32)
    return out


def _ply_columns(g: TargetGaussians) -> list[tuple[str, np.ndarray]]:
    cols: list[tuple[str, np.ndarray]] = [("x", g.means[:, 0]), ("y", g.means[:, 1]), ("z", g.means[:, 2])]
    if g.normals is not None:
        cols += [("nx", g.normals[:, 0]), ("ny", g.normals[:, 1]), ("nz", g.normals[:, 2])]
    cols += [(f"f_dc_{c}", g.sh[:, 0, c]) for c in range(3)]
    k = g.sh.shape[1]
    cols += [(f"f_rest_{c * (k - 1) + j - 1}", g.sh[:, j, c]) for c in range(3) for j in range(1, k)]
    cols.append(("opacity", g.opacity_logits))
    cols += [(f"scale_{i}", g.log_scales[:, i]) for i in range(3)]
    cols += [(f"rot_{i}", g.quats[:, i]) for i in range(4)]
    return cols


def gaussians_table(gaussians: TargetGaussians) -> np.ndarray:
    """(N,) structured float32 array of the Inria properties, in file order.

    Built as one contiguous (N, P) float32 matrix from a few block copies and viewed as the structured
    type (assigning P strided columns one by one took 2.8 s for 2 M Gaussians).
    """
    g = gaussians
    k = g.sh.shape[1]
    blocks = [g.means] + ([g.normals] if g.normals is not None else []) + [g.sh[:, 0, :]]
    if k > 1:  # channel-major: all R coefficients, then G, then B
        blocks.append(np.transpose(g.sh[:, 1:, :], (0, 2, 1)).reshape(g.num, 3 * (k - 1)))
    blocks += [g.opacity_logits[:, None], g.log_scales, g.quats]
    matrix = np.concatenate([np.asarray(b, dtype="<f4") for b in blocks], axis=1)
    names = [n for n, _ in _ply_columns(g)]
    return matrix.view(np.dtype([(n, "<f4") for n in names])).reshape(g.num)


def write_gaussians_ply(path: str | os.PathLike[str], gaussians: TargetGaussians) -> Path:
    """Write ``gaussians`` as a binary little-endian Inria 3DGS ``.ply``, atomically (temp file + rename)."""
    gaussians.validate()
    from sync4d.io.atomic import atomic_write

    ply = plyfile.PlyData([plyfile.PlyElement.describe(gaussians_table(gaussians), "vertex")], byte_order="<")
    return atomic_write(Path(path), lambda tmp: ply.write(str(tmp)))
