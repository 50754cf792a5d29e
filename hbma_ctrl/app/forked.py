"""Work done in a forked child process beside this one's, its result a file the work writes.

The protocol's figures take about as long as its simulation and need none of its results (Fig. 6) or
only a few logs already in memory (Figs. 7 and 9): on a machine with a second core they are drawn by a
forked child while this process simulates and writes the trials' CSVs. A fork shares the parent's
memory, so nothing is imported twice in this process; what the parent produces after the fork (the
logs) reaches the child through :meth:`Forked.send`.
"""

from __future__ import annotations

import multiprocessing as mp
import os
from typing import Any, Callable

__all__ = ["Forked"]


def _run(fn: Callable[..., Any], args: tuple, conn, parents_end) -> None:
    if parents_end is not None:
        parents_end.close()  # so that a parent gone before sending ends recv() with EOFError, not a hang
    try:
        fn(*((conn.recv,) if conn is not None else ()), *args)
    except BaseException:  # noqa: BLE001 - the parent redoes the work and reports the error itself
        os._exit(1)


class Forked:
    """``fn(*args)`` started in a forked child; :meth:`join` waits for it. When the child failed, or
    where fork is not available (or only one CPU is), ``join`` runs ``fn`` in this process, so the
    work is never lost and an error is raised here, once.

    With ``inbox=True`` the work is called as ``fn(recv, *args)``: each ``recv()`` returns the next
    object the parent passed to :meth:`send` (in order, waiting for it), so the child can start
    before everything it needs exists.
    """

    def __init__(self, fn: Callable[..., Any], *args: Any, inbox: bool = False):
        self.fn, self.args, self.inbox = fn, args, inbox
        self.sent: list[Any] = []
        self.proc = self.conn = None
        if "fork" in mp.get_all_start_methods() and (os.cpu_count() or 1) > 1:
            try:
                ctx = mp.get_context("fork")
                child_end, self.conn = ctx.Pipe(duplex=False) if inbox else (None, None)
                self.proc = ctx.Process(target=_run, args=(fn, args, child_end, self.conn), daemon=True)
                self.proc.start()
                if child_end is not None:
                    child_end.close()
            except OSError:
                self.proc = self.conn = None

    def send(self, obj: Any) -> None:
        """Hand ``obj`` to the work's next ``recv()`` (kept here too, for a redo in this process)."""
        if not self.inbox:
            raise ValueError("Forked.send: this work was started without inbox=True")
        self.sent.append(obj)
        if self.conn is not None:
            try:
                self.conn.send(obj)
            except OSError:  # the child has ended (failed): join redoes the work here
                self.conn.close()
                self.conn = None

    def join(self) -> None:
        """Wait for the child; redo the work here when it did not succeed."""
        if self.conn is not None:
            self.conn.close()
            self.conn = None
        if self.proc is not None:
            self.proc.join()
            ok = self.proc.exitcode == 0
            self.proc.close()
            self.proc = None
            if ok:
                return
        if self.inbox:
            sent = iter(self.sent)
            self.fn(lambda: next(sent), *self.args)
        else:
            self.fn(*self.args)
