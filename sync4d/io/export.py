"""Exports of an animated result: an animated USD, an animated glTF binary and a ``.npz`` of the sequence.

No standard Gaussian-sequence format exists; viewers (SuperSplat, GaussianSplats3D) open one 3DGS
``.ply`` per frame (written by :mod:`sync4d.io.ply`). Beside those, a run writes:

* ``sequence.usd`` (:func:`export_usd`): a ``UsdGeom.Points`` prim ``/sync4d/gaussians`` whose
  ``points`` (and ``widths``, ``extent``) are time-sampled once per frame (time code = frame index,
  ``timeCodesPerSecond`` = fps), with ``primvars:displayColor`` / ``displayOpacity``; and, when given,
  the reference mesh ``/sync4d/reference`` as a ``UsdGeom.Mesh`` (time-sampled if a vertex sequence is
  given). Y is up (as in the project's scenes; ``up_axis`` changes it) and one unit is one metre. Opens in usdview, Blender (File > Import > USD),
  Houdini, Omniverse.
* ``sequence.glb`` (:func:`export_glb`): the Gaussian centres as an animated glTF 2.0 point cloud (one
  morph target a frame, one weights animation), for Blender, three.js and game engines; it passes the
  Khronos validator with no errors or warnings (tests/test_export.py).
* ``sequence.npz`` (:func:`export_npz`): means (T, N, 3), covariances per frame (or quats/scales),
  colours / SH, opacities, fps; read back with :func:`load_npz` or ``numpy.load``.

The compact whole-sequence file ``sequence.s4d`` is :mod:`sync4d.io.seq4d`.

Every file is written atomically (a temporary name in the same folder, then renamed).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from sync4d.errors import InputError
from sync4d.io.atomic import atomic_save_npz, atomic_write

NPZ_FORMAT_VERSION = 1


def widths_from_covariances(covariances: np.ndarray, *, sigmas: float = 2.0) -> np.ndarray:
    """Point widths (diameters) for display: ``sigmas`` x the geometric-mean standard deviation.

    Args:
        covariances: (..., 3, 3) covariances [m^2].
        sigmas: diameter in standard deviations (2 = one sigma each side).

    Returns:
        (...,) widths [m].
    """
    det = np.clip(np.linalg.det(np.asarray(covariances, dtype=np.float64)), 0.0, None)
    return sigmas * det ** (1.0 / 6.0)


def widths_from_scales(scales: np.ndarray, *, sigmas: float = 2.0) -> np.ndarray:
    """(..., 3) per-axis standard deviations [m] -> (...,) widths ``sigmas * (s1 s2 s3)^(1/3)`` [m]."""
    s = np.asarray(scales, dtype=np.float64)
    return sigmas * np.exp(np.log(np.clip(s, 1e-12, None)).mean(axis=-1))


def _check_sequence(frames_means: np.ndarray) -> tuple[int, int]:
    if frames_means.ndim != 3 or frames_means.shape[2] != 3:
        raise InputError(f"export: frames_means must be (T, N, 3), got {frames_means.shape}")
    if frames_means.shape[0] == 0:
        raise InputError("export: the sequence has no frames")
    if not np.isfinite(frames_means).all():
        raise InputError("export: frames_means contains NaN/inf; the simulation diverged or the input is bad")
    return int(frames_means.shape[0]), int(frames_means.shape[1])


def export_usd(
    path: str | Path,
    frames_means: np.ndarray,
    colors: np.ndarray | None = None,
    widths: np.ndarray | float | None = None,
    fps: float = 24.0,
    *,
    opacities: np.ndarray | None = None,
    mesh_vertices: np.ndarray | None = None,
    mesh_faces: np.ndarray | None = None,
    mesh_color: tuple[float, float, float] = (0.7, 0.7, 0.75),
    up_axis: str = "Y",
) -> Path:
    """Write the Gaussian sequence (and optionally the reference mesh) as one animated USD stage.

    Args:
        path: output ``.usd`` (binary crate), ``.usdc`` or ``.usda`` (text).
        frames_means: (T, N, 3) Gaussian centres per frame [m].
        colors: (N, 3) RGB in [0, 1] (``displayColor``), or None.
        widths: point diameters [m]: a scalar, (N,) fixed or (T, N) per frame (see
            :func:`widths_from_scales`); None gives 1 cm.
        fps: frames per second; frame t is stored at time code t.
        opacities: (N,) in [0, 1] (``displayOpacity``), or None.
        mesh_vertices: (V, 3) static or (T, V, 3) per-frame reference mesh vertices [m], or None.
        mesh_faces: (F, 3) triangles of the reference mesh (required with ``mesh_vertices``).
        mesh_color: display colour of the mesh.
        up_axis: stage up axis, "Y" (the project's scenes) or "Z".

    Returns:
        The path written.
    """
    means = np.asarray(frames_means, dtype=np.float32)
    w = check_usd_inputs(means, colors, widths, opacities, mesh_vertices, mesh_faces)
    stage = new_stage(len(means), fps, up_axis)
    define_points(stage, "/sync4d/gaussians", means, w, colors, opacities)
    if mesh_vertices is not None:
        _define_mesh(stage, "/sync4d/reference", np.asarray(mesh_vertices, np.float32),
                     np.asarray(mesh_faces), mesh_color)

    def write(tmp: Path) -> None:
        if not stage.GetRootLayer().Export(str(tmp)):
            raise OSError(f"export_usd: USD could not write {tmp}")

    return atomic_write(path, write)


def check_usd_inputs(means: np.ndarray, colors: np.ndarray | None, widths: np.ndarray | float | None,
                     opacities: np.ndarray | None, mesh_vertices: np.ndarray | None,
                     mesh_faces: np.ndarray | None) -> np.ndarray:
    """Check :func:`export_usd`'s inputs (one :class:`InputError` naming the argument); returns the point
    widths [m] as (N,) or (T, N) float32."""
    num_frames, num = _check_sequence(means)
    if colors is not None and np.shape(colors) != (num, 3):
        raise InputError(f"export_usd: colors must be ({num}, 3), got {np.shape(colors)}")
    if opacities is not None and np.shape(opacities) != (num,):
        raise InputError(f"export_usd: opacities must be ({num},), got {np.shape(opacities)}")
    w = np.full(num, 0.01, np.float32) if widths is None else np.asarray(widths, dtype=np.float32)
    if w.ndim == 0:
        w = np.full(num, float(w), np.float32)
    if w.shape not in ((num,), (num_frames, num)):
        raise InputError(f"export_usd: widths must be a scalar, ({num},) or ({num_frames}, {num}), got {w.shape}")
    if mesh_vertices is not None and mesh_faces is None:
        raise InputError("export_usd: mesh_vertices given without mesh_faces")
    return w


def new_stage(num_frames: int, fps: float, up_axis: str) -> Any:
    """An in-memory USD stage of ``num_frames`` time codes at ``fps``, metres, with a ``/sync4d`` root."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.CreateInMemory()
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(num_frames - 1)
    stage.SetTimeCodesPerSecond(float(fps))
    stage.SetFramesPerSecond(float(fps))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z if up_axis.upper() == "Z" else UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/sync4d")
    stage.SetDefaultPrim(root.GetPrim())
    return stage


def define_points(stage: Any, prim_path: str, means: np.ndarray, w: np.ndarray, colors: np.ndarray | None,
                  opacities: np.ndarray | None) -> None:
    """Animated USD points: (T, N, 3) positions [m] per time code, widths (N,) or (T, N) [m], colours and
    opacities (fixed), and an extent per frame that bounds the points with their widths."""
    from pxr import Gf, Usd, UsdGeom, Vt

    num_frames, num = means.shape[:2]
    points = UsdGeom.Points.Define(stage, prim_path)
    points_attr, extent_attr, widths_attr = points.GetPointsAttr(), points.GetExtentAttr(), points.GetWidthsAttr()
    points.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
    if w.ndim == 1:
        widths_attr.Set(Vt.FloatArray.FromNumpy(w))
    for t in range(num_frames):
        code = Usd.TimeCode(t)
        points_attr.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(means[t])), code)
        w_t = w[t] if w.ndim == 2 else w
        if w.ndim == 2:
            widths_attr.Set(Vt.FloatArray.FromNumpy(np.ascontiguousarray(w_t)), code)
        # Extent must bound the points including their widths for viewers to frame and cull correctly.
        pad = 0.5 * float(w_t.max()) if num else 0.0
        lo = means[t].min(axis=0) - pad if num else np.zeros(3)
        hi = means[t].max(axis=0) + pad if num else np.zeros(3)
        extent_attr.Set(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]), code)
    if colors is not None:
        color_pv = points.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex)
        color_pv.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(np.clip(colors, 0, 1), dtype=np.float32)))
    if opacities is not None:
        opacity_pv = points.CreateDisplayOpacityPrimvar(UsdGeom.Tokens.vertex)
        opacity_pv.Set(Vt.FloatArray.FromNumpy(np.ascontiguousarray(np.clip(opacities, 0, 1), dtype=np.float32)))


