"""The one driver of a system on a lockstep rig: read, tick, write, once per sample period (SI).

:func:`run_lockstep` is what every simulated closed loop runs: the scenes, the benches and tuning. A
real-time loop (the rig daemon) paces the same three calls with a wall clock and its watchdog.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from hbma_ctrl.core import interrupt
from hbma_ctrl.core.params import check_range
from hbma_ctrl.system.base import System
from hbma_ctrl.system.rigio import Readings, RigIO

__all__ = ["run_lockstep"]


def run_lockstep(system: System, rig: RigIO, duration: float,
                 before: Callable[[int, float], None] | None = None,
                 ticked: Callable[[int, Readings, np.ndarray], None] | None = None,
                 advanced: Callable[[int, Readings, np.ndarray], bool | None] | None = None,
                 clock: Callable[[Readings], float] | None = None) -> int:
    """Drive ``system`` (its ``tick`` and ``warming``) on the lockstep ``rig`` until its closed loop has run
    ``duration`` s; the start-up calibration's periods come first and do not count. Returns the number of closed-loop periods run.

    Each closed-loop period k (at loop time t = k periods, s): ``before(k, t)`` (a scene puts its
    scheduled loads on the rig here), the rig's readings, the system's tick, ``ticked(k, readings, u)``
    (the state the readings were taken in: a scene logs it here), the command written to the rig, which
    advances it one period, and ``advanced(k, readings, u)`` (the state the period ended in); a true
    return of ``advanced`` ends the run there (a diverged plant). No hook runs in a calibration period.
    ``clock(readings)``: the time (s) the system is ticked at; None = the readings' own stamp.
    """
    check_range("run_lockstep", "duration", duration, 0.0, 1e5, "s", lo_open=True)
    Ts = rig.sample_period
    n = int(round(duration / Ts))
    k = 0
    while k < n:
        interrupt.check()  # an ending signal lost inside a solver ends the run here
        closed = not system.warming
        if closed and before is not None:
            before(k, k * Ts)
        r = rig.read()
        u = system.tick(r.t if clock is None else clock(r), r.p, r.held)
        if closed and ticked is not None:
            ticked(k, r, u)
        rig.write(u)
        if closed:
            k += 1
            if advanced is not None and advanced(k - 1, r, u):
                break
    return k
