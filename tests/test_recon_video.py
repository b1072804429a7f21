"""recon=video on a tiny synthetic video (two textured plates on a hinge), plus its image helpers."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from sync4d.errors import ConfigError, InputError
from sync4d.recon.video import (
    background_masks,
    feature_motions,
    flow_consistency,
    optical_flow,
    rotation_angle_deg,
    sample_image,
    track_points,
)
from sync4d.registry import build
from sync4d.types import Camera, ReferenceInput, VideoClip

H, W = 96, 128
K = np.array([[120.0, 0, W / 2], [0, 120.0, H / 2], [0, 0, 1]])


def rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0, 0, 1.0]])


def hinge_video(frames: int = 6, max_deg: float = 40.0) -> tuple[VideoClip, np.ndarray, np.ndarray]:
    """Two textured plates seen by a camera at the origin (OpenCV axes), slightly tilted: a base on the
    left and an arm hinged at its right edge, turning about the (nearly) viewing direction by up to
    ``max_deg``. Rendered by z-buffered point splatting. Returns (clip, part labels (T, H, W) 0/1/2,
    arm angles [deg])."""
    rng = np.random.default_rng(0)
    n = 30000
    uv = rng.uniform(0, 1, (n, 2))
    tilt = np.array([0.0, 0.94, 0.34])  # the plates' second axis, tilted away from the camera
    hinge = np.array([0.0, 0.0, 1.2])
    base = hinge + (uv[:, :1] - 1.0) * 0.35 * np.array([1.0, 0, 0]) + (uv[:, 1:] - 0.5) * 0.2 * tilt
    lid_rest = hinge + uv[:, :1] * 0.3 * np.array([1.0, 0, 0]) + (uv[:, 1:] - 0.5) * 0.15 * tilt
    checker = ((np.floor(uv[:, 0] * 6) + np.floor(uv[:, 1] * 4)) % 2)[:, None]
    col_base = np.array([60, 90, 200]) + checker * np.array([120, 80, 0]) + uv[:, 1:] * 40
    col_lid = np.array([200, 70, 40]) + checker * np.array([0, 120, 120]) + uv[:, :1] * 40
    angles = np.linspace(0.0, max_deg, frames)
    imgs, labels = [], []
    for a in angles:
        lid = (lid_rest - hinge) @ rot_z(np.deg2rad(-a)).T + hinge
        pts = np.concatenate([base, lid])
        cols = np.concatenate([col_base, col_lid])
        part = np.concatenate([np.ones(n, int), np.full(n, 2)])
        pix = pts @ K.T
        u = (pix[:, 0] / pix[:, 2]).astype(int)
        v = (pix[:, 1] / pix[:, 2]).astype(int)
        inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
        order = np.argsort(-pts[:, 2])  # far first; near points overwrite
        img = np.zeros((H, W, 3), np.uint8)
        lab = np.zeros((H, W), int)
        for i in order[inside[order]]:
            img[v[i], u[i]] = np.clip(cols[i], 0, 255)
            lab[v[i], u[i]] = part[i]
        imgs.append(img)
        labels.append(lab)
    clip = VideoClip(frames=np.stack(imgs), masks=np.stack(labels) > 0, fps=10.0, intrinsics=K, source="synthetic")
    return clip.validate(), np.stack(labels), angles


def test_flow_helpers_on_a_translating_pattern() -> None:
    yy, xx = np.mgrid[0:H, 0:W]
    base = (128 + 60 * np.sin(xx / 3.0) * np.cos(yy / 4.0)).astype(np.uint8)
    frames = np.stack([np.repeat(np.roll(base, s, axis=1)[..., None], 3, -1) for s in (0, 2, 4)])
    fwd, bwd = optical_flow(frames, "dis")
    centre = (slice(10, 38), slice(12, 52))
    assert np.abs(np.median(fwd[0][centre][..., 0]) - 2.0) < 0.3
    assert flow_consistency(fwd, bwd)[0][centre].mean() > 0.8
    tracks = track_points(np.array([[30.0, 24.0]]), fwd)
    assert np.allclose(tracks[-1], [34.0, 24.0], atol=0.6)
    assert np.allclose(sample_image(np.arange(12.0).reshape(3, 4), np.array([[1.5, 1.0]])), 5.5)


def test_feature_motions_follow_a_translating_texture() -> None:
    """A random texture shifted by (3, 1) px per frame: every kept corner moves by that shift, starts
    inside its frame's mask, and carries its frame index; a still pair of frames yields no motion."""
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.integers(0, 255, (H + 20, W + 20)).astype(np.uint8), (0, 0), 1.5)
    shifts = [(0, 0), (3, 1), (6, 2), (6, 2)]  # frames 2 -> 3 stand still
    frames = np.stack([np.repeat(texture[10 - dy: 10 - dy + H, 10 - dx: 10 - dx + W, None], 3, -1)
                       for dx, dy in shifts])
    masks = np.zeros((4, H, W), bool)
    masks[:, 20:70, 30:100] = True
    motions = feature_motions(frames, masks)
    assert len(motions) > 40 and set(np.unique(motions.frame)) == {0, 1}
    assert np.allclose(motions.end - motions.start, [3.0, 1.0], atol=0.1)
    # pixel k covers [k, k + 1): a corner found in the mask starts inside its cells
    assert np.all((motions.start >= [30, 20]) & (motions.start <= [100, 70]))


