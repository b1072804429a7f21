"""``python -m sync4d_tools.match_labels.picture OUT.png``: the benchmark's ground truth in one picture.

One panel per label file (its target seen across its long horizontal axis), each label one colour, grey
where nothing is scored, ``*`` marking the trunk label: what the labels claim can be checked by eye.
"""

from __future__ import annotations

import sys

import numpy as np


def save_label_picture(path: str) -> None:
    """Draw every default label file's target with its labels into ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sync4d_tools.evaluate.match_gt import load_label_target
    from sync4d_tools.match_labels.labels import default_label_files, read_label_file, vertex_labels

    files = default_label_files()
    fig, axes = plt.subplots((len(files) + 4) // 5, 5, figsize=(16, 3.4 * ((len(files) + 4) // 5)))
    colours = plt.cm.tab10(np.arange(10))[:, :3]
    for ax in axes.ravel():
        ax.set_axis_off()
    for ax, file in zip(axes.ravel(), files):
        spec = read_label_file(file)
        vertices, _, names = load_label_target(spec)
        labels = vertex_labels(spec, vertices, names)
        across = 0 if np.ptp(vertices[:, 0]) >= np.ptp(vertices[:, 2]) else 2
        order = np.argsort(vertices[:, 2 - across])
        colour = np.where(labels[:, None] >= 0, colours[labels % 10], 0.85)
        ax.scatter(vertices[order, across], vertices[order, 1], c=colour[order], s=1.5)
        ax.set_aspect("equal")
        ax.set_title(spec.name + "\n" + ", ".join(lab.name + ("*" if lab.trunk else "") for lab in spec.labels),
                     fontsize=7)
    fig.suptitle("ground truth of the matching benchmark: each colour one label (grey: not scored; * the trunk)")
    fig.tight_layout()
    fig.savefig(path, dpi=55)
    plt.close(fig)


if __name__ == "__main__":
    save_label_picture(sys.argv[1] if len(sys.argv) > 1 else "matching_labels.png")
