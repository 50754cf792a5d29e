"""Work done in a forked child process beside this one's, its result a file the work writes.

The protocol's figures take about as long as its simulation and need none of its results (Fig. 6) or
only the logs already in memory (Figs. 7 and 9): on a machine with a second core they are drawn by a
forked child while this process simulates or writes the trials' CSVs. A fork shares the parent's
memory, so nothing is pickled or imported again.
"""

from __future__ import annotations

import multiprocessing as mp
import os
from typing import Any, Callable

__all__ = ["Forked"]


def _run(fn: Callable[..., Any], args: tuple) -> None:
    try:
        fn(*args)
    except BaseException:  # noqa: BLE001 - the parent redoes the work and reports the error itself
        os._exit(1)


class Forked:
    """``fn(*args)`` started in a forked child; :meth:`join` waits for it. When the child failed, or
    where fork is not available (or only one CPU is), ``join`` runs ``fn`` in this process, so the
    work is never lost and an error is raised here, once."""

    def __init__(self, fn: Callable[..., Any], *args: Any):
        self.fn, self.args = fn, args
        self.proc = None
        if "fork" in mp.get_all_start_methods() and (os.cpu_count() or 1) > 1:
            try:
                self.proc = mp.get_context("fork").Process(target=_run, args=(fn, args), daemon=True)
                self.proc.start()
            except OSError:
                self.proc = None

    def join(self) -> None:
        """Wait for the child; redo the work here when it did not succeed."""
        if self.proc is not None:
            self.proc.join()
            ok = self.proc.exitcode == 0
            self.proc.close()
            self.proc = None
            if ok:
                return
        self.fn(*self.args)
