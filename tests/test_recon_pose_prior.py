"""The quadruped fit's pose prior learned from the AI4Animation dog trot (sync4d.recon.pose.pose_prior)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sync4d.recon.pose import pose_prior as pp


def test_gaussian_keeps_the_leading_components_and_floors_the_rest() -> None:
    rng = np.random.default_rng(0)
    samples = rng.normal(size=(400, 1)) * np.array([[0.5, 0.5, 0.0, 0.0]]) + rng.normal(size=(400, 4)) * 1e-4
    mean, precision = pp.gaussian(samples, explained=0.95, floor_deg=5.0)
    cov = np.linalg.inv(precision)
    along = np.array([1.0, 1.0, 0.0, 0.0]) / math.sqrt(2)
    # the one direction the samples move in keeps its variance; the others get the floor, not ~1e-8
    assert along @ cov @ along == pytest.approx(0.5, rel=0.15)
    assert np.array([0.0, 0.0, 1.0, 0.0]) @ cov @ np.array([0.0, 0.0, 1.0, 0.0]) == pytest.approx(
        math.radians(5.0) ** 2, rel=1e-3)
    assert np.allclose(mean, samples.mean(0))


def test_nll_grows_away_from_the_mean_and_ignores_uninformed_dims() -> None:
    prior = pp.PosePrior(torch.zeros(6), torch.diag(torch.tensor([4.0, 4.0, 4.0, 0.0, 0.0, 0.0])), 3)
    at_mean = prior.nll(torch.zeros(2, 2, 3))
    off = torch.zeros(2, 2, 3)
    off[:, 0, 0] = 0.5
    free = torch.zeros(2, 2, 3)
    free[:, 1] = 2.0  # the second joint is not informed: no cost
    assert float(at_mean) == 0.0 and float(prior.nll(free)) == 0.0
    assert float(prior.nll(off)) == pytest.approx(0.5 * 4.0 * 0.25 / 3)


def test_informed_joints_are_the_ancestors_of_fitted_ones() -> None:
    parents = np.array([-1, 0, 1, 0, 3])
    assert pp.informed(parents, [2]).tolist() == [True, True, False, False, False]
    assert pp.informed(parents, [2, 4]).tolist() == [True, True, False, True, False]


@pytest.mark.slow
def test_dog_trot_prior_prefers_the_trot_to_the_rest_pose() -> None:
    if not pp.DOG_TROT.is_file():
        pytest.skip("../shared/data/motion/dog_mocap is not here")
    from sync4d.io.mocap import read_joint_positions

    prior = pp.dog_trot_prior("fox")
    local, keep = pp.retarget("fox", read_joint_positions(pp.DOG_TROT, num_joints=27))
    assert prior.dims == 3 * int(keep.sum()) and 0 < prior.dims < local[0].size
    trot = float(prior.nll(torch.tensor(local, dtype=torch.float32)))
    rest = float(prior.nll(torch.zeros(1, *local.shape[1:])))
    assert trot < 0.5 < rest
