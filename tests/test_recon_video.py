"""recon=video on tiny synthetic videos (two textured plates on a hinge or a slide), its stages and helpers."""

from __future__ import annotations

import numpy as np
import pytest

from sync4d.errors import ConfigError, InputError
from sync4d.recon.video import (
    background_masks,
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


def plates_video(frames: int = 6, amount: float = 40.0, *, kind: str = "hinge") -> tuple[VideoClip, np.ndarray, np.ndarray]:
    """Two textured plates seen by a camera at the origin (OpenCV axes), slightly tilted: a base on the
    left and an arm at its right edge, turning about the (nearly) viewing direction by up to ``amount``
    degrees (``hinge``) or sliding right by up to ``amount`` [m] (``slide``). Rendered by z-buffered point
    splatting. Returns (clip, part labels (T, H, W) 0/1/2, joint values [deg or m])."""
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
    if kind == "slide":
        lid_rest = lid_rest + np.array([0.02, 0.0, 0.0])  # a gap, so the parts do not overlap
    angles = np.linspace(0.0, amount, frames)
    imgs, labels = [], []
    for a in angles:
        if kind == "hinge":
            lid = (lid_rest - hinge) @ rot_z(np.deg2rad(-a)).T + hinge
        else:
            lid = lid_rest + np.array([a, 0.0, 0.0])
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


def test_background_model_finds_the_moving_object() -> None:
    frames = np.full((7, H, W, 3), 40, np.uint8)
    for t in range(7):
        frames[t, 10:20, 5 + 6 * t : 15 + 6 * t] = 220
    masks = background_masks(frames)
    assert masks[3, 12:18, 25:31].all() and not masks[3, :, :20].any()


def test_composite_weights_hide_a_dense_surface_behind_an_opaque_one() -> None:
    """One opaque Gaussian in front of ten translucent ones: compositing gives the front one nearly all
    the weight (T alpha, as a rasteriser blends); the soft z-buffer vote lets the ten behind outvote it."""
    import torch

    from sync4d.recon.video.softsplat import composite_weights, front_weights

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




def test_config_errors_name_the_key() -> None:
    with pytest.raises(ConfigError, match="bones"):
        build("recon", {"type": "video", "bones": 0})
    with pytest.raises(ConfigError, match="points"):
        build("recon", {"type": "video", "tracks": {"points": 3}})
    with pytest.raises(ConfigError, match="patch_ncc"):
        build("recon", {"type": "video", "tracks": {"patch_ncc": 1.5}})
    with pytest.raises(ConfigError, match="recon.fit.nonsense"):
        build("recon", {"type": "video", "fit": {"nonsense": 1}})
    with pytest.raises(ConfigError, match="source"):
        build("recon", {"type": "video", "masks": {"source": "magic"}})
    with pytest.raises(InputError, match="needs a video"):
        build("recon", {"type": "video"}).reconstruct(ReferenceInput(name="none", fps=1.0))


def test_config_is_small_and_the_yaml_only_selects() -> None:
    """At most 25 keys in nested blocks; conf/recon/video.yaml holds only ``type: video``."""
    import dataclasses
    from pathlib import Path

    import yaml

    from sync4d.recon.video import VideoReconstructor

    def count(cls: type) -> int:
        return sum(count(type(getattr(cls(), f.name))) if dataclasses.is_dataclass(getattr(cls(), f.name)) else 1
                   for f in dataclasses.fields(cls))

    assert count(VideoReconstructor.Config) <= 25
    conf = yaml.safe_load((Path(__file__).resolve().parents[1] / "conf" / "recon" / "video.yaml").read_text())
    assert {k: v for k, v in conf.items() if k != "defaults"} == {"type": "video"}


def test_joint_transforms_of_a_hinge_and_a_slide() -> None:
    """A hinge leaves its pivot in place and turns by its value; a slide moves every point by value x axis."""
    from scipy.spatial.transform import Rotation

    from sync4d.recon.video.joints import JointFit

    axis = np.array([0.0, 0.6, 0.8])
    fit = JointFit(labels=np.zeros(3, int), root=0, depth=np.ones(3), kinds=["root", "hinge", "slide"],
                   axes=np.stack([np.zeros(3), axis, [1.0, 0, 0]]), pivots=np.array([[0, 0, 0], [0.1, 0.2, 0.3],
                                                                                   [0, 0, 0.0]]),
                   values=np.array([[0, 0, 0], [0, 0.5, 0.2]]), root_motion=np.tile(np.eye(4), (2, 1, 1)),
                   data_loss=0.0)
    j = fit.transforms()
    assert np.allclose(j[:, 0], np.eye(4))
    assert np.allclose(j[1, 1, :3, :3] @ [0.1, 0.2, 0.3] + j[1, 1, :3, 3], [0.1, 0.2, 0.3])
    assert np.allclose(Rotation.from_matrix(j[1, 1, :3, :3]).as_rotvec(), 0.5 * axis)
    assert np.allclose(j[1, 2, :3, 3], [0.2, 0, 0]) and np.allclose(j[1, 2, :3, :3], np.eye(3))


def test_the_fit_s_own_autograd_steps_match_torch_s_to_the_bit() -> None:
    """The fit's cheaper products (``moved``, the projection's division, ``pair_sum``) give the values and
    gradients of the plain torch expressions they replace, bit for bit (the fit's results depend on it)."""
    import torch

    from sync4d.recon.video.joints import _Divided, moved, pair_sum

    gen = torch.Generator().manual_seed(0)
    motion = torch.randn(5, 3, 3, 4, dtype=torch.float64, generator=gen, requires_grad=True)
    points = torch.randn(40, 3, dtype=torch.float64, generator=gen, requires_grad=True)
    labels = torch.randint(0, 3, (40,), generator=gen)
    num = torch.randn(5, 40, 2, dtype=torch.float64, generator=gen, requires_grad=True)
    den = (torch.rand(5, 40, 1, dtype=torch.float64, generator=gen) + 0.5).requires_grad_()

    def plain() -> list[torch.Tensor]:
        j = motion[:, labels]
        return [torch.einsum("tnij,nj->tni", j[..., :3], points) + j[..., 3], num / den, (num**2).sum(-1)]

    def fit_s() -> list[torch.Tensor]:
        return [moved(motion, labels, points), _Divided.apply(num, den), pair_sum(num**2)]

    for ours, theirs in zip(fit_s(), plain()):
        assert torch.equal(ours, theirs)
        weights = torch.randn(ours.shape, dtype=torch.float64, generator=gen)
        inputs = [t for t in (motion, points, num, den) if t.requires_grad]
        grads = torch.autograd.grad((ours * weights).sum(), inputs, allow_unused=True)
        expected = torch.autograd.grad((theirs * weights).sum(), inputs, allow_unused=True)
        for g, e in zip(grads, expected):
            assert (g is None and e is None) or torch.equal(g, e)


def _fit(kind: str, amount: float) -> tuple[object, np.ndarray, np.ndarray]:
    clip, labels, values = plates_video(kind=kind, amount=amount)
    camera = Camera(K=K, world_to_cam=np.eye(4), width=W, height=H)
    recon = build("recon", {"type": "video", "bones": 2, "tracks": {"points": 500},
                            "fit": {"steps": 120, "axis_starts": 3}}, device="cpu")
    return recon.reconstruct_detailed(ReferenceInput(name=kind, fps=10.0, video=clip, camera=camera)), labels, values


def _label_agreement(fit: object, labels: np.ndarray) -> float:
    """Fraction of tracked points whose part is the plate under their first-frame pixel (either naming)."""
    u, v = fit.tracks.uv0.astype(int).T  # type: ignore[attr-defined]
    plate = labels[0][v, u]
    part = fit.joints.labels  # type: ignore[attr-defined]
    return max(float(((part == plate - 1)).mean()), float((part == 2 - plate).mean()))


def test_two_plate_hinge_is_found_and_followed() -> None:
    fit, labels, angles = _fit("hinge", 40.0)
    ref = fit.reference
    assert ref.num_bones == 2 and ref.num_frames == len(angles) and ref.rest_faces is None
    moving = 1 - fit.joints.root
    assert fit.joints.kinds[moving] == "hinge", fit.joints.kinds
    assert _label_agreement(fit, labels) > 0.9
    j = ref.bone_transforms
    rel = rotation_angle_deg(np.einsum("tji,tjk->tik", j[:, 0, :3, :3], j[:, 1, :3, :3]))
    assert np.abs(rel - angles).max() < 4.0, rel
    # the evaluation reads the stages' results, not side channels
    # (the tracked frame-0 points first, then the surfaces later frames reveal)
    assert fit.means.shape == ref.rest_vertices.shape and len(fit.means) >= len(fit.tracks.uv0) and fit.seconds > 0


def plate_depths(uv: np.ndarray) -> np.ndarray:
    """(N,) true camera depth [m] of the plates' plane (through the hinge (0, 0, 1.2), spanned by x and the
    tilt of :func:`plates_video`) under pixels uv (N, 2)."""
    normal = np.cross([1.0, 0.0, 0.0], [0.0, 0.94, 0.34])
    rays = np.concatenate([(uv - K[:2, 2]) / K[0, 0], np.ones((len(uv), 1))], 1)
    return float(normal @ [0.0, 0.0, 1.2]) / (rays @ normal)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="measured: read as a slide, but 35.5 deg off its direction and its travel "
                   "50 % over (docs/results/articulated.md); strict: passing again fails until this marker goes")
