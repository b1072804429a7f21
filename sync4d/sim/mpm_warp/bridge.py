"""The torch <-> Warp bridge: a whole rollout as one ``torch.autograd.Function``."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from sync4d.sim.mpm_warp.model import WarpState
from sync4d.sim.mpm_warp.solver import RolloutPlan


class RolloutFunction(torch.autograd.Function):
    """(x, v, F, C) -> (x, v, F, C) after ``plan.substeps`` substeps; differentiable in all four inputs.

    ``check`` is called with the plan and the final state after the forward pass (it raises when a substep
    diverged), before anything is returned.
    """

    @staticmethod
    def forward(
        ctx: Any, x: torch.Tensor, v: torch.Tensor, F: torch.Tensor, C: torch.Tensor, plan: RolloutPlan,
        check: Callable[[RolloutPlan, WarpState], None],
    ) -> tuple[torch.Tensor, ...]:
        store = any(ctx.needs_input_grad[:4])
        final = plan.forward(x, v, F, C, store=store)
        check(plan, final)
        ctx.plan = plan
        ctx.device = x.device
        return tuple(t.to(x.device) for t in final.to_torch())

    @staticmethod
    def backward(ctx: Any, gx: torch.Tensor, gv: torch.Tensor, gF: torch.Tensor, gC: torch.Tensor) -> Any:
        plan: RolloutPlan = ctx.plan
        grads = plan.backward([gx, gv, gF, gC], like=gx if gx is not None else torch.empty(0, device=ctx.device))
        ctx.plan = None  # free the checkpoints
        return grads[0], grads[1], grads[2], grads[3], None, None


def run_rollout(
    plan: RolloutPlan, x: torch.Tensor, v: torch.Tensor, F: torch.Tensor, C: torch.Tensor,
    check: Callable[[RolloutPlan, WarpState], None], *, timers: dict[str, float] | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Run ``plan`` on (x, v, F, C): through autograd, or, with ``timers``, forward only and profiled."""
    if timers is None:
        return RolloutFunction.apply(x, v, F, C, plan, check)
    with torch.no_grad():
        final = plan.forward(x, v, F, C, store=False, timers=timers)
        check(plan, final)
        xo, vo, Fo, Co = (t.to(x.device) for t in final.to_torch())
        return xo, vo, Fo, Co
