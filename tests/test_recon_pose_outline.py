"""The quadruped fit's full-resolution image terms: zero (surface) and near zero (outline) at the truth, larger
for a pose that is off."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tests.test_recon_pose import _template_clip


def test_outline_terms_are_lowest_at_the_truth(shared_data: Path) -> None:
    import torch

    from sync4d.recon.pose import quadruped_fit as qf

    truth, _, camera, masks, _ = _template_clip()
    cfg = qf.QuadrupedFitConfig(surface_weight=1.0, outline_weight=1.0)
    prob = qf.QuadrupedProblem(masks, camera, cfg)
    frames = np.arange(len(masks))

    def terms(params: qf.Params) -> tuple[float, float]:
        with torch.no_grad():
            _, verts = qf.pose_body(prob.tt, params)
            uv, radius = qf.projected_samples(prob, verts, None, params["log_scale"].exp())
            surface, outline = qf.outline_terms(prob, frames, uv, radius)
        return float(surface), float(outline)

    at_truth = terms(truth)
    bent = {k: v.detach().clone() for k, v in truth.items()}
    bent["local"][:, prob.tt.template.names.index("fl_upper"), 2] += 0.8  # one fore leg swung forward
    off = terms(bent)
    assert at_truth[0] < 0.02 and at_truth[1] < 0.05, at_truth
    assert off[0] > 5 * max(at_truth[0], 1e-3) and off[1] > 10 * at_truth[1], (at_truth, off)


def test_quadruped_climb_needs_a_clip() -> None:
    """sync4d_tools.quadruped_climb: --clip is required (argparse exits 2 before any work)."""
    import pytest

    from sync4d_tools import quadruped_climb

    with pytest.raises(SystemExit) as err:
        quadruped_climb.main([])
    assert err.value.code == 2
