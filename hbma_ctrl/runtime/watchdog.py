"""The rig daemon's safety monitor: raw readings and sent commands -> faults -> safe state (SI, no I/O).

:class:`SafetyMonitor` is independent of the estimator and the controller: it sees only what the
rig reported (pressures, freshness) and the commands the loop actually sent, so a wrong model or a
diverged filter cannot hide a fault from it. Once any fault is found, :attr:`SafetyMonitor.latched`
is True: the loop must send the safe command (pump off, inlets closed, outlets open) every period
until a person resets the monitor (:meth:`SafetyMonitor.reset`).

Call order, once per period: read the rig, then ``check(t, readings, u_sent, deadline_missed)``
with ``u_sent`` the command the loop last wrote (the one held while the pressure in these readings
built up; the safe command before the first write).

Detections (per chamber unless stated; N = a count of periods of ``sample_period``; "delay" =
periods from the first faulty reading to the check that reports the fault):

=================  ==========================================================  ===================
kind               condition                                                   delay (periods)
=================  ==========================================================  ===================
over_pressure      a reading >= p_max                                          0
sensor_missing     ``nan_periods`` readings in a row NaN                       nan_periods - 1
sensor_frozen      ``stale_periods`` readings in a row not fresh, or           stale_periods - 1
                   ``same_value_periods`` identical values in a row            (same_value_periods
                                                                               - 2 when fresh)
out_of_range       ``range_periods`` readings in a row below vacuum_floor or   range_periods - 1
                   above sensor_range
overrun            (whole rig) ``missed_deadlines`` deadlines missed in a row  missed_deadlines - 1
leak               pumping (pump >= pump_min, inlet >= inlet_min, outlet <=    burst: < 10; a fall
                   outlet_closed) and the pressure (mean of smooth_periods     of leak_drop within
                   readings) fell by more than leak_drop, and by more than     leak_window: at most
                   leak_fraction of it, from its highest value since pumping   leak_window / Ts
                   began, at most leak_window s back
pump_failure       pumping, and over the last pump_effort of it (speed x       pump_effort / (pump
                   inlet duty x time) the pressure rose by less than           x inlet) / Ts (25
                   pump_rise from below pump_low                               at full pump)
=================  ==========================================================  ===================

Readings out of range take no part in the leak and pump tests. The leak and pump thresholds are
chosen above what the mismatched rig shows in normal operation: inflating past the membrane's limit
point lets the pressure fall while pumping (at most about 1.3 kPa/s at full pump on the default
actuator with 400 g, i.e. 0.65 kPa over leak_window), and an unloaded membrane starts slowly (the
slowest case measured, r1 12.5 mm t0 2 mm at 20 % speed and half inlet duty, gains 0.27 kPa in 1 s;
the test waits for pump_effort, 2.5 s at that rate, by when the pressure has risen several kPa).
A stiffer membrane pushed past its limit point falls faster (the robot's chambers driven to their
far branch at 7 mm: 1.3-1.4 kPa within leak_window, as much as a leak): there ``leak_p_max`` keeps
the leak test below the limit-point pressure. The robot's chambers fall further in normal work
(past their limit point and when a neighbour of their layer takes over its load: falls of up to
11 kPa, 35 % of the pressure, within leak_window in four soaks): there ``leak_fraction`` makes the
test one of a burst or a leak that more than halves the pressure while pumping.

A large leak that starts at low pressure keeps the pressure from rising at all: it is reported as
pump_failure (from pressure alone the two look the same); a sensor reading that jumps down by more
than leak_drop while pumping is reported as a leak. Not detected here (none of them raises the
pressure): a small leak that the controller makes up for by pumping; a failed pump or a closed
stuck inlet above pump_low.

:attr:`SafetyMonitor.closest` keeps how near the trend tests came to firing (the largest pressure
fall while pumping, Pa, and as a fraction of the pressure it fell from where that exceeded
leak_drop; the least rise where the pump test applied, Pa): the margins to check when
tuning the thresholds on a rig.

Each fault is reported once when its condition starts (a condition that clears and comes back is
reported again); :attr:`SafetyMonitor.counts` counts reports by kind.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from hbma_ctrl.core.settings import Settings, setting

__all__ = ["FAULT_KINDS", "Fault", "MonitorSettings", "SafetyMonitor"]

#: every kind a monitor reports: the detections of the module doc, then the external causes
#: :meth:`SafetyMonitor.raise_fault` takes ("burst": the robot loop's model-based burst test,
#: :mod:`hbma_ctrl.runtime.burst`, which this monitor, independent of the estimator, does not run)
FAULT_KINDS = ("over_pressure", "sensor_missing", "sensor_frozen", "out_of_range", "overrun", "leak",
               "pump_failure", "link_loss", "exception", "signal", "external", "burst")


@dataclass
class MonitorSettings(Settings):
    """Thresholds of :class:`SafetyMonitor` (SI; each field's unit, range and one-line doc are in its
    declaration).

    same_value_periods None is off (for a coarsely quantised sensor that can repeat a value while
    nothing moves). leak_fraction: a burst empties the chamber, while normal work can lower a pressure
    by a share of it (the robot's chambers pass their limit point and take over each other's load).
    leak_p_max: set it below the actuator's limit-point pressure (e.g. 0.8 times the model's lowest
    one) when the controller drives chambers past the limit point (the robot's far branch): there
    pumping makes the pressure fall as a leak would. pump_effort is the sum of pump speed x inlet duty
    x period (0.25 s = a quarter second at full speed, fully open). pump_test off: the robot's
    chambers inflate from flat for seconds at about 1 kPa, which pressure alone cannot tell from a
    failed pump.
    """

    WHERE = "monitor"

    p_max: float = setting(35e3, lo=0.0, hi=1e6, lo_open=True, unit="Pa",
                           doc="hard pressure cap: a reading at or above it is an over-pressure at once")
    sensor_range: float = setting(35e3, lo=0.0, hi=1e6, lo_open=True, unit="Pa",
                                  doc="the sensor's top: a reading above it is out of range")
    vacuum_floor: float = setting(-5e3, lo=-1e5, hi=0.0, unit="Pa",
                                  doc="the lowest plausible gauge pressure: below it is out of range")
    sample_period: float = setting(0.01, lo=0.0, hi=1.0, lo_open=True, unit="s",
                                   doc="the loop's period (turns the windows into periods)")
    nan_periods: int = setting(10, integer=True, lo=1, doc="NaN readings in a row that make a missing sensor")
    stale_periods: int = setting(10, integer=True, lo=1, doc="not-fresh readings in a row that make a frozen sensor")
    same_value_periods: int | None = setting(25, integer=True, lo=2, optional=True,
                                             doc="identical readings in a row that make a frozen sensor (None: off)")
    range_periods: int = setting(3, integer=True, lo=1, doc="out-of-range readings in a row that make a fault")
    missed_deadlines: int = setting(3, integer=True, lo=1, doc="missed loop deadlines in a row that make an overrun")
    pump_min: float = setting(0.2, lo=0.0, hi=1.0, lo_open=True, doc="pump speed at which a chamber counts as pumped")
    inlet_min: float = setting(0.5, lo=0.0, hi=1.0, lo_open=True, doc="inlet duty at which the inlet counts as open")
    outlet_closed: float = setting(0.02, lo=0.0, hi=1.0, doc="outlet duty at or below which the outlet counts as closed")
    smooth_periods: int = setting(5, integer=True, lo=1, doc="readings averaged before the leak and pump tests")
    leak_window: float = setting(0.5, lo=0.0, hi=60.0, lo_open=True, unit="s",
                                 doc="how far back the leak test looks for the highest pressure while pumping")
    leak_drop: float = setting(1.2e3, lo=0.0, hi=1e6, lo_open=True, unit="Pa", doc="pressure fall while pumping that makes a leak")
    leak_test: bool = setting(True, doc="run the leak test at all")
    leak_fraction: float = setting(0.0, lo=0.0, hi=1.0,
                                   doc="the fall must also exceed this fraction of its highest pressure (0: leak_drop alone)")
    leak_p_max: float | None = setting(None, lo=0.0, hi=1e6, lo_open=True, unit="Pa",
                                       doc="the leak test applies only below this pressure (None: at every pressure)")
    pump_effort: float = setting(0.25, lo=0.0, hi=60.0, lo_open=True, unit="s",
                                 doc="how much pumping from a low pressure must fail to raise it")
    pump_low: float = setting(5e3, lo=0.0, hi=1e6, unit="Pa", doc="the pump test applies from pressures below this")
    pump_rise: float = setting(0.3e3, lo=0.0, hi=1e6, unit="Pa",
                               doc="the least pressure rise expected over the last pump_effort of pumping from below pump_low")
    pump_test: bool = setting(True, doc="run the pump test at all")

    def check_rules(self) -> None:
        if self.leak_window < self.smooth_periods * self.sample_period:
            raise ValueError("monitor.leak_window must be at least smooth_periods * sample_period")

    def periods(self, seconds: float) -> int:
        """A window in s as a whole number of periods (at least 1)."""
        return max(1, int(round(seconds / self.sample_period)))


@dataclass(frozen=True)
class Fault:
    """One fault: time t (s), kind (one of FAULT_KINDS), chamber index (None = the whole rig) and a
    cause for people (numbers in kPa)."""

    t: float
    kind: str
    chamber: int | None
    cause: str


def _kpa(p: float) -> str:
    return f"{p / 1e3:.2f} kPa"


class SafetyMonitor:
    """The monitor of the module doc for ``n`` chambers. No I/O; all state on the instance."""

    def __init__(self, settings: MonitorSettings | None = None, n: int = 1):
        if not isinstance(n, int) or isinstance(n, bool) or n < 1:
            raise ValueError(f"monitor.n = {n!r} must be an integer >= 1")
        self.settings = (settings or MonitorSettings()).validate()
        self.n = n
        s = self.settings
        self._w_leak = s.periods(s.leak_window)
        self._hist_len = max(self._w_leak + 1, s.smooth_periods)
        # the longest run the pump test looks back over: pump_effort at the least effort that counts
        least = s.pump_min * s.inlet_min * s.sample_period
        self._run_len = int(np.ceil(s.pump_effort / least)) + s.smooth_periods + 2
        self.reset()

    def reset(self) -> None:
        """Forget everything: no fault, nothing latched, counts zero (a person cleared the fault)."""
        n = self.n
        self.latched = False
        self.faults: list[Fault] = []
        self.counts: dict = {k: 0 for k in FAULT_KINDS}
        self._nan = np.zeros(n, dtype=int)
        self._stale = np.zeros(n, dtype=int)
        self._same = np.zeros(n, dtype=int)
        self._range = np.zeros(n, dtype=int)
        self._missed = 0
        self._pumping = np.zeros(n, dtype=int)  # periods in a row the chamber was pumped
        # per chamber, over the current pumping run: (pumping so far, s of full-pump equivalent; reading, Pa)
        self._run: list = [deque(maxlen=self._run_len) for _ in range(n)]
        self._prev: np.ndarray | None = None
        self._hist: deque = deque(maxlen=self._hist_len)  # raw readings, newest last
        self._on: dict = {}  # (kind, chamber) -> condition held at the last check
        self.closest: dict = {"leak_drop": 0.0, "leak_fraction": 0.0, "pump_rise": float("inf")}

    # --- reporting --------------------------------------------------------------------------------
    def _edge(self, out: list, t: float, kind: str, chamber: int | None, cond: bool, cause) -> None:
        key = (kind, chamber)
        was = self._on.get(key, False)
        self._on[key] = bool(cond)
        if cond and not was:
            out.append(self._report(t, kind, chamber, cause() if callable(cause) else cause))

    def _report(self, t: float, kind: str, chamber: int | None, cause: str) -> Fault:
        f = Fault(float(t), kind, chamber, cause)
        self.faults.append(f)
        self.counts[kind] += 1
        self.latched = True
        return f

    def raise_fault(self, t: float, kind: str, cause: str, chamber: int | None = None) -> Fault:
        """Report a fault found outside the monitor (link loss, an exception in the loop, a signal, a
        burst the loop's filters found in ``chamber``) at time t (s); latches the safe state."""
        if kind not in FAULT_KINDS:
            raise ValueError(f"fault kind '{kind}': allowed {', '.join(FAULT_KINDS)}")
        return self._report(t, kind, chamber, str(cause))

    # --- the checks --------------------------------------------------------------------------------
    def check(self, t: float, readings, u_sent, deadline_missed: bool = False) -> list[Fault]:
        """The new faults at time t (s) (see the module doc).

        readings : has ``p`` ((n,) Pa, NaN = missing) and ``fresh`` ((n,) bool; empty = all fresh).
        u_sent : the command last written, (3, n): pump speed, inlet duty, outlet duty per chamber.
        deadline_missed : whether the loop missed this period's deadline.
        """
        s, n = self.settings, self.n
        out: list[Fault] = []
        p = np.asarray(readings.p, dtype=float).reshape(n)
        fresh = np.asarray(getattr(readings, "fresh", ()), dtype=bool)
        if fresh.size != n:
            fresh = np.ones(n, dtype=bool)
        u = np.asarray(u_sent, dtype=float).reshape(3, n)
        finite = np.isfinite(p)

        # over-pressure: at once
        for i in np.nonzero(finite)[0]:
            self._edge(out, t, "over_pressure", int(i), p[i] >= s.p_max,
                       lambda i=i: f"reading {_kpa(p[i])} >= p_max {_kpa(s.p_max)}")
        for i in np.nonzero(~finite)[0]:
            self._on[("over_pressure", int(i))] = False

        # missing
        self._nan = np.where(finite, 0, self._nan + 1)
        for i in range(n):
            self._edge(out, t, "sensor_missing", i, self._nan[i] >= s.nan_periods,
                       lambda i=i: f"no reading for {self._nan[i]} periods")

        # frozen: not fresh, or the very same value again
        self._stale = np.where(fresh, 0, self._stale + 1)
        same = finite & (self._prev == p) if self._prev is not None else np.zeros(n, dtype=bool)
        self._same = np.where(same, self._same + 1, 0)
        self._prev = p.copy()
        for i in range(n):
            stale = self._stale[i] >= s.stale_periods
            rep = s.same_value_periods is not None and self._same[i] + 1 >= s.same_value_periods
            self._edge(out, t, "sensor_frozen", i, stale or rep,
                       lambda i=i, stale=stale: (f"no fresh sample for {self._stale[i]} periods" if stale else
                                                 f"the same reading {_kpa(p[i])} {self._same[i] + 1} times"))

        # out of range
        bad = finite & ((p < s.vacuum_floor) | (p > s.sensor_range))
        self._range = np.where(bad, self._range + 1, 0)
        for i in range(n):
            self._edge(out, t, "out_of_range", i, self._range[i] >= s.range_periods,
                       lambda i=i: f"reading {_kpa(p[i])} outside [{_kpa(s.vacuum_floor)}, "
                                   f"{_kpa(s.sensor_range)}] for {self._range[i]} periods")

        # loop overrun
        self._missed = self._missed + 1 if deadline_missed else 0
        self._edge(out, t, "overrun", None, self._missed >= s.missed_deadlines,
                   lambda: f"{self._missed} deadlines missed in a row")

        # leak and pump failure: pressure trends while pumping into a closed chamber (readings out of
        # range are left out: that fault has its own test)
        pumped = (u[0] >= s.pump_min) & (u[1] >= s.inlet_min) & (u[2] <= s.outlet_closed)
        p_tr = np.where(bad, np.nan, p)
        prev = self._hist[-1] if self._hist else p_tr
        self._hist.append(p_tr.copy())
        H = np.array(self._hist)  # (k, n), newest last
        m = s.smooth_periods
        for i in range(n):
            if not pumped[i]:
                self._pumping[i] = 0
            else:
                if self._pumping[i] == 0:
                    self._run[i].clear()
                    self._run[i].append((0.0, float(prev[i])))  # the reading before the first pumped period
                self._pumping[i] += 1
                cum = self._run[i][-1][0] + float(u[0, i] * u[1, i]) * s.sample_period
                self._run[i].append((cum, float(p_tr[i])))
            leak, pump, why = False, False, ""
            run = int(self._pumping[i])
            # the readings since pumping began (the one before the first pumped period included)
            L = min(run, self._w_leak)
            if run and L + 1 >= m:
                means = _running_mean(H[-(L + 1):, i], m)
                ok = means.size > 0 and np.isfinite(means[-1])
                top = float(np.max(means[np.isfinite(means)])) if ok else np.nan
                if s.leak_test and np.isfinite(top) and (s.leak_p_max is None or top < s.leak_p_max):
                    drop = top - means[-1]
                    self.closest["leak_drop"] = max(self.closest["leak_drop"], float(drop))
                    if drop > s.leak_drop:
                        self.closest["leak_fraction"] = max(self.closest["leak_fraction"], float(drop / top))
                    if drop > s.leak_drop and drop > s.leak_fraction * top:
                        leak, why = True, (f"pressure fell {_kpa(drop)} to {_kpa(means[-1])} while pumping "
                                           "into a closed chamber")
            self._edge(out, t, "leak", i, leak, why)
            if run and s.pump_test:
                # the pressure pump_effort of pumping ago (the latest reading that far back) and now
                cum, vals = np.array(self._run[i]).T
                back = np.nonzero(cum[-1] - cum >= s.pump_effort - 1e-12)[0]
                if back.size:
                    j = back[-1]
                    with np.errstate(all="ignore"):
                        first, last = _nanmean(vals[j:j + m]), _nanmean(vals[-m:])
                    if np.isfinite(first) and np.isfinite(last) and first < s.pump_low:
                        self.closest["pump_rise"] = min(self.closest["pump_rise"], float(last - first))
                    if (np.isfinite(first) and np.isfinite(last) and first < s.pump_low
                            and last - first < s.pump_rise):
                        pump, why = True, (f"pressure rose {_kpa(last - first)} from {_kpa(first)} in "
                                           f"{len(vals) - 1 - j} periods of pumping into a closed chamber")
            self._edge(out, t, "pump_failure", i, pump, why)
        return out


def _nanmean(a: np.ndarray) -> float:
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else float("nan")


def _running_mean(x: np.ndarray, m: int) -> np.ndarray:
    """Means of every m consecutive values (NaN-aware; NaN where a block has no value)."""
    ok = np.isfinite(x)
    c = np.concatenate([[0.0], np.cumsum(np.where(ok, x, 0.0))])
    k = np.concatenate([[0], np.cumsum(ok)])
    tot, cnt = c[m:] - c[:-m], k[m:] - k[:-m]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cnt > 0, tot / np.maximum(cnt, 1), np.nan)
