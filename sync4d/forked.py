"""Independent CPU jobs run side by side in forked processes.

A forked child inherits the parent's memory, so a job's inputs (a reconstruction's scene, tens of MB) are not
copied or pickled; only each job's result comes back through a pipe, pickled. Each child runs torch on one
thread. Where ``fork`` does not exist (Windows, macOS's default), in a daemonic process or with ``workers <= 1``
the jobs run here, in order: the results are the same either way.
"""

from __future__ import annotations

import multiprocessing
import os
import pickle
import traceback
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

T = TypeVar("T")


def cpu_seconds() -> float:
    """CPU time of this process and of its finished (joined) children [s]: the forked jobs' work included."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def usable_workers(requested: int) -> int:
    """``requested`` (0: one per CPU core this process may use) capped by those cores, at least 1."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity on this OS (macOS, Windows): every core
        cores = os.cpu_count() or 1
    return max(1, min(requested, cores) if requested > 0 else cores)


def _child(job: Callable[[], Any], pipe: Any) -> None:
    import torch

    torch.set_num_threads(1)
    # plain pickle: multiprocessing's own pickler hands torch tensors over as shared-memory handles, which
    # die with the child
    try:
        pipe.send_bytes(pickle.dumps((True, job())))
    except BaseException:  # the parent re-raises it with the child's traceback
        pipe.send_bytes(pickle.dumps((False, traceback.format_exc())))
    finally:
        pipe.close()


def run_forked(jobs: Sequence[Callable[[], T]], workers: int) -> list[T]:
    """Every job's result, in order; up to ``workers`` jobs at a time, each in a forked child.

    Raises:
        RuntimeError: a job raised in its child (the message carries the child's traceback).
    """
    # a daemonic process (a pool's worker) may not have children: there the jobs run in turn
    if (workers <= 1 or len(jobs) <= 1 or "fork" not in multiprocessing.get_all_start_methods()
            or multiprocessing.current_process().daemon):
        return [job() for job in jobs]
    ctx = multiprocessing.get_context("fork")
    results: list[T] = []
    for first in range(0, len(jobs), workers):
        running = []
        for job in jobs[first:first + workers]:
            receive, send = ctx.Pipe(duplex=False)
            process = ctx.Process(target=_child, args=(job, send), daemon=True)
            process.start()
            send.close()
            running.append((process, receive))
        for process, receive in running:
            ok, value = pickle.loads(receive.recv_bytes())
            process.join()
            if not ok:
                raise RuntimeError(f"a forked job failed:\n{value}")
            results.append(value)
    return results
