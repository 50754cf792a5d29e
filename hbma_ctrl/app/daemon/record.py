"""The daemon's ``log.mcap``: a :class:`hbma_ctrl.app.logs.signals.SignalLog` fed by the loop each period,
with the simulated rig's true state beside the loop's signals (topics: :mod:`hbma_ctrl.app.logs.signals`)."""

from __future__ import annotations

import time
from pathlib import Path

from hbma_ctrl.app.logs.signals import GROUPS, SignalLog
from hbma_ctrl.runtime.stats import StepStats

__all__ = ["DaemonRecord"]


class DaemonRecord(SignalLog):
    """The daemon loop's MCAP log.

    path, names, design, metadata, attachments, queue_size : as :class:`hbma_ctrl.app.logs.signals.SignalLog`'s.
    truth : a callable giving the simulated rig's true state (``h`` m, ``p`` Pa, ``t`` s), None for a rig
        without one (then the log has no truth topics).
    """

    def __init__(self, path: Path | str, names, design=None, truth=None, metadata: dict | None = None,
                 attachments: dict | None = None, queue_size: int = 65536):
        groups = GROUPS if truth is not None else tuple(g for g in GROUPS if g != "truth")
        super().__init__(path, names, groups, design, metadata, attachments, queue_size)
        self.truth = truth
        #: the loop thread's time in :meth:`step` (copying the period's arrays, reading the simulated
        #: rig's truth, queueing), s: all that the log costs the loop itself; wall clock (preemptions
        #: by other processes included) and the thread's CPU time
        self.handoff_s = StepStats(8192)
        self.handoff_cpu_s = StepStats(8192)

    def step(self, t: float, mode: str, p, p_est, h, h_std, target, u, step_s: float, faults: str) -> None:
        """Queue one period of the loop (SI arrays per chamber, ``u`` (3, n), ``step_s`` s, ``faults`` the
        latched kinds) with the rig's true state now; never blocks (a full queue drops and counts it)."""
        c0, cpu0 = time.perf_counter(), time.thread_time()
        tr = None
        if self.truth is not None:
            d = self.truth()
            tr = (float(d.get("t", t)), d["h"], d["p"])
        self.period(t, p=p, p_est=p_est, h=h, h_std=h_std, target=target, u=u, truth=tr, mode=mode,
                    step_s=step_s, faults=faults)
        self.handoff_s.add(time.perf_counter() - c0)
        self.handoff_cpu_s.add(time.thread_time() - cpu0)

    def close(self, stats: dict | None = None, calibration: dict | None = None) -> dict:
        """As :meth:`hbma_ctrl.app.logs.signals.SignalLog.close`, the counts with ``handoff_us_median``,
        ``handoff_us_p99`` (the loop's wall time handing a period over, us) and ``handoff_cpu_us_median``,
        ``handoff_cpu_us_p99`` (its thread's CPU time in it, us)."""
        out = super().close(stats, calibration)
        for key, st in (("handoff_us", self.handoff_s), ("handoff_cpu_us", self.handoff_cpu_s)):
            h = st.summary()
            out[f"{key}_median"], out[f"{key}_p99"] = h["median"] * 1e6, h["p99"] * 1e6
        return out
