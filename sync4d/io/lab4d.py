"""Readers for Lab4D exports and plain OBJ mesh sequences.

Two layouts are understood:

* **Lab4D export** (``lab4d/export.py``): ``fg.obj`` (rest/canonical mesh), ``fg-%05d.obj`` (posed
  meshes, optional), ``fg-motion.json`` with ``field2cam`` (T x 4 x 4, object -> camera) and
  ``t_articulation`` (T x K x 4 x 4, per-bone rest -> frame transforms), optionally ``fg-skin.npy``
  (V x K rest skinning weights; Lab4D's export does not write one, so it may be absent).
* **Per-frame layout** of ``gengshan-y/ppr-diffphys`` (MIT; the shared folder
  ``lab4d_export/shiba-haru-1002``): ``<name>-mesh-%05d.obj`` posed meshes with vertex colours and fixed
  topology, ``<name>-cam-%05d.txt`` (3x4 world-to-camera, then a row fx fy cx cy),
  ``<name>-se3-%05d.txt`` (K x (3x3 rotation row-major + translation) per frame) and
  ``val-rest-skin.npy`` (V x K' rest skinning).

Readers only read and check shapes; whether the parts agree (K vs K') is decided by
:mod:`sync4d.recon.lab4d`.
"""

from __future__ import annotations

import glob
import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sync4d.errors import DataMissingError, InputError


