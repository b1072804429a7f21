"""Write the corpus of malformed inputs under ``tests/data/bad/`` (small, deterministic files).

Run ``python tests/data/make_bad_inputs.py`` to (re)create it; running it twice gives identical bytes.
Each file is broken in exactly one way, named by the file; ``tests/test_bad_inputs.py`` feeds every one
of them (and the bad configurations listed there) to ``train.py`` and checks the one-line error.

The files are written with NumPy and the standard library only (never with sync4d's own writers, which
refuse to write malformed data).
"""

from __future__ import annotations

import json
import shutil
import struct
import zlib
from pathlib import Path

import numpy as np

BAD = Path(__file__).resolve().parent / "bad"
PLY_PROPS = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3"]  # fmt: skip
NUM_GAUSSIANS = 8


# ----------------------------------------------------------------------------------------------- PLY
def gaussian_table(n: int = NUM_GAUSSIANS) -> dict[str, np.ndarray]:
    """A valid table of ``n`` Gaussians on a small grid (float32 columns, unit quaternions)."""
    i = np.arange(n, dtype=np.float32)
    return {
        "x": 0.01 * i, "y": 0.02 * (i % 3), "z": 0.03 * (i % 2),
        "f_dc_0": np.full(n, 0.5, np.float32), "f_dc_1": np.full(n, 0.2, np.float32),
        "f_dc_2": np.full(n, -0.1, np.float32), "opacity": np.full(n, 2.0, np.float32),
        "scale_0": np.full(n, -4.0, np.float32), "scale_1": np.full(n, -4.5, np.float32),
        "scale_2": np.full(n, -5.0, np.float32), "rot_0": np.ones(n, np.float32),
        "rot_1": np.zeros(n, np.float32), "rot_2": np.zeros(n, np.float32), "rot_3": np.zeros(n, np.float32),
    }  # fmt: skip


def ply_bytes(columns: dict[str, np.ndarray], count: int | None = None) -> bytes:
    """A binary little-endian PLY with one float property per column; ``count`` overrides the header."""
    names = list(columns)
    n = len(next(iter(columns.values()))) if columns else 0
    data = np.empty(n, dtype=[(name, "<f4") for name in names])
    for name in names:
        data[name] = columns[name]
    header = "ply\nformat binary_little_endian 1.0\n"
    header += f"element vertex {n if count is None else count}\n"
    header += "".join(f"property float {name}\n" for name in names)
    header += "end_header\n"
    return header.encode("ascii") + data.tobytes()


def write_plys(folder: Path) -> None:
    """Truncated, not-a-PLY, NaN, inf, zero Gaussians and missing properties."""
    good = ply_bytes(gaussian_table())
    (folder / "ply_truncated.ply").write_bytes(good[: len(good) - 3 * 4 * len(PLY_PROPS) - 7])
    (folder / "ply_not_ply.ply").write_bytes(b"This is a text file renamed to .ply, not a point cloud.\n")
    nan = gaussian_table()
    nan["x"][3] = np.nan
    (folder / "ply_nan.ply").write_bytes(ply_bytes(nan))
    inf = gaussian_table()
    inf["scale_1"][5] = np.inf
    (folder / "ply_inf.ply").write_bytes(ply_bytes(inf))
    (folder / "ply_zero_gaussians.ply").write_bytes(ply_bytes({name: np.zeros(0, np.float32) for name in PLY_PROPS}))
    missing = {k: v for k, v in gaussian_table().items() if k not in ("opacity", "rot_0", "rot_1", "rot_2", "rot_3")}
    (folder / "ply_missing_properties.ply").write_bytes(ply_bytes(missing))
    (folder / "ply_one_gaussian.ply").write_bytes(ply_bytes(gaussian_table(1)))


# ---------------------------------------------------------------------------------------------- mesh
def write_meshes(folder: Path) -> None:
    """An OBJ holding vertices but no faces, and one whose only face has no area."""
    lines = ["# eight cube corners and no faces"]
    lines += [f"v {x} {y} {z}" for x in (0.0, 0.1) for y in (0.0, 0.1) for z in (0.0, 0.1)]
    (folder / "mesh_no_faces.obj").write_text("\n".join(lines) + "\n")
    (folder / "mesh_degenerate.obj").write_text("# three coincident vertices\nv 0 0 0\nv 0 0 0\nv 0 0 0\nf 1 2 3\n")


