"""The daemon's runner when the rig's board runs the controller (``[daemon] board_controller = true``, SI).

The board (the reference firmware's hosted build, ``make -C firmware host-hosted LIB=DIR``) ticks the
chamber library that ``hbma-ctrl codegen CONFIG --library`` generated on its own samples and holds its
commands; the daemon runs no estimator or controller. :class:`BoardSystem` stands where the chamber's
:class:`~hbma_ctrl.system.chamber.ChamberSystem` stands in the loop: each period it sets the target (the
file's schedule, or the API's setpoint) on the link, which sends it as ``TGT``, and returns the command
the board reported for the sample, so the run log, the status and the safety monitor see what the board
decided. Its estimates are the board's (height and pressure; no standard deviation: the line carries
none).
"""

from __future__ import annotations

import math

import numpy as np

from hbma_ctrl.system.base import Neutral
from hbma_ctrl.system.chamber import chamber_setpoint
from hbma_ctrl.system.rigio import safe_u
from hbma_ctrl.system.roles import controller_settings_of
from hbma_ctrl.system.board_link import BoardControlledRig

__all__ = ["BoardSystem", "board_system", "ABSENT_STATS"]

#: the controller's statistics a board does not report (None in metrics.json): its solve times and its
#: supervisor's guard activations are not on the line
ABSENT_STATS = ("solve_ms_median", "solve_ms_p99", "solve_ms_max", "guard_activations")


class BoardSystem(Neutral):
    """One chamber whose controller runs on the board (module doc): ``reference`` (m at the loop's time
    s), reachable targets ``h_range`` (lo, hi) m, pressure limit ``p_limit`` Pa, the rig's sample period
    s. :attr:`link` (a :class:`~hbma_ctrl.system.board_link.BoardControlledRig`) is set by the daemon's
    :func:`~hbma_ctrl.app.daemon.build.make_rig`."""

    kind = "chamber"
    warming = False

    def __init__(self, reference, h_range: tuple[float, float], p_limit: float, sample_period: float,
                 names=("C1",)) -> None:
        self.reference = reference
        self.h_range = (float(h_range[0]), float(h_range[1]))
        self.p_limit = float(p_limit)
        self.sample_period = float(sample_period)
        self.names = tuple(names)
        self.n = len(self.names)
        self.link: BoardControlledRig | None = None
        self.t_closed: float | None = None  # the rig time of the first tick, s
        self._target = math.nan
        self._report = None
        self._events: list[tuple[str, str]] = []
        self._ticks = 0
        self._failed = 0  # reports of a failed controller step (status 1)
        self._errors = 0  # reports of a library error (status < 0)
        self._last_status = 0

    def tick(self, t: float, p: np.ndarray, held: np.ndarray | None = None) -> np.ndarray:
        """One period at rig time t (s): the target at the loop's time goes to the link; the command (3, 1)
        the board reported for the sample of ``p`` (the safe command before its first report). ``p`` and
        ``held`` are the board's business: it ticks its controller on them itself."""
        if self.t_closed is None:
            self.t_closed = float(t)
        tl = round((float(t) - self.t_closed) / self.sample_period) * self.sample_period
        self._target = float(self.reference(tl))
        self.link.set_target(np.full(self.n, self._target))
        rep = self.link.report()
        self._report = rep
        if rep is None:
            return safe_u(self.n)
        self._ticks += 1
        status = int(max(rep.status, key=abs))
        self._failed += int(status == 1)
        self._errors += int(status < 0)
        if status != self._last_status:
            what = {0: "ok", 1: "the controller's step failed: the supervisor's fallback is out"}.get(
                status, "a library error: the board holds the chamber vented")
            self._events.append(("board_controller", f"status {status}: {what}"))
            self._last_status = status
        return np.array(rep.u, dtype=float)

    def targets(self) -> np.ndarray:
        """This period's target height per chamber, m (NaN before the first tick)."""
        return np.full(self.n, self._target)

    def effective_targets(self) -> np.ndarray:
        """The targets as sent (the board's controller reports no reach)."""
        return self.targets()

    def estimates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(height m, its std m, pressure Pa) per chamber as the board reported them; the std is NaN (not
        on the line), all NaN before the first report."""
        if self._report is None:
            return (np.full(self.n, np.nan),) * 3
        return self._report.height.copy(), np.full(self.n, np.nan), self._report.pressure.copy()

    def layers(self) -> list:
        """No layers: a single chamber."""
        return []

    def check_setpoint(self, request: dict) -> dict:
        """Heights {0: h m} -> {"applied", "clipped"}, clipped to ``h_range``; ValueError for layers or
        another chamber."""
        return chamber_setpoint(request, self.h_range)

    def apply_setpoint(self, applied: dict, t: float) -> None:
        """Hold the applied height from now on (the file's target schedule ends)."""
        h = applied.get("heights", {}).get(0)
        if h is not None:
            self.reference = lambda _t, h=float(h): h

    def take_events(self) -> list[tuple[str, str]]:
        """(kind, cause) events since the last call: changes of the board controller's status."""
        ev, self._events = self._events, []
        return ev

    def stats(self) -> dict:
        """The controller's statistics as the board reported them: ``steps`` (samples it reported),
        ``fallbacks`` (reports of a failed step), ``board_errors`` (reports of a library error), and
        :data:`ABSENT_STATS` as None; ``board_controller`` True."""
        return {"board_controller": True, "steps": self._ticks, "fallbacks": self._failed,
                "board_errors": self._errors, **{k: None for k in ABSENT_STATS}}


def board_system(section, sample_period: float) -> BoardSystem:
    """The runner of a ``[controller]`` section whose controller runs on the board: its target schedule,
    its height range and pressure limit."""
    settings = controller_settings_of(section)
    return BoardSystem(section.reference, (settings.h_min, settings.h_max), section.p_max, sample_period)
