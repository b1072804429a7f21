"""A reader for skinned, animated glTF 2.0 files (``.gltf`` JSON with embedded or external buffers).

What it reads: the first skinned mesh primitive (``POSITION``, optional ``TEXCOORD_0``, ``JOINTS_0``,
``WEIGHTS_0``, optional indices; triangles only), the node hierarchy with its rest translation / rotation
/ scale, the skin (joint nodes, inverse bind matrices), the base-colour texture when it is embedded, and
every animation's translation / rotation / scale channels (``LINEAR``: rotations by spherical linear
interpolation along the shorter arc, as the specification says; ``STEP`` keeps the previous key; cubic
splines are refused). Positions are returned in file units:
glTF says metres, but many files are in centimetres, so the caller scales.

Skinning follows the glTF specification: joint matrix ``j = world(node_j) @ inverse_bind_j``, a vertex
``v_t = sum_k w_k joint_matrix[J_k] @ v`` (the mesh node's own transform is ignored for skinned meshes).

Data this was written against (keep the credit where the file is used): ``../shared/data/skinned/fox/Fox.gltf``
from KhronosGroup/glTF-Sample-Models: low poly fox by PixelMannen (CC0), rigging and animation by
@tomkranis (CC-BY 4.0), glTF conversion by @AsoboStudio and @scurest.
"""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sync4d.errors import DataMissingError, InputError
from sync4d.geometry import quat_to_matrix
from sync4d.types import Reference

COMPONENT = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
NORMALISED_MAX = {np.int8: 127.0, np.uint8: 255.0, np.int16: 32767.0, np.uint16: 65535.0}


@dataclass(frozen=True)
class GltfChannel:
    """One animated property of one node.

    Attributes:
        node: index of the node it drives.
        path: ``translation`` (K, 3) [file units], ``rotation`` (K, 4) unit quaternion xyzw, ``scale`` (K, 3).
        times: (K,) key times [s], increasing.
        values: (K, 3 or 4) key values.
        interpolation: ``LINEAR`` or ``STEP``.
    """

    node: int
    path: str
    times: np.ndarray
    values: np.ndarray
    interpolation: str = "LINEAR"


@dataclass(frozen=True)
class GltfAnimation:
    """A named animation: its channels and duration [s] (the last key time of any channel)."""

    name: str
    channels: tuple[GltfChannel, ...]

    @property
    def duration(self) -> float:
        return max(float(c.times[-1]) for c in self.channels) if self.channels else 0.0


@dataclass(frozen=True)
class SkinnedMesh:
    """A skinned mesh, its node hierarchy and animations, as stored in a glTF file (file units).

    Attributes:
        positions: (V, 3) bind-pose vertices [file units].
        faces: (F, 3) int64 triangles.
        joints: (V, 4) int64 skin-joint indices per vertex (into ``skin_nodes``).
        weights: (V, 4) float64 weights per vertex, rows sum to 1.
        uv: (V, 2) texture coordinates, or None.
        node_names: (N,) node names.
        node_parents: (N,) parent node, -1 for a root.
        translation: (N, 3) rest translation per node [file units].
        rotation: (N, 4) rest rotation per node, unit quaternion xyzw.
        scale: (N, 3) rest scale per node.
        skin_nodes: (J,) node index of each skin joint.
        inverse_bind: (J, 4, 4) inverse bind matrices.
        animations: the file's animations.
        texture: (H, W, 3) uint8 base-colour texture, or None.
        source: the file read.
    """

    positions: np.ndarray
    faces: np.ndarray
    joints: np.ndarray
    weights: np.ndarray
    uv: np.ndarray | None
    node_names: tuple[str, ...]
    node_parents: np.ndarray
    translation: np.ndarray
    rotation: np.ndarray
    scale: np.ndarray
    skin_nodes: np.ndarray
    inverse_bind: np.ndarray
    animations: tuple[GltfAnimation, ...]
    texture: np.ndarray | None = None
    source: str = ""

    @property
    def joint_names(self) -> tuple[str, ...]:
        return tuple(self.node_names[n] for n in self.skin_nodes)

    @property
    def joint_parents(self) -> np.ndarray:
        """(J,) parent of each skin joint among the skin joints (-1 for one whose parent is not a joint)."""
        index = {int(n): j for j, n in enumerate(self.skin_nodes)}
        return np.array([index.get(int(self.node_parents[n]), -1) for n in self.skin_nodes], dtype=np.int64)

    def animation(self, name: str) -> GltfAnimation:
        """The animation called ``name``; InputError listing the names when there is none."""
        for anim in self.animations:
            if anim.name == name:
                return anim
        raise InputError(f"{self.source}: no animation '{name}'; it has {[a.name for a in self.animations]}")


