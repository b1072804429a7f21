"""The AI4Animation dog trot's skeleton (CC BY-NC 4.0): joint names, parents and capsule radii, the truth and the
capsule body of the rendered dog-trot clips (:mod:`sync4d_tools.body_clips`). The quadruped fit itself uses a skinned mesh template
(:mod:`sync4d.recon.pose.templates`), not this.
"""

from __future__ import annotations

import numpy as np

DOG_PARENTS = np.array([-1, 0, 1, 2, 3, 4, 2, 6, 7, 8, 9, 2, 11, 12, 13, 14, 0, 16, 17, 18, 0, 20, 21, 22, 0, 24, 25])
DOG_NAMES = (
    "pelvis",
    "spine0",
    "spine1",
    "neck",
    "head",
    "head_end",
    "fl_scapula",
    "fl_upper",
    "fl_middle",
    "fl_wrist",
    "fl_paw",
    "fr_scapula",
    "fr_upper",
    "fr_middle",
    "fr_wrist",
    "fr_paw",
    "hl_upper",
    "hl_middle",
    "hl_hock",
    "hl_paw",
    "hr_upper",
    "hr_middle",
    "hr_hock",
    "hr_paw",
    "tail_base",
    "tail1",
    "tail_end",
)
# capsule radius of the segment ending at each joint, as a fraction of the template's body length
DOG_RADII = np.array(
    [
        0,
        0.10,
        0.10,
        0.07,
        0.07,
        0.06,
        0.05,
        0.05,
        0.04,
        0.03,
        0.03,
        0.05,
        0.05,
        0.04,
        0.03,
        0.03,
        0.06,
        0.05,
        0.035,
        0.03,
        0.06,
        0.05,
        0.035,
        0.03,
        0.04,
        0.03,
        0.025,
    ]
)