# --------------------------------------------------------------------------------------------- video
def png_bytes(image: np.ndarray) -> bytes:
    """An 8-bit greyscale or RGB PNG (no compression library beyond zlib, deterministic)."""
    image = np.ascontiguousarray(image, dtype=np.uint8)
    height, width = image.shape[:2]
    colour = 2 if image.ndim == 3 else 0
    raw = b"".join(b"\x00" + image[row].tobytes() for row in range(height))

    def chunk(kind: bytes, payload: bytes) -> bytes:
        return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))

    header = struct.pack(">IIBBBBB", width, height, 8, colour, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b"")


def write_images(folder: Path, images: list[np.ndarray]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for i, image in enumerate(images):
        (folder / f"{i:05d}.png").write_bytes(png_bytes(image))


def square_masks(size: int, frames: int, *, empty: bool = False) -> list[np.ndarray]:
    masks = []
    for t in range(frames):
        mask = np.zeros((size, size), np.uint8)
        if not empty:
            mask[size // 4 : size // 2, size // 4 + t : size // 2 + t] = 255
        masks.append(mask)
    return masks


def write_videos(folder: Path) -> None:
    """A video (image folder) with no frames; masks of the wrong size; all-empty masks."""
    empty = folder / "video_no_frames"
    empty.mkdir()
    (empty / "README.txt").write_text("An image-folder video with no frames (no .png/.jpg here).\n")
    frames = [np.full((16, 16, 3), 40 * (t + 1), np.uint8) for t in range(3)]
    root = folder / "video_mask_size"
    write_images(root / "rgb", frames)
    write_images(root / "masks", square_masks(8, 3))
    root = folder / "video_empty_mask"
    write_images(root / "rgb", frames)
    write_images(root / "masks", square_masks(16, 3, empty=True))


# ---------------------------------------------------------------------------------------------- BVH
def write_bvh(folder: Path) -> None:
    """A BVH whose MOTION rows hold fewer numbers than the declared channels (6 + 3 = 9)."""
    text = """HIERARCHY
ROOT Hips
{
  OFFSET 0.0 0.0 0.0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Spine
  {
    OFFSET 0.0 10.0 0.0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0.0 10.0 0.0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.033333
0.0 0.0 0.0 0.0 0.0 0.0
0.0 1.0 0.0 0.0 5.0 0.0
"""
    (folder / "bvh_wrong_channels.bvh").write_text(text)


# --------------------------------------------------------------------------------------------- Lab4D
def write_lab4d(folder: Path) -> None:
    """A Lab4D export (fg.obj + fg-motion.json + fg-skin.npy) with 3 bone transforms but 2 skinning columns."""
    root = folder / "lab4d_bone_skin_mismatch"
    root.mkdir()
    vertices = [(x, y, z) for x in (0.0, 0.1) for y in (0.0, 0.1) for z in (0.0, 0.1)]
    faces = [(1, 2, 4), (1, 4, 3), (5, 7, 8), (5, 8, 6), (1, 5, 6), (1, 6, 2),
             (3, 4, 8), (3, 8, 7), (1, 3, 7), (1, 7, 5), (2, 6, 8), (2, 8, 4)]  # fmt: skip
    obj = [f"v {x} {y} {z}" for x, y, z in vertices] + [f"f {a} {b} {c}" for a, b, c in faces]
    (root / "fg.obj").write_text("\n".join(obj) + "\n")
    frames, bones = 2, 3
    eye = np.eye(4).tolist()
    motion = {"field2cam": [eye] * frames, "t_articulation": [[eye] * bones] * frames}
    (root / "fg-motion.json").write_text(json.dumps(motion))
    skin = np.zeros((len(vertices), 2))
    skin[:4, 0] = skin[4:, 1] = 1.0
    np.save(root / "fg-skin.npy", skin)


def main() -> None:
    """Recreate ``tests/data/bad/`` from scratch."""
    if BAD.exists():
        shutil.rmtree(BAD)
    BAD.mkdir(parents=True)
    for write in (write_plys, write_meshes, write_videos, write_bvh, write_lab4d):
        write(BAD)
    total = sum(p.stat().st_size for p in BAD.rglob("*") if p.is_file())
    print(f"wrote {sum(1 for p in BAD.rglob('*') if p.is_file())} files ({total} bytes) under {BAD}")


if __name__ == "__main__":
    main()
