"""sync4d.forked: independent jobs in forked processes give what they give in this process."""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest
import torch

from sync4d.forked import run_forked, usable_workers


def _job(data: np.ndarray, k: int) -> dict[str, torch.Tensor]:
    """A job that reads a large inherited array and returns a tensor built from it."""
    return {"sum": torch.as_tensor(data[k::5].sum()), "row": torch.as_tensor(data[k, :3].copy())}


def test_forked_jobs_return_in_order_and_equal_to_running_them_here() -> None:
    data = np.random.default_rng(0).normal(size=(200_000, 8))  # 12.8 MB: inherited, never pickled
    jobs = [partial(_job, data, k) for k in range(5)]
    here, forked = run_forked(jobs, 1), run_forked(jobs, 2)
    assert len(forked) == 5
    for a, b in zip(here, forked):
        assert torch.equal(a["sum"], b["sum"]) and torch.equal(a["row"], b["row"])


def _fails() -> None:
    raise ValueError("bad start 3")


def test_a_failing_forked_job_raises_with_its_message() -> None:
    with pytest.raises(RuntimeError, match="bad start 3"):
        run_forked([_fails, _fails], 2)


def test_usable_workers_is_capped_by_the_cores() -> None:
    assert usable_workers(1) == 1
    assert 1 <= usable_workers(0) == usable_workers(10_000)


def _spin() -> int:
    total = 0
    for i in range(3_000_000):
        total += i
    return total


def test_cpu_seconds_count_the_forked_jobs() -> None:
    """The children's CPU time is counted once they are joined (the reconstruction reports it as its own)."""
    from sync4d.forked import cpu_seconds

    import time

    start, own = cpu_seconds(), time.process_time()
    run_forked([_spin, _spin, _spin, _spin], 2)
    total, parent = cpu_seconds() - start, time.process_time() - own
    assert total > 0.2  # the children's work, counted
    # this process only waited: its own CPU (the forks' copy-on-write faults grow with its memory, some tens of ms
    # late in a test session) is a small part of the jobs', which it would exceed had it run them itself
    assert parent < 0.25 * total
