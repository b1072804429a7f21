"""The AI4Animation dog trot's skeleton as a template pose (CC BY-NC 4.0): the truth and the capsule body of the
rendered dog-trot clips (:mod:`sync4d_tools.body_clips`). The quadruped fit itself uses a skinned mesh template
(:mod:`sync4d.recon.pose.templates`), not this.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sync4d.errors import InputError

DOG_FILE = Path(__file__).resolve().parents[4] / "shared" / "data" / "motion" / "dog_mocap" / "dog_trot_joint_pos.txt"
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



def dog_template() -> np.ndarray:
    """(27, 3) template joints, centred on the pelvis, body length 1 (template units), facing -x, y up, +z left.

    The trot's average pose: every segment points along its mean direction over the clip (pelvis-relative),
    with the mocap's mean segment lengths, then made mirror-symmetric about the z = 0 plane (a left joint
    and its right twin averaged with z negated; midline joints put on the plane), so that a leg and its
    mirrored twin are the same rotations conjugated by the mirror. No single frame of the clip.
    """
    from sync4d.io.mocap import read_joint_positions

    if not DOG_FILE.is_file():
        raise InputError(f"quadruped template {DOG_FILE} not found; it comes with ../shared/data/motion/dog_mocap")
    pos = read_joint_positions(DOG_FILE)
    offsets = np.zeros(pos.shape[1:])
    for j in range(1, len(DOG_PARENTS)):
        off = pos[:, j] - pos[:, DOG_PARENTS[j]]
        length = float(np.linalg.norm(off, axis=-1).mean())
        mean = off.mean(0)
        offsets[j] = mean / max(np.linalg.norm(mean), 1e-12) * length if length > 1e-9 else 0.0
    twin = np.array([dog_twin(n) for n in DOG_NAMES])
    mirror = np.array([1.0, 1.0, -1.0])
    sym = 0.5 * (offsets + offsets[twin] * mirror)
    sym[twin == np.arange(len(twin)), 2] = 0.0
    out = np.zeros_like(sym)
    for j in range(1, len(DOG_PARENTS)):
        out[j] = out[DOG_PARENTS[j]] + sym[j]
    return out / np.linalg.norm(out[4] - out[24])


def dog_twin(name: str) -> int:
    """Index of the left/right twin of a template joint (itself if none)."""
    for a, b in (("fl_", "fr_"), ("fr_", "fl_"), ("hl_", "hr_"), ("hr_", "hl_")):
        if name.startswith(a):
            return DOG_NAMES.index(b + name[3:])
    return DOG_NAMES.index(name)
