"""``recon_meshseq``: fit ``recon=skinning_fit`` to a posed mesh sequence and report the vertex error.

    python -m sync4d.evaluate recon_meshseq --data ../shared/data/lab4d_export/shiba-haru-1002 --bones 13
    python -m sync4d.evaluate recon_meshseq --data ... --curve 2:25     # error-vs-B curve as well

Prints one JSON object on the last line: ``vertex_error_pct`` (mean over frames and vertices, % of the
rest bounding-box diagonal), ``max_frame_error_pct``, ``frame_error_pct``, ``bones``, ``seconds`` and,
with ``--curve``, ``curve`` = [[B, vertex_error_pct, seconds], ...].

Data: ``lab4d_export/shiba-haru-1002`` is from ``gengshan-y/ppr-diffphys`` (MIT).
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

from sync4d.io.lab4d import find_mesh_files, read_mesh_sequence
from sync4d.recon.skinning_fit import SkinningFit
from sync4d.sources.references import resolve_path


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m sync4d.evaluate recon_meshseq", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default="../shared/data/lab4d_export/shiba-haru-1002",
                        help="folder of posed .obj meshes (fixed topology)")
    parser.add_argument("--bones", default="13", help="bone count or 'auto'")
    parser.add_argument("--iterations", type=int, default=600)
    parser.add_argument("--fit-vertices", type=int, default=2000)
    parser.add_argument("--curve", default="", help="also fit B in LO:HI (inclusive), e.g. 2:25")
    args = parser.parse_args(argv)

    start = time.perf_counter()
    root = resolve_path(args.data, what="mesh sequence folder")
    files = [f for f in find_mesh_files(root)]
    seq, _, _ = read_mesh_sequence(files)
    cfg = SkinningFit.Config(bones=args.bones, iterations=args.iterations, fit_vertices=args.fit_vertices)
    recon = SkinningFit(cfg)
    recon.fit(seq)
    report = recon.last_fit_report
    out: dict[str, Any] = {
        "vertex_error_pct": round(report["mean_error_pct"], 4),
        "max_frame_error_pct": round(report["max_frame_error_pct"], 4),
        "bones": report["bones"],
        "frames": int(seq.shape[0]),
        "vertices": int(seq.shape[1]),
        "frame_error_pct": [round(e, 4) for e in report["frame_error_pct"]],
        "seconds": round(time.perf_counter() - start, 2),
    }
    if report["bones_curve"]:
        out["auto_curve"] = report["bones_curve"]
    if args.curve:
        lo, hi = (int(x) for x in args.curve.split(":"))
        curve = []
        for b in range(lo, hi + 1):
            t0 = time.perf_counter()
            r = SkinningFit(SkinningFit.Config(bones=b, iterations=args.iterations, fit_vertices=args.fit_vertices))
            r.fit(seq)
            curve.append([b, round(r.last_fit_report["mean_error_pct"], 4), round(time.perf_counter() - t0, 2)])
        out["curve"] = curve
    print(json.dumps(out))
    return out
