"""Part-map pictures: PNG on disk and an image in TensorBoard."""

from __future__ import annotations

import numpy as np
from PIL import Image

from sync4d.match.pictures import OUTLIER_COLOR, label_colors, match_figure, figure_to_array, part_colors


def test_colours_distinct_and_outliers_black() -> None:
    pal = part_colors(13)
    assert len({tuple(np.round(c, 3)) for c in pal}) == 13
    cols = label_colors(np.array([0, -1, 2]), 3)
    assert np.allclose(cols[1], OUTLIER_COLOR) and np.allclose(cols[0], pal[0])
    assert part_colors(30).shape == (30, 3)


def test_figure_png_and_tensorboard(tmp_path) -> None:
    import matplotlib.pyplot as plt
    from torch.utils.tensorboard import SummaryWriter

    rng = np.random.default_rng(0)
    pts = rng.normal(size=(300, 3))
    labels = (pts[:, 0] > 0).astype(int)
    tgt_labels = labels.copy()
    tgt_labels[:10] = -1
    fig = match_figure(pts, labels, pts + 0.1, tgt_labels, 2, views=((0, 10), (90, 10)))
    image = figure_to_array(fig)
    plt.close(fig)
    assert image.ndim == 3 and image.shape[2] == 3 and image.dtype == np.uint8
    assert (image < 30).all(axis=2).any()  # black outliers drawn
    Image.fromarray(image).save(tmp_path / "m.png")
    assert Image.open(tmp_path / "m.png").size == (image.shape[1], image.shape[0])
    writer = SummaryWriter(str(tmp_path / "tb"))
    writer.add_image("match/parts", image, global_step=3, dataformats="HWC")
    writer.close()
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(tmp_path / "tb"))
    acc.Reload()
    assert "match/parts" in acc.Tags()["images"]
