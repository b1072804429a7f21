"""Every malformed input and bad configuration ends ``train.py`` with one readable line and exit code 2.

The file corpus is ``tests/data/bad/`` (made by ``tests/data/make_bad_inputs.py``). Each case runs
``python train.py <overrides> debug=smoke`` in a subprocess and checks: exit code 2, exactly one line
on stderr, starting ``sync4d:``, naming the input (file or config key) and what is wrong, and no
traceback. One case is re-run with ``HYDRA_FULL_ERROR=1`` to check the traceback is then shown.
"""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
BAD = ROOT / "tests" / "data" / "bad"
TIMEOUT_S = 300


@dataclass(frozen=True)
class Case:
    """One bad input: the overrides that feed it to ``train.py`` and words its error line must hold.

    Attributes:
        name: the case id.
        overrides: command-line overrides (``{bad}`` is replaced by the corpus folder).
        expect: case-insensitive substrings of the error line (the input's name, then what is wrong).
        corpus: the corpus entry (file or folder under ``tests/data/bad``) the case uses, if any.
    """

    name: str
    overrides: tuple[str, ...]
    expect: tuple[str, ...]
    corpus: str | None = None


def _ply(name: str, *expect: str) -> Case:
    return Case(name, ("target=ply", f"target.path={{bad}}/{name}"), (name, *expect), name)


def _video(folder: str, *expect: str) -> Case:
    return Case(
        folder,
        ("reference=video", "recon=ground_truth", f"reference.video={{bad}}/{folder}/rgb",
         f"reference.masks={{bad}}/{folder}/masks", "reference.camera=", "reference.fps=10"),
        expect, folder,
    )  # fmt: skip


CASES: tuple[Case, ...] = (
    _ply("ply_truncated.ply", "truncated"),
    _ply("ply_not_ply.ply", "not a PLY"),
    _ply("ply_nan.ply", "property 'x'", "NaN"),
    _ply("ply_inf.ply", "property 'scale_1'", "inf"),
    _ply("ply_zero_gaussians.ply", "zero Gaussians"),
    _ply("ply_missing_properties.ply", "missing", "opacity"),
    _ply("ply_one_gaussian.ply", "1 Gaussian", "at least 4"),
    Case("mesh_degenerate.obj", ("target=mesh", "target.path={bad}/mesh_degenerate.obj"),
         ("mesh_degenerate.obj", "no area"), "mesh_degenerate.obj"),
    Case("device=tpu", ("device=tpu",), ("device=tpu", "device=cpu")),
    Case("sim.n_grid=1", ("sim.n_grid=1", "shrink.sim.n_grid=1"), ("sim.n_grid=1", ">= 10")),  # debug=smoke would shrink it
    Case("mesh_no_faces.obj", ("target=mesh", "target.path={bad}/mesh_no_faces.obj"),
         ("mesh_no_faces.obj", "no faces"), "mesh_no_faces.obj"),
    Case("video_no_frames",
         ("reference=video", "recon=ground_truth", "reference.video={bad}/video_no_frames", "reference.masks=",
          "reference.camera=", "reference.fps=10"),
         ("video_no_frames", "no images"), "video_no_frames"),
    _video("video_mask_size", "video_mask_size/masks", "8x8", "16x16"),
    _video("video_empty_mask", "video_empty_mask/masks", "empty"),
    Case("bvh_wrong_channels.bvh", ("reference=bvh", "recon=mocap", "reference.path={bad}/bvh_wrong_channels.bvh"),
         ("bvh_wrong_channels.bvh", "channels (9)"), "bvh_wrong_channels.bvh"),
    Case("lab4d_bone_skin_mismatch",
         ("reference=lab4d", "recon=lab4d", "reference.path={bad}/lab4d_bone_skin_mismatch"),
         ("lab4d_bone_skin_mismatch", "3 bones", "2 columns"), "lab4d_bone_skin_mismatch"),
    Case("sim.nu=0.5", ("sim.nu=0.5",), ("sim.nu=0.5",)),
    Case("sim.E=0", ("sim.E=0",), ("sim.E=0", "> 0")),
    Case("sim.E=-1000", ("sim.E=-1000",), ("sim.E=-1000", "> 0")),
    Case("recon.bones=0", ("reference=laptop", "recon=skinning_fit", "recon.bones=0"), ("recon.bones=0",)),
    Case("recon.bones=100000", ("reference=laptop", "recon=skinning_fit", "recon.bones=100000"),
         ("recon.bones=100000", "vertices")),
    Case("sim=no_such_sim", ("sim=no_such_sim",), ("sim", "no_such_sim", "available")),
    Case("sim.type=no_such_sim", ("sim.type=no_such_sim",), ("no_such_sim", "sim")),
    Case("sim.nuu=0.3", ("sim.nuu=0.3",), ("sim.nuu", "no such key", "spelling")),
    Case("target=ply without path", ("target=ply",), ("target.path", "required")),
    Case("frames=abc", ("frames=abc",), ("frames='abc'", "integer")),
)