def _define_mesh(stage: Any, prim_path: str, verts: np.ndarray, faces: np.ndarray,
                 color: tuple[float, float, float]) -> None:
    from pxr import Gf, Usd, UsdGeom, Vt

    if faces.ndim != 2 or faces.shape[1] != 3:
        raise InputError(f"export_usd: mesh_faces must be (F, 3), got {faces.shape}")
    if verts.ndim not in (2, 3) or verts.shape[-1] != 3:
        raise InputError(f"export_usd: mesh_vertices must be (V, 3) or (T, V, 3), got {verts.shape}")
    num_v = verts.shape[-2]
    if faces.size and (faces.min() < 0 or faces.max() >= num_v):
        raise InputError(f"export_usd: mesh_faces index outside [0, {num_v})")
    mesh = UsdGeom.Mesh.Define(stage, prim_path)
    mesh.GetFaceVertexCountsAttr().Set(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
    mesh.GetFaceVertexIndicesAttr().Set(Vt.IntArray.FromNumpy(np.ascontiguousarray(faces.reshape(-1), np.int32)))
    mesh.GetSubdivisionSchemeAttr().Set(UsdGeom.Tokens.none)
    mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(Vt.Vec3fArray([Gf.Vec3f(*color)]))
    seq = verts if verts.ndim == 3 else verts[None]
    for t, v in enumerate(seq):
        # A static mesh gets a default value, a sequence one sample per frame of its own length.
        code = Usd.TimeCode(t) if verts.ndim == 3 else Usd.TimeCode.Default()
        mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(v)), code)
        lo, hi = v.min(axis=0), v.max(axis=0)
        mesh.GetExtentAttr().Set(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]), code)


