"""A model-based burst test: a chamber losing gas faster than its valves let it (dimensionless, no I/O).

A membrane that bursts, or an outlet stuck open, empties a chamber in a few periods whatever the
valves are told. The pressure alone cannot tell that from normal work (the robot's chambers fall by a
third of their pressure while pumping, past their limit point or when a neighbour takes over their
load: :mod:`hbma_ctrl.runtime.watchdog`), but the chamber's filter can: its model predicts each
period's pressure from the valve commands the rig held, and a burst's readings fall far below that
prediction, period after period. Normal mismatch (the pump's map, the valves' timing, the membrane's
law) stays within a few of the filter's own standard deviations.

:class:`BurstTest` is Page's one-sided CUSUM over each chamber's signed normalised innovation
``r = (z - p_pred) / sqrt(S)`` (:class:`estimators.robot_ekf.ChamberEKFBank`'s ``r``):

    g <- max(0, g + min(-r - allowance, step_cap)),   flag when g >= threshold

``allowance`` is what normal work may read below the model in one period; ``step_cap`` bounds what one
reading adds, so a single wild reading (a glitch the EKF's gate rejects) cannot flag a burst alone:
with the defaults it takes at least three periods of readings 25 sigma under the model, and a fall
of 10 sigma a period takes ten. A reading the filter did not use (missing, out of range, saturated)
has r = 0 and lets g decay.

Measured (the robot's structured default rig, ``[robot] burst_sigma`` 50, README Run on a rig):
in clean runs the largest g was under 1 (the 20-seed scene sweeps, ``bench poses``); an outlet stuck
fully open is found within a few periods unless the controller was venting that chamber already (its
model then predicts the fall).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hbma_ctrl.core.params import check_range

__all__ = ["BurstTestSettings", "BurstTest"]


@dataclass(frozen=True)
class BurstTestSettings:
    """Settings of :class:`BurstTest` (in the filter's standard deviations, sigma).

    threshold : the sum of falls (beyond the allowance) that flags a burst, (0, 1e4] sigma.
    allowance : how far under the model one normal reading may fall without adding, [0, 100] sigma.
    step_cap : the most one reading adds, (0, threshold] sigma (one wild reading is not a burst).
    """

    threshold: float = 50.0
    allowance: float = 5.0
    step_cap: float = 20.0

    def validate(self) -> "BurstTestSettings":
        """Check the ranges; ValueError naming the field and its range."""
        check_range("burst", "threshold", self.threshold, 0.0, 1e4, "sigma", lo_open=True)
        check_range("burst", "allowance", self.allowance, 0.0, 100.0, "sigma")
        check_range("burst", "step_cap", self.step_cap, 0.0, self.threshold, "sigma", lo_open=True)
        return self


class BurstTest:
    """Per-chamber CUSUM of the readings' falls below the filter's prediction (module doc).

    ``update(r)`` takes the n signed normalised innovations of one period (NaN counts as 0, -inf as a
    fall at the cap) and returns
    the chambers whose sum reached the threshold this period (bool (n,)); ``flagged`` keeps every
    chamber flagged since the last :meth:`reset`, ``g`` the running sums and ``peak`` each chamber's
    largest sum (the margin to the threshold, for tuning on a rig)."""

    def __init__(self, n: int, settings: BurstTestSettings | None = None):
        self.settings = (settings or BurstTestSettings()).validate()
        self.n = int(n)
        self.g = np.zeros(self.n)
        self.peak = np.zeros(self.n)
        self.flagged = np.zeros(self.n, dtype=bool)

    def update(self, r) -> np.ndarray:
        """One period's innovations r (n,) -> the chambers newly flagged (bool (n,))."""
        s = self.settings
        rv = np.asarray(r, dtype=float).reshape(self.n)
        # +-inf go through: -inf adds the cap, +inf empties the sum
        rv = np.where(np.isnan(rv), 0.0, rv)
        self.g = np.maximum(self.g + np.minimum(-rv - s.allowance, s.step_cap), 0.0)
        self.peak = np.maximum(self.peak, self.g)
        new = (self.g >= s.threshold) & ~self.flagged
        self.flagged |= new
        return new

    def reset(self, mask=None) -> None:
        """Clear the sums and flags of the chambers in ``mask`` (bool (n,); None = all)."""
        m = np.ones(self.n, dtype=bool) if mask is None else np.asarray(mask, dtype=bool).reshape(self.n)
        self.g[m] = 0.0
        self.flagged[m] = False