def test_background_model_finds_the_moving_object() -> None:
    frames = np.full((7, H, W, 3), 40, np.uint8)
    for t in range(7):
        frames[t, 10:20, 5 + 6 * t : 15 + 6 * t] = 220
    masks = background_masks(frames)
    assert masks[3, 12:18, 25:31].all() and not masks[3, :, :20].any()


def test_config_errors() -> None:
    with pytest.raises(ConfigError, match="auto"):
        build("recon", {"type": "video", "bones": "auto"})
    with pytest.raises(ConfigError, match="same length"):
        build("recon", {"type": "video", "levels": [4, 2], "iterations": [10]})
    with pytest.raises(InputError, match="needs a video"):
        build("recon", {"type": "video"}).reconstruct(ReferenceInput(name="none", fps=1.0))
    with pytest.raises(ConfigError, match="silhouette_hypothesis_cells=1"):
        build("recon", {"type": "video", "silhouette_hypotheses": 2, "silhouette_hypothesis_cells": 1})
    with pytest.raises(ConfigError, match="silhouette_flow_cap=0"):
        build("recon", {"type": "video", "silhouette_flow_cap": 0})
    with pytest.raises(ConfigError, match="silhouette_restarts=0"):
        build("recon", {"type": "video", "silhouette_restarts": 0})
    with pytest.raises(ConfigError, match="own or candidate"):
        build("recon", {"type": "video", "silhouette_relabel_surface": "mine"})


@pytest.mark.slow
@pytest.mark.parametrize("options", [
    {},
    # the opt-in flow-scored search: flow term, fresh tilt/hinge hypotheses, candidate-surface relabelling
    {"silhouette_flow_weight": 0.5, "silhouette_hypotheses": 1, "silhouette_hypothesis_cells": 2,
     "silhouette_relabel_surface": "candidate"},
    # one start of the clustering and silhouette stage (the default ranks three by the corners' motions)
    {"silhouette_restarts": 1},
], ids=["default", "flow_hypotheses", "one_start"])
def test_two_plate_hinge_is_recovered(options: dict) -> None:
    clip, labels, angles = hinge_video()
    camera = Camera(K=K, world_to_cam=np.eye(4), width=W, height=H)
    recon = build("recon", {"type": "video", "bones": 2, "gaussians": 300, "init_depth": 1.2, "levels": [2],
                            "iterations": [20], "track_steps": 20, "first_frame_steps": 20, "pixels_per_frame": 400,
                            "flow_pixels_per_frame": 200, "frames_per_step": 3, **options}, device="cpu")
    ref = recon.reconstruct(ReferenceInput(name="hinge", fps=10.0, video=clip, camera=camera))
    assert ref.num_bones == 2 and ref.num_frames == len(angles) and ref.rest_faces is None
    # parts: each Gaussian's bone agrees with the plate under its first-frame pixel
    import torch

    from sync4d.recon._softsplat import project_points

    uv, _ = project_points(torch.as_tensor(ref.rest_vertices), torch.as_tensor(K), torch.eye(4, dtype=torch.float64))
    u = np.clip(uv[:, 0].numpy().astype(int), 0, W - 1)
    v = np.clip(uv[:, 1].numpy().astype(int), 0, H - 1)
    plate = labels[0][v, u]
    bone = ref.part_labels()
    on = plate > 0
    agree = max(((bone == plate - 1) & on).sum(), ((bone == 2 - plate) & on).sum()) / on.sum()
    assert agree > 0.9, agree
    # the relative rotation between the bones follows the lid angle
    j = ref.bone_transforms
    rel = rotation_angle_deg(np.einsum("tji,tjk->tik", j[:, 0, :3, :3], j[:, 1, :3, :3]))
    assert abs(rel[-1] - angles[-1]) < 8.0, rel
    assert np.all(np.diff(rel) > 0), rel  # opening monotonically, as the arm does
    # silhouette_dense_gaussians: one Gaussian per raster cell of the first mask, not the 300 sampled ones
    from sync4d.recon._video_silhouette import downsample_mask

    assert recon.last_fit_report["gaussians"] == int(downsample_mask(clip.masks[0], 2).sum())
    starts = recon.last_fit_report["silhouette_starts"]
    restarts = options.get("silhouette_restarts", 3)
    assert len(starts) == (restarts if restarts > 1 else 0)
    if starts:  # the chosen start predicts the corners best
        chosen = recon.last_fit_report["silhouette_start"]
        assert starts[chosen]["corners"] >= 20
        assert starts[chosen]["corner_residual_px"] == min(s["corner_residual_px"] for s in starts)


# --------------------------------------------------------------------------------------------------
# Silhouette tracking helpers (sync4d.recon._video_silhouette)
# --------------------------------------------------------------------------------------------------

from sync4d.recon import _video_silhouette as vsil  # noqa: E402


def test_about_pivot_fixes_the_pivot_and_rotates() -> None:
    rot = vsil.rotvec_to_matrix(np.array([0.0, 0.0, np.pi / 2]))
    assert np.allclose(rot @ [1.0, 0, 0], [0, 1.0, 0], atol=1e-12)
    tf = vsil.about_pivot(rot, np.array([1.0, 2.0, 3.0]))
    assert np.allclose(tf[:3, :3] @ [1.0, 2.0, 3.0] + tf[:3, 3], [1.0, 2.0, 3.0])
    assert np.allclose(tf[:3, :3] @ [2.0, 2.0, 3.0] + tf[:3, 3], [1.0, 3.0, 3.0])