def read_gltf(path: str | Path) -> SkinnedMesh:
    """Read the first skinned mesh of a ``.gltf`` file with its skin and animations.

    Raises:
        DataMissingError: the file (or an external buffer) is missing.
        InputError: not glTF 2.0 JSON, no skinned mesh, a malformed accessor, non-triangle primitives,
            cubic-spline animation, or weights that do not sum to 1.
    """
    path = Path(path)
    if not path.is_file():
        raise DataMissingError(f"glTF file not found: {path}")
    try:
        doc = json.loads(path.read_text(errors="replace"))
    except json.JSONDecodeError as err:
        raise InputError(f"{path}: not glTF JSON ({err.msg} at line {err.lineno}); give a .gltf file") from None
    if not isinstance(doc, dict) or str(doc.get("asset", {}).get("version", "")).split(".")[0] != "2":
        raise InputError(f"{path}: not a glTF 2.0 file (asset.version must be 2.x)")
    buffers = [load_buffer(b, path) for b in doc.get("buffers", [])]
    nodes = doc.get("nodes", [])
    mesh_node = next((i for i, n in enumerate(nodes) if "mesh" in n and "skin" in n), None)
    if mesh_node is None:
        raise InputError(f"{path}: no skinned mesh node (a node with both 'mesh' and 'skin')")
    mesh = doc["meshes"][nodes[mesh_node]["mesh"]]
    skin = doc["skins"][nodes[mesh_node]["skin"]]
    geometry = read_primitive(doc, buffers, mesh["primitives"][0], path)
    parents = np.full(len(nodes), -1, dtype=np.int64)
    for i, node in enumerate(nodes):
        for c in node.get("children", []):
            parents[c] = i
    translation, rotation, scale = rest_trs(nodes, path)
    joints = np.asarray(skin["joints"], dtype=np.int64)
    if "inverseBindMatrices" in skin:
        inv = accessor(doc, buffers, skin["inverseBindMatrices"], path).reshape(-1, 4, 4).transpose(0, 2, 1)
    else:
        inv = np.tile(np.eye(4), (len(joints), 1, 1))
    if len(inv) != len(joints):
        raise InputError(f"{path}: {len(inv)} inverse bind matrices for {len(joints)} skin joints")
    animations = tuple(read_animation(doc, buffers, a, i, path) for i, a in enumerate(doc.get("animations", [])))
    return SkinnedMesh(
        node_names=tuple(str(n.get("name", f"node{i}")) for i, n in enumerate(nodes)),
        node_parents=parents, translation=translation, rotation=rotation, scale=scale, skin_nodes=joints,
        inverse_bind=inv.astype(np.float64), animations=animations,
        texture=base_colour_texture(doc, buffers, mesh["primitives"][0], path), source=str(path), **geometry,
    )


def load_buffer(buffer: dict[str, Any], path: Path) -> bytes:
    """The bytes of a glTF buffer: a base64 ``data:`` URI or a file beside ``path``."""
    uri = buffer.get("uri")
    if uri is None:
        raise InputError(f"{path}: a buffer without 'uri' (binary .glb chunks are not read); use a .gltf file")
    if uri.startswith("data:"):
        try:
            data = base64.b64decode(uri.split(",", 1)[1], validate=True)
        except (ValueError, IndexError):
            raise InputError(f"{path}: a buffer's base64 data URI does not decode") from None
    else:
        file = path.parent / uri
        if not file.is_file():
            raise DataMissingError(f"{path}: its buffer {file} is missing")
        data = file.read_bytes()
    if len(data) < int(buffer.get("byteLength", 0)):
        raise InputError(f"{path}: a buffer holds {len(data)} bytes, fewer than its byteLength {buffer['byteLength']}")
    return data


