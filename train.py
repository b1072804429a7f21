"""sync4d entry point: ``python train.py [group=name ...] [key=value ...]`` (Hydra). See README.md."""

from __future__ import annotations

import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent
os.environ.setdefault("WARP_CACHE_PATH", str(ROOT / ".warp_cache"))

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from sync4d.cli import check_command_line  # noqa: E402
from sync4d.config_schemas import register_schemas  # noqa: E402


@hydra.main(version_base="1.3", config_path=str(ROOT / "conf"), config_name="config")
def main(cfg: DictConfig) -> float | None:
    from sync4d.run.pipeline import run_guarded

    metrics = run_guarded(cfg)
    return None if not metrics else metrics.get("pose_error_pct") or metrics.get("displacement_error_pct")


if __name__ == "__main__":
    register_schemas()
    check_command_line(sys.argv[1:], ROOT / "conf")
    main()
