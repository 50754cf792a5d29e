"""A model-based burst test: a chamber losing gas faster than its valves let it (dimensionless, no I/O).

A membrane that bursts, or an outlet stuck open, empties a chamber in a few periods whatever the
valves are told. The pressure alone cannot tell that from normal work (the robot's chambers fall by a
third of their pressure while pumping, past their limit point or when a neighbour takes over their
load: :mod:`hbma_ctrl.runtime.watchdog`), but the chamber's filter can: its model predicts each
period's pressure from the valve commands the rig held, and a burst's readings fall far below that
prediction, period after period. Normal mismatch (the pump's map, the valves' timing, the membrane's
law) stays within a few of the filter's own standard deviations.

:class:`BurstTest` is Page's one-sided CUSUM over each chamber's signed normalised innovation
``r = (z - p_pred) / sqrt(S)`` (:class:`hbma_ctrl.estimators.robot_ekf.ChamberEKFBank`'s ``r``):

    g <- max(0, g + min(-r - allowance, step_cap)),   flag when g >= threshold

``allowance`` is what normal work may read below the model in one period; ``step_cap`` bounds what one
reading adds, so a single wild reading (a glitch the EKF's gate rejects) cannot flag a burst alone:
with the defaults it takes at least three periods of readings 25 sigma under the model, and a fall
of 10 sigma a period takes ten. A reading the filter did not use (missing, out of range, saturated)
has r = 0 and lets g decay.

A burst the controller answers at once by venting (the model then predicts most of the fall) can
stay under the threshold. What follows gives it away: the chamber, pumped again towards its target,
does not rise, its filter drives its flow factor to its bound, and the loop's lost-estimate rule
vents it, releases it, and loses it again, over and over (every few tens of milliseconds in the
drills). ``relapses`` lost episodes of one chamber within ``relapse_window`` flag it too
(:meth:`BurstTest.lost`); a clean run loses an estimate rarely (one episode in the 80 runs of the
robot scenes' 20-seed sweep).

Measured (the robot's structured default rig, README Run on a rig, the burst row): in clean runs the
largest g was 2.7 (the 20-seed scene sweeps, ``bench poses``); an outlet stuck fully open was found
in 40 of 40 random drills (``hbma-ctrl bench drills``), 36 by the sum within 0.09 s and 4 by the lost
estimates within 0.29 s.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from hbma_ctrl.core.codegen import is_nan
from hbma_ctrl.core.settings import Settings, setting

__all__ = ["BurstTestSettings", "BurstTest", "burst_function", "burst_state"]


@dataclass(frozen=True)
class BurstTestSettings(Settings):
    """Settings of :class:`BurstTest` (in the filter's standard deviations, sigma; each field's range and
    one-line doc are in its declaration). One wild reading is not a burst: ``step_cap`` is at most
    the threshold."""

    WHERE = "burst"

    threshold: float = setting(50.0, lo=0.0, hi=1e4, lo_open=True, unit="sigma",
                               doc="the sum of falls (beyond the allowance) that flags a burst")
    allowance: float = setting(5.0, lo=0.0, hi=100.0, unit="sigma",
                               doc="how far under the model one normal reading may fall without adding")
    step_cap: float = setting(20.0, lo=0.0, hi=1e4, lo_open=True, unit="sigma", doc="the most one reading adds")
    relapses: int = setting(3, integer=True, lo=2, hi=1000,
                            doc="lost-estimate episodes of one chamber within relapse_window that flag it")
    relapse_window: float = setting(2.0, lo=0.0, hi=3600.0, lo_open=True, unit="s", doc="the window relapses are counted in")

    def check_rules(self) -> None:
        self.within("step_cap", hi=self.threshold)


class BurstTest:
    """Per-chamber CUSUM of the readings' falls below the filter's prediction (module doc).

    ``update(r)`` takes the n signed normalised innovations of one period (NaN counts as 0, -inf as a
    fall at the cap) and returns the chambers whose sum reached the threshold this period (bool (n,));
    ``flagged`` keeps every
    chamber flagged since the last :meth:`reset` (``why``: what flagged each, for the fault's cause),
    ``g`` the running sums and ``peak`` each chamber's largest sum (the margin to the threshold, for
    tuning on a rig). ``lost(t, new)`` counts the chambers' lost-estimate episodes (module doc)."""

    def __init__(self, n: int, settings: BurstTestSettings | None = None):
        self.settings = (settings or BurstTestSettings()).validate()
        self.n = int(n)
        self.g = np.zeros(self.n)
        self.peak = np.zeros(self.n)
        self.flagged = np.zeros(self.n, dtype=bool)
        self.why = [""] * self.n
        self._lost_t: list = [[] for _ in range(self.n)]

    def update(self, r) -> np.ndarray:
        """One period's innovations r (n,) -> the chambers newly flagged (bool (n,))."""
        s = self.settings
        rv = np.asarray(r, dtype=float).reshape(self.n)
        # +-inf go through: -inf adds the cap, +inf empties the sum
        rv = np.where(np.isnan(rv), 0.0, rv)
        self.g = np.maximum(self.g + np.minimum(-rv - s.allowance, s.step_cap), 0.0)
        self.peak = np.maximum(self.peak, self.g)
        new = (self.g >= s.threshold) & ~self.flagged
        for i in np.nonzero(new)[0]:
            self.why[i] = f"its readings fell {self.g[i]:.0f} sigma below its filter's prediction over the last periods"
        self.flagged |= new
        return new

    def lost(self, t: float, new) -> np.ndarray:
        """The chambers whose estimate was lost anew at time t (s) (bool (n,)) -> those newly flagged
        for ``relapses`` such episodes within ``relapse_window`` (bool (n,))."""
        s = self.settings
        out = np.zeros(self.n, dtype=bool)
        for i in np.nonzero(np.asarray(new, dtype=bool).reshape(self.n))[0]:
            times = [u for u in self._lost_t[i] if u > t - s.relapse_window] + [float(t)]
            self._lost_t[i] = times
            if len(times) >= s.relapses and not self.flagged[i]:
                out[i] = True
                self.flagged[i] = True
                self.why[i] = (f"its estimate was lost {len(times)} times within {t - times[0]:.2f} s: it "
                               "does not rise when pumped")
        return out

    def restart(self, mask) -> None:
        """The sums of the chambers in ``mask`` (bool (n,)) back to 0: their filters restarted. Flags and
        lost-estimate episodes are kept (a restart is one of those episodes)."""
        self.g[np.asarray(mask, dtype=bool).reshape(self.n)] = 0.0

    def reset(self, mask=None) -> None:
        """Clear the sums and flags of the chambers in ``mask`` (bool (n,); None = all)."""
        m = np.ones(self.n, dtype=bool) if mask is None else np.asarray(mask, dtype=bool).reshape(self.n)
        self.g[m] = 0.0
        self.flagged[m] = False
        for i in np.nonzero(m)[0]:
            self.why[i] = ""
            self._lost_t[i] = []


