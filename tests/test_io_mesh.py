"""Mesh -> Gaussians: counts, surface alignment, interior fill, colours; the winding number."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from sync4d.errors import InputError
from sync4d.io.mesh import load_mesh, mesh_to_gaussians, winding_number
from sync4d.geometry import quat_to_matrix


def test_winding_number_inside_outside():
    box = trimesh.creation.box(extents=[1, 1, 1])
    w = winding_number(np.array([[0, 0, 0], [0.4, -0.3, 0.2], [2, 0, 0], [0, 0.6, 0]]), box.vertices, box.faces)
    np.testing.assert_allclose(w, [1, 1, 0, 0], atol=1e-9)


def test_surface_gaussians_are_flat_and_aligned_with_the_surface():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    g = mesh_to_gaussians(sphere.vertices, sphere.faces, num_surface=500, num_interior=200, seed=1)
    assert g.num == 700
    surf = g.subset(np.arange(500))
    np.testing.assert_allclose(np.linalg.norm(surf.means, axis=1), 0.1, atol=2e-3)
    # The thin axis (third column of the rotation) is the radial direction.
    normal = quat_to_matrix(surf.quats)[:, :, 2]
    radial = surf.means / np.linalg.norm(surf.means, axis=1, keepdims=True)
    assert np.abs((normal * radial).sum(axis=1)).min() > 0.95
    assert np.all(surf.scales[:, 2] < 0.2 * surf.scales[:, 0])
    inner = g.means[500:]
    assert np.linalg.norm(inner, axis=1).max() < 0.1


def test_shared_mesh_to_gaussians(shared_data):
    v, f, colors = load_mesh(shared_data / "targets/meshes/spot_low_resolution.obj")
    g = mesh_to_gaussians(v, f, num_surface=800, num_interior=300, seed=0)
    assert g.num == 1100
    assert np.all(g.means.min(0) >= v.min(0) - 1e-3) and np.all(g.means.max(0) <= v.max(0) + 1e-3)
    g.validate()


def test_vertex_colours_are_interpolated():
    box = trimesh.creation.box(extents=[1, 1, 1])
    colors = np.tile([[1.0, 0.0, 0.0]], (len(box.vertices), 1))
    g = mesh_to_gaussians(box.vertices, box.faces, num_surface=50, vertex_colors=colors)
    np.testing.assert_allclose(g.colors(), np.tile([1.0, 0.0, 0.0], (50, 1)), atol=1e-5)


def test_mesh_without_faces_is_refused(tmp_path):
    path = tmp_path / "points.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(InputError, match="points.obj: the mesh has no faces"):
        load_mesh(path)