def test_two_plate_slide_is_found_as_a_slide() -> None:
    """The sliding plate is read as a slide along its true direction (image x: within 5 deg) and its travel is
    within 10 % of the truth's range once the one scale a single view cannot see is removed (the plate's true
    mean depth against the fitted one); a correlation alone would pass any direction and any scale."""
    fit, labels, travel = _fit("slide", 0.1)
    moving = 1 - fit.joints.root
    assert fit.joints.kinds[moving] == "slide", fit.joints.kinds
    assert _label_agreement(fit, labels) > 0.9
    axis = fit.joints.axes[moving]
    direction_error = np.degrees(np.arccos(min(1.0, abs(axis[0]) / np.linalg.norm(axis))))
    own = fit.joints.labels == moving
    scale = plate_depths(fit.tracks.uv0[own]).mean() / fit.joints.depth[own].mean()
    found = scale * fit.joints.values[:, moving] * np.sign(axis[0])
    travel_error = np.abs(found - travel).mean() / np.ptp(travel)
    assert direction_error <= 5.0 and travel_error <= 0.1, (direction_error, travel_error, found, travel)


def test_tracks_on_a_plain_face_are_not_verified() -> None:
    """A plain lid slides 3 px a frame over a static plain base of similar grey (a closed laptop's lid on
    its base); a textured square moves the same. On the plain lid the chained flow sticks (small and still
    forward-backward consistent), so 'trusted' alone keeps tracks that report too little motion (with the
    subject's flow on frames enlarged 2x: 6 of 72, at 9.5 of 15 px; at the frames' own size all 72, at 6.3
    px); the patch check drops them and keeps the textured square's, which are right."""
    from sync4d.recon.video.stages import TrackConfig, track_grid

    yy, xx = np.mgrid[0:H, 0:W]
    texture = (120 + 70 * np.sin(xx / 2.0) * np.cos(yy / 2.5)).astype(np.uint8)
    frames, masks = np.full((6, H, W, 3), 30, np.uint8), np.zeros((6, H, W), bool)
    for t in range(6):
        x = 10 + 3 * t
        frames[t, 16:80, 4:60] = 150  # the static base
        frames[t, 20:76, x:x + 30] = 170  # the plain lid
        frames[t, 20:76, x + 60:x + 90] = texture[20:76, 10:40, None]  # textured, carried with its square
        masks[t, 16:80, 4:60] = masks[t, 20:76, x:x + 30] = masks[t, 20:76, x + 60:x + 90] = True
    tracks = track_grid(frames, masks, TrackConfig(points=600))
    lid = (tracks.uv0[:, 0] > 16) & (tracks.uv0[:, 0] < 34) & (tracks.uv0[:, 1] > 30) & (tracks.uv0[:, 1] < 66)
    textured = (tracks.uv0[:, 0] > 72) & (tracks.uv0[:, 0] < 98) & (tracks.uv0[:, 1] > 24) & (tracks.uv0[:, 1] < 72)
    moved = tracks.uv[-1, :, 0] - tracks.uv0[:, 0]
    sticking = tracks.trusted[-1] & lid
    assert sticking.any() and np.median(moved[sticking]) < 0.7 * 15.0  # trusted, yet short of the true 15 px
    assert not tracks.verified[-1, lid].any()
    assert tracks.verified[-1, textured].mean() > 0.9
    assert np.allclose(moved[tracks.verified[-1] & textured], 15.0, atol=1.0)