def run_train(overrides: tuple[str, ...], run_dir: Path, *, full_error: bool = False) -> subprocess.CompletedProcess:
    """``python train.py <overrides> debug=smoke`` into ``run_dir``; returns the finished process."""
    env = {**os.environ, "WARP_CACHE_PATH": str(ROOT / ".warp_cache")}
    env.pop("HYDRA_FULL_ERROR", None)
    if full_error:
        env["HYDRA_FULL_ERROR"] = "1"
    args = [o.replace("{bad}", str(BAD)) for o in overrides]
    cmd = [sys.executable, str(ROOT / "train.py"), *args, "debug=smoke", f"hydra.run.dir={run_dir}"]
    return subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=TIMEOUT_S, check=False)


def test_corpus_is_complete() -> None:
    """Every corpus entry is used by a case, and every case's entry exists (regenerate if this fails)."""
    entries = {p.name for p in BAD.iterdir()}
    used = {c.corpus for c in CASES if c.corpus}
    assert used == entries, f"unused corpus entries {entries - used}, missing {used - entries}"


#: Cases also run through a real ``train.py`` process: the command-line contract (exit code, stderr) itself.
SUBPROCESS_CASES = ("ply_nan.ply", "sim.E=0", "sim=no_such_sim", "sim.nuu=0.3")
#: The longest a bad input may take to be refused: before any expensive stage runs.
REFUSE_WITHIN_S = 10.0


def check_one_line(case: Case, code: int, stderr: str, run_dir: Path) -> None:
    """Exit code 2, one ``sync4d:`` line naming the input and the problem, no traceback, no outputs."""
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert code == 2, f"exit {code}; stderr:\n{stderr[-3000:]}"
    assert "Traceback" not in stderr, stderr[-3000:]
    assert len(lines) == 1, f"expected one line on stderr, got {len(lines)}:\n{stderr[-3000:]}"
    line = lines[0]
    assert line.startswith("sync4d: "), line
    for word in case.expect:
        assert word.lower() in line.lower(), f"{word!r} not in {line!r}"
    assert not (run_dir / "metrics.json").exists()


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_bad_input_gives_one_line(case: Case, tmp_path: Path) -> None:
    """The pipeline refuses each bad input with one line, in seconds (in this process: no interpreter start)."""
    import time

    from _runs import train_in_process

    started = time.perf_counter()
    code, stderr = train_in_process(tmp_path / "run", *(o.replace("{bad}", str(BAD)) for o in case.overrides))
    elapsed = time.perf_counter() - started
    check_one_line(case, code, stderr, tmp_path / "run")
    assert elapsed < REFUSE_WITHIN_S, f"refused after {elapsed:.1f} s: expensive work ran first"


@pytest.mark.parametrize("case", [c for c in CASES if c.name in SUBPROCESS_CASES],
                         ids=[c.name for c in CASES if c.name in SUBPROCESS_CASES])
def test_bad_input_through_train_py(case: Case, tmp_path: Path) -> None:
    proc = run_train(case.overrides, tmp_path / "run")
    assert "Traceback" not in proc.stdout
    check_one_line(case, proc.returncode, proc.stderr, tmp_path / "run")


def test_full_error_shows_traceback(tmp_path: Path) -> None:
    """With ``HYDRA_FULL_ERROR=1`` the same failure shows its traceback (and a non-zero exit)."""
    proc = run_train(("target=ply", "target.path={bad}/ply_nan.ply"), tmp_path / "run", full_error=True)
    assert proc.returncode != 0
    assert "Traceback" in proc.stderr
    assert "InputError" in proc.stderr and "ply_nan.ply" in proc.stderr
