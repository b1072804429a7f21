"""A plugin installed as a package registers its components and its config options: the example
(``plugins/box_target``) installed into a temporary folder on ``PYTHONPATH`` is selectable as ``target=box``."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "plugins" / "box_target"


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``pip install --target`` of a copy of the example (the build leaves nothing in the project)."""
    work = tmp_path_factory.mktemp("plugin")
    source = shutil.copytree(EXAMPLE, work / "source", ignore=shutil.ignore_patterns("__pycache__", "build", "*.egg-info"))
    site = work / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation", "--no-index",
                    "--target", str(site), str(source)], check=True, capture_output=True, timeout=300)
    return site


def train(*args: str, site: Path | None) -> subprocess.CompletedProcess[str]:
    paths = [str(site)] if site is not None else []
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([*paths, str(ROOT)])}
    return subprocess.run([sys.executable, str(ROOT / "train.py"), *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=600)


def test_without_the_plugin_box_is_unknown():
    result = train("target=box", site=None)
    assert result.returncode == 2 and "unknown target 'box'" in result.stderr, result.stderr


def test_the_installed_plugin_brings_its_option(installed: Path):
    """Its entry point registers ``BoxTarget``; its own ``conf/target/box.yaml`` is the option, over the schema."""
    result = train("target=box", "target.num_surface=200", "--cfg", "job", site=installed)
    assert result.returncode == 0, result.stderr
    assert "type: box" in result.stdout and "num_surface: 200" in result.stdout and "num_interior: 500" in result.stdout


@pytest.mark.slow
def test_the_installed_plugin_runs_from_the_command_line(installed: Path, tmp_path: Path):
    run_dir = tmp_path / "run"
    result = train("target=box", "debug=smoke", "frames=2", "render_video=false", f"hydra.run.dir={run_dir}",
                   site=installed)
    assert result.returncode == 0, result.stderr[-2000:]
    assert sorted(p.name for p in (run_dir / "frames").glob("*.ply")) == ["000000.ply", "000001.ply"]
