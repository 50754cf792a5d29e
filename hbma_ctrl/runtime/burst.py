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
(:meth:`BurstTest.step`); a clean run loses an estimate rarely (one episode in the 80 runs of the
robot scenes' 20-seed sweep).

Measured (the robot's structured default rig; docs/results/drills.md and docs/results/poses.md): in clean runs the
largest g was 2.7 (the 20-seed scene sweeps, ``bench poses``); an outlet stuck fully open was found
in 40 of 40 random drills (``hbma-ctrl bench drills``), 36 by the sum within 0.09 s and 4 by the lost
estimates within 0.29 s.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from hbma_ctrl.core.codegen import FastFunction, is_nan
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
    """Per-chamber CUSUM of the readings' falls below the filter's prediction (module doc); each period
    is one call of :func:`burst_function` (the block a generated loop runs).

    ``step(t, r, lost)`` takes the n signed normalised innovations of one period (NaN counts as 0,
    -inf as a fall at the cap) and the chambers whose estimate was lost anew, and returns the
    chambers flagged this period (bool (n,)); ``flagged`` are the chambers flagged since the last
    :meth:`reset` (``why``: what flagged each, for the fault's cause), ``g`` the running sums and
    ``peak`` each chamber's largest sum (the margin to the threshold, for tuning on a rig)."""

    def __init__(self, n: int, settings: BurstTestSettings | None = None):
        self.settings = (settings or BurstTestSettings()).validate()
        self.n = int(n)
        self._keep, size = _state_parts(self.n, self.settings)
        #: the state in :func:`burst_function`'s layout (:func:`burst_state`)
        self.state = np.concatenate([np.zeros(3 * self.n), np.full(size - 3 * self.n, np.nan)])
        self.why = [""] * self.n
        self._restarted = np.zeros(self.n)
        self._fn = FastFunction(burst_function(self.settings, self.n), compile=False)

    @property
    def g(self) -> np.ndarray:
        """The running sums, sigma (n,)."""
        return self.state[:self.n]

    @property
    def peak(self) -> np.ndarray:
        """Each chamber's largest sum since it was made, sigma (n,)."""
        return self.state[self.n:2 * self.n]

    @property
    def flagged(self) -> np.ndarray:
        """The chambers flagged since the last reset (bool (n,))."""
        return self.state[2 * self.n:3 * self.n] > 0.5

    def step(self, t: float, r, lost) -> np.ndarray:
        """One period at time t (s): the innovations r (n,), the chambers whose estimate was lost anew
        (bool (n,)) -> the chambers newly flagged (bool (n,)); the restarts since the last period
        are applied first."""
        n, keep = self.n, self._keep
        times0 = self.state[3 * n:].reshape(n, keep)
        now, _, state = self._fn(t, r, lost, self._restarted, self.state)
        new = now > 0.5
        for i in np.nonzero(new)[0]:
            # a chamber is flagged by its sum first; else by its relapses, the oldest kept time the first
            if state[i] >= self.settings.threshold:
                self.why[i] = f"its readings fell {state[i]:.0f} sigma below its filter's prediction over the last periods"
            else:
                self.why[i] = (f"its estimate was lost {keep + 1} times within {t - times0[i, 0]:.2f} s: it "
                               "does not rise when pumped")
        self.state = state.copy()
        self._restarted[:] = 0.0
        return new

    def restart(self, mask) -> None:
        """The sums of the chambers in ``mask`` (bool (n,)) back to 0 at the next step: their filters
        restarted. Flags and lost-estimate episodes are kept (a restart is one of those episodes)."""
        self._restarted[np.asarray(mask, dtype=bool).reshape(self.n)] = 1.0

    def reset(self, mask=None) -> None:
        """Clear the sums, flags and lost-estimate episodes of the chambers in ``mask`` (bool (n,); None = all)."""
        m = np.ones(self.n, dtype=bool) if mask is None else np.asarray(mask, dtype=bool).reshape(self.n)
        n = self.n
        self.state[:n][m] = 0.0
        self.state[2 * n:3 * n][m] = 0.0
        self.state[3 * n:].reshape(n, self._keep)[m] = np.nan
        for i in np.nonzero(m)[0]:
            self.why[i] = ""


def _state_parts(n: int, settings: BurstTestSettings) -> tuple[int, int]:
    """(times kept per chamber, state length): a chamber's flag needs only its newest relapses - 1
    lost times (older ones are older than the window whenever a newer one is)."""
    keep = settings.relapses - 1
    return keep, n * (3 + keep)


def burst_state(test: BurstTest) -> np.ndarray:
    """``test``'s state in :func:`burst_function`'s layout (a copy): the sums g, their peaks, the flags (n
    each), then per chamber its newest relapses - 1 lost times, oldest first (NaN: none)."""
    return test.state.copy()


def burst_function(settings: BurstTestSettings, n: int, name: str = "burst") -> ca.Function:
    """One period of :class:`BurstTest` for n chambers as ONE casadi Function (a generated loop's block)::

        burst(t, r[n], lost_new[n], restarted[n], state[S]) -> (flagged_now[n], flagged[n], state_next[S])

    ``restarted``: the chambers whose filters were restarted since the last period (the supervisor's
    release; :meth:`BurstTest.restart`), their sums zeroed first; then the sums take r and flag at
    the threshold, and a chamber lost anew for the ``relapses``-th time within the window, not
    flagged yet, is flagged. ``flagged_now`` are those flagged this period by either; ``flagged``
    all flagged so far. State layout: :func:`burst_state`."""
    s = settings.validate()
    keep, S = _state_parts(n, s)
    SX = ca.SX
    t, r, lost_new, restarted, st = SX.sym("t"), SX.sym("r", n), SX.sym("lost_new", n), SX.sym("restarted", n), SX.sym("state", S)
    g0, peak0, flag0 = st[:n], st[n:2 * n], st[2 * n:3 * n]
    times0 = st[3 * n:]
    g, peak, flag, now, times = [], [], [], [], []
    for i in range(n):
        gi = ca.if_else(restarted[i] != 0, 0.0, g0[i])
        ri = ca.if_else(is_nan(r[i]), 0.0, r[i])  # a reading not used; +-inf go through
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