def read_usd_points(path: str | Path, prim_path: str = "/sync4d/gaussians") -> tuple[np.ndarray, float]:
    """Read back the time-sampled points of an exported stage.

    Returns:
        (T, N, 3) positions [m] at time codes 0..T-1 and the stage's time codes per second.
    """
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    if stage is None:
        raise InputError(f"read_usd_points: cannot open {path} as USD")
    prim = stage.GetPrimAtPath(prim_path)
    if not prim.IsValid():
        raise InputError(f"read_usd_points: {path} has no prim {prim_path}")
    attr = UsdGeom.Points(prim).GetPointsAttr()
    times = attr.GetTimeSamples()
    frames = np.stack([np.asarray(attr.Get(Usd.TimeCode(t)), dtype=np.float32) for t in times])
    return frames, float(stage.GetTimeCodesPerSecond())


def export_npz(
    path: str | Path,
    frames_means: np.ndarray,
    *,
    fps: float,
    colors: np.ndarray | None = None,
    sh: np.ndarray | None = None,
    opacities: np.ndarray | None = None,
    covariances: np.ndarray | None = None,
    quats: np.ndarray | None = None,
    scales: np.ndarray | None = None,
    deformation: np.ndarray | None = None,
    global_transforms: np.ndarray | None = None,
    **extras: np.ndarray,
) -> Path:
    """Write the Gaussian sequence as a compressed ``.npz`` (atomically).

    Args:
        path: output file (``.npz``).
        frames_means: (T, N, 3) centres per frame [m].
        fps: frames per second [1/s].
        colors: (N, 3) RGB in [0, 1].
        sh: (N, K, 3) SH coefficients (3DGS order).
        opacities: (N,) in [0, 1].
        covariances: (N, 3, 3) fixed or (T, N, 3, 3) per-frame covariances [m^2].
        quats: (N, 4) or (T, N, 4) wxyz rotations, with ``scales`` (N, 3) or (T, N, 3) [m].
        deformation: (T, N, 3, 3) deformation gradients of the simulation.
        global_transforms: (T, 4, 4) global transforms applied for output.
        **extras: any further arrays (stored under their names).

    Returns:
        The path written.
    """
    means = np.asarray(frames_means)
    num_frames, num = _check_sequence(means)
    arrays: dict[str, Any] = {
        "format_version": np.int64(NPZ_FORMAT_VERSION),
        "means": means.astype(np.float32),
        "fps": np.float64(fps),
    }
    checks = {
        "colors": (colors, [(num, 3)]),
        "sh": (sh, None),
        "opacities": (opacities, [(num,)]),
        "covariances": (covariances, [(num, 3, 3), (num_frames, num, 3, 3)]),
        "quats": (quats, [(num, 4), (num_frames, num, 4)]),
        "scales": (scales, [(num, 3), (num_frames, num, 3)]),
        "deformation": (deformation, [(num_frames, num, 3, 3)]),
        "global_transforms": (global_transforms, [(num_frames, 4, 4)]),
    }
    for name, (value, shapes) in checks.items():
        if value is None:
            continue
        arr = np.asarray(value)
        if name == "sh" and (arr.ndim != 3 or arr.shape[0] != num or arr.shape[2] != 3):
            raise InputError(f"export_npz: sh must be ({num}, K, 3), got {arr.shape}")
        if shapes is not None and arr.shape not in shapes:
            raise InputError(f"export_npz: {name} must have shape {' or '.join(map(str, shapes))}, got {arr.shape}")
        arrays[name] = arr.astype(np.float32)
    for name, value in extras.items():
        if name in arrays:
            raise InputError(f"export_npz: extra array '{name}' clashes with a standard field")
        arrays[name] = np.asarray(value)
    return atomic_save_npz(path, **arrays)


