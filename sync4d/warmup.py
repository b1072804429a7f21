"""``python -m sync4d.warmup [--device cpu|cuda]``: compile the Warp kernels once into the shared cache.

Warp compiles a kernel module on first use and stores the binary under ``WARP_CACHE_PATH`` (default:
``.warp_cache/`` in the project). Parallel sweep jobs (``hydra/launcher=joblib``/``submitit_*``)
started on a cold cache would all compile the same module at once; run this once before them so each
job only loads the cached binary.
"""

from __future__ import annotations

import argparse
import os
import time
from typing import Sequence

from sync4d.paths import PROJECT_ROOT

KERNEL_MODULES: tuple[str, ...] = ("sync4d.sim.mpm_warp.kernels",)


def warm(device: str = "cpu", modules: Sequence[str] = KERNEL_MODULES) -> float:
    """Compile (or load from the cache) every Warp module in ``modules`` for ``device``.

    Returns:
        wall time [s] (seconds on a cold cache, well under one on a warm one).
    """
    os.environ.setdefault("WARP_CACHE_PATH", str(PROJECT_ROOT / ".warp_cache"))
    import importlib

    from sync4d.device import warp_device

    import warp as wp

    started = time.perf_counter()
    target = warp_device(device)
    for name in modules:
        wp.load_module(importlib.import_module(name), device=target)
    return time.perf_counter() - started


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sync4d.warmup", description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cpu", help="cpu | cuda | cuda:N (default cpu)")
    args = parser.parse_args(argv)
    seconds = warm(args.device)
    print(f"sync4d.warmup: Warp kernels ready for {args.device} in {seconds:.1f} s "
          f"(cache {os.environ['WARP_CACHE_PATH']})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
