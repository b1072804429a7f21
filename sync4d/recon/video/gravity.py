"""Joint axes level or plumb: the joints of things that stand on a level floor (a laptop's or a chest's lid, a
door, a drawer, a sliding window) turn about, or slide along, a level or a vertical line. When the world's up
is known (the front end's upright world, or a given ``world_up``), an axis the fit found within
``ALIGN_DEG`` of level or of vertical is tried exactly there, and the data decide
(:func:`sync4d.recon.video.joints.gravity_aligned`). Measured: ``docs/results/articulated.md``.
"""

from __future__ import annotations

import numpy as np

#: an axis within this angle of level (or of vertical) is tried exactly there [deg]
ALIGN_DEG = 10.0


def aligned_axis(axis: np.ndarray, up: np.ndarray) -> np.ndarray | None:
    """(3,) unit ``axis`` (3,) made exactly level (its component along the unit ``up`` removed) or exactly
    vertical (``up``, with the axis's sign), whichever it lies within ``ALIGN_DEG`` of; None when neither, or
    when it is already there (within 1e-6 rad)."""
    unit = np.asarray(axis, np.float64) / max(float(np.linalg.norm(axis)), 1e-12)
    along = float(unit @ up)
    elevation = np.degrees(np.arcsin(min(1.0, abs(along))))
    if elevation <= ALIGN_DEG:
        level = unit - along * up
        target = level / max(float(np.linalg.norm(level)), 1e-12)
    elif elevation >= 90.0 - ALIGN_DEG:
        target = np.sign(along) * np.asarray(up, np.float64)
    else:
        return None
    return None if float(np.linalg.norm(target - unit)) < 1e-6 else target