def accessor(doc: dict[str, Any], buffers: list[bytes], index: int, path: Path) -> np.ndarray:
    """(count, width) float64 values of accessor ``index`` (strides and normalised integers honoured)."""
    acc = doc["accessors"][index]
    dtype = np.dtype(COMPONENT.get(acc.get("componentType"), np.void))
    width = WIDTH.get(acc.get("type", ""), 0)
    if dtype == np.void or width == 0 or "bufferView" not in acc:
        raise InputError(f"{path}: accessor {index} has an unknown component type, type or no bufferView")
    view = doc["bufferViews"][acc["bufferView"]]
    data = buffers[view["buffer"]]
    count = int(acc["count"])
    stride = int(view.get("byteStride", 0)) or dtype.itemsize * width
    start = int(view.get("byteOffset", 0)) + int(acc.get("byteOffset", 0))
    end = start + stride * (count - 1) + dtype.itemsize * width
    if count < 1 or end > int(view.get("byteOffset", 0)) + int(view["byteLength"]) or end > len(data):
        raise InputError(f"{path}: accessor {index} reads past its buffer view")
    raw = np.ndarray((count, width), dtype=dtype.newbyteorder("<"), buffer=data, offset=start,
                     strides=(stride, dtype.itemsize))
    out = raw.astype(np.float64)
    if acc.get("normalized") and dtype.type in NORMALISED_MAX:
        out = np.maximum(out / NORMALISED_MAX[dtype.type], -1.0)
    if not np.isfinite(out).all():
        raise InputError(f"{path}: accessor {index} holds non-finite values")
    return out


def read_primitive(doc: dict[str, Any], buffers: list[bytes], prim: dict[str, Any], path: Path) -> dict[str, Any]:
    """Positions, faces, joints, weights and uv of a triangle primitive."""
    if prim.get("mode", 4) != 4:
        raise InputError(f"{path}: the skinned primitive's mode is {prim['mode']}; only triangles (4) are read")
    attrs = prim.get("attributes", {})
    for key in ("POSITION", "JOINTS_0", "WEIGHTS_0"):
        if key not in attrs:
            raise InputError(f"{path}: the skinned primitive has no {key}")
    positions = accessor(doc, buffers, attrs["POSITION"], path)
    n = len(positions)
    faces = (accessor(doc, buffers, prim["indices"], path).astype(np.int64).reshape(-1, 3) if "indices" in prim
             else np.arange(n - n % 3, dtype=np.int64).reshape(-1, 3))
    joints = accessor(doc, buffers, attrs["JOINTS_0"], path).astype(np.int64)
    weights = accessor(doc, buffers, attrs["WEIGHTS_0"], path)
    if len(joints) != n or len(weights) != n or faces.size and faces.max() >= n:
        raise InputError(f"{path}: the primitive's attributes disagree in length or its indices exceed {n} vertices")
    sums = weights.sum(1)
    if np.abs(sums - 1).max() > 1e-2:
        raise InputError(f"{path}: skin weights must sum to 1 per vertex (found {sums.min():.3f}..{sums.max():.3f})")
    uv = accessor(doc, buffers, attrs["TEXCOORD_0"], path) if "TEXCOORD_0" in attrs else None
    return {"positions": positions, "faces": faces, "joints": joints, "weights": weights / sums[:, None], "uv": uv}


def rest_trs(nodes: list[dict[str, Any]], path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, 3) translations, (N, 4) xyzw rotations and (N, 3) scales of the nodes' rest transforms."""
    t = np.zeros((len(nodes), 3))
    r = np.tile([0.0, 0.0, 0.0, 1.0], (len(nodes), 1))
    s = np.ones((len(nodes), 3))
    for i, node in enumerate(nodes):
        if "matrix" in node:
            raise InputError(f"{path}: node {i} ('{node.get('name')}') has a matrix; only TRS nodes are read")
        t[i] = node.get("translation", t[i])
        r[i] = node.get("rotation", r[i])
        s[i] = node.get("scale", s[i])
    return t, r / np.linalg.norm(r, axis=1, keepdims=True), s


def read_animation(doc: dict[str, Any], buffers: list[bytes], anim: dict[str, Any], index: int, path: Path
                   ) -> GltfAnimation:
    """The translation / rotation / scale channels of one animation (weights channels are skipped)."""
    channels = []
    for ch in anim.get("channels", []):
        target = ch.get("target", {})
        if target.get("path") not in ("translation", "rotation", "scale") or "node" not in target:
            continue
        sampler = anim["samplers"][ch["sampler"]]
        interp = sampler.get("interpolation", "LINEAR")
        if interp not in ("LINEAR", "STEP"):
            raise InputError(f"{path}: animation {index} uses {interp} interpolation; LINEAR and STEP are read")
        times = accessor(doc, buffers, sampler["input"], path)[:, 0]
        values = accessor(doc, buffers, sampler["output"], path)
        if len(values) != len(times) or np.any(np.diff(times) < 0):
            raise InputError(f"{path}: animation {index} has keys out of order or a count mismatch")
        if target["path"] == "rotation":
            values = values / np.linalg.norm(values, axis=1, keepdims=True)
        channels.append(GltfChannel(int(target["node"]), target["path"], times, values, interp))
    return GltfAnimation(str(anim.get("name", f"animation{index}")), tuple(channels))