def read_obj(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Read a Wavefront OBJ keeping the file's vertex order (needed for correspondence across frames).

    Polygons are fan-triangulated; ``v x y z r g b`` colour extensions are read.

    Args:
        path: the .obj file.

    Returns:
        (vertices (V, 3) float64 [file units], faces (F, 3) int64, colours (V, 3) float64 in [0, 1] or None).

    Raises:
        DataMissingError: the file does not exist.
        InputError: no vertices, or a face index out of range.
    """
    path = Path(path)
    if not path.is_file():
        raise DataMissingError(f"mesh file not found: {path}")
    text = path.read_text(errors="replace")
    v_lines = re.findall(r"^v[ \t]+([^\n]*)", text, flags=re.M)
    if not v_lines:
        raise InputError(f"{path}: no vertices ('v' lines) found; is it an OBJ mesh?")
    widths = {len(line.split()) for line in v_lines}
    width = min(min(widths), 6)
    try:
        if len(widths) == 1:  # the common case: one numeric parse of every vertex line
            arr = np.array(" ".join(v_lines).split(), dtype=np.float64).reshape(len(v_lines), -1)[:, :width]
        else:
            arr = np.array([[float(x) for x in line.split()[:width]] for line in v_lines], dtype=np.float64)
    except ValueError:
        raise InputError(f"{path}: a 'v' line is not numeric") from None
    faces: list[list[int]] = []
    for line in re.findall(r"^f[ \t]+([^\n]*)", text, flags=re.M):
        idx = [int(tok.split("/")[0]) for tok in line.split()]
        for k in range(1, len(idx) - 1):
            faces.append([idx[0], idx[k], idx[k + 1]])
    n = len(arr)
    f = np.array(faces, dtype=np.int64).reshape(-1, 3)
    # OBJ indices are 1-based; negative ones count back from the end.
    f = np.where(f > 0, f - 1, n + f)
    if f.size and (f.min() < 0 or f.max() >= n):
        raise InputError(f"{path}: face index out of range [1, {n}]")
    colors = arr[:, 3:6] if width >= 6 else None
    if colors is not None and colors.max() > 1.0:
        colors = colors / 255.0
    return arr[:, :3].copy(), f, colors


def write_obj(path: str | Path, vertices: np.ndarray, faces: np.ndarray | None = None) -> None:
    """Write vertices (V, 3) and optional faces (F, 3, 0-based) as an OBJ (used by tests and exports)."""
    with Path(path).open("w") as fh:
        for v in vertices:
            fh.write(f"v {v[0]:.8f} {v[1]:.8f} {v[2]:.8f}\n")
        if faces is not None:
            for tri in faces:
                fh.write(f"f {tri[0] + 1} {tri[1] + 1} {tri[2] + 1}\n")


def _numbered(files: list[Path]) -> list[Path]:
    """Sort files by the last integer in their name (so frame 10 follows frame 9)."""

    def key(p: Path) -> tuple[int, str]:
        nums = re.findall(r"\d+", p.stem)
        return (int(nums[-1]) if nums else -1, p.name)

    return sorted(files, key=key)


def read_mesh_sequence(paths: list[Path]) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Read OBJ meshes with fixed topology into one array.

    Args:
        paths: the .obj files in frame order.

    Returns:
        (vertices (T, V, 3), faces (F, 3) of the first mesh, colours (V, 3) of the first mesh or None).

    Raises:
        DataMissingError: ``paths`` is empty.
        InputError: the meshes do not share a vertex count and face list.
    """
    if not paths:
        raise DataMissingError("no .obj meshes to read")
    verts, faces, colors = read_obj(paths[0])
    frames = [verts]
    for p in paths[1:]:
        v, f, _ = read_obj(p)
        if v.shape != verts.shape:
            raise InputError(
                f"{p}: {len(v)} vertices but {paths[0].name} has {len(verts)}; a mesh sequence needs fixed topology"
            )
        if f.shape != faces.shape or not np.array_equal(f, faces):
            raise InputError(f"{p}: faces differ from {paths[0].name}; a mesh sequence needs fixed topology")
        frames.append(v)
    return np.stack(frames), faces, colors


def find_mesh_files(path: str | Path) -> list[Path]:
    """OBJ files of a sequence: a folder (every ``*.obj`` except ``*-bone.obj``), or a glob pattern.

    Raises:
        DataMissingError: nothing matches.
    """
    p = Path(path)
    if p.is_dir():
        files = [f for f in p.glob("*.obj") if not f.stem.endswith("-bone")]
    else:
        files = [Path(f) for f in glob.glob(str(p)) if f.endswith(".obj")]
    if not files:
        raise DataMissingError(f"no .obj meshes found at {path}")
    return _numbered(files)


@dataclass(frozen=True)
class Lab4DExport:
    """A Lab4D-style export as read from disk (no consistency decisions yet).

    Attributes:
        layout: ``"export"`` (fg.obj + fg-motion.json) or ``"per_frame"`` (ppr-diffphys files).
        rest_vertices: (V, 3) rest mesh [m], or None when the layout has no rest mesh (per-frame).
        faces: (F, 3) int64.
        colors: (V, 3) in [0, 1] or None.
        posed_vertices: (T, V, 3) posed meshes [m] or None.
        bone_transforms: (T, K, 4, 4) per-bone rest -> frame t transforms, or None.
        object_to_camera: (T, 4, 4) object (or world) -> camera per frame, or None.
        intrinsics: (T, 4) fx fy cx cy [px], or None.
        rest_skinning: (V, K') rest skinning weights, or None.
        path: the folder.
    """

    layout: str
    rest_vertices: np.ndarray | None
    faces: np.ndarray
    colors: np.ndarray | None
    posed_vertices: np.ndarray | None
    bone_transforms: np.ndarray | None
    object_to_camera: np.ndarray | None
    intrinsics: np.ndarray | None
    rest_skinning: np.ndarray | None
    path: str


def read_lab4d_export(path: str | Path) -> Lab4DExport:
    """Read either Lab4D layout from a folder (detected from the files present).

    Raises:
        DataMissingError: the folder is missing or holds neither layout.
        InputError: a file has the wrong shape.
    """
    root = Path(path)
    if not root.is_dir():
        raise DataMissingError(f"Lab4D export folder not found: {root}")
    if (root / "fg-motion.json").is_file() or (root / "fg.obj").is_file():
        return _read_new_layout(root)
    if list(root.glob("*-mesh-*.obj")):
        return _read_per_frame_layout(root)
    raise DataMissingError(
        f"{root}: neither a Lab4D export (fg.obj + fg-motion.json) nor a per-frame export (*-mesh-*.obj)"
    )


def _read_new_layout(root: Path) -> Lab4DExport:
    if not (root / "fg.obj").is_file():
        raise DataMissingError(f"{root}: fg-motion.json found but the rest mesh fg.obj is missing")
    if not (root / "fg-motion.json").is_file():
        raise DataMissingError(f"{root}: fg.obj found but fg-motion.json is missing")
    rest, faces, colors = read_obj(root / "fg.obj")
    with (root / "fg-motion.json").open() as fh:
        motion = json.load(fh)
    field2cam = _as_array(motion, "field2cam", root)
    if field2cam.ndim != 3 or field2cam.shape[1:] != (4, 4):
        raise InputError(f"{root}/fg-motion.json: field2cam must be T x 4 x 4, got {field2cam.shape}")
    art = None
    if "t_articulation" in motion and motion["t_articulation"] is not None:
        art = _as_array(motion, "t_articulation", root)
        if art.ndim != 4 or art.shape[2:] != (4, 4) or art.shape[0] != field2cam.shape[0]:
            raise InputError(
                f"{root}/fg-motion.json: t_articulation must be T x K x 4 x 4 with T={field2cam.shape[0]} "
                f"(as field2cam), got {art.shape}"
            )
    posed_files = _numbered([p for p in root.glob("fg-*.obj") if re.fullmatch(r"fg-\d+", p.stem)])
    posed = None
    if posed_files:
        posed, pf, _ = read_mesh_sequence(posed_files)
        if posed.shape[1] != len(rest):
            raise InputError(f"{root}: posed meshes have {posed.shape[1]} vertices, fg.obj has {len(rest)}")
    skin = None
    if (root / "fg-skin.npy").is_file():
        skin = np.load(root / "fg-skin.npy").astype(np.float64)
    return Lab4DExport("export", rest, faces, colors, posed, art, field2cam, None, skin, str(root))


def _as_array(motion: dict, key: str, root: Path) -> np.ndarray:
    if key not in motion:
        raise InputError(f"{root}/fg-motion.json: key '{key}' missing (keys: {', '.join(motion)})")
    arr = np.asarray(motion[key], dtype=np.float64)
    if not np.isfinite(arr).all():
        raise InputError(f"{root}/fg-motion.json: '{key}' contains NaN/inf")
    return arr


def _read_per_frame_layout(root: Path) -> Lab4DExport:
    mesh_files = _numbered(list(root.glob("*-mesh-*.obj")))
    posed, faces, colors = read_mesh_sequence(mesh_files)
    n_frames = len(mesh_files)
    se3_files = _numbered(list(root.glob("*-se3-*.txt")))
    bones = None
    if se3_files:
        if len(se3_files) != n_frames:
            raise InputError(f"{root}: {len(se3_files)} se3 files but {n_frames} meshes")
        rows = [np.loadtxt(f).reshape(-1) for f in se3_files]
        if any(r.size % 12 for r in rows) or len({r.size for r in rows}) != 1:
            raise InputError(f"{root}: se3 files must each hold K x 12 numbers (3x3 rotation + translation)")
        raw = np.stack(rows).reshape(n_frames, -1, 12)
        bones = np.tile(np.eye(4), (n_frames, raw.shape[1], 1, 1))
        bones[..., :3, :3] = raw[..., :9].reshape(n_frames, -1, 3, 3)
        bones[..., :3, 3] = raw[..., 9:]
    cam_files = _numbered(list(root.glob("*-cam-*.txt")))
    w2c = intr = None
    if cam_files:
        if len(cam_files) != n_frames:
            raise InputError(f"{root}: {len(cam_files)} cam files but {n_frames} meshes")
        cams = np.stack([np.loadtxt(f) for f in cam_files])
        if cams.shape[1:] != (4, 4):
            raise InputError(f"{root}: a cam file must hold 3x4 world-to-camera plus a row fx fy cx cy")
        w2c = np.tile(np.eye(4), (n_frames, 1, 1))
        w2c[:, :3, :] = cams[:, :3, :]
        intr = cams[:, 3, :]
    skin = None
    skin_file = root / "val-rest-skin.npy"
    if skin_file.is_file():
        skin = np.load(skin_file).astype(np.float64)
        if skin.ndim != 2 or skin.shape[0] != posed.shape[1]:
            raise InputError(f"{skin_file}: expected (V={posed.shape[1]}, K) weights, got {skin.shape}")
    return Lab4DExport("per_frame", None, faces, colors, posed, bones, w2c, intr, skin, str(root))
