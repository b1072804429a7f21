"""The viewer's data side and server: run folders read lazily, placement, viser's splat layout, serving."""

from __future__ import annotations

import socket
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from sync4d.errors import InputError
from tests._viewrun import lid_sequence, make_run


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_load_run_reads_every_part_and_frames_on_demand(tmp_path: Path) -> None:
    from sync4d.view.data import load_run

    run = load_run(make_run(tmp_path / "run", frames=5, n=200))
    assert run.num_frames == 5 and run.reference is not None and run.video is not None
    assert run.particles is not None and run.particles.shape == (5, 200, 3)
    frame = run.target.frame(3)
    means, _, parts = lid_sequence(5, 200, seed=0)
    assert np.abs(frame.means - means[3]).max() < 1e-3 and (frame.parts == parts).all()
    assert run.video(7).shape == (48, 64, 3)  # wraps: frame 7 of a 5-frame video
    np.testing.assert_allclose(run.up, [0, 1, 0])


def test_load_run_falls_back_to_ply_frames_and_rejects_non_runs(tmp_path: Path) -> None:
    from sync4d.io.ply import write_gaussians_ply
    from sync4d.types import TargetGaussians
    from sync4d.view.data import load_run

    n = 30
    g = TargetGaussians(means=np.zeros((n, 3), np.float32) + np.arange(n)[:, None] * 0.01,
                        quats=np.tile([1.0, 0, 0, 0], (n, 1)).astype(np.float32),
                        log_scales=np.full((n, 3), -4.0, np.float32), opacity_logits=np.zeros(n, np.float32),
                        sh=np.zeros((n, 1, 3), np.float32))
    for t in range(3):
        write_gaussians_ply(tmp_path / "old" / "frames" / f"{t:06d}.ply", g)
    run = load_run(tmp_path / "old")
    assert run.num_frames == 3 and run.reference is None and run.video is None
    assert run.target.frame(2).means.shape == (n, 3)
    with pytest.raises(InputError, match="no such run folder"):
        load_run(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="neither sequence.s4d"):
        load_run(tmp_path / "empty")


def test_placement_is_upright_unit_sized_and_faces_the_motion_plane() -> None:
    from sync4d.view.data import place

    means, _, _ = lid_sequence(6, 300, seed=0)
    turn = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0.0]])  # the same object turned 90 deg about up
    for seq in (means, means @ turn.T):
        p = place(seq, np.array([2.0, 0.0, 0.0]), up=np.array([0.0, 1.0, 0.0]))
        np.testing.assert_allclose(p.rotation @ p.rotation.T, np.eye(3), atol=1e-9)
        assert np.linalg.det(p.rotation) == pytest.approx(1.0)
        np.testing.assert_allclose(p.rotation[1], [0, 1, 0], atol=1e-9)  # up stays up
        shown = np.stack([p.points(x) for x in seq])
        # The lid swings in the y-z plane of the object; placed, it swings in the viewer's x-y plane (facing +z).
        motion = (shown - shown.mean(axis=0)).reshape(-1, 3)
        assert np.abs(motion[:, 2]).max() < 1e-6 + 0.02 * np.abs(motion[:, :2]).max()
        radius = np.linalg.norm(shown.reshape(-1, 3) - shown.reshape(-1, 3).mean(axis=0), axis=1).max()
        assert 0.3 < radius <= 0.55  # the bounding sphere (about the box centre) has radius 0.5


def test_splat_buffer_matches_visers_own_layout() -> None:
    import viser

    from sync4d.view.data import splat_buffer

    rng = np.random.default_rng(0)
    n = 50
    means, colors, opac = rng.normal(size=(n, 3)), rng.uniform(0, 1, (n, 3)), rng.uniform(0, 1, n)
    a = rng.normal(size=(n, 3, 3)) * 0.05
    covs = a @ np.swapaxes(a, 1, 2)
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    try:
        handle = server.scene.add_gaussian_splats("/g", centers=means, covariances=covs, rgbs=colors,
                                                  opacities=opac[:, None])
        mine = splat_buffer(means, covs, colors, opac)
        np.testing.assert_array_equal(mine[:, :7], handle.buffer[:, :7])
        rgba_mine, rgba_viser = mine[:, 7:].view(np.uint8), handle.buffer[:, 7:].view(np.uint8)
        assert np.abs(rgba_mine.astype(int) - rgba_viser.astype(int)).max() <= 1  # viser truncates, we round
    finally:
        server.stop()