def test_raster_iou_and_downsampling() -> None:
    mask = np.zeros((8, 8), bool)
    mask[2:6, 2:6] = True
    small = vsil.downsample_mask(mask, 2)
    assert small.shape == (4, 4) and small.sum() == 4 and small[1:3, 1:3].all()
    # every pixel centre of the square, rasterised at stride 2, gives back the 2 x 2 cells
    vv, uu = np.nonzero(mask)
    img = vsil.raster_points(np.stack([uu, vv], 1) + 0.5, (8, 8), 2)
    assert np.array_equal(img, small)
    half = small.copy()
    half[1, 1:3] = False
    assert vsil.mask_iou(half, small) == 0.5 and vsil.mask_iou(small, small) == 1.0
    assert np.isclose(vsil.outside_distance(small)[1, 0], 1.0) and vsil.outside_distance(small)[1, 1] == 0.0


def test_pattern_search_finds_a_quadratic_peak() -> None:
    x, best = vsil.pattern_search(lambda x: -((x[0] - 1.3) ** 2) - (x[1] + 0.4) ** 2, np.zeros(2),
                                  np.array([1.0, 1.0]), min_scale=1e-3, max_evals=2000)
    assert np.allclose(x, [1.3, -0.4], atol=2e-3) and best > -1e-5


def test_ray_plane_depths_and_tilted_normal() -> None:
    rays = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
    d = vsil.ray_plane_depths(rays, np.zeros(3), np.array([0.0, 0.0, 2.0]), np.array([0.0, 0.0, 1.0]))
    assert np.allclose(d, [2.0, 2.5])
    # no tilt: the normal faces the camera; 90 deg about the camera's x axis turns it onto -y... (+/-)
    n0 = vsil.tilted_normal(np.array([0.0, 0.0, 1.0]), np.zeros(2), np.eye(3))
    n1 = vsil.tilted_normal(np.array([0.0, 0.0, 1.0]), np.array([np.pi / 2, 0.0]), np.eye(3))
    assert np.allclose(n0, [0, 0, -1.0]) and np.allclose(np.abs(n1), [0, 1.0, 0], atol=1e-12)


def _two_part_image() -> np.ndarray:
    img = np.full((10, 12), -1)
    img[2:8, 1:6] = 0
    img[2:8, 6:11] = 1
    return img


def test_boundary_pivot_tree_and_islands() -> None:
    img = _two_part_image()
    assert np.allclose(vsil.boundary_pivot(img, 1, 0, radius=1), [6.5, 5.0])
    assert vsil.kinematic_tree(img, 2, root=0).tolist() == [-1, 0]
    noisy = img.copy()
    noisy[3, 9] = 0  # an island of part 0 inside part 1
    assert np.array_equal(vsil.merge_label_islands(noisy, 2), img)


def test_joint_from_motion_recovers_the_rotation_centre() -> None:
    pivot = np.array([0.3, -0.2, 1.0])
    tfs = np.stack([vsil.about_pivot(vsil.rotvec_to_matrix(v), pivot)
                    for v in ([0.3, 0.1, 0.0], [0.0, 0.5, 0.2], [0.4, 0.0, -0.3])])
    assert np.allclose(vsil.joint_from_motion(tfs, np.zeros(3), prior_weight=1e-9), pivot, atol=1e-6)
    # a hinge leaves the position along its axis to the prior
    axis = np.array([1.0, 0.0, 0.0])
    hinge = np.stack([vsil.about_pivot(vsil.rotvec_to_matrix(axis * a), pivot) for a in (0.2, 0.6, 1.0)])
    got = vsil.joint_from_motion(hinge, np.array([0.0, 0.0, 0.9]), prior_weight=1e-9, axis=axis)
    assert np.allclose(got, [0.0, -0.2, 1.0], atol=1e-5)


def test_hinge_axis_detection() -> None:
    axis = np.array([0.0, 0.6, 0.8])
    rv = np.outer([0.1, 0.5, 1.2, 0.7], axis) + 1e-3 * np.random.default_rng(0).normal(size=(4, 3))
    got = vsil.hinge_axis(rv)
    assert got is not None and np.allclose(got, axis, atol=0.01)
    assert vsil.hinge_axis(np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])) is None


def test_articulated_pose_parameters() -> None:
    art = vsil.Articulation(labels=np.array([0, 1]), parent=np.array([-1, 0]),
                            pivots=np.array([[0.0, 0, 0], [1.0, 0, 0]]), tilts=np.zeros((2, 2)),
                            axes=np.array([[np.nan] * 3, [0.0, 0.0, 1.0]]))
    assert vsil.param_offsets(art).tolist() == [0, 6, 7]
    params = np.zeros(7)
    params[3] = 0.5  # root translation [object widths]
    params[6] = np.pi / 2  # hinge angle about z through (1, 0, 0)
    tfs = vsil.pose_transforms(params, art, width=2.0)
    pts = vsil.posed_points(np.array([[0.0, 0, 0], [2.0, 0, 0]]), art.labels, tfs)
    assert np.allclose(pts, [[1.0, 0, 0], [2.0, 1.0, 0]])
    ball = vsil.hinge_params_to_ball(params[None], art)
    assert ball.shape == (1, 9) and np.allclose(ball[0, 6:], [0, 0, np.pi / 2])


