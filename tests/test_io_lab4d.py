"""OBJ and Lab4D export readers."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sync4d.errors import DataMissingError, InputError
from sync4d.io.lab4d import find_mesh_files, read_lab4d_export, read_mesh_sequence, read_obj, write_obj


def test_read_obj_colours_quads_and_negative_indices(tmp_path: Path) -> None:
    path = tmp_path / "quad.obj"
    path.write_text(
        "# a quad\nv 0 0 0 255 0 0\nv 1 0 0 0 255 0\nv 1 1 0 0 0 255\nv 0 1 0 255 255 255\n"
        "vt 0 0\nf 1/1/1 2/2/2 3/3/3 4/4/4\nf -4 -2 -1\n"
    )
    verts, faces, colors = read_obj(path)
    assert verts.shape == (4, 3)
    assert faces.tolist() == [[0, 1, 2], [0, 2, 3], [0, 2, 3]]
    assert colors is not None and np.allclose(colors[0], [1, 0, 0])


def test_read_obj_errors(tmp_path: Path) -> None:
    with pytest.raises(DataMissingError, match="nope.obj"):
        read_obj(tmp_path / "nope.obj")
    (tmp_path / "empty.obj").write_text("# nothing\n")
    with pytest.raises(InputError, match="no vertices"):
        read_obj(tmp_path / "empty.obj")
    (tmp_path / "bad.obj").write_text("v 0 0 0\nf 1 2 3\n")
    with pytest.raises(InputError, match="face index out of range"):
        read_obj(tmp_path / "bad.obj")


def test_mesh_sequence_sorted_by_frame_number_and_topology_checked(tmp_path: Path) -> None:
    tri = np.array([[0, 1, 2]])
    for t in (0, 2, 10):
        write_obj(tmp_path / f"m-{t}.obj", np.eye(3) * (t + 1), tri)
    files = find_mesh_files(tmp_path)
    assert [f.name for f in files] == ["m-0.obj", "m-2.obj", "m-10.obj"]
    seq, faces, _ = read_mesh_sequence(files)
    assert seq.shape == (3, 3, 3) and np.allclose(seq[2], np.eye(3) * 11)
    write_obj(tmp_path / "m-11.obj", np.ones((4, 3)), tri)
    with pytest.raises(InputError, match="fixed topology"):
        read_mesh_sequence(find_mesh_files(tmp_path))
    with pytest.raises(DataMissingError):
        find_mesh_files(tmp_path / "*.nothing")


def test_new_layout_reader(tmp_path: Path) -> None:
    write_obj(tmp_path / "fg.obj", np.eye(3), np.array([[0, 1, 2]]))
    motion = {"field2cam": np.tile(np.eye(4), (2, 1, 1)).tolist(), "t_articulation": np.tile(np.eye(4), (2, 3, 1, 1)).tolist()}
    (tmp_path / "fg-motion.json").write_text(json.dumps(motion))
    export = read_lab4d_export(tmp_path)
    assert export.layout == "export" and export.bone_transforms.shape == (2, 3, 4, 4)
    assert export.posed_vertices is None and export.rest_skinning is None
    motion["t_articulation"] = np.tile(np.eye(4), (3, 3, 1, 1)).tolist()
    (tmp_path / "fg-motion.json").write_text(json.dumps(motion))
    with pytest.raises(InputError, match="t_articulation must be T x K x 4 x 4 with T=2"):
        read_lab4d_export(tmp_path)


def test_missing_export_folder(tmp_path: Path) -> None:
    with pytest.raises(DataMissingError, match="not found"):
        read_lab4d_export(tmp_path / "absent")
    with pytest.raises(DataMissingError, match="neither a Lab4D export"):
        read_lab4d_export(tmp_path)


def test_shiba_per_frame_layout(shared_data: Path) -> None:
    """ppr-diffphys shiba-haru-1002 (MIT)."""
    export = read_lab4d_export(shared_data / "lab4d_export" / "shiba-haru-1002")
    assert export.layout == "per_frame"
    assert export.posed_vertices.shape == (21, 10002, 3)
    assert export.bone_transforms.shape == (21, 25, 4, 4)
    assert export.rest_skinning.shape == (10002, 13)
    rot = export.bone_transforms[..., :3, :3]
    assert np.allclose(rot @ np.swapaxes(rot, -1, -2), np.eye(3), atol=1e-4)
    assert export.intrinsics.shape == (21, 4) and export.object_to_camera.shape == (21, 4, 4)