def test_part_boxes_bound_each_part() -> None:
    from sync4d.view.data import part_boxes

    pts = np.array([[0, 0, 0], [1, 2, 3], [5, 5, 5], [6, 7, 5.0]])
    centers, sizes = part_boxes(pts, np.array([0, 0, 1, 1]), 3)
    np.testing.assert_allclose(centers[:2], [[0.5, 1, 1.5], [5.5, 6, 5]])
    np.testing.assert_allclose(sizes, [[1, 2, 3], [1, 2, 0], [0, 0, 0]])


def test_viewer_serves_two_runs_and_steps_frames(tmp_path: Path) -> None:
    from sync4d.view.app import Viewer, ViewerConfig
    from sync4d.view.data import load_run

    runs = [load_run(make_run(tmp_path / "a", frames=4, n=300)),
            load_run(make_run(tmp_path / "b", frames=3, n=200, video=False))]
    viewer = Viewer(runs, ViewerConfig(port=free_port()))
    try:
        page = urllib.request.urlopen(f"http://127.0.0.1:{viewer.port}/", timeout=10).read()
        assert b"<html" in page.lower()
        first = viewer.rows[0].panels["target"].splats.buffer.copy()
        viewer.step(2)
        assert int(viewer.slider.value) == 2
        moved = viewer.rows[0].panels["target"].splats.buffer
        assert not np.array_equal(first[:, :3], moved[:, :3])
        viewer.part_colours.value, viewer.boxes.value, viewer.particles.value = True, True, True
        viewer.show(2)
        assert viewer.rows[0].particles is not None and viewer.rows[0].particles.visible
        assert all(b.visible for b in viewer.rows[0].panels["target"].boxes)
        viewer.step(2)  # wraps at the longest run's length; the shorter run loops
        assert int(viewer.slider.value) == 0
    finally:
        viewer.server.stop()


def test_cli_reports_a_bad_folder_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from sync4d.view.__main__ import main

    assert main([str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no such run folder" in err


def test_large_objects_show_a_fixed_subset(tmp_path: Path) -> None:
    from sync4d.view.app import Viewer, ViewerConfig
    from sync4d.view.data import load_run

    viewer = Viewer([load_run(make_run(tmp_path / "a", frames=3, n=400, video=False))],
                    ViewerConfig(port=free_port(), max_gaussians=150))
    try:
        panel = viewer.rows[0].panels["target"]
        assert len(panel.splats.buffer) == 150
        before = panel.subset.copy()
        viewer.step(1)
        assert len(panel.splats.buffer) == 150 and (panel.subset == before).all()
    finally:
        viewer.server.stop()


def test_play_advances_frames_at_the_chosen_rate(tmp_path: Path) -> None:
    import threading
    import time

    from sync4d.view.app import Viewer, ViewerConfig
    from sync4d.view.data import load_run

    viewer = Viewer([load_run(make_run(tmp_path / "a", frames=40, n=100, video=False))],
                    ViewerConfig(port=free_port(), fps=20.0, play=True))
    loop = threading.Thread(target=viewer.serve_forever)
    loop.start()
    time.sleep(1.0)
    viewer.playing.value = False
    reached = int(viewer.slider.value)
    time.sleep(0.3)
    viewer.stop()
    loop.join(timeout=10)
    assert 3 <= reached <= 21  # 20 frames/s for 1 s, less when the machine is busy
    assert int(viewer.slider.value) == reached  # paused


def test_frames_of_a_control_point_run_take_each_gaussians_part(tmp_path: Path) -> None:
    """A control-point run stores ``part`` per simulated point (P) and ``gaussian_part`` per Gaussian (N):
    the .ply frames (N Gaussians) are coloured by the latter, not dropped for a length mismatch."""
    from sync4d.view.data import gaussian_parts

    path = tmp_path / "trajectory.npz"
    np.savez(path, x=np.zeros((2, 3, 3)), part=np.array([0, 1, 1]), gaussian_part=np.array([0, 0, 1, 1, 1]))
    assert gaussian_parts(path, np.array([0, 1, 1])).tolist() == [0, 0, 1, 1, 1]
    np.savez(path, x=np.zeros((2, 3, 3)), part=np.array([0, 1, 1]))
    assert gaussian_parts(path, np.array([0, 1, 1])).tolist() == [0, 1, 1]
    assert gaussian_parts(tmp_path / "missing.npz", None) is None