def _state_parts(n: int, settings: BurstTestSettings) -> tuple[int, int]:
    """(times kept per chamber, state length): a chamber's flag needs only its newest relapses - 1
    lost times (older ones are older than the window whenever a newer one is)."""
    keep = settings.relapses - 1
    return keep, n * (3 + keep)


def burst_state(test: BurstTest) -> np.ndarray:
    """``test``'s state in :func:`burst_function`'s layout: the sums g, their peaks, the flags (n
    each), then per chamber its newest relapses - 1 lost times, oldest first (NaN: none)."""
    keep, _ = _state_parts(test.n, test.settings)
    times = np.full((test.n, keep), np.nan)
    for i, ts in enumerate(test._lost_t):
        ts = ts[-keep:]
        if ts:
            times[i, keep - len(ts):] = ts
    return np.concatenate([test.g, test.peak, test.flagged.astype(float), times.ravel()])


def burst_function(settings: BurstTestSettings, n: int, name: str = "burst") -> ca.Function:
    """One period of :class:`BurstTest` for n chambers as ONE casadi Function (a generated loop's block)::

        burst(t, r[n], lost_new[n], restarted[n], state[S]) -> (flagged_now[n], flagged[n], state_next[S])

    ``restarted``: the chambers whose filters were restarted since the last period (the supervisor's
    release; :meth:`BurstTest.restart`, applied first); then ``update(r)`` and ``lost(t, lost_new)``
    as the class calls them. ``flagged_now`` are those flagged this period by either; ``flagged`` all
    flagged so far. State layout: :func:`burst_state`."""
    s = settings.validate()
    keep, S = _state_parts(n, s)
    SX = ca.SX
    t, r, lost_new, restarted, st = SX.sym("t"), SX.sym("r", n), SX.sym("lost_new", n), SX.sym("restarted", n), SX.sym("state", S)
    g0, peak0, flag0 = st[:n], st[n:2 * n], st[2 * n:3 * n]
    times0 = st[3 * n:]
    g, peak, flag, now, times = [], [], [], [], []
    for i in range(n):
        gi = ca.if_else(restarted[i] != 0, 0.0, g0[i])
        ri = ca.if_else(is_nan(r[i]), 0.0, r[i])  # a reading not used; +-inf go through, as in update()
        gi = ca.fmax(gi + ca.fmin(-ri - s.allowance, s.step_cap), 0.0)
        new_u = ca.logic_and(gi >= s.threshold, flag0[i] == 0)
        fl = ca.logic_or(flag0[i] != 0, new_u)
        # lost anew: the times within the window, this one appended
        ts = [times0[i * keep + j] for j in range(keep)]
        lost_i = lost_new[i] != 0
        count = 1
        for u in ts:
            count = count + ca.logic_and(ca.logic_not(is_nan(u)), u > t - s.relapse_window)
        new_l = ca.logic_and(ca.logic_and(lost_i, count >= s.relapses), ca.logic_not(fl))
        # the newest keep times: shifted by one with t appended when lost anew
        shifted = ts[1:] + [t]
        ts_next = [ca.if_else(lost_i, ca.if_else(sv > t - s.relapse_window, sv, np.nan) if j < keep - 1 else sv,
                              ts[j]) for j, sv in enumerate(shifted)]
        g.append(gi)
        peak.append(ca.fmax(peak0[i], gi))
        flag.append(ca.logic_or(fl, new_l))
        now.append(ca.logic_or(new_u, new_l))
        times += ts_next
    return ca.Function(name, [t, r, lost_new, restarted, st],
                       [ca.vertcat(*now), ca.vertcat(*flag), ca.vertcat(*g, *peak, *flag, *times)],
                       ["t", "r", "lost_new", "restarted", "state"], ["flagged_now", "flagged", "state_next"])
