"""The joint fitted to a part's whole recovered motion (``sync4d.recon.video.screw``) and the depth-reversed
reading of a hinge (``joints.mirrored``)."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from sync4d.recon.video import joints as jt
from sync4d.recon.video.screw import fit_screw, hinge_angles, joint_motions

K = np.array([[200.0, 0, 80.0], [0, 200.0, 60.0], [0, 0, 1.0]])
STRIDE = 2.0


def project(x: np.ndarray) -> np.ndarray:
    """(T, N, 2) pixels of world points (T, N, 3) seen by a camera at the origin looking along +z."""
    uv = x @ K.T
    return uv[..., :2] / uv[..., 2:3]


def plate(n: int = 200) -> np.ndarray:
    """(N, 3) points of a 0.5 x 0.3 m plate at 1 m from the camera, tilted [m]."""
    rng = np.random.default_rng(0)
    uv = rng.uniform(-0.5, 0.5, (n, 2))
    return np.array([0.0, 0.0, 1.0]) + uv[:, :1] * [0.5, 0.0, 0.15] + uv[:, 1:] * [0.0, 0.3, 0.08]


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(min(1.0, abs(a @ b) / np.linalg.norm(a) / np.linalg.norm(b)))))


def test_hinge_angles_are_exact_on_a_pure_rotation() -> None:
    x0 = plate()
    axis, pivot = np.array([0.0, 1.0, 0.0]), np.array([0.25, 0.0, 1.08])
    angles = np.radians(np.linspace(0, 60, 8))
    xt = np.einsum("tij,nj->tni", joint_motions("hinge", axis, pivot, angles)[:, :3, :3], x0) + \
        joint_motions("hinge", axis, pivot, angles)[:, None, :3, 3]
    assert np.allclose(hinge_angles(axis, pivot, x0, xt), angles, atol=1e-9)


def test_a_hinge_is_found_over_all_frames_despite_a_wild_frame() -> None:
    """A plate turning 70 deg about a tilted line, the motions jittered, one frame turned about
    another line: the hinge is read, its axis within 2 deg and its angles within 2 deg in the good frames."""
    x0 = plate()
    axis = np.array([0.2, 1.0, 0.3]) / np.linalg.norm([0.2, 1.0, 0.3])
    pivot = np.array([0.25, 0.0, 1.08])
    angles = np.radians(np.linspace(0, 70, 16))
    motions = joint_motions("hinge", axis, pivot, angles)
    rng = np.random.default_rng(1)
    noise = Rotation.from_rotvec(rng.normal(0, np.radians(0.1), (16, 3))).as_matrix()
    motions[:, :3, :3] = noise @ motions[:, :3, :3]
    motions[9] = joint_motions("hinge", np.array([1.0, 0.0, 0.0]), pivot, np.radians([40.0]))[0]
    fit = fit_screw(motions, x0, project, STRIDE)
    assert fit.kind == "hinge", fit.costs
    assert angle_deg(fit.axis, axis) < 2.0
    sign = np.sign(fit.axis @ axis)
    good = np.arange(16) != 9
    assert np.degrees(np.abs(sign * fit.values - angles)[good]).max() < 2.0
    assert fit.residuals[9] > fit.residuals[good].max()


def test_a_slide_and_a_still_part_are_told_from_a_hinge() -> None:
    x0 = plate()
    direction = np.array([0.6, 0.0, -0.8])
    travel = np.linspace(0, 0.25, 12)
    slide = fit_screw(joint_motions("slide", direction, np.zeros(3), travel), x0, project, STRIDE)
    assert slide.kind == "slide", slide.costs
    assert angle_deg(slide.axis, direction) < 1.0
    assert np.abs(np.abs(slide.values) - travel).max() < 1e-6
    still = np.tile(np.eye(4), (12, 1, 1))
    still[:, :3, 3] = np.random.default_rng(2).normal(0, 2e-4, (12, 3))  # sub-pixel jitter
    assert fit_screw(still, x0, project, STRIDE).kind == "fixed"


def test_the_depth_reversed_hinge_images_the_same_and_reverses_back() -> None:
    """A tilted plate far from the camera (near-affine viewing) turning 30 deg about a line near the view
    direction: its depth-reversed reading projects within a fifth of the motion of the original (the two-fold
    ambiguity the fit must judge) while its axis is 40 deg away, and reversing twice gives the original."""
    rng = np.random.default_rng(0)
    n, frames = 300, 6
    uv0 = np.stack([rng.uniform(40, 120, n), rng.uniform(30, 90, n)], 1)
    rays = np.concatenate([(uv0 - K[:2, 2]) / K[0, 0], np.ones((n, 1))], 1)
    labels = (uv0[:, 0] > 80).astype(int)
    normal = np.array([0.0, 0.6, -1.0])
    depth = (normal @ [0.0, 0.0, 20.0]) / (rays @ normal)
    d = torch.float64
    scene = jt.Scene(rays=torch.as_tensor(rays, dtype=d), centre=torch.zeros(3, dtype=d), K=torch.as_tensor(K, dtype=d),
                     w2c=torch.eye(4, dtype=d), tracks=torch.zeros(frames, n, 2, dtype=d),
                     trusted=torch.ones(frames, n, dtype=torch.bool), verified=torch.ones(frames, n, dtype=torch.bool),
                     outside=torch.zeros(frames, 120, 160, dtype=d), cover_px=[torch.zeros(0, 2, dtype=d)] * frames,
                     root_motion=torch.as_tensor(np.tile(np.eye(4), (frames, 1, 1)), dtype=d), stride=STRIDE,
                     width=8.0, z_ref=20.0)
    axes = np.array([[0.0, 0, 0], [0.2, 0.3, 0.93]])
    pivots = np.array([[0.0, 0, 0], [0.0, 0.0, 20.0]])
    values = np.zeros((frames, 2))
    values[:, 1] = np.radians(np.linspace(0, 30, frames))
    model = jt.Articulation(scene, labels, 0, ["root", "hinge"], axes, pivots, values, np.log(depth))
    with torch.no_grad():  # the plates' tilt (the constructor starts every part flat)
        for b in range(2):
            own = labels == b
            model.plane[b] = torch.as_tensor(np.linalg.lstsq(model.coords.numpy()[own], 1.0 / depth[own], rcond=None)[0])
    mirror = jt.mirrored(model, 1)
    with torch.no_grad():
        uv, uv_m = jt.project(scene, model.posed()), jt.project(scene, mirror.posed())
        motion = (uv - uv[:1]).norm(dim=-1).max()
        assert (uv - uv_m).norm(dim=-1).max() < 0.2 * motion, ((uv - uv_m).norm(dim=-1).max(), motion)
        assert angle_deg(mirror.axes[1].numpy(), axes[1]) > 40.0  # another joint
        back = jt.mirrored(mirror, 1)
        assert angle_deg(back.axes[1].numpy(), axes[1]) < 1e-6
        assert torch.allclose(back.values, model.values) and torch.allclose(back.pivots(), model.pivots(), atol=0.05)


def test_hinge_angles_matched_to_image_motion_recover_a_70_degree_turn() -> None:
    """The angles per frame whose projection matches a part's image motion (the starts of a hinge rival to a
    slide reading, ``joints.gauss_newton_angles``): a plate turning 70 deg about a known line is followed to
    within 0.01 deg from zero, despite steps clipped at 0.5 rad."""
    frames, x0 = 8, plate()
    n = len(x0)
    d = torch.float64
    scene = jt.Scene(rays=torch.zeros(n, 3, dtype=d), centre=torch.zeros(3, dtype=d), K=torch.as_tensor(K, dtype=d),
                     w2c=torch.eye(4, dtype=d), tracks=torch.zeros(frames, n, 2, dtype=d),
                     trusted=torch.ones(frames, n, dtype=torch.bool), verified=torch.ones(frames, n, dtype=torch.bool),
                     outside=torch.zeros(frames, 120, 160, dtype=d), cover_px=[torch.zeros(0, 2, dtype=d)] * frames,
                     root_motion=torch.as_tensor(np.tile(np.eye(4), (frames, 1, 1)), dtype=d), stride=STRIDE,
                     width=0.5, z_ref=1.0)
    axis = np.array([1.0, 0.2, 0.1]) / np.linalg.norm([1.0, 0.2, 0.1])
    pivot = np.array([0.0, 0.15, 1.05])
    angles = np.radians(np.linspace(0, 70, frames))
    target = project(np.einsum("tij,nj->tni", jt.rodrigues_np(axis, angles), x0 - pivot) + pivot)
    found = jt.gauss_newton_angles(x0, axis, pivot, target, scene)
    assert np.degrees(np.abs(found - angles)).max() < 0.01, np.degrees(found)
