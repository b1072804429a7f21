"""``python -m sync4d_tools.evaluate.match_cpu --seed N``: CPU seconds of part matching on the benchmark.

Runs ``python -m sync4d.evaluate match_gt --cross-category`` (auto, no pictures) at the seed with
``sync4d_tools.evaluate.match_gt.match_parts`` wrapped to add up ``time.process_time()`` around each call:
the three within-category pairs, then every labelled pair. Prints one JSON line: seed, within-category,
labelled and total seconds, the load average at the start and the end. Run it with
``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1`` (one thread: process time is then the matching's own).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import time
from typing import Any

from sync4d_tools.evaluate import match_gt


def timed_main(seed: int) -> dict[str, Any]:
    """Seconds of ``match_parts`` per kind of pair at ``seed`` (auto, labelled pairs without pictures)."""
    from sync4d_tools.match_labels.labels import default_label_files

    spent = {"within": 0.0, "labelled": 0.0}
    phase = ["within"]
    original, original_cross = match_gt.match_parts, match_gt.cross_category

    def wrapped(*args: Any, **kwargs: Any) -> Any:
        start = time.process_time()
        try:
            return original(*args, **kwargs)
        finally:
            spent[phase[0]] += time.process_time() - start

    def cross(*args: Any, **kwargs: Any) -> Any:
        phase[0] = "labelled"
        return original_cross(*args, **kwargs)

    load = os.getloadavg()[0]
    match_gt.match_parts, match_gt.cross_category = wrapped, cross
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            match_gt.main(["--seed", str(seed), *[a for f in default_label_files() for a in ("--labels", str(f))]])
    finally:
        match_gt.match_parts, match_gt.cross_category = original, original_cross
    return {"seed": seed, "within_category_s": round(spent["within"], 1), "labelled_s": round(spent["labelled"], 1),
            "total_s": round(spent["within"] + spent["labelled"], 1), "load_start": round(load, 2),
            "load_end": round(os.getloadavg()[0], 2)}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(prog="python -m sync4d_tools.evaluate.match_cpu", description=__doc__.split("\n")[0])
    p.add_argument("--seed", type=int, default=0)
    out = timed_main(p.parse_args(argv).seed)
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
