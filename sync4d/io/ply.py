"""3D Gaussian Splatting ``.ply`` files in the Inria layout.

Properties (binary little-endian float32, one vertex element)::

    x y z [nx ny nz] f_dc_0..2 [f_rest_0..3*(K-1)-1] opacity scale_0..2 rot_0..3

``opacity`` is a logit, ``scale_*`` are natural logs of standard deviations, ``rot_*`` is a wxyz
quaternion. ``f_rest`` is stored channel-major (all R coefficients, then G, then B), as the Inria code
writes it. Reading normalises quaternions that are not already unit length (to float32 precision), so a
file written by :func:`write_gaussians_ply` and read back gives bit-identical arrays.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from sync4d.errors import InputError
from sync4d.types import TargetGaussians

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3"]  # fmt: skip


def _parse_header(path: Path, raw: bytes) -> tuple[str, int, list[tuple[str, str]], int]:
    """Returns (format, vertex count, [(name, numpy dtype)], header length in bytes)."""
    if not raw.startswith(b"ply"):
        raise InputError(f"{path}: not a PLY file (it does not start with 'ply'); give a 3DGS .ply, "
                         "or target=mesh for a triangle mesh")
    end = raw.find(b"end_header")
    if end < 0:
        raise InputError(f"{path}: PLY header has no 'end_header' (truncated or not a PLY file)")
    newline = raw.find(b"\n", end)
    header_len = newline + 1 if newline >= 0 else len(raw)
    lines = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt, count, props, element = "", -1, [], None
    for number, line in enumerate(lines[1:], start=2):
        try:
            fmt, count, element = _header_line(path, line, fmt, count, element, props)
        except (IndexError, ValueError):
            raise InputError(f"{path}: malformed PLY header line {number}: {line.strip()!r}") from None
    if count < 0:
        raise InputError(f"{path}: PLY has no 'vertex' element")
    return fmt, count, props, header_len


def _header_line(path: Path, line: str, fmt: str, count: int, element: str | None,
                 props: list[tuple[str, str]]) -> tuple[str, int, str | None]:
    """Parse one header line into (format, vertex count, current element); appends vertex properties."""
    words = line.split()
    if words and words[0] not in ("comment", "obj_info"):
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            element = words[1]
            if element == "vertex":
                count = int(words[2])
                if count < 0:
                    raise ValueError(count)
            # Elements after the vertices are not read; elements before would shift the data.
        elif words[0] == "property" and element == "vertex":
            if words[1] == "list":
                raise InputError(f"{path}: list property '{words[-1]}' in the vertex element is not supported")
            if words[1] not in _PLY_TYPES:
                raise InputError(f"{path}: unknown PLY property type '{words[1]}'")
            props.append((words[2], _PLY_TYPES[words[1]]))
    return fmt, count, element


def read_gaussians_ply(path: str | os.PathLike[str], *, name: str | None = None) -> TargetGaussians:
    """Read a 3DGS ``.ply`` (Inria layout, SH degree 0-3, with or without normals).

    Raises:
        InputError: not a PLY, truncated, missing a required property, NaN/inf, zero Gaussians; the
            message names the file and the problem.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    raw = path.read_bytes()
    fmt, count, props, header_len = _parse_header(path, raw)
    names = [p[0] for p in props]
    missing = [p for p in REQUIRED if p not in names]
    if missing:
        raise InputError(f"{path}: missing 3DGS property(ies) {', '.join(missing)}; is this a Gaussian splat .ply?")
    if count == 0:
        raise InputError(f"{path}: contains zero Gaussians ('element vertex 0'); export the trained splat again")
    if fmt == "binary_little_endian":
        dtype = np.dtype([(n, "<" + t) for n, t in props])
    elif fmt == "binary_big_endian":
        dtype = np.dtype([(n, ">" + t) for n, t in props])
    elif fmt == "ascii":
        dtype = None
    else:
        raise InputError(f"{path}: unknown PLY format '{fmt}'")
    if dtype is not None:
        need = count * dtype.itemsize
        if len(raw) - header_len < need:
            raise InputError(
                f"{path}: truncated: header declares {count} Gaussians ({need} bytes), file holds "
                f"{len(raw) - header_len} bytes of data; the file was cut short, copy or export it again"
            )
        data = np.frombuffer(raw, dtype=dtype, count=count, offset=header_len)
        columns = {n: np.asarray(data[n], dtype=np.float32) for n in names}
    else:
        text = raw[header_len:].decode("ascii", errors="replace").split()
        if len(text) < count * len(names):
            raise InputError(f"{path}: truncated ASCII PLY: fewer values than {count} x {len(names)}")
        try:
            table = np.array(text[: count * len(names)], dtype=np.float64).reshape(count, len(names))
        except ValueError as err:
            raise InputError(f"{path}: ASCII PLY holds a value that is not a number ({err})") from None
        columns = {n: table[:, i].astype(np.float32) for i, n in enumerate(names)}
    check_finite_columns(path, columns)

    rest_names = sorted((n for n in names if n.startswith("f_rest_")), key=lambda n: int(n.split("_")[-1]))
    n_rest = len(rest_names)
    if n_rest % 3 or (n_rest // 3 + 1) not in (1, 4, 9, 16):
        raise InputError(f"{path}: {n_rest} f_rest properties do not form SH degree 0-3 (expected 0, 9, 24 or 45)")
    k = n_rest // 3 + 1
    sh = np.zeros((count, k, 3), dtype=np.float32)
    sh[:, 0, :] = np.stack([columns[f"f_dc_{c}"] for c in range(3)], axis=1)
    if n_rest:
        rest = np.stack([columns[n] for n in rest_names], axis=1).reshape(count, 3, k - 1)
        sh[:, 1:, :] = np.transpose(rest, (0, 2, 1))
    quats = np.stack([columns[f"rot_{i}"] for i in range(4)], axis=1)
    normals = np.stack([columns[a] for a in ("nx", "ny", "nz")], axis=1) if "nx" in names else None
    gaussians = TargetGaussians(
        means=np.stack([columns["x"], columns["y"], columns["z"]], axis=1),
        quats=normalize_quats(quats, path),
        log_scales=np.stack([columns[f"scale_{i}"] for i in range(3)], axis=1),
        opacity_logits=columns["opacity"].copy(),
        sh=sh,
        normals=normals,
        name=name or path.stem,
    )
    try:
        return gaussians.validate()
    except InputError as err:
        raise InputError(f"{path}: {err}") from None


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


def normalize_quats(quats: np.ndarray, source: object = "quats") -> np.ndarray:
    """Unit-normalise (N, 4) float32 quaternions; rows already unit to float32 precision are kept as is.

    Keeping near-unit rows untouched makes write -> read bit-identical (renormalising a unit float32
    quaternion can change its last bit).
    """
    norms = np.linalg.norm(quats.astype(np.float64), axis=1, keepdims=True)
    if np.any(norms < 1e-12):
        raise InputError(f"{source}: {int((norms < 1e-12).sum())} zero-length rotation quaternion(s)")
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
    if k > 1:
        rest = np.transpose(g.sh[:, 1:, :], (0, 2, 1)).reshape(g.num, 3 * (k - 1))
        cols += [(f"f_rest_{i}", rest[:, i]) for i in range(rest.shape[1])]
    cols.append(("opacity", g.opacity_logits))
    cols += [(f"scale_{i}", g.log_scales[:, i]) for i in range(3)]
    cols += [(f"rot_{i}", g.quats[:, i]) for i in range(4)]
    return cols


def write_gaussians_ply(path: str | os.PathLike[str], gaussians: TargetGaussians) -> Path:
    """Write ``gaussians`` as a binary little-endian Inria 3DGS ``.ply``, atomically (temp file + rename)."""
    gaussians.validate()
    path = Path(path)
    cols = _ply_columns(gaussians)
    data = np.empty(gaussians.num, dtype=[(n, "<f4") for n, _ in cols])
    for n, values in cols:
        data[n] = values
    header = "ply\nformat binary_little_endian 1.0\n"
    header += f"element vertex {gaussians.num}\n"
    header += "".join(f"property float {n}\n" for n, _ in cols)
    header += "end_header\n"
    from sync4d.io.atomic import atomic_write_bytes

    atomic_write_bytes(path, header.encode("ascii") + data.tobytes())
    return path


def sh_degree_of_property_names(names: list[str]) -> int:
    """SH degree implied by a list of property names (for diagnostics)."""
    n_rest = sum(1 for n in names if re.fullmatch(r"f_rest_\d+", n))
    return int(round(np.sqrt(n_rest // 3 + 1))) - 1