def test_part_motion_and_nearest_index() -> None:
    tracks = np.zeros((3, 4, 2))
    tracks[1:, 2:] += [[3.0, 4.0]]
    ok = np.ones((3, 4), bool)
    moves = vsil.part_motion_px(tracks, ok, np.array([0, 0, 1, 1]), 3)
    assert np.allclose(moves[:2], [0.0, 5.0]) and np.isnan(moves[2])
    assert vsil.nearest_index(np.array([[0.0, 0], [10.0, 0]]), np.array([[9.0, 1.0], [1.0, 0]])).tolist() == [1, 0]


def test_occlusion_ordering_helpers() -> None:
    from sync4d.recon._video_occlusion import cell_colors, child_depth_buffer, ordering_loss

    frames = np.zeros((1, 4, 4, 3), np.uint8)
    frames[0, :2, :2] = 100  # one 2x2 cell fully set, one pixel of another
    frames[0, 3, 3] = 40
    c = cell_colors(frames, 2)
    assert c.shape == (1, 2, 2, 3)
    assert np.allclose(c[0, 0, 0], 100) and np.allclose(c[0, 1, 1], 10) and np.allclose(c[0, 0, 1], 0)
    buf = child_depth_buffer(np.array([[0, 0], [0, 0], [1, 0], [5, 5]]), np.array([2.0, 1.0, 3.0, 0.5]), (2, 2))
    assert buf[0, 0] == 1.0 and buf[0, 1] == 3.0 and np.isinf(buf[1]).all()  # nearest wins; out of range ignored
    z_child = np.array([[1.0, 1.0, np.inf]])
    hidden = np.array([[True, False, True]])
    # hidden point behind by 0.5 and visible point in front: no violation, only the slack term
    assert ordering_loss(np.array([1.5, 0.5, 9.0]), z_child, hidden, slack=0.1) == pytest.approx(0.05)
    # both orderings broken by 0.5 each: mean violation 0.5 (the uncovered third point does not count)
    assert ordering_loss(np.array([0.5, 1.5, 9.0]), z_child, hidden, slack=0.0) == pytest.approx(0.5)


def test_contact_root_plane_lies_behind_a_folding_part() -> None:
    from sync4d.recon._video_occlusion import root_plane_depths

    # camera at the origin looking down +z; a root plate left of x = 0 and a child plate right of it, both at
    # z = 2; at frame 1 the child folds 120 deg about the y axis through (0, 0, 2) towards the camera
    k = np.array([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]])
    vv, uu = np.mgrid[16:48:2, 8:56:2]
    uv = np.stack([uu.ravel(), vv.ravel()], 1) + 1.0
    rays = vsil.pixel_rays(uv, k, np.eye(3))
    labels = (uv[:, 0] > 32).astype(int)
    masks = np.ones((2, 32, 32), bool)
    scene = vsil.SilhouetteScene(uv0=uv, rays=rays, cam_center=np.zeros(3), cam_rot=np.eye(3), K=k,
                                 world_to_cam=np.eye(4), masks=masks, stride=2, image_shape=(64, 64),
                                 base_depth=2.0 / rays[:, 2], width=0.5)
    art = vsil.Articulation(labels=labels, parent=np.array([-1, 0]),
                            pivots=np.array([[-0.2, 0.0, 2.0], [0.0, 0.0, 2.0]]), tilts=np.zeros((2, 2)))
    params = np.zeros((2, 9))
    params[1, 6:9] = [0.0, np.radians(120.0), 0.0]  # x -> towards -x and -z (the camera)
    frames = np.zeros((2, 64, 64, 3), np.uint8)
    depths, rep = root_plane_depths(scene, art, params, frames, 0, contact=True, grid_deg=(-60.0, -30.0, 0.0, 30.0, 60.0))
    assert depths is not None and rep["plane_loss_m"] <= rep["stand_in_loss_m"]
    z_root = depths[labels == 0] * rays[labels == 0, 2]
    # the folded child is in front of the stand-in; the contact plane comes forward to meet it (from the joint)
    assert z_root.mean() < 2.0 - 0.05 and np.allclose(depths[labels == 1], scene.base_depth[labels == 1])


def test_composite_weights_hide_a_dense_surface_behind_an_opaque_one() -> None:
    """One opaque Gaussian in front of ten translucent ones: compositing gives the front one nearly all
    the weight (T alpha, as a rasteriser blends); the soft z-buffer vote lets the ten behind outvote it."""
    import torch

    from sync4d.recon._softsplat import composite_weights, front_weights

    alpha = torch.tensor([[[0.99]] + [[0.6]] * 10], dtype=torch.float64)  # (F=1, N=11, P=1)
    z = torch.tensor([[1.0] + [1.01 + 0.001 * i for i in range(10)]], dtype=torch.float64)
    w = composite_weights(alpha, z)[0, :, 0]
    assert w[0].item() == pytest.approx(0.99)
    assert w[1].item() == pytest.approx(0.01 * 0.6)  # light through the front one, then the first behind
    assert w[1:].sum().item() == pytest.approx(0.01 * (1 - 0.4**10))
    # the Gaussians' input order does not matter, only their depths
    perm = torch.tensor([3, 0, 5, 1, 2, 4, 6, 7, 8, 9, 10])
    w_perm = composite_weights(alpha[:, perm], z[:, perm])[0, :, 0]
    assert torch.allclose(w_perm, w[perm])
    soft = front_weights(alpha, z, tau=0.05)[0, :, 0]
    assert soft[1:].sum() > soft[0]


