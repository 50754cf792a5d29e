"""When a command acts, as the pressure sensor sees it: the valves' switching delay and the sensor's lag.

Why: a solenoid valve opens or shuts a few milliseconds after its command, and a pressure sensor
behind a tube reads the chamber a few milliseconds late. At a 10 ms sample period both are a large
part of a period. A model that takes the command as acting at once sees the chamber's pressure rise
start too early: the start-up calibration then fits a dead volume 20-35 % too large, and the EKF's
lift-off detector takes the missing early rise for a membrane lifting at zero load (a 400 g load
that never leaves the plate is then estimated as a free cap at the target). Modelled here as pure
dead times, which is what the estimator and the calibration need (the flow over each period), not
the rig's own structure (``hbma_ctrl.sim.rig`` has a first-order sensor lag and a minimum on-time):

- the valves act ``valve_delay + sensor_delay`` after their command;
- the pump's speed acts ``sensor_delay`` after it (it is driven directly; only the sensor is late).

A delayed output of a time-invariant system is the system driven by the delayed input, so the
sensor's delay is carried by the inputs and the model's pressure is compared with the reading as
it is. :class:`CommandTiming` turns the commands held over each period into the command acting,
averaged over the same period (SI: seconds; commands are (speed, inlet, outlet) in [0, 1]).
"""

from __future__ import annotations

import math
from typing import Any

import casadi as ca
import numpy as np

from hbma_ctrl.core.params import check_range
from hbma_ctrl.core.settings import setting

__all__ = ["CommandTiming", "acting_average", "check_delays", "acting_function", "acting_state",
           "sensor_delay_setting", "valve_delay_setting"]

#: delays allowed, s: up to ten 10 ms periods (a slower valve or sensor is another rig)
DELAY_MAX = 0.1


def valve_delay_setting(default: float) -> Any:
    """The valves' switching delay, s, [0, DELAY_MAX]; the scenario's ``valve_delay_ms``."""
    return setting(default, lo=0.0, hi=DELAY_MAX, unit="s", user="ms",
                   doc="the valves act this long after their command (datasheet)")


def sensor_delay_setting(default: float) -> Any:
    """The pressure sensor's lag, s, [0, DELAY_MAX]; the scenario's ``sensor_delay_ms``."""
    return setting(default, lo=0.0, hi=DELAY_MAX, unit="s", user="ms", doc="the pressure sensor reads this long late")


def check_delays(where: str, valve_delay: float, sensor_delay: float) -> None:
    """Refuse a valve or sensor delay (s) outside [0, DELAY_MAX], naming ``where`` (the section)."""
    check_range(where, "valve_delay", valve_delay, 0.0, DELAY_MAX, "s")
    check_range(where, "sensor_delay", sensor_delay, 0.0, DELAY_MAX, "s")


def _acting_terms(n_hist: int, k: int, period: float, delay: float) -> list:
    """How :func:`acting_average` weighs its commands: (j, w) in the order it sums them, j = 0 for the
    command held now and j >= 1 for ``history[-j]``, w the time (s) it acts within the window; the
    first term is always the command held now (its weight may be 0)."""
    span = k * period
    # the window [-span - delay, -delay] of the held-command function (t = 0 now): u_new holds over
    # (-span, 0], history[-j] over (-span - j T, -span - (j - 1) T], the oldest before that
    lo, hi = -span - delay, -delay
    terms = [(0, max(0.0, hi - max(lo, -span)))]
    end = -span  # end of the current history segment
    for j in range(1, n_hist + 1):
        start = end - period if j < n_hist else -math.inf
        w = max(0.0, min(hi, end) - max(lo, start))
        if w > 0.0:
            terms.append((j, w))
        end = start
        if end <= lo:
            break
    if not n_hist:
        terms.append((0, max(0.0, min(hi, -span) - lo)))  # nothing before: the first command always held
    return terms


