"""An open-loop recording run through the daemon: a ``[schedule]`` of pump / hold / vent steps (SI).

The daemon runs a scenario with a ``[schedule]`` table and no ``[controller]`` as a recording: each
period it writes the command of the step in force, with the daemon's safety monitor on as in a closed
loop (a reading at ``p_max_kpa`` latches the safe state) and the run log written as always, which
``hbma-ctrl fit`` reads as it is. An ``[estimator]`` table, when written, runs beside it (its
estimates fill the log's ``h_est`` columns); it never acts on the commands.

Steps (``[[schedule.step]]``, in order, ``repeat`` times), each for ``duration_s`` of rig time:

- ``pump``: compressor at ``speed_pct`` (default 100), inlet open (``inlet_duty``, default 1),
  outlet shut (``outlet_duty``, default 0); a chamber whose reading reaches ``pump_stop_kpa``
  holds for the rest of the step (the valves shut, the pump off);
- ``hold``: pump off, both valves shut;
- ``vent``: pump off, inlet shut, outlet open (``outlet_duty``, default 1).

A step drives the chamber named by ``chamber`` (the run log's name, ``C1`` for a single chamber) or,
without it, every chamber; the others keep the command they had (vented before the first step).
After the last step every chamber vents; without a duration (``[daemon] duration_s``,
``--duration-s``) the run ends there.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hbma_ctrl.core import units as U
from hbma_ctrl.core.interfaces import Command
from hbma_ctrl.core.settings import Settings, setting
from hbma_ctrl.system.rigio import safe_u

__all__ = ["Schedule", "ScheduleStep", "ScheduleSystem", "ACTIONS"]

#: the step kinds and the command each gives without overrides: (speed, inlet, outlet)
ACTIONS = {"pump": (1.0, 1.0, 0.0), "hold": (0.0, 0.0, 0.0), "vent": (0.0, 0.0, 1.0)}


@dataclass
class ScheduleStep(Settings):
    """One step of a schedule (SI; each field's unit, range and one-line doc are in its declaration)."""

    WHERE = "schedule.step"

    action: str = setting("hold", choices=tuple(ACTIONS), doc="pump, hold (valves shut) or vent")
    duration: float = setting(1.0, lo=0.0, hi=1e5, lo_open=True, unit="s", key="duration_s",
                              doc="rig time the step lasts")
    speed: float | None = setting(None, lo=0.0, hi=1.0, user="%", doc="compressor speed (pump steps; default 100 %)")
    inlet: float | None = setting(None, lo=0.0, hi=1.0, key="inlet_duty",
                                  doc="inlet valve duty (pump steps; default 1)")
    outlet: float | None = setting(None, lo=0.0, hi=1.0, key="outlet_duty",
                                   doc="outlet valve duty (pump steps default 0, vent steps 1)")
    chamber: str | None = setting(None, text=True, doc="the chamber the step drives, by name (none: every chamber)")

    def check_rules(self) -> None:
        if self.action != "pump" and (self.speed is not None or self.inlet is not None):
            raise ValueError(f"{self.WHERE}: speed_pct and inlet_duty are for pump steps (a {self.action} runs "
                             "the pump off with the inlet shut)")
        if self.action == "hold" and self.outlet is not None:
            raise ValueError(f"{self.WHERE}: outlet_duty is for pump and vent steps (a hold keeps the valves shut)")

    def command(self) -> np.ndarray:
        """(speed, inlet, outlet), 0-1."""
        d = ACTIONS[self.action]
        return np.array([d[0] if self.speed is None else self.speed, d[1] if self.inlet is None else self.inlet,
                         d[2] if self.outlet is None else self.outlet])


@dataclass
class Schedule(Settings):
    """The steps and how they run (SI; each field's unit, range and one-line doc are in its declaration)."""

    WHERE = "schedule"

    repeat: int = setting(1, integer=True, lo=1, hi=10000, doc="times the steps run, one after the other")
    pump_stop: float = setting(30e3, lo=0.0, hi=1e6, lo_open=True, unit="Pa", user="kPa",
                               doc="a pumped chamber whose reading reaches this holds for the rest of the step")
    p_max: float = setting(35e3, lo=0.0, hi=1e6, lo_open=True, unit="Pa", user="kPa",
                           doc="the safety monitor's pressure cap: a reading at or above it latches the safe state")
    steps: tuple = field(default=())

    def check_rules(self) -> None:
        if not self.steps:
            raise ValueError("schedule: no steps; add [[schedule.step]] tables (action, duration_s)")
        for i, s in enumerate(self.steps):
            try:
                s.validate()
            except ValueError as exc:
                raise ValueError(str(exc).replace("schedule.step", f"schedule.step[{i}]", 1)) from None
        if self.pump_stop >= self.p_max:
            raise ValueError(f"schedule.pump_stop_kpa = {U.to_kpa(self.pump_stop):g} must be below p_max_kpa = "
                             f"{U.to_kpa(self.p_max):g} (pumping stops before the monitor's cap)")

    @property
    def length(self) -> float:
        """Rig time of all the steps, repeats included, s."""
        return self.repeat * sum(s.duration for s in self.steps)


class ScheduleSystem:
    """The daemon's runner of a :class:`Schedule` on the chambers ``names`` (the system interface of
    :class:`hbma_ctrl.system.base.System`): ``tick(t, p, held) -> u`` (3, n). ``p_limit`` (Pa): the
    monitor's cap. ``estimator``: one chamber's filter stepped beside it (None: no estimates)."""

    kind = "schedule"
    warming = False

    def __init__(self, schedule: Schedule, names=("C1",), estimator=None):
        self.schedule = schedule
        self.names = tuple(names)
        self.n = len(self.names)
        self.p_limit = float(schedule.p_max)
        for i, s in enumerate(schedule.steps):
            if s.chamber is not None and s.chamber not in self.names:
                raise ValueError(f"[schedule] step[{i}].chamber = {s.chamber!r}: no such chamber; the chambers are "
                                 f"{', '.join(self.names)}")
        self._ends = np.cumsum([s.duration for s in schedule.steps])
        self.estimator = estimator
        self.estimate = None
        self._t0: float | None = None
        self._u = safe_u(self.n)
        self._step = -1  # index into the repeated steps, -1 before the first
        self._stopped = np.zeros(self.n, dtype=bool)  # chambers a pump step holds (pump_stop reached)
        self._events: list[tuple[str, str]] = []
        self.steps_run = 0
        self.pump_stops = 0

    def _index(self, ts: float) -> int:
        """The repeated step in force at schedule time ``ts`` (s); len(steps) * repeat after the end."""
        period = float(self._ends[-1])
        rep = int(ts // period)
        if rep >= self.schedule.repeat:
            return len(self.schedule.steps) * self.schedule.repeat
        k = int(np.searchsorted(self._ends, ts - rep * period + 1e-9, side="right"))
        return rep * len(self.schedule.steps) + min(k, len(self.schedule.steps) - 1)

    def tick(self, t: float, p: np.ndarray, held: np.ndarray | None = None) -> np.ndarray:
        """One period at rig time t (s) with the readings p (Pa, (n,)) -> the command (3, n)."""
        if self._t0 is None:
            self._t0 = float(t)
        p = np.asarray(p, dtype=float).reshape(self.n)
        if self.estimator is not None:
            h = self._u[:, 0] if held is None else np.asarray(held, dtype=float).reshape(3, self.n)[:, 0]
            self.estimate = self.estimator.step(t, float(p[0]), Command(*(float(x) for x in h)))
        k = self._index(float(t) - self._t0)
        steps = self.schedule.steps
        if k != self._step:
            self._step = k
            self._stopped[:] = False
            if k >= len(steps) * self.schedule.repeat:
                self._u = safe_u(self.n)
                self._events.append(("schedule", "the schedule ended: every chamber vents"))
            else:
                s = steps[k % len(steps)]
                cols = range(self.n) if s.chamber is None else (self.names.index(s.chamber),)
                for i in cols:
                    self._u[:, i] = s.command()
                self.steps_run += 1
                sp, inl, out = s.command()
                self._events.append(("schedule", f"step {k + 1} of {len(steps) * self.schedule.repeat}: "
                                                 f"{s.action} {s.duration:g} s, speed {100 * sp:g} %, inlet "
                                                 f"{inl:g}, outlet {out:g} ({s.chamber or 'every chamber'})"))
        if k < len(steps) * self.schedule.repeat:  # any chamber pumping, by this step or one before it
            hit = (p >= self.schedule.pump_stop) & ~self._stopped & (self._u[0] > 0)
            for i in np.flatnonzero(hit):
                self._stopped[i] = True
                self._u[:, i] = ACTIONS["hold"]
                self.pump_stops += 1
                self._events.append(("schedule", f"{self.names[i]}: {U.to_kpa(p[i]):.2f} kPa reached pump_stop_kpa "
                                                  f"{U.to_kpa(self.schedule.pump_stop):g}: held for the rest of the "
                                                  "step"))
        return self._u.copy()

    # --- what the daemon reads of a system ----------------------------------------------------------
    def take_events(self) -> list[tuple[str, str]]:
        """(kind, cause) events since the last call: each step's start, a pump stop, the end."""
        ev, self._events = self._events, []
        return ev

    def take_faults(self) -> list[tuple[str, int, str]]:
        """No faults of its own (the daemon's monitor watches the readings)."""
        return []

    def burst_peak(self) -> None:
        """No burst test."""
        return None

    def tick_timing(self) -> None:
        """Not measured."""
        return None

    def tick_parts(self) -> dict:
        """No parts."""
        return {}

    def controller_report(self) -> None:
        """No controller."""
        return None

    def targets(self) -> np.ndarray:
        """No targets: NaN per chamber."""
        return np.full(self.n, np.nan)

    def effective_targets(self) -> np.ndarray:
        """No targets to reach: NaN per chamber."""
        return self.targets()

    def estimates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(height m, its std m, pressure Pa) of the estimator beside the schedule, NaN without one."""
        e = self.estimate
        if e is None:
            return (np.full(self.n, np.nan),) * 3
        return np.array([e.h]), np.array([float(e.std.get("h", np.nan))]), np.array([e.p])

    def layers(self) -> list:
        """No layers."""
        return []

    def check_setpoint(self, request: dict) -> dict:
        """Refused: a recording runs its schedule (ValueError, the API's 422)."""
        raise ValueError("this daemon runs an open-loop [schedule] (a recording): it takes no setpoints")

    def apply_setpoint(self, applied: dict, t: float) -> None:
        """Never called: :meth:`check_setpoint` refuses every setpoint."""

    def stats(self) -> dict:
        """The schedule's counts: steps started, pump steps ended early at pump_stop_kpa."""
        return {"steps_run": self.steps_run, "pump_stops": self.pump_stops,
                "schedule_s": self.schedule.length}