def test_a_thin_part_s_tracks_are_not_dragged_by_the_background() -> None:
    """A textured bar 4 px wide moves right 3 px a frame over a textured background moving left 2 px a frame
    (a thin lid before a room, filmed by a moving camera). The flow's support is wider than the bar: computed
    on the whole frame no track of the bar survives; on the subject alone (outside its masks blanked) and on
    frames enlarged 2x they follow the bar within 2 % (blanked at the frames' own size: 3 % short)."""
    from sync4d.recon.video.stages import TrackConfig, track_grid

    yy, xx = np.mgrid[0:H, 0:2 * W]
    room = (110 + 80 * np.sin(xx / 3.1) * np.cos(yy / 2.3)).astype(np.uint8)
    bar = (120 + 90 * np.sin(yy[:, :4] / 1.7 + xx[:, :4] / 1.3)).astype(np.uint8)
    frames, masks = np.zeros((6, H, W, 3), np.uint8), np.zeros((6, H, W), bool)
    for t in range(6):
        frames[t] = room[:, 40 + 2 * t:40 + 2 * t + W, None]
        x = 30 + 3 * t
        frames[t, 20:76, x:x + 4] = bar[20:76, :, None]
        masks[t, 20:76, x:x + 4] = True
    tracks = track_grid(frames, masks, TrackConfig(points=200))
    ok = tracks.trusted[-1]
    assert ok.sum() >= 0.5 * len(ok)
    moved = (tracks.uv[-1, ok, 0] - tracks.uv0[ok, 0]) / 15.0
    assert abs(float(np.median(moved)) - 1.0) < 0.02


