"""A pose prior for the quadruped fit learned from real motion: a Gaussian over a template's joint rotations.

The AI4Animation dog trot (``../shared/data/motion/dog_mocap/dog_trot_joint_pos.txt``; CC BY-NC 4.0, via
``erwincoumans/motion_imitation``: joint positions, y up, the dog facing -x, +z its left, the
:data:`sync4d.recon.pose.dog.DOG_NAMES` joints) is retargeted onto the template: per frame the template's
root follows the mocap's pelvis and heading, and its joint rotations, bone lengths and scale are fitted to
the mocap joints the template's vocabulary names (under the fit's length and limit priors). The prior is a
probabilistic PCA over the fitted rotations (the leading components kept, an isotropic variance, never below
``floor_deg`` squared, for the rest): its negative log-likelihood per dimension is the fit's term.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch

from sync4d.recon.pose import quadruped_fit as qf
from sync4d.recon.pose.dog import DOG_NAMES
from sync4d.recon.pose.templates import SHARED, body_template

DOG_TROT = SHARED / "motion" / "dog_mocap" / "dog_trot_joint_pos.txt"


@dataclass(frozen=True)
class PosePrior:
    """Mean (D,) and precision (D, D) of the joint rotations (J * 3 axis-angle components) [rad]; ``dims``: how
    many of the D the mocap informs (the others have zero precision)."""

    mean: torch.Tensor
    precision: torch.Tensor
    dims: int

    def nll(self, local: torch.Tensor) -> torch.Tensor:
        """Mean over frames of the Mahalanobis term per dimension of (T, J, 3) joint rotations."""
        x = local.reshape(len(local), -1) - self.mean
        return 0.5 * ((x @ self.precision) * x).sum(-1).mean() / self.dims


def gaussian(samples: np.ndarray, explained: float = 0.95, floor_deg: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """Mean and precision of a probabilistic PCA of (N, D) samples: the components explaining ``explained`` of
    the variance kept, the rest given their mean variance (at least ``floor_deg`` squared, in radians)."""
    mean = samples.mean(0)
    vals, vecs = np.linalg.eigh(np.cov(samples - mean, rowvar=False, bias=True))
    vals, vecs = np.clip(vals[::-1], 0.0, None), vecs[:, ::-1]
    k = int(np.searchsorted(np.cumsum(vals) / max(vals.sum(), 1e-12), explained) + 1)
    rest = max(float(vals[k:].mean()) if k < len(vals) else 0.0, math.radians(floor_deg) ** 2)
    cov = (vecs[:, :k] * np.maximum(vals[:k] - rest, 0.0)) @ vecs[:, :k].T + rest * np.eye(len(mean))
    return mean, np.linalg.inv(cov)


def mocap_start(tt: qf.TemplateTensors, positions: np.ndarray) -> qf.Params:
    """Template parameters whose root follows the mocap's pelvis and heading (pelvis to neck), y up."""
    from scipy.spatial.transform import Rotation

    up = np.array([0.0, 1.0, 0.0])
    pelvis, neck = positions[:, DOG_NAMES.index("pelvis")], positions[:, DOG_NAMES.index("neck")]
    rots = []
    for fwd in neck - pelvis:
        fwd = fwd - up * (up @ fwd)
        fwd /= np.linalg.norm(fwd)
        rots.append(Rotation.from_matrix(np.stack([-fwd, up, np.cross(-fwd, up)], 1)).as_rotvec())
    length = float(np.linalg.norm(positions[:, DOG_NAMES.index("head")] - positions[:, DOG_NAMES.index("tail_base")],
                                  axis=-1).mean())
    nj = len(tt.parents)
    return {"root_rot": qf.leaf(np.array(rots)), "root_pos": qf.leaf(pelvis), "local": qf.leaf(np.zeros((len(positions), nj, 3))),
            "log_len": qf.leaf(np.zeros(nj)), "log_girth": qf.leaf(np.zeros(nj)), "log_scale": qf.leaf(math.log(length)),
            "log_thick": qf.leaf(0.0)}


def informed(parents: np.ndarray, ids: list[int]) -> np.ndarray:
    """(J,) bool: joints with a fitted joint (``ids``) below them, whose rotations the mocap determines."""
    out = np.zeros(len(parents), dtype=bool)
    for j in ids:
        p = int(parents[j])
        while p >= 0:
            out[p], p = True, int(parents[p])
    return out


def retarget(template: str, positions: np.ndarray, steps: int = 800) -> tuple[np.ndarray, np.ndarray]:
    """(T, J, 3) the template's joint rotations fitted to mocap joint positions (T, 27, 3) (the dog's joints),
    and (J,) which of them the mocap determines (:func:`informed`)."""
    tt = qf.TemplateTensors(body_template(template))
    tmpl = tt.template
    pairs = [(tmpl.names.index(j), DOG_NAMES.index(v)) for v, j in tmpl.vocabulary if v in DOG_NAMES]
    ids, src = [p for p, _ in pairs], [s for _, s in pairs]
    target = torch.tensor(positions[:, src], dtype=qf.DTYPE)
    params = mocap_start(tt, positions)
    cfg = qf.QuadrupedFitConfig()
    opt = torch.optim.Adam([v for k, v in params.items() if k not in ("log_thick", "log_girth")], lr=0.02)
    with qf.deterministic_torch():
        for _ in range(steps):
            opt.zero_grad()
            joints = qf.pose_joints(tt, params)
            loss = 100 * ((joints[:, ids] - target) / params["log_scale"].exp()).pow(2).sum(-1).mean()
            lengths, limit = qf.shape_priors(tt, params, cfg)
            (loss + cfg.length_weight * lengths + cfg.limit_weight * limit).backward()
            opt.step()
    return params["local"].detach().numpy().astype(np.float64), informed(tt.parents, ids)


@lru_cache(maxsize=4)
def dog_trot_prior(template: str) -> PosePrior:
    """The :class:`PosePrior` of the AI4Animation dog trot retargeted onto ``template`` (built once)."""
    from sync4d.io.mocap import read_joint_positions

    local, keep = retarget(template, read_joint_positions(DOG_TROT, num_joints=len(DOG_NAMES)))
    dims = np.repeat(keep, 3)
    mean, precision = np.zeros(dims.size), np.zeros((dims.size, dims.size))
    mean[dims], precision[np.ix_(dims, dims)] = gaussian(local.reshape(len(local), -1)[:, dims])
    return PosePrior(torch.tensor(mean, dtype=qf.DTYPE), torch.tensor(precision, dtype=qf.DTYPE), int(dims.sum()))