def load_npz(path: str | Path) -> dict[str, Any]:
    """Read a sequence written by :func:`export_npz`: arrays by name, ``fps`` as a float."""
    with np.load(str(path), allow_pickle=False) as data:
        out: dict[str, Any] = {k: data[k] for k in data.files}
    if "means" not in out or "fps" not in out:
        raise InputError(f"load_npz: {path} is not a sync4d sequence (no 'means'/'fps')")
    out["fps"] = float(out["fps"])
    out["format_version"] = int(out.get("format_version", 0))
    return out


def _pad4(data: bytes, fill: bytes) -> bytes:
    return data + fill * (-len(data) % 4)


def _glb_bytes(gltf: dict[str, Any], binary: bytes) -> bytes:
    """A GLB container: 12-byte header, a JSON chunk (space padded), a BIN chunk (zero padded)."""
    import json
    import struct

    js = _pad4(json.dumps(gltf, separators=(",", ":")).encode(), b" ")
    bn = _pad4(binary, b"\x00")
    total = 12 + 8 + len(js) + 8 + len(bn)
    return (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<I4s", len(js), b"JSON") + js
            + struct.pack("<I4s", len(bn), b"BIN\x00") + bn)


class _GltfBuffer:
    """Collects arrays into one binary buffer with a bufferView and an accessor each."""

    def __init__(self) -> None:
        self.data = bytearray()
        self.views: list[dict[str, Any]] = []
        self.accessors: list[dict[str, Any]] = []

    def add(self, array: np.ndarray, kind: str, *, target: int | None = None, min_max: bool = False) -> int:
        """Append ``array`` (float32 rows of ``kind`` "SCALAR"/"VEC3"/"VEC4"); returns its accessor index."""
        arr = np.ascontiguousarray(array, dtype=np.float32)
        self.data += b"\x00" * (-len(self.data) % 4)
        view: dict[str, Any] = {"buffer": 0, "byteOffset": len(self.data), "byteLength": arr.nbytes}
        if target is not None:
            view["target"] = target
        self.data += arr.tobytes()
        self.views.append(view)
        rows = arr.reshape(len(arr), -1)
        accessor: dict[str, Any] = {"bufferView": len(self.views) - 1, "componentType": 5126, "count": len(arr),
                                    "type": kind}
        if min_max:
            accessor["min"] = rows.min(axis=0).tolist()
            accessor["max"] = rows.max(axis=0).tolist()
        self.accessors.append(accessor)
        return len(self.accessors) - 1