def test_still_points_are_triangulated_under_a_moving_camera_and_a_moving_one_is_not() -> None:
    """static_depths: points standing still are found at their true depth with no residual; a point that moves
    on its own leaves a residual of pixels (what the parts are clustered on); camera_moves tells the cases."""
    from sync4d.recon.video.images import camera_moves, static_depths
    from sync4d.sources.references import camera_from_look

    rng = np.random.default_rng(0)
    Kc = np.array([[120.0, 0, 80], [0, 120.0, 60], [0, 0, 1]])
    angles = np.linspace(0.0, 0.5, 10)
    cams = [camera_from_look(Kc, [2.0 * np.sin(a), 0.6, 2.0 * np.cos(a)], [-np.sin(a), -0.3, -np.cos(a)],
                             [0.0, 1.0, 0.0], 160, 120).world_to_cam for a in angles]
    w2c = np.stack(cams)
    points = rng.uniform(-0.3, 0.3, (40, 3))
    motion = np.zeros((10, 40, 3))
    motion[:, -5:, 1] = np.linspace(0.0, 0.2, 10)[:, None]  # the last five rise on their own
    world = points[None] + motion
    pc = np.einsum("tij,tnj->tni", w2c[:, :3, :3], world) + w2c[:, None, :3, 3]
    uv = (pc @ Kc.T)[..., :2] / pc[..., 2:3]
    depth, residual, predicted = static_depths(uv[0], uv, np.ones((10, 40), bool), Kc, w2c)
    np.testing.assert_allclose(depth[:-5], pc[0, :-5, 2], rtol=2e-3)
    assert residual[:-5].max() < 0.3 and residual[-5:].min() > 2.0, residual
    np.testing.assert_allclose(predicted[:, :-5], uv[:, :-5], atol=0.5)
    assert camera_moves(w2c) and not camera_moves(np.repeat(w2c[:1], 10, 0)) and not camera_moves(None)


@pytest.mark.slow
def test_the_hand_held_laptop_is_reconstructed_with_its_moving_camera() -> None:
    """The default scene's hand-held film (small) with its exact per-frame camera: recon=video keeps the poses
    (VideoFit.extrinsics), the base stays still in the world, the lid is a hinge near the true axis; the film
    gives the world's up, so the hinge, found near level, is held exactly level (``recon.video.gravity``)."""
    from sync4d.recon.video.reconstructor import VideoReconstructor

    source = build("reference", {"type": "laptop", "video_exact": "masks_camera"}, device="cpu").load()
    fit = VideoReconstructor(VideoReconstructor.Config()).reconstruct_detailed(source)
    assert fit.extrinsics is not None and np.allclose(fit.extrinsics, source.video.extrinsics)
    lid = 1 - fit.joints.root
    assert fit.joints.kinds[lid] == "hinge", fit.joints.kinds
    assert np.allclose(fit.joints.root_motion, np.eye(4))
    axis_error = np.degrees(np.arccos(min(1.0, abs(float(fit.joints.axes[lid][0])))))
    assert axis_error < 3.0 and abs(float(fit.joints.axes[lid][1])) < 1e-9, fit.joints.axes[lid]
