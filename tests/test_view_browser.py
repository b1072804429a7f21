"""The viewer in a real browser: headless Chromium (Debian's, driven by playwright-core) opens
``python -m sync4d.view``, screenshots two frames, and the splats must be drawn and must move.

Needs chromium (``make browser`` installs it, with tests/js/node_modules, which the test also installs
when npm is there); skipped, saying so, when chromium is absent.
The screenshots stay in the test's tmp folder (pytest prints it with -v on failure).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests._node import JS, node_tool
from tests._viewrun import RED, make_run
from tests.test_view import free_port

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (make browser installs it)"),
]


def red_pixels(path: Path) -> np.ndarray:
    """(H, W) bool: pixels of the target's red in the scene part of a screenshot (left of the GUI panel)."""
    from PIL import Image

    # Rows 150-640 and columns 60-940: the scene, clear of the notice toast (orange), the axes widget
    # (a red x axis) at the bottom left and the GUI panel on the right.
    img = np.asarray(Image.open(path).convert("RGB")).astype(int)[150:640, 60:940]
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    # The target's red, also where its splats blend with the white background at their edges.
    return (r > 0.6 * RED[0] * 255) & (g < 0.45 * r) & (b < 0.45 * r)


def start_viewer(run: Path, port: int) -> subprocess.Popen:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "sync4d.view", str(run), "--port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                            cwd=Path(__file__).parent.parent)
    deadline = time.monotonic() + 60
    assert proc.stdout is not None
    for line in proc.stdout:  # the viewer prints "serving ..." once it listens
        if "sync4d.view: serving" in line:
            return proc
        if time.monotonic() > deadline:
            break
    proc.kill()
    raise AssertionError("the viewer did not start")


def test_viewer_draws_and_moves_the_splats_in_chromium(tmp_path: Path) -> None:
    if not node_tool("playwright-core"):
        pytest.fail("chromium is installed but node or playwright-core is not: run make browser")
    run = make_run(tmp_path / "run", frames=4, n=1500)
    port = free_port()
    started = time.monotonic()
    viewer = start_viewer(run, port)
    startup = time.monotonic() - started
    shots = [tmp_path / "frame0.png", tmp_path / "frame3.png"]
    steps = [["text", "Next frame"], ["wait", 5000], ["shot", str(shots[0])],
             ["click", "Next frame"], ["click", "Next frame"], ["click", "Next frame"], ["wait", 5000],
             ["shot", str(shots[1])]]
    try:
        out = subprocess.run(["node", str(JS / "screenshots.mjs"), f"http://127.0.0.1:{port}/", json.dumps(steps)],
                             capture_output=True, text=True, timeout=180, check=False, env={**os.environ,
                                                                                           "CHROMIUM": CHROMIUM})
    finally:
        viewer.terminate()
        viewer.wait(timeout=30)
    assert out.returncode == 0, out.stderr[-2000:]
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert "WebGL support: true" in report["webgl"], report
    assert startup < 30.0
    first, last = red_pixels(shots[0]), red_pixels(shots[1])
    # Splats are drawn: the red target covers a real area in both frames.
    assert first.sum() > 2000 and last.sum() > 2000, (first.sum(), last.sum())
    # ... and move: the lid swings from upright (frame 0) to flat (frame 3), so the red area gets lower.
    rows0, rows3 = np.nonzero(first.any(axis=1))[0], np.nonzero(last.any(axis=1))[0]
    height0, height3 = rows0.max() - rows0.min(), rows3.max() - rows3.min()
    assert height3 < 0.8 * height0, (height0, height3)
    assert (first != last).mean() > 0.005