def export_glb(
    path: str | Path,
    frames_means: np.ndarray,
    *,
    fps: float,
    colors: np.ndarray | None = None,
    name: str = "sync4d_target",
) -> Path:
    """Write the Gaussian centres as an animated glTF 2.0 binary: a point cloud with one morph target a frame.

    The mesh holds one POINTS primitive at frame 0's positions (with ``COLOR_0`` when colours are
    given) and T - 1 morph targets, target k being the displacement of frame k + 1 from frame 0. One
    animation ("sequence") drives the morph weights: at time t / fps the weights are one-hot on frame t
    (linear interpolation between frames), so every frame shows exactly the exported positions. Y is
    up and one unit is one metre (glTF's convention, and the project's scenes'). Blender imports the
    targets as shape keys; three.js's GLTFLoader plays it with an AnimationMixer.

    Args:
        path: output ``.glb``.
        frames_means: (T, N, 3) centres per frame [m].
        fps: frame rate [1/s].
        colors: (N, 3) RGB in [0, 1], or None.
        name: the node and mesh name.

    Returns:
        The path written.
    """
    means = np.asarray(frames_means, dtype=np.float32)
    num_frames, num = _check_sequence(means)
    if colors is not None and np.shape(colors) != (num, 3):
        raise InputError(f"export_glb: colors must be ({num}, 3), got {np.shape(colors)}")
    if not fps > 0:
        raise InputError(f"export_glb: fps must be > 0, got {fps}")
    buf = _GltfBuffer()
    attributes = {"POSITION": buf.add(means[0], "VEC3", target=34962, min_max=True)}
    if colors is not None:
        # glTF vertex colours are linear; the run's colours are display (sRGB) values.
        linear = np.clip(np.asarray(colors, dtype=np.float64), 0, 1) ** 2.2
        attributes["COLOR_0"] = buf.add(linear, "VEC3", target=34962)
    targets = [{"POSITION": buf.add(means[k] - means[0], "VEC3", target=34962, min_max=True)}
               for k in range(1, num_frames)]
    primitive: dict[str, Any] = {"attributes": attributes, "mode": 0, "material": 0}
    mesh: dict[str, Any] = {"name": name, "primitives": [primitive]}
    gltf: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": "sync4d"},
        "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"name": name, "mesh": 0}],
        "materials": [{"name": "points", "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1],
                                                                  "metallicFactor": 0.0, "roughnessFactor": 1.0}}],
        "meshes": [mesh],
    }
    if targets:
        primitive["targets"] = targets
        mesh["weights"] = [0.0] * len(targets)
        mesh["extras"] = {"targetNames": [f"frame_{k:04d}" for k in range(1, num_frames)]}
        times = buf.add(np.arange(num_frames, dtype=np.float32) / float(fps), "SCALAR", min_max=True)
        # Row t: the weights at frame t, one-hot on target t - 1 (all zero at frame 0).
        weights = np.zeros((num_frames, num_frames - 1), np.float32)
        weights[np.arange(1, num_frames), np.arange(num_frames - 1)] = 1.0
        out = buf.add(weights.reshape(-1), "SCALAR")
        gltf["animations"] = [{"name": "sequence", "samplers": [{"input": times, "output": out,
                                                                 "interpolation": "LINEAR"}],
                               "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}]}]
    gltf["accessors"], gltf["bufferViews"] = buf.accessors, buf.views
    gltf["buffers"] = [{"byteLength": len(buf.data) + (-len(buf.data) % 4)}]
    return atomic_write(path, lambda tmp: Path(tmp).write_bytes(_glb_bytes(gltf, bytes(buf.data))))


def read_glb(path: str | Path) -> tuple[dict[str, Any], bytes]:
    """The JSON and BIN chunks of a ``.glb`` (for checks). Raises :class:`InputError` if it is not one."""
    import json
    import struct

    data = Path(path).read_bytes()
    if len(data) < 20 or data[:4] != b"glTF":
        raise InputError(f"{path}: not a glTF binary (no 'glTF' magic)")
    _, _, total = struct.unpack_from("<4sII", data, 0)
    js_len, _ = struct.unpack_from("<I4s", data, 12)
    gltf = json.loads(data[20 : 20 + js_len])
    off = 20 + js_len
    binary = b""
    if off + 8 <= total:
        bn_len, _ = struct.unpack_from("<I4s", data, off)
        binary = data[off + 8 : off + 8 + bn_len]
    return gltf, binary
