"""A real (smoke) run's outputs for people and other tools: compare.mp4 shows the input video beside the
reference and the target, sequence.s4d holds the ply sequence within its bound, sequence.glb validates,
and the viewer opens the folder."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests._node import node_tool, run_node
from tests._runs import run_train

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("viewrun") / "run"
    done = run_train(folder)
    assert done.returncode == 0, done.stderr[-3000:]
    return folder


def test_compare_video_starts_with_the_input_video(run: Path) -> None:
    from PIL import Image

    from sync4d.render.video import read_video

    video, compare = read_video(run / "input.mp4"), read_video(run / "compare.mp4")
    height = compare.shape[1]
    width = int(round(video.shape[2] * height / video.shape[1]))
    assert compare.shape[2] > 3 * width // 2  # video | reference | target
    for t in range(len(compare)):
        expected = np.asarray(Image.fromarray(video[t % len(video)]).resize((width, height), Image.BILINEAR), float)
        shown = compare[t, :, :width].astype(float)
        shown[:14, :40], expected[:14, :40] = 0, 0  # the caption
        assert np.abs(shown - expected).mean() < 12.0  # H.264 twice
        other = np.asarray(Image.fromarray(video[(t + 1) % len(video)]).resize((width, height)), float)
        assert np.abs(shown - expected).mean() <= np.abs(shown - other).mean() + 1e-9
    assert (run / "compare.gif").read_bytes()[:6] == b"GIF89a"


def test_compact_sequence_holds_the_ply_frames(run: Path) -> None:
    from sync4d.io.ply import read_gaussians_ply
    from sync4d.io.seq4d import Sequence4D

    seq = Sequence4D(run / "sequence.s4d")
    plys = sorted((run / "frames").glob("*.ply"))
    assert seq.num_frames == len(plys) and seq.parts is not None
    for t, path in enumerate(plys):
        means, _ = seq.frame(t)
        # The .ply holds float32; the .s4d's bound is on the float64 centres the run wrote both from.
        assert np.abs(means - read_gaussians_ply(path).means).max() <= seq.position_error + 1e-6


@pytest.mark.skipif(not node_tool("gltf-validator"), reason="the Khronos glTF validator is not installed: make browser")
def test_run_glb_validates(run: Path) -> None:
    report = run_node("validate_gltf.mjs", str(run / "sequence.glb"))
    assert report["errors"] == 0, report["messages"]


def test_viewer_opens_the_run(run: Path) -> None:
    from sync4d.view.data import load_run

    data = load_run(run)
    assert data.reference is not None and data.video is not None and data.particles is not None
    assert data.target.frame(data.num_frames - 1).parts is not None