def test_relabel_ties_go_to_the_root() -> None:
    """Points that either part's motion explains equally (the child never moves) keep their label under
    ``tie_part=None`` and go to the root with ``tie_part``; a point only the child explains stays child."""
    h, w = 20, 20
    masks = np.zeros((3, h, w), bool)
    masks[:, 5:15, 5:15] = True
    uv0 = (np.stack(np.meshgrid(np.arange(5, 15), np.arange(5, 15)), -1).reshape(-1, 2) + 0.5).astype(float)
    rays = vsil.pixel_rays(uv0, K_small := np.array([[20.0, 0, 10], [0, 20.0, 10], [0, 0, 1]]), np.eye(3))
    scene = vsil.SilhouetteScene(uv0=uv0, rays=rays, cam_center=np.zeros(3), cam_rot=np.eye(3), K=K_small,
                                 world_to_cam=np.eye(4), masks=masks, stride=1, image_shape=(h, w),
                                 base_depth=np.ones(len(uv0)) / rays[:, 2], width=0.5)
    labels = (uv0[:, 0] > 10).astype(int)  # right half starts as the child
    art = vsil.Articulation(labels=labels, parent=np.array([-1, 0]), pivots=np.array([[0, 0, 1.0], [0, 0, 1.0]]),
                            tilts=np.zeros((2, 2)))
    params = np.zeros((3, int(vsil.param_offsets(art)[-1])))  # nothing moves: every point is a tie
    kept = vsil.relabel(scene, art, params, margin=0.05)
    assert np.array_equal(kept, labels)
    to_root = vsil.relabel(scene, art, params, margin=0.05, tie_part=0, min_points=0)
    assert np.all(to_root == 0)


def test_relabel_flow_term_keeps_a_part_turning_in_the_image_plane() -> None:
    """The child (right half of a square) turns 20 deg about the viewing axis at the square's centre while
    the silhouette stays the same square. Silhouettes alone explain most child points by the static root
    (they stay inside the mask), so root ties take them; their flow tracks follow the turn, so with the
    flow term the child keeps the points that move more than a few pixels."""
    h, w = 40, 40
    masks = np.zeros((3, h, w), bool)
    masks[:, 8:32, 8:32] = True
    K_small = np.array([[40.0, 0, 20], [0, 40.0, 20], [0, 0, 1]])
    uv0 = (np.stack(np.meshgrid(np.arange(8, 32), np.arange(8, 32)), -1).reshape(-1, 2) + 0.5).astype(float)
    rays = vsil.pixel_rays(uv0, K_small, np.eye(3))
    scene = vsil.SilhouetteScene(uv0=uv0, rays=rays, cam_center=np.zeros(3), cam_rot=np.eye(3), K=K_small,
                                 world_to_cam=np.eye(4), masks=masks, stride=1, image_shape=(h, w),
                                 base_depth=np.ones(len(uv0)) / rays[:, 2], width=0.5)
    child = uv0[:, 0] > 20
    labels = child.astype(int)
    art = vsil.Articulation(labels=labels, parent=np.array([-1, 0]), pivots=np.array([[0, 0, 1.0], [0, 0, 1.0]]),
                            tilts=np.zeros((2, 2)))
    angles = np.radians([0.0, 10.0, 20.0])
    params = np.zeros((3, int(vsil.param_offsets(art)[-1])))
    params[:, 6:9] = np.outer(angles, [0.0, 0.0, 1.0])  # the child's ball joint: about the optical axis
    points = vsil.canonical_points(scene, art)
    tracks = np.stack([scene.project(vsil.posed_points(points, labels, vsil.pose_transforms(p, art, scene.width)))
                       for p in params])
    ok = np.ones((3, len(uv0)), bool)
    silhouettes_only = vsil.relabel(scene, art, params, margin=0.05, tie_part=0, min_points=0)
    with_flow = vsil.relabel(scene, art, params, margin=0.05, tie_part=0, min_points=0, tracks=tracks, track_ok=ok)
    far = child & (np.linalg.norm(uv0 - 20.0, axis=1) > 8.0)  # moves > 2.7 px by the last frame
    assert silhouettes_only[far].mean() < 0.5  # most go to the root: the mask never changes
    assert with_flow[far].mean() > 0.95
    assert np.all(with_flow[~child] == 0)  # the static half stays root


