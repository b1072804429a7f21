"""Speed of ``recon=video``: the default run's clip (the filmed laptop, 24 frames, 160x120, two parts) and a
48-frame 320x240 MuJoCo clip of the Meta-World laptop (rendered into ``outputs/cache/articulated_speed``).

    python benchmarks/recon_video_speed.py

Prints a table and writes ``benchmarks/results/recon_video_speed.json``: wall and CPU seconds of the
reconstruction, the forked fits' CPU included. One-time imports (torch's optimiser machinery pulls in
``torch._dynamo``, about 1.4 s) happen before the timing: a process pays them once, not per clip.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")


def main() -> list[dict]:
    from sync4d.sources.references import VideoSource
    from sync4d.recon.video import VideoReconstructor
    from sync4d.scenes.laptop import filmed_laptop_case

    import torch

    torch.optim.Adam([torch.zeros(1, requires_grad=True)])  # the one-time import, outside the timing
    rows = []
    source, _ = filmed_laptop_case()
    fit = VideoReconstructor(VideoReconstructor.Config()).reconstruct_detailed(source)
    rows.append({"clip": "default run: filmed laptop 24 x 160x120", "wall_s": round(fit.seconds, 1),
                 "cpu_s": round(fit.cpu_seconds, 1), "budget_s": 30})
    cache = Path("outputs/cache/articulated_speed")
    clip = cache / "clips" / "mw_laptop-left"
    if not (clip / "gt.npz").exists():
        from sync4d_tools.articulated.render import main as render

        render(["--out", str(cache), "--frames", "48", "--size", "320", "240", "--only", "mw_laptop"])
    source = VideoSource(VideoSource.Config(video=str(clip / "rgb.mp4"), masks=str(clip / "masks"),
                                            camera=str(clip / "gt.npz"))).load()
    fit = VideoReconstructor(VideoReconstructor.Config()).reconstruct_detailed(source)
    rows.append({"clip": "Meta-World laptop 48 x 320x240", "wall_s": round(fit.seconds, 1),
                 "cpu_s": round(fit.cpu_seconds, 1), "budget_s": 120})
    print("| clip | wall [s] | CPU [s] | budget [s] |\n|---|---|---|---|")
    for r in rows:
        print(f"| {r['clip']} | {r['wall_s']} | {r['cpu_s']} | {r['budget_s']} |")
    out = Path(__file__).parent / "results" / "recon_video_speed.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main()