def base_colour_texture(doc: dict[str, Any], buffers: list[bytes], prim: dict[str, Any], path: Path
                        ) -> np.ndarray | None:
    """(H, W, 3) uint8 base-colour texture of the primitive's material when embedded, else None."""
    try:
        material = doc["materials"][prim["material"]]
        image = doc["images"][doc["textures"][material["pbrMetallicRoughness"]["baseColorTexture"]["index"]]["source"]]
    except (KeyError, IndexError, TypeError):
        return None
    if str(image.get("uri", "")).startswith("data:"):
        data = base64.b64decode(image["uri"].split(",", 1)[1])
    elif "bufferView" in image:
        view = doc["bufferViews"][image["bufferView"]]
        start = int(view.get("byteOffset", 0))
        data = buffers[view["buffer"]][start: start + int(view["byteLength"])]
    else:
        return None
    import imageio.v2 as imageio

    pixels = np.asarray(imageio.imread(data))
    if pixels.ndim == 2:
        pixels = np.repeat(pixels[..., None], 3, axis=-1)
    return pixels[..., :3].astype(np.uint8)


def sample_channel(channel: GltfChannel, time: float) -> np.ndarray:
    """The channel's value at ``time`` [s] (clamped to its keys): linear (rotations: slerp along the shorter
    arc) or step."""
    times, values = channel.times, channel.values
    if time <= times[0] or len(times) == 1:
        return values[0].copy()
    if time >= times[-1]:
        return values[-1].copy()
    k = int(np.searchsorted(times, time, side="right")) - 1
    if channel.interpolation == "STEP":
        return values[k].copy()
    s = (time - times[k]) / (times[k + 1] - times[k])
    a, b = values[k], values[k + 1]
    if channel.path == "rotation":
        b = -b if a @ b < 0 else b
        return slerp(a, b, s)
    return (1 - s) * a + s * b


def slerp(a: np.ndarray, b: np.ndarray, s: float) -> np.ndarray:
    """Spherical interpolation between unit quaternions ``a`` and ``b`` (same hemisphere) at ``s`` in [0, 1]."""
    cos = float(np.clip(a @ b, -1.0, 1.0))
    if cos > 0.9995:
        q = (1 - s) * a + s * b
        return q / np.linalg.norm(q)
    angle = np.arccos(cos)
    return (np.sin((1 - s) * angle) * a + np.sin(s * angle) * b) / np.sin(angle)