def acting_average(history: list, u_new: np.ndarray, k: int, period: float, delay: float) -> np.ndarray:
    """The command acting over the last ``k`` periods, averaged, when it acts ``delay`` s after sent.

    ``history``: the commands held over the periods before these (oldest first, one per period;
    the oldest stands for all earlier time); ``u_new``: the command held over the last k periods.
    Every component is delayed by the same ``delay`` (s, >= 0)."""
    u_new = np.asarray(u_new, dtype=float)
    if delay <= 0.0 or k <= 0:
        return u_new.copy()
    acc = np.zeros_like(u_new)
    vmin, vmax = u_new.copy(), u_new.copy()
    for j, w in _acting_terms(len(history), k, period, delay):
        h = u_new if j == 0 else np.asarray(history[-j], dtype=float)
        acc += w * h
        vmin, vmax = np.minimum(vmin, h), np.maximum(vmax, h)
    # a weighted mean lies between its values; rounding must not put a command past 1
    return np.clip(acc / (k * period), vmin, vmax)


class CommandTiming:
    """The command acting over each period (averaged), given the commands sent (module doc).

    ``acting(u, k)``: ``u`` held for the last ``k`` periods (k >= 1; 0 records it without a period
    passing, as at a filter's first reading); returns (speed, inlet, outlet) acting on average over
    those periods; ``u`` may also be 3 x n (n chambers' commands, the robot's bank): the same per
    column. ``valve_delay`` and ``sensor_delay`` in s, [0, 0.1]; both 0: the command itself.
    """

    def __init__(self, period: float, valve_delay: float = 0.0, sensor_delay: float = 0.0):
        check_delays("estimator", valve_delay, sensor_delay)
        self.period = float(period)
        self.speed_delay = float(sensor_delay)
        self.valve_delay = float(valve_delay) + float(sensor_delay)
        # periods of history the longer delay reaches back (+1: the partly covered one)
        self._keep = int(math.ceil(max(self.speed_delay, self.valve_delay) / self.period - 1e-12)) + 1
        self._hist: list = []
        # one period (k = 1) with the history full, every step after the first few: the command acting is
        # a fixed weighted mean of the last keep + 1 commands sent, so its weights are computed once
        # (acting_average on unit commands); the Python loop cost a third of an EKF step
        # (plain floats: on three components and a few commands numpy's per-call cost is most of it)
        w = np.vstack([self._weights(self.speed_delay), *[self._weights(self.valve_delay)] * 2]).T
        # per component: the (index, weight) of each command that weighs (oldest first; a zero weight
        # adds nothing to the sum and does not bound the mean)
        self._terms = [tuple((i, float(w[i, j])) for i in range(w.shape[0]) if w[i, j] > 0.0) for j in range(3)]

    def _weights(self, delay: float) -> np.ndarray:
        """acting_average's weight of each of the last keep + 1 commands (oldest first) for k = 1."""
        n = self._keep + 1
        return np.array([acting_average([np.eye(n)[j, i:i + 1] for i in range(self._keep)], np.eye(n)[j, -1:], 1,
                                         self.period, delay)[0] for j in range(n)])

    @property
    def active(self) -> bool:
        """True when any delay is modelled (else ``acting`` returns the command itself)."""
        return self.valve_delay > 0.0

    def acting(self, u, k: int = 1) -> np.ndarray:
        """The command acting, averaged over the last k periods, for ``u`` held over them."""
        if not isinstance(u, np.ndarray) or u.dtype != np.float64:
            u = np.asarray(u, dtype=float)
        if k == 1 and u.shape == (3,) and len(self._hist) == self._keep and self.active:
            # one period on a full history (every step after the first few): a fixed weighted mean of
            # the last keep + 1 commands, in plain floats (numpy's per-call cost on three components
            # and a few commands would be most of it)
            cur = u.tolist()  # kept in the history
            H = self._hist + [cur]
            out = [0.0, 0.0, 0.0]
            for j, terms in enumerate(self._terms):
                v = 0.0
                lo = hi = H[terms[0][0]][j]
                for i, wi in terms:
                    x = H[i][j]
                    v += wi * x
                    if x < lo:
                        lo = x
                    elif x > hi:
                        hi = x
                # the weighted mean, clipped to the commands it weighs (rounding must not put one past 1)
                out[j] = lo if v < lo else (hi if v > hi else v)
            del H[0]
            self._hist = H
            return np.array(out)
        u = np.array(u, dtype=float)  # a copy: kept in the history
        u = u.reshape(3) if u.ndim < 2 else u.reshape(3, -1)
        if not self.active:
            return u
        out = u.copy()
        if k > 0:
            out[0] = acting_average([h[:1] for h in self._hist], u[:1], k, self.period, self.speed_delay)[0]
            out[1:] = acting_average([h[1:] for h in self._hist], u[1:], k, self.period, self.valve_delay)
        n = min(int(k), self._keep) if k > 0 else 1
        self._hist = (self._hist + [u.tolist()] * n)[-self._keep:]
        return out

    def reset(self) -> None:
        """Forget the commands sent (a new run)."""
        self._hist = []


