"""Bounded step-timing statistics: a ring buffer of the last K samples plus streaming count and max.

A daemon runs for days; a list of every step time grows without bound. :class:`StepStats` keeps the
last ``capacity`` samples (median and p99 are over those) and a streaming count and maximum over
all samples. With ``capacity`` >= the number of samples the numbers equal
:func:`hbma_ctrl.controllers.mpc_settings.timing_stats` of the full list (same numpy calls on the same values).
"""

from __future__ import annotations

import numpy as np

__all__ = ["StepStats"]


class StepStats:
    """Ring buffer of the last ``capacity`` samples (any unit; callers use ms or s) with streaming n and max."""

    def __init__(self, capacity: int = 4096):
        if not isinstance(capacity, int) or isinstance(capacity, bool) or capacity < 1:
            raise ValueError(f"StepStats.capacity = {capacity!r} must be an integer >= 1")
        self.capacity = capacity
        self._buf = np.zeros(capacity)
        self._next = 0
        self.n = 0
        self.max = float("nan")

    def add(self, value: float) -> None:
        """Record one sample (O(1), no allocation)."""
        v = float(value)
        self._buf[self._next] = v
        self._next = (self._next + 1) % self.capacity
        self.n += 1
        self.max = v if self.n == 1 else max(self.max, v)

    def values(self) -> np.ndarray:
        """The buffered samples, oldest first (a copy; at most ``capacity``)."""
        if self.n < self.capacity:
            return self._buf[:self.n].copy()
        return np.concatenate([self._buf[self._next:], self._buf[:self._next]])

    def summary(self) -> dict:
        """{"median", "p99", "max", "n"}: median and p99 over the buffer, max and n over every sample;
        NaN (n = 0) when empty."""
        if self.n == 0:
            return {"median": float("nan"), "p99": float("nan"), "max": float("nan"), "n": 0}
        a = self.values()
        return {"median": float(np.median(a)), "p99": float(np.percentile(a, 99)), "max": float(self.max),
                "n": int(self.n)}
