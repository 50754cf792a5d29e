"""Benchmarks behind ``hbma-ctrl bench ...``: each module measures one part (simulator, loop, NMPC, fit,
soak, drills, poses) and writes its JSON and plots into a run directory."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor

__all__ = ["map_jobs"]


def map_jobs(fn: Callable, jobs: list, workers: int, progress: Callable | None = None) -> list:
    """``fn(job)`` for each of ``jobs``, in their order, in up to ``workers`` processes (one: in this
    process); ``progress(result)`` after each."""
    from hbma_ctrl.sim.batch import quiet_worker

    workers = max(1, min(int(workers), len(jobs), os.cpu_count() or 1))
    out = []
    pool = ProcessPoolExecutor(max_workers=workers, initializer=quiet_worker) if workers > 1 else None
    with pool or contextlib.nullcontext() as ex:
        for r in (ex.map if ex else map)(fn, jobs):
            out.append(r)
            if progress:
                progress(r)
    return out
