"""``python -m sync4d_tools.match_labels.skeleton_picture [--seed N] DIR [PAIR ...]``: what the structure match sees.

One picture per labelled pair (``DIR/matching_skeleton_<pair>.png``, 64 colours), two views (front, side), three panels:

* the reference's limbs (subtrees of its bone tree off the trunk, each one colour, the trunk grey) and the
  first part of each limb written at its tip;
* the target's curve skeleton: its branches (each one colour), the trunk's core black, and at each
  branch's tip ``b<i> -> <limb>``, the reference limb it was given (``-``: none);
* the parts the target's points end up with (reference part colours, as the match pictures).

The target is drawn in its own normalised frame (unturned), the reference in its own.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

VIEWS = ((0.0, 10.0), (90.0, 10.0))


def limb_colours(count: int) -> np.ndarray:
    """(count, 3) distinct RGB colours (tab10, cycled)."""
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    return np.array([cmap(i % 10)[:3] for i in range(count)])


def _annotate(ax: Any, texts: list[tuple[np.ndarray, str]], view: tuple[float, float]) -> None:
    az, el = np.deg2rad(view[0]), np.deg2rad(view[1])
    toward = np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
    right = np.cross([0.0, 1.0, 0.0], toward)
    right /= np.linalg.norm(right)
    up = np.cross(toward, right)
    for at, text in texts:
        ax.text(float(at @ right), float(at @ up), text, fontsize=6, ha="center", va="bottom",
                bbox={"facecolor": "white", "alpha": 0.7, "pad": 1, "linewidth": 0})


def skeleton_figure(structure: Any, ref_labels: np.ndarray, names: tuple[str, ...], title: str) -> Any:
    """A matplotlib figure of a :class:`sync4d.match.structure.StructureMatch` (see the module docstring);
    ``ref_labels``: the part of each of its reference skeleton's points."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from sync4d.match.pictures import draw_points, label_colors

    ref, tgt = structure.reference, structure.target
    ref_limb = np.full(len(ref.points), -1)
    for i, parts in enumerate(structure.limbs):
        ref_limb[np.isin(ref_labels, parts)] = i
    palette = limb_colours(max(len(structure.limbs), len(tgt.branches)))
    ref_colour = np.where(ref_limb[:, None] >= 0, palette[np.maximum(ref_limb, 0)], 0.75)
    branch_colour = palette[tgt.branch % len(palette)]
    branch_colour[tgt.core] = 0.0
    given = {int(t): int(r) for r, t in structure.pairs}
    ref_texts = [(ref.points[ref_limb == i][np.argmax(ref.geodesic[ref_limb == i])], names[parts[0]])
                 for i, parts in enumerate(structure.limbs) if (ref_limb == i).any()]
    tgt_texts = [(b.tip, f"b{i} -> " + (names[structure.limbs[given[i]][0]] if i in given else "-"))
                 for i, b in enumerate(tgt.branches) if i > 0]
    fig, axes = plt.subplots(len(VIEWS), 3, figsize=(11, 3.6 * len(VIEWS)), squeeze=False)
    for row, view in enumerate(VIEWS):
        draw_points(axes[row, 0], ref.points, ref_colour, view=view, size=1.0)
        _annotate(axes[row, 0], ref_texts, view)
        draw_points(axes[row, 1], tgt.points, branch_colour, view=view, size=1.0)
        _annotate(axes[row, 1], tgt_texts, view)
        draw_points(axes[row, 2], tgt.points, label_colors(structure.point_part, len(names)), view=view, size=1.0)
    for ax, text in zip(axes[0], ("reference limbs (trunk grey)", "target skeleton: branches, core black",
                                  "target parts")):
        ax.set_title(text, fontsize=8)
    fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    return fig


def save_small(fig: Any, path: Path) -> None:
    """Write a figure as a PNG of 64 colours (a few tens of kB)."""
    import io

    from PIL import Image

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=62)
    buf.seek(0)
    Image.open(buf).convert("RGB").quantize(64).save(path, optimize=True)


def save_skeleton_pictures(out: Path, seed: int, pairs: list[str]) -> dict[str, dict[str, float]]:
    """Run the structure match on the labelled pairs (all, or those named) at ``seed`` and draw each."""
    from dataclasses import replace

    import matplotlib.pyplot as plt

    import sync4d_tools.evaluate.match_gt as match_gt
    from sync4d.match import MatchConfig
    from sync4d_tools.match_labels.labels import default_label_files, read_label_file

    match_gt.SEED = seed
    options = replace(MatchConfig(method="structure"), align="upright_icp")
    specs = [read_label_file(p) for p in default_label_files()]
    specs = [s for s in specs if not pairs or s.name in pairs]
    builders = {"human": match_gt.human_body, "dog": match_gt.dog_body, "laptop": match_gt.laptop_body}
    bodies = {name: builders[name]() for name in {s.reference for s in specs}}
    scores = {}
    out.mkdir(parents=True, exist_ok=True)
    for spec in specs:
        body = bodies[spec.reference]
        reference = match_gt.body_reference(body, name=spec.reference)
        result, numbers, _ = match_gt.labelled_match(spec, body, reference, None, options)
        title = (f"{spec.name}, seed {seed}, structure: chance-corrected {numbers['corrected']:.2f}, limbs "
                 f"{numbers['limb_accuracy']:.2f}; per label " + ", ".join(
                     f"{k} {v:.2f}" for k, v in numbers["per_label"].items()))
        labels = result.diagnostics.reference_labels
        assert labels is not None, "the structure match records the reference's part labels"
        fig = skeleton_figure(result.diagnostics.structure, labels, body.names, title)
        save_small(fig, out / f"matching_skeleton_{spec.name}.png")
        plt.close(fig)
        scores[spec.name] = {"corrected": numbers["corrected"], "limb_accuracy": numbers["limb_accuracy"]}
    return scores


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m sync4d_tools.match_labels.skeleton_picture",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("pairs", nargs="*", help="label file names (default: every pair)")
    args = parser.parse_args(argv)
    for name, numbers in save_skeleton_pictures(args.out, args.seed, args.pairs).items():
        print(f"{name}: corrected {numbers['corrected']:.2f} limbs {numbers['limb_accuracy']:.2f}")


if __name__ == "__main__":
    main()
