"""``recon.video.gravity``: an axis near level or vertical is put exactly there; one far from both is left."""

import numpy as np

from sync4d.recon.video.gravity import ALIGN_DEG, aligned_axis

UP = np.array([0.0, 1.0, 0.0])


def tilted(elevation_deg: float, azimuth_deg: float = 30.0) -> np.ndarray:
    e, a = np.radians(elevation_deg), np.radians(azimuth_deg)
    return np.array([np.cos(e) * np.cos(a), np.sin(e), np.cos(e) * np.sin(a)])


def test_an_axis_a_few_degrees_out_of_level_is_made_level_keeping_its_heading() -> None:
    out = aligned_axis(2.5 * tilted(4.0), UP)
    assert out is not None
    np.testing.assert_allclose(out, tilted(0.0), atol=1e-12)


def test_an_axis_near_vertical_is_made_vertical_with_its_sign() -> None:
    np.testing.assert_allclose(aligned_axis(tilted(85.0), UP), UP)
    np.testing.assert_allclose(aligned_axis(-tilted(85.0), UP), -UP)


def test_an_axis_far_from_level_and_vertical_or_already_there_is_left() -> None:
    assert aligned_axis(tilted(ALIGN_DEG + 1.0), UP) is None
    assert aligned_axis(tilted(90.0 - ALIGN_DEG - 1.0), UP) is None
    assert aligned_axis(tilted(45.0), UP) is None
    assert aligned_axis(tilted(0.0), UP) is None
    assert aligned_axis(UP, UP) is None
