"""The burst test's period in numpy, step by step: the oracle :class:`hbma_ctrl.runtime.burst.BurstTest`
(which runs :func:`hbma_ctrl.runtime.burst.burst_function`) is compared with. Page's CUSUM and the
lost-estimate relapses as the module docstring of :mod:`hbma_ctrl.runtime.burst` states them."""

from __future__ import annotations

import numpy as np

from hbma_ctrl.runtime.burst import BurstTestSettings


class BurstTestOracle:
    """Per-chamber CUSUM of the readings' falls below the filter's prediction, in numpy: ``update(r)``
    and ``lost(t, new)`` return the chambers each newly flagged; ``restart`` zeroes the sums at once."""

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
        """The chambers whose estimate was lost anew at time t (s) -> those newly flagged for
        ``relapses`` such episodes within ``relapse_window`` (bool (n,))."""
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
        """The sums of the chambers in ``mask`` back to 0 (flags and lost episodes kept)."""
        self.g[np.asarray(mask, dtype=bool).reshape(self.n)] = 0.0

    def reset(self, mask=None) -> None:
        """Clear the sums, flags and lost episodes of the chambers in ``mask`` (None = all)."""
        m = np.ones(self.n, dtype=bool) if mask is None else np.asarray(mask, dtype=bool).reshape(self.n)
        self.g[m] = 0.0
        self.flagged[m] = False
        for i in np.nonzero(m)[0]:
            self.why[i] = ""
            self._lost_t[i] = []


def oracle_state(test: BurstTestOracle) -> np.ndarray:
    """``test``'s state in :func:`hbma_ctrl.runtime.burst.burst_function`'s layout: g, peak, flags, then per
    chamber its newest relapses - 1 lost times, oldest first (NaN: none)."""
    keep = test.settings.relapses - 1
    times = np.full((test.n, keep), np.nan)
    for i, ts in enumerate(test._lost_t):
        ts = ts[-keep:]
        if ts:
            times[i, keep - len(ts):] = ts
    return np.concatenate([test.g, test.peak, test.flagged.astype(float), times.ravel()])
