"""The glTF 2.0 reader (``sync4d.io.gltf``) on the Khronos fox (low poly fox by PixelMannen, CC0; rigging and
animation by @tomkranis, CC-BY 4.0; glTF conversion by @AsoboStudio and @scurest) and on malformed files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sync4d.errors import DataMissingError, InputError
from sync4d.io import gltf


@pytest.fixture(scope="module")
def fox(shared_data: Path) -> gltf.SkinnedMesh:
    return gltf.read_gltf(shared_data / "skinned/fox/Fox.gltf")


def test_fox_counts_and_rest_pose(fox: gltf.SkinnedMesh) -> None:
    assert fox.positions.shape == (1728, 3) and fox.faces.shape == (576, 3)
    assert len(fox.skin_nodes) == 24 and fox.inverse_bind.shape == (24, 4, 4)
    assert fox.joint_names[2] == "b_Hip_01" and fox.joint_parents[0] == -1
    assert np.allclose(fox.weights.sum(1), 1.0) and fox.joints.max() < 24
    assert np.allclose(fox.positions.min(0), [-12.592718, -0.121745, -88.095], atol=1e-4)
    assert [(a.name, len(a.channels)) for a in fox.animations] == [("Survey", 21), ("Walk", 21), ("Run", 21)]
    assert fox.animation("Walk").duration == pytest.approx(0.7083333, abs=1e-6)
    assert fox.texture is not None and fox.texture.shape == (1024, 1024, 3)
    # the rest transforms match the inverse bind matrices: the bind pose skins to itself
    assert np.allclose(gltf.joint_matrices(fox, None, 0.0), np.eye(4), atol=1e-4)
    assert np.allclose(gltf.skin_vertices(fox, gltf.joint_matrices(fox, None, 0.0)), fox.positions, atol=1e-3)
    assert np.allclose(gltf.dense_weights(fox).sum(1), 1.0)
    with pytest.raises(InputError, match="Walk"):
        fox.animation("Gallop")


def _independent_vertex(fox_file: Path, name: str, time: float, vertex: int) -> np.ndarray:
    """One vertex posed from the JSON by scipy's quaternions and Slerp, composed node by node (no reader code)."""
    import base64

    from scipy.spatial.transform import Rotation, Slerp

    doc = json.loads(fox_file.read_text())
    buf = base64.b64decode(doc["buffers"][0]["uri"].split(",", 1)[1])

    def read(index: int, dtype, width: int) -> np.ndarray:
        acc, = [doc["accessors"][index]]
        view = doc["bufferViews"][acc["bufferView"]]
        start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        stride = view.get("byteStride", np.dtype(dtype).itemsize * width)
        rows = [np.frombuffer(buf, dtype, width, start + i * stride) for i in range(acc["count"])]
        return np.array(rows, dtype=np.float64)

    nodes = doc["nodes"]
    anim = next(a for a in doc["animations"] if a["name"] == name)
    pose = {i: (np.array(n.get("translation", [0, 0, 0.0])), Rotation.from_quat(n.get("rotation", [0, 0, 0, 1.0])))
            for i, n in enumerate(nodes)}
    for ch in anim["channels"]:
        sampler = anim["samplers"][ch["sampler"]]
        times = read(sampler["input"], "<f4", 1)[:, 0]
        node, path = ch["target"]["node"], ch["target"]["path"]
        if path == "rotation":
            rot = Slerp(times, Rotation.from_quat(read(sampler["output"], "<f4", 4)))(time)
            pose[node] = (pose[node][0], rot)
        else:
            vals = read(sampler["output"], "<f4", 3)
            pose[node] = (np.array([np.interp(time, times, vals[:, k]) for k in range(3)]), pose[node][1])
    parent = {c: i for i, n in enumerate(nodes) for c in n.get("children", [])}

    def world(i: int) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = pose[i][1].as_matrix(), pose[i][0]
        return m if i not in parent else world(parent[i]) @ m

    prim = doc["meshes"][0]["primitives"][0]["attributes"]
    pos = read(prim["POSITION"], "<f4", 3)[vertex]
    jnt = read(prim["JOINTS_0"], "<u2", 4)[vertex].astype(int)
    wts = read(prim["WEIGHTS_0"], "<f4", 4)[vertex]
    inv = read(doc["skins"][0]["inverseBindMatrices"], "<f4", 16).reshape(-1, 4, 4).transpose(0, 2, 1)
    joints = doc["skins"][0]["joints"]
    out = sum(w * (world(joints[j]) @ inv[j] @ np.append(pos, 1.0)) for j, w in zip(jnt, wts))
    return out[:3]


@pytest.mark.parametrize(("clip", "time", "vertex"), [("Walk", 0.25, 100), ("Run", 0.61, 1500), ("Survey", 2.0, 7)])
def test_fox_posed_vertex_matches_an_independent_computation(fox: gltf.SkinnedMesh, shared_data: Path,
                                                             clip: str, time: float, vertex: int) -> None:
    posed = gltf.skin_vertices(fox, gltf.joint_matrices(fox, fox.animation(clip), time))
    expected = _independent_vertex(shared_data / "skinned/fox/Fox.gltf", clip, time, vertex)
    assert np.linalg.norm(posed[vertex] - fox.positions[vertex]) > 0.5  # it moved (file units)
    assert np.allclose(posed[vertex], expected, atol=1e-3)


def test_malformed_gltf_names_the_file(tmp_path: Path) -> None:
    with pytest.raises(DataMissingError, match="missing.gltf"):
        gltf.read_gltf(tmp_path / "missing.gltf")
    bad = tmp_path / "bad.gltf"
    bad.write_text("{not json")
    with pytest.raises(InputError, match="bad.gltf: not glTF JSON"):
        gltf.read_gltf(bad)
    bad.write_text(json.dumps({"asset": {"version": "1.0"}}))
    with pytest.raises(InputError, match="not a glTF 2.0"):
        gltf.read_gltf(bad)
    bad.write_text(json.dumps({"asset": {"version": "2.0"}, "nodes": [{"name": "a"}]}))
    with pytest.raises(InputError, match="no skinned mesh"):
        gltf.read_gltf(bad)


def test_truncated_buffer_is_refused(tmp_path: Path, shared_data: Path) -> None:
    doc = json.loads((shared_data / "skinned/fox/Fox.gltf").read_text())
    uri = doc["buffers"][0]["uri"]
    doc["buffers"][0]["uri"] = uri[: len(uri) // 2 // 4 * 4]
    path = tmp_path / "short.gltf"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="short.gltf"):
        gltf.read_gltf(path)


def test_gltf_reference_has_exact_bones(fox: gltf.SkinnedMesh) -> None:
    """``reference=gltf``: the posed meshes are the file's own skinning, the Reference reproduces them exactly,
    and ``recon=ground_truth`` hands that Reference on."""
    from sync4d.registry import build

    source = build("reference", {"type": "gltf", "animation": "Run", "fps": 10.0}).load()
    truth = source.ground_truth
    assert truth is not None and truth.num_frames == 11 and truth.num_bones == 22  # two empty root joints dropped
    expected = gltf.skin_vertices(fox, gltf.joint_matrices(fox, fox.animation("Run"), 0.5)) * 0.01
    assert np.allclose(source.mesh_sequence[5], expected, atol=1e-5)
    assert np.allclose(truth.posed_vertices(5, apply_global=True), expected, atol=1e-5)
    assert build("recon", {"type": "ground_truth"}).reconstruct(source).num_bones == 22