def acting_state(timing: CommandTiming, n: int | None = None) -> tuple[np.ndarray, float | np.ndarray]:
    """The (hist, fill) inputs of :func:`acting_function` that stand for ``timing``'s commands sent so
    far: hist column-major 3 x keep, oldest first, zeros before the first command, and fill the
    history's length. With ``n`` (a timing fed 3 x n commands, the robot's bank): the inputs of the
    Function mapped over the n chambers, hist 3 x (keep n) with chamber i's block in columns
    i keep .. (i + 1) keep - 1 (column-major, flat) and fill (n,)."""
    keep, past = timing._keep, timing._hist
    if n is None:
        hist = np.zeros((3, keep))
        if past:
            hist[:, keep - len(past):] = np.asarray(past, dtype=float).T
        return hist.ravel(order="F"), float(len(past))
    hist = np.zeros((3, n, keep))  # component, chamber, age (oldest first)
    if past:
        hist[:, :, keep - len(past):] = np.moveaxis(np.asarray(past, dtype=float).reshape(len(past), 3, n), 0, -1)
    return hist.reshape(3, n * keep).ravel(order="F"), np.full(n, float(len(past)))


def acting_function(timing: CommandTiming, name: str = "acting") -> ca.Function:
    """:meth:`CommandTiming.acting` for one period (k = 1) as a casadi Function, for loops without Python:

        acting(u[3], hist[3 keep], fill[1]) -> (u_acting[3], hist_next[3 keep], fill_next[1])

    ``hist`` the last ``keep`` commands sent (oldest first, column-major 3 x keep), of which the newest
    ``fill`` count (the history's length in :class:`CommandTiming`, 0..keep). It sums as ``acting``
    does on each path (its fixed weights on a full history, :func:`acting_average` on a shorter one), so
    it gives the same bits."""
    keep = timing._keep
    u, hist, fill = ca.SX.sym("u", 3), ca.SX.sym("hist", 3, keep), ca.SX.sym("fill")
    if not timing.active:
        return ca.Function(name, [u, hist, fill], [u, hist, fill], ["u", "hist", "fill"],
                           ["u_acting", "hist_next", "fill_next"])
    H = [hist[:, i] for i in range(keep)] + [u]  # the fast path's list: oldest first, u last
    full = []
    for j, terms in enumerate(timing._terms):
        v = 0.0
        vals = [H[i][j] for i, _ in terms]
        for (i, wi), x in zip(terms, vals):
            v = v + wi * x
        lo, hi = vals[0], vals[0]
        for x in vals[1:]:
            lo, hi = ca.fmin(lo, x), ca.fmax(hi, x)
        full.append(ca.fmin(ca.fmax(v, lo), hi))
    out = ca.vertcat(*full)
    for n in range(keep - 1, -1, -1):  # a shorter history: acting_average on its newest n commands
        short = []
        for comp, delay in ((0, timing.speed_delay), (1, timing.valve_delay), (2, timing.valve_delay)):
            if delay <= 0.0:
                short.append(u[comp])
                continue
            acc, lo, hi = 0.0, u[comp], u[comp]
            for j, w in _acting_terms(n, 1, timing.period, delay):
                h = u[comp] if j == 0 else hist[comp, keep - j]
                acc = acc + w * h
                lo, hi = ca.fmin(lo, h), ca.fmax(hi, h)
            short.append(ca.fmin(ca.fmax(acc / timing.period, lo), hi))
        out = ca.if_else(fill == n, ca.vertcat(*short), out)
    nxt = ca.horzcat(hist[:, 1:], u)
    return ca.Function(name, [u, hist, fill], [out, nxt, ca.fmin(fill + 1, keep)], ["u", "hist", "fill"],
                       ["u_acting", "hist_next", "fill_next"])