def pose_trs(mesh: SkinnedMesh, animation: GltfAnimation | None, time: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every node's local translation, rotation (xyzw) and scale at ``time`` [s] (rest where not animated)."""
    t, r, s = mesh.translation.copy(), mesh.rotation.copy(), mesh.scale.copy()
    for ch in animation.channels if animation is not None else ():
        {"translation": t, "rotation": r, "scale": s}[ch.path][ch.node] = sample_channel(ch, time)
    return t, r, s


def world_matrices(parents: np.ndarray, t: np.ndarray, r: np.ndarray, s: np.ndarray) -> np.ndarray:
    """(N, 4, 4) node-to-world matrices ``T R S`` composed down the hierarchy (parents in any order)."""
    local = np.tile(np.eye(4), (len(parents), 1, 1))
    local[:, :3, :3] = quat_to_matrix(r[:, [3, 0, 1, 2]]) * s[:, None, :]  # glTF stores x, y, z, w
    local[:, :3, 3] = t
    world = np.full_like(local, np.nan)

    def resolve(i: int) -> np.ndarray:
        if np.isnan(world[i, 0, 0]):
            p = int(parents[i])
            world[i] = local[i] if p < 0 else resolve(p) @ local[i]
        return world[i]

    for i in range(len(parents)):
        resolve(i)
    return world


def joint_matrices(mesh: SkinnedMesh, animation: GltfAnimation | None, time: float) -> np.ndarray:
    """(J, 4, 4) skinning matrices (bind pose -> pose at ``time``): ``world(joint) @ inverse_bind``."""
    world = world_matrices(mesh.node_parents, *pose_trs(mesh, animation, time))[mesh.skin_nodes]
    return world @ mesh.inverse_bind


def joint_world(mesh: SkinnedMesh, animation: GltfAnimation | None, time: float) -> np.ndarray:
    """(J, 4, 4) world matrices of the skin joints at ``time`` (their origins are the joint positions)."""
    return world_matrices(mesh.node_parents, *pose_trs(mesh, animation, time))[mesh.skin_nodes]


def skin_vertices(mesh: SkinnedMesh, matrices: np.ndarray) -> np.ndarray:
    """(V, 3) vertices blended by the (J, 4, 4) skinning matrices (linear blend skinning, file units)."""
    homo = np.concatenate([mesh.positions, np.ones((len(mesh.positions), 1))], axis=1)
    blend = np.einsum("vk,vkij->vij", mesh.weights, matrices[mesh.joints])
    return np.einsum("vij,vj->vi", blend, homo)[:, :3]


def dense_weights(mesh: SkinnedMesh) -> np.ndarray:
    """(V, J) skinning weights (rows sum to 1) from the per-vertex (joint, weight) pairs."""
    out = np.zeros((len(mesh.positions), len(mesh.skin_nodes)))
    np.add.at(out, (np.repeat(np.arange(len(out)), 4), mesh.joints.ravel()), mesh.weights.ravel())
    return out


def vertex_colours(mesh: SkinnedMesh) -> np.ndarray | None:
    """(V, 3) float colours in [0, 1] sampled from the base-colour texture at each vertex's uv, or None."""
    if mesh.texture is None or mesh.uv is None:
        return None
    h, w = mesh.texture.shape[:2]
    u = np.clip((mesh.uv[:, 0] % 1.0) * w, 0, w - 1).astype(int)
    v = np.clip((mesh.uv[:, 1] % 1.0) * h, 0, h - 1).astype(int)
    return mesh.texture[v, u].astype(np.float64) / 255.0


def skinned_reference(mesh: SkinnedMesh, animation: GltfAnimation, fps: float, *, unit_scale: float = 1.0,
                      frames: int = 0, name: str = "gltf") -> Reference:
    """The exact articulated :class:`~sync4d.types.Reference` of a skinned mesh playing ``animation``: one bone
    per skin joint that carries weight, the file's skinning weights, its joint matrices per frame as the bone
    transforms (identity global transforms), bone Gaussians from each bone's weighted vertices.

    Args:
        mesh: the skinned mesh.
        animation: the clip to play, sampled at ``fps`` from t = 0 over one loop (or ``frames`` frames).
        fps: sampling rate [1/s].
        unit_scale: metres per file unit.
        frames: frames to sample; 0 = one loop (``floor(duration * fps)``, at least 1).
        name: a label.
    """
    count = frames or max(1, int(np.floor(animation.duration * fps)))
    weights = dense_weights(mesh)
    used = np.flatnonzero(weights.sum(0) > 1e-6)
    skin = weights[:, used] / weights[:, used].sum(1, keepdims=True)
    rest = mesh.positions * unit_scale
    mass = skin.sum(0)
    centers = skin.T @ rest / mass[:, None]
    diff = rest[None] - centers[:, None]  # (B, V, 3)
    covs = np.einsum("vb,bvi,bvj->bij", skin, diff, diff) / mass[:, None, None] + 1e-8 * np.eye(3)
    mats = np.stack([joint_matrices(mesh, animation, t / fps)[used] for t in range(count)])
    mats[..., :3, 3] *= unit_scale
    index = {int(j): b for b, j in enumerate(used)}
    skin_parents = mesh.joint_parents[used]
    parents = np.array([index.get(int(p), -1) for p in skin_parents], dtype=np.int64)
    return Reference(
        rest_vertices=rest, rest_faces=mesh.faces.copy(), bone_centers=centers, bone_covariances=covs, skinning=skin,
        bone_transforms=mats, global_transforms=np.tile(np.eye(4), (count, 1, 1)), fps=float(fps),
        vertex_colors=vertex_colours(mesh), bone_names=tuple(mesh.joint_names[j] for j in used), name=name,
        bone_parents=parents,
    ).validate()
