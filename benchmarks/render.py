"""Benchmark of ``render=splat_torch``: milliseconds per frame at 256x256 for 5k, 20k and 50k Gaussians.

The scene is random anisotropic Gaussians filling a box that fills the view, with scales drawn so that
each Gaussian's standard deviation on screen is 0.7-4 px (its 3-sigma footprint a few to tens of pixels
across), random orientations and opacities in [0.3, 1], SH degree 0 colours. Times are the median (and
the minimum: this machine's 2 cores are shared, so the minimum is the uncontended speed) of ``--repeats``
renders after one warm-up, forward only (numpy in, numpy out, no autograd) and, with
``--backward``, forward + backward of a sum of the image w.r.t. means, covariances, colours, opacities.

Usage::

    python benchmarks/render.py [--sizes 5000 20000 50000] [--res 256] [--repeats 5] [--backward]
                                [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from sync4d.render.camera import look_at  # noqa: E402
from sync4d.render.splat_torch import SplatTorch  # noqa: E402
from sync4d.geometry import quat_to_matrix  # noqa: E402
from sync4d.types import Camera  # noqa: E402


def random_scene(n: int, camera: Camera, *, seed: int = 0) -> dict[str, np.ndarray]:
    """Random Gaussians in a 1 m box at the origin, sized in pixels for ``camera``.

    Returns:
        means (n, 3) [m], covariances (n, 3, 3) [m^2], sh (n, 1, 3), opacities (n,).
    """
    rng = np.random.default_rng(seed)
    means = rng.uniform(-0.5, 0.5, size=(n, 3))
    depth = means @ camera.world_to_cam[2, :3] + camera.world_to_cam[2, 3]
    f = camera.K[0, 0]
    sigma_px = np.exp(rng.uniform(np.log(0.7), np.log(4.0), size=(n, 1)))
    aniso = np.exp(rng.uniform(-0.5, 0.5, size=(n, 3)))
    scales = sigma_px * aniso * depth[:, None] / f
    quats = rng.normal(size=(n, 4))
    rot = quat_to_matrix(quats)
    scaled = rot * scales[:, None, :]
    covs = scaled @ np.swapaxes(scaled, 1, 2)
    sh = rng.normal(scale=0.8, size=(n, 1, 3))
    opac = rng.uniform(0.3, 1.0, size=n)
    return {"means": means, "covariances": covs, "sh": sh, "opacities": opac}


def bench(n: int, res: int, repeats: int, backward: bool) -> dict[str, float]:
    """Time one scene size; returns a JSON-able record."""
    # The 1 m box (bounding sphere radius 0.87 m) fills most of a 40 deg view from 2.8 m.
    cam = look_at((1.6, -1.9, 1.3), (0, 0, 0), (0, 0, 1), 40.0, res, res)
    scene = random_scene(n, cam)
    renderer = SplatTorch(SplatTorch.Config(width=res, height=res), device="cpu")
    args = (scene["means"], scene["covariances"], scene["sh"], scene["opacities"], cam)
    renderer.render_full(*args)  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = renderer.render_full(*args)
        times.append(time.perf_counter() - t0)
    proj = renderer.project(
        torch.as_tensor(scene["means"], dtype=torch.float32),
        torch.as_tensor(scene["covariances"], dtype=torch.float32),
        torch.as_tensor(scene["opacities"], dtype=torch.float32),
        cam,
    )
    boxes = proj.boxes
    pairs = int(((boxes[:, 1] - boxes[:, 0] + 1) * (boxes[:, 3] - boxes[:, 2] + 1)).sum())
    record = {
        "gaussians": n,
        "resolution": res,
        "visible": int(proj.index.numel()),
        "footprint_px": pairs,
        "coverage": float((out["alpha"] > 0.5).mean()),
        "forward_ms": 1e3 * statistics.median(times),
        "forward_min_ms": 1e3 * min(times),
    }
    if backward:
        tensors = [torch.tensor(scene[k], dtype=torch.float32, requires_grad=True) for k in
                   ("means", "covariances", "sh", "opacities")]
        btimes = []
        for i in range(repeats + 1):
            t0 = time.perf_counter()
            means, covariances, sh, opacities = tensors
            img = renderer.render(means, covariances, sh, opacities, cam)
            img.sum().backward()
            if i:
                btimes.append(time.perf_counter() - t0)
        record["forward_backward_ms"] = 1e3 * statistics.median(btimes)
        record["forward_backward_min_ms"] = 1e3 * min(btimes)
    return record


def main(argv: list[str] | None = None) -> list[dict[str, float]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[5000, 20000, 50000])
    parser.add_argument("--res", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--backward", action="store_true", help="also time forward + backward")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0 = torch's default)")
    parser.add_argument("--json", type=Path, default=None, help="write the records to this JSON file")
    args = parser.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    print(f"splat_torch on {platform.processor() or platform.machine()}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads, {args.res}x{args.res}, median of {args.repeats}")
    header = f"{'gaussians':>10} {'visible':>8} {'box px':>10} {'cover':>6} {'fwd ms':>9} {'(min)':>7}"
    if args.backward:
        header += f" {'fwd+bwd ms':>11} {'(min)':>7}"
    print(header)
    records = []
    for n in args.sizes:
        rec = bench(n, args.res, args.repeats, args.backward)
        records.append(rec)
        line = (f"{rec['gaussians']:>10} {rec['visible']:>8} {rec['footprint_px']:>10} {rec['coverage']:>6.2f} "
                f"{rec['forward_ms']:>9.1f} {rec['forward_min_ms']:>7.1f}")
        if args.backward:
            line += f" {rec['forward_backward_ms']:>11.1f} {rec['forward_backward_min_ms']:>7.1f}"
        print(line, flush=True)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        payload = {"benchmark": "render.splat_torch", "torch": torch.__version__,
                   "threads": torch.get_num_threads(), "records": records}
        args.json.write_text(json.dumps(payload, indent=2))
    return records


if __name__ == "__main__":
    main()