def test_horizontal_root_depths_put_the_root_on_the_plane_through_its_joint() -> None:
    """A camera 30 deg above a table looks at a static root (label 0) with a child (label 1) hinged at
    y = 0: the root's points land on the plane y = 0 through the joint, in front of the camera."""
    elevation = np.radians(30.0)
    cam_center = np.array([0.0, np.sin(elevation), -np.cos(elevation)]) * 2.0
    forward = -cam_center / np.linalg.norm(cam_center)
    down = np.array([0.0, -1.0, 0.0]) - forward * -forward[1]  # world down, orthogonal to the view
    down /= np.linalg.norm(down)
    right = np.cross(down, forward)  # (right, down, forward) right-handed, as OpenCV's axes
    cam_rot = np.stack([right, down, forward], 1)  # camera-to-world, OpenCV axes
    K_small = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    uv0 = np.stack(np.meshgrid(np.arange(10, 54, 4.0), np.arange(2, 46, 4.0)), -1).reshape(-1, 2)
    rays = vsil.pixel_rays(uv0, K_small, cam_rot)
    w2c = np.eye(4)
    w2c[:3, :3] = cam_rot.T
    w2c[:3, 3] = -cam_rot.T @ cam_center
    scene = vsil.SilhouetteScene(uv0=uv0, rays=rays, cam_center=cam_center, cam_rot=cam_rot, K=K_small,
                                 world_to_cam=w2c, masks=np.ones((1, 48, 64), bool), stride=1,
                                 image_shape=(48, 64), base_depth=np.full(len(uv0), 2.0), width=0.5)
    labels = np.zeros(len(uv0), int)
    labels[:5] = 1
    art = vsil.Articulation(labels=labels, parent=np.array([-1, 0]),
                            pivots=np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.2]]), tilts=np.zeros((2, 2)))
    depth = vsil.horizontal_root_depths(scene, art, 0, np.array([0.0, 2.0, 0.0]))
    points = cam_center + depth[:, None] * rays[labels == 0]
    clip = 2.0 * np.linalg.norm(art.pivots[1] - cam_center)  # rays meeting the table beyond twice the joint's distance
    on_plane = depth < clip - 1e-9
    assert on_plane.sum() >= 30 and (~on_plane).sum() >= 1
    assert np.allclose(points[on_plane, 1], 0.0, atol=1e-9)
    assert np.allclose(depth[~on_plane], clip)
    assert np.all(depth > 0)
    lone = vsil.Articulation(labels=np.zeros(len(uv0), int), parent=np.array([-1]), pivots=np.zeros((1, 3)),
                             tilts=np.zeros((1, 2)))
    assert vsil.horizontal_root_depths(scene, lone, 0, np.array([0.0, 1.0, 0.0])) is None


def test_render_parts_matches_posing_then_rendering() -> None:
    """The pose search's composed per-part projection draws the same silhouette as moving every point by
    its part's transform and projecting it."""
    rng = np.random.default_rng(3)
    K_small = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    w2c = np.eye(4)
    w2c[:3, :3] = vsil.rotvec_to_matrix(np.array([0.1, -0.2, 0.05]))
    w2c[:3, 3] = [0.05, -0.02, 1.5]
    scene = vsil.SilhouetteScene(uv0=np.zeros((1, 2)), rays=np.zeros((1, 3)), cam_center=np.zeros(3),
                                 cam_rot=np.eye(3), K=K_small, world_to_cam=w2c, masks=np.ones((1, 24, 32), bool),
                                 stride=2, image_shape=(48, 64), base_depth=np.ones(1), width=0.5)
    points = rng.normal(0.0, 0.2, (2000, 3))
    labels = rng.integers(0, 3, 2000)
    transforms = np.stack([vsil.about_pivot(vsil.rotvec_to_matrix(rng.normal(0, 0.3, 3)), rng.normal(0, 0.1, 3))
                           for _ in range(3)])
    transforms[:, :3, 3] += rng.normal(0.0, 0.05, (3, 3))
    expected = scene.render(vsil.posed_points(points, labels, transforms))
    got = scene.render_parts([points[labels == b] for b in range(3)], transforms)
    assert expected.any() and not expected.all()
    assert np.array_equal(got, expected)


def test_pose_search_shortcuts_give_the_plain_results() -> None:
    """The pose search's shortcuts change nothing: a precomputed pose layout gives the same transforms,
    and cells drawn beforehand (a static part's) plus the other points give the raster of all points."""
    rng = np.random.default_rng(5)
    art = vsil.Articulation(labels=np.zeros(1, int), parent=np.array([-1, 0, 1]), pivots=rng.normal(0, 0.1, (3, 3)),
                            tilts=np.zeros((3, 2)), axes=np.array([[np.nan] * 3, [0.0, 0.6, 0.8], [np.nan] * 3]))
    params = rng.normal(0.0, 0.3, int(vsil.param_offsets(art)[-1]))
    layout = vsil.pose_layout(art)
    assert layout.hinge.tolist() == [False, True, False] and layout.offsets.tolist() == [0, 6, 7, 10]
    assert np.array_equal(vsil.pose_transforms(params, art, 0.5, layout), vsil.pose_transforms(params, art, 0.5))
    uv = rng.uniform(-5, 70, (400, 2))
    cells = vsil.raster_points(uv[:150], (48, 64), 2, grow=0).astype(np.uint8)
    together = vsil.raster_points(uv, (48, 64), 2)
    assert together.any() and np.array_equal(vsil.raster_points(uv[150:], (48, 64), 2, cells=cells), together)
    assert cells.sum() == vsil.raster_points(uv[:150], (48, 64), 2, grow=0).sum()  # the copy left it alone


