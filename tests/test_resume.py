"""A run killed with SIGKILL resumes from its checkpoint and ends exactly as an uninterrupted run.

Also: a run never writes into another run's folder (neither a finished one nor the one it resumes).
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest
import torch

from sync4d.io.ply import read_gaussians_ply
from _runs import assert_same_run, run_train, start_train

FRAMES = ("frames=6",)
KILL_AFTER = "000003.ply"
POLL_S = 0.01


def kill_after_frame(run_dir: Path, log: Path, timeout_s: float = 600.0) -> None:
    """Start a 6-frame run and SIGKILL its process group once ``frames/000003.ply`` exists."""
    proc = start_train(run_dir, *FRAMES, log=log)
    target = run_dir / "frames" / KILL_AFTER
    deadline = time.monotonic() + timeout_s
    try:
        while not target.exists():
            ended = proc.poll()
            assert ended is None, f"the run ended (code {ended}) before {KILL_AFTER}:\n{log.read_text()[-3000:]}"
            assert time.monotonic() < deadline, f"no {KILL_AFTER} after {timeout_s} s"
            time.sleep(POLL_S)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=60)


@pytest.mark.slow  # three train.py processes, one killed mid-run
def test_killed_run_resumes_to_the_same_result(tmp_path: Path) -> None:
    """Uninterrupted vs killed-after-frame-3-then-resumed: same frames (bytes) and metrics (timings aside)."""
    full, killed, resumed = tmp_path / "full", tmp_path / "killed", tmp_path / "resumed"
    proc = run_train(full, *FRAMES)
    assert proc.returncode == 0, proc.stderr[-3000:]

    kill_after_frame(killed, tmp_path / "killed.log")
    assert not (killed / "metrics.json").exists(), "the run finished before it was killed"
    checkpoint = torch.load(killed / "checkpoint.pt", map_location="cpu", weights_only=False)
    assert 2 <= checkpoint["frame"] < 5, f"checkpoint after frame {checkpoint['frame']}"
    # the checkpoint holds one frame's simulator state, not the frames so far (those are in state/)
    assert "frames_x" not in checkpoint and len(list((killed / "state").glob("*.npz"))) >= checkpoint["frame"] + 1
    for frame in sorted((killed / "frames").glob("*.ply")):  # atomic writes: every final name is complete
        read_gaussians_ply(frame)

    proc = run_train(resumed, *FRAMES, f"resume={killed}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "resuming from" in (resumed / "train.log").read_text()
    assert_same_run(full, resumed)
    assert not (killed / "metrics.json").exists(), "the resumed run wrote into the interrupted run's folder"


@pytest.mark.slow  # three train.py processes, one killed mid-run
def test_resume_names_a_missing_frame_state(tmp_path: Path) -> None:
    """A checkpoint whose frame states were deleted: one clear line naming the missing file, exit 2."""
    full = tmp_path / "full"
    proc = run_train(full, "frames=3")
    assert proc.returncode == 0, proc.stderr[-3000:]
    (full / "state" / "000001.npz").unlink()
    proc = run_train(tmp_path / "again", "frames=3", f"resume={full}")
    assert proc.returncode == 2
    assert "000001.npz is missing or unreadable" in proc.stderr


@pytest.mark.slow  # three train.py processes, one killed mid-run
def test_resume_refuses_other_settings(tmp_path: Path) -> None:
    """Resuming with different settings names the first differing key; exit code 2."""
    killed = tmp_path / "killed"
    kill_after_frame(killed, tmp_path / "killed.log")
    proc = run_train(tmp_path / "other", *FRAMES, "sim.E=20000", f"resume={killed}")
    assert proc.returncode == 2, proc.stderr[-3000:]
    line = proc.stderr.strip().splitlines()[-1]
    assert line.startswith("sync4d: ConfigError: resume=") and "sim.E=30000.0" in line and "20000" in line, line


def test_never_writes_into_another_runs_folder(tmp_path: Path) -> None:
    """A folder with a finished run's metrics.json, or the folder being resumed, is refused (exit code 2)."""
    done = tmp_path / "done"
    (done / "frames").mkdir(parents=True)
    (done / "metrics.json").write_text('{"status": "ok"}')
    before = {p: p.read_bytes() for p in done.rglob("*") if p.is_file()}

    proc = run_train(done, *FRAMES)
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert "never overwrites" in proc.stderr and "metrics.json" in proc.stderr, proc.stderr
    proc = run_train(done, *FRAMES, f"resume={done}")
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert "also this run's folder" in proc.stderr, proc.stderr
    after = {p: p.read_bytes() for p in done.rglob("*") if p.is_file()}
    assert after == before, f"the refused run wrote {sorted(set(after) - set(before))}"