def _fronto_square_scene(n_frames: int, *, stride: int = 1) -> vsil.SilhouetteScene:
    """A 24 x 24 px square of points on the plane z = 1 (identity camera, f = 40 px), static masks."""
    h, w = 40, 40
    K_small = np.array([[40.0, 0, 20], [0, 40.0, 20], [0, 0, 1]])
    uv0 = (np.stack(np.meshgrid(np.arange(8, 32), np.arange(8, 32)), -1).reshape(-1, 2) + 0.5).astype(float)
    rays = vsil.pixel_rays(uv0, K_small, np.eye(3))
    masks = np.zeros((n_frames, h // stride, w // stride), bool)
    masks[:, 8 // stride: 32 // stride, 8 // stride: 32 // stride] = True
    return vsil.SilhouetteScene(uv0=uv0, rays=rays, cam_center=np.zeros(3), cam_rot=np.eye(3), K=K_small,
                                world_to_cam=np.eye(4), masks=masks, stride=stride, image_shape=(h, w),
                                base_depth=np.ones(len(uv0)) / rays[:, 2], width=0.5)


def test_flow_penalty_against_a_uniform_flow() -> None:
    """Flow (dx, 0) px everywhere: a static pose misses every trusted point by dx / stride cells (capped);
    the pose translating by dx follows it exactly; untrusted flow adds nothing; the tracked score is the
    IoU minus weight x penalty."""
    scene = _fronto_square_scene(3, stride=2)
    art = vsil.Articulation(labels=np.zeros(len(scene.uv0), int), parent=np.array([-1]), pivots=np.array([[0, 0, 1.0]]),
                            tilts=np.zeros((1, 2)))
    points = vsil.canonical_points(scene, art)
    dx = 3.0
    scene.flow = np.zeros((2, 40, 40, 2))
    scene.flow[..., 0] = dx
    scene.flow_valid = np.ones((2, 40, 40), bool)
    scene.flow_weight, scene.flow_cap = 0.5, 2.0
    still = np.zeros(6)
    moved = np.array([0, 0, 0, dx / 40.0 / scene.width, 0, 0])  # dx px at depth 1 with f = 40 px
    assert vsil.flow_penalty(scene, art, points, still, still, 1) == pytest.approx(dx / 2)
    assert vsil.flow_penalty(scene, art, points, still, moved, 1) == pytest.approx(0.0, abs=1e-9)
    scene.flow_cap = 1.0
    assert vsil.flow_penalty(scene, art, points, still, still, 1) == pytest.approx(1.0)
    scene.flow_cap = 2.0
    scene.flow_valid[:, :, :20] = False  # the left half of the square is untrusted
    assert vsil.flow_penalty(scene, art, points, still, still, 1) == pytest.approx(dx / 2 / 2)
    # the tracked score: the pose search follows the silhouette (static), the flow term charges the miss
    params, scores = vsil.track(scene, art, None, root_motion=False, max_evals=20)
    assert np.allclose(params, 0.0)
    assert scores[0] == pytest.approx(1.0)
    assert np.allclose(scores[1:], 1.0 - 0.5 * dx / 2 / 2)
    assert np.allclose(vsil.sequence_ious(scene, art, params), 1.0)


def _leaning_lid(angles_deg: tuple[float, ...]) -> dict:
    """A lid hinged along y = 0 on a root plane z = 1 (identity camera, f = 60 px, 64 x 64 px), leaning
    40 deg back and swinging forward (over the root) by ``angles_deg`` [deg] in its frames. Returns the
    scene (masks of the true motion), the true articulation, its (T, 7) parameters and the lid's points."""
    K_small = np.array([[60.0, 0, 32], [0, 60.0, 40], [0, 0, 1]])
    h, w = 64, 64
    lean = np.radians(40.0)
    # lid plane through the hinge line (y = 0, z = 1), rising towards -y and leaning away (+z)
    up_lid = np.array([0.0, -np.cos(lean), np.sin(lean)])
    s, t = np.meshgrid(np.linspace(-0.2, 0.2, 25), np.linspace(0.01, 0.25, 16))
    lid = np.array([0, 0, 1.0]) + s.reshape(-1, 1) * np.array([1.0, 0, 0]) + t.reshape(-1, 1) * up_lid
    rs, rt = np.meshgrid(np.linspace(-0.2, 0.2, 25), np.linspace(0.01, 0.2, 12))
    root = np.stack([rs.ravel(), rt.ravel(), np.ones(rs.size)], 1)
    pts = np.concatenate([root, lid])
    truth = np.concatenate([np.zeros(len(root), int), np.ones(len(lid), int)])
    uv0 = pts @ K_small.T
    uv0 = uv0[:, :2] / uv0[:, 2:]
    rays = vsil.pixel_rays(uv0, K_small, np.eye(3))
    angles = np.radians(np.asarray(angles_deg, float))
    axis = np.array([1.0, 0, 0])
    pivot = np.array([0, 0, 1.0])
    masks = []
    for a in angles:
        moved = (lid - pivot) @ vsil.rotvec_to_matrix(axis * a).T + pivot
        proj = np.concatenate([root, moved]) @ K_small.T
        masks.append(vsil.raster_points(proj[:, :2] / proj[:, 2:], (h, w), 1, grow=2))
    view = pivot / np.linalg.norm(pivot)
    # the lid's tilt in the scene's parametrisation: its normal, turned from facing the camera
    normal = np.cross(axis, up_lid)
    normal = normal if normal @ view < 0 else -normal
    from scipy.optimize import minimize

    tilt = minimize(lambda x: np.sum((vsil.tilted_normal(view, x, np.eye(3)) - normal) ** 2), np.zeros(2),
                    method="Nelder-Mead", options={"xatol": 1e-9, "fatol": 1e-14}).x
    scene = vsil.SilhouetteScene(uv0=uv0, rays=rays, cam_center=np.zeros(3), cam_rot=np.eye(3), K=K_small,
                                 world_to_cam=np.eye(4), masks=np.stack(masks), stride=1, image_shape=(h, w),
                                 base_depth=1.0 / rays[:, 2], width=0.5)
    art = vsil.Articulation(labels=truth, parent=np.array([-1, 0]), pivots=np.array([pivot, pivot]),
                            tilts=np.array([[0.0, 0.0], tilt]), axes=np.array([[np.nan] * 3, axis]))
    assert np.allclose(vsil.canonical_points(scene, art)[truth == 1], lid, atol=1e-9)  # the tilt fits
    params = np.zeros((len(angles), int(vsil.param_offsets(art)[-1])))
    params[:, 6] = angles
    return {"scene": scene, "art": art, "params": params, "lid": lid, "axis": axis, "pivot": pivot, "K": K_small}


def test_relabel_judges_a_point_on_the_candidate_part_surface() -> None:
    """A lid leaning 40 deg back swings 120 deg forward. Lid points mislabelled as root sit on the root's
    plane; judged there, the lid's motion would move them along the wrong arc. Judged on the lid's plane,
    they follow the lid and all return to it."""
    case = _leaning_lid((0.0, -60.0, -120.0))
    scene, true_art, params = case["scene"], case["art"], case["params"]
    truth = true_art.labels
    labels = truth.copy()
    wrong = (truth == 1) & (np.arange(len(truth)) % 3 == 0)  # a third of the lid's points start as root
    labels[wrong] = 0
    art = vsil.Articulation(labels=labels, parent=true_art.parent, pivots=true_art.pivots, tilts=true_art.tilts,
                            axes=true_art.axes)
    cost = vsil.relabel_costs(scene, art, params)
    assert np.all(cost[wrong, 1] == 0.0)  # on the lid's plane, the lid's motion keeps them in every mask
    assert np.all(cost[wrong, 0] > 0.5)  # left behind by the root, they fall out of the later masks
    new = vsil.relabel(scene, art, params, margin=0.05, tie_part=0, min_points=0, smooth_px=1)
    assert np.all(new[wrong] == 1)
    assert np.all(new[truth == 0] == 0)


def test_motion_residual_scores_the_lid_corners_against_the_true_swing() -> None:
    """Corners on the lid, moved by the true swing between frames, are predicted exactly by the true
    articulation; a 20 % smaller swing misses them; each miss is capped; corners moving where only the
    static root projects (shadows) are not scored."""
    case = _leaning_lid((0.0, -10.0, -20.0))
    scene, art, params, lid, axis, pivot, K_small = (case[k] for k in ("scene", "art", "params", "lid", "axis",
                                                                         "pivot", "K"))

    def image(points: np.ndarray, angle: float) -> np.ndarray:
        moved = (points - pivot) @ vsil.rotvec_to_matrix(axis * angle).T + pivot
        proj = moved @ K_small.T
        return proj[:, :2] / proj[:, 2:]

    corners = lid[::7]
    frame = np.concatenate([np.full(len(corners), t) for t in range(2)])
    start = np.concatenate([image(corners, params[t, 6]) for t in range(2)])
    end = np.concatenate([image(corners, params[t + 1, 6]) for t in range(2)])
    value, count = vsil.motion_residual(scene, art, params, frame, start, end)
    assert count == len(frame)  # the lid stands clear of the root's image in frames 0 and 1
    assert value == pytest.approx(0.0, abs=1e-9)
    # a shadow moving 3 px on the root, away from the lid: not scored
    shadow = np.array([[32.0, 40.0 + 60.0 * 0.15]])
    assert not scene.render_parts([lid], np.eye(4)[None])[int(shadow[0, 1]), int(shadow[0, 0])]
    value2, count2 = vsil.motion_residual(scene, art, params, np.append(frame, 0), np.vstack([start, shadow]),
                                          np.vstack([end, shadow + [3.0, 0.0]]))
    assert (value2, count2) == (pytest.approx(0.0, abs=1e-9), count)
    smaller = params.copy()
    smaller[:, 6] *= 0.8
    value3, count3 = vsil.motion_residual(scene, art, smaller, frame, start, end)
    assert count3 > 0 and 0.05 < value3 <= 2.0
    value4, _ = vsil.motion_residual(scene, art, params, frame, start, end + 50.0, cap_px=1.5)
    assert value4 == pytest.approx(1.5)
    assert vsil.motion_residual(scene, art, params, frame[:0], start[:0], end[:0]) == (pytest.approx(float("nan"),
                                                                                                  nan_ok=True), 0)


def test_tilt_grid_ranks_cells_and_leaves_the_articulation() -> None:
    """Every cell of the grid is scored once, best first, and the part keeps its tilt; a part that never
    moves scores the same at every tilt (a static plane's silhouette is its first-frame pixels)."""
    scene = _fronto_square_scene(3)
    labels = (scene.uv0[:, 0] > 20).astype(int)
    art = vsil.Articulation(labels=labels, parent=np.array([-1, 0]), pivots=np.array([[0, 0, 1.0], [0, 0, 1.0]]),
                            tilts=np.array([[0.0, 0.0], [0.1, -0.2]]))
    cells = vsil.tilt_grid(scene, art, 1, frames=3, grid_deg=(-20.0, 0.0, 20.0), root_motion=False, max_evals=10)
    assert len(cells) == 9
    assert [c[0] for c in cells] == sorted((c[0] for c in cells), reverse=True)
    assert {tuple(np.round(np.degrees(c[1]), 6)) for c in cells} == {(a, b) for a in (-20.0, 0.0, 20.0)
                                                                     for b in (-20.0, 0.0, 20.0)}
    assert np.allclose([c[0] for c in cells], 1.0)
    assert np.allclose(art.tilts[1], [0.1, -0.2])
