"""The valves' minimum on-time in numpy: the oracle :class:`hbma_ctrl.runtime.pwm.MinOnTime` (which runs
:meth:`hbma_ctrl.runtime.pwm.MinOnTime.function`) is compared with. Error diffusion as the module
docstring of :mod:`hbma_ctrl.runtime.pwm` states it."""

from __future__ import annotations

import numpy as np

from hbma_ctrl.core.interfaces import Command


class MinOnTimeOracle:
    """Inlet and outlet duties each 0 or at least ``min_on`` / ``period``, a smaller one carried to the
    next period; one chamber (:meth:`shape`) or n at once (:meth:`shape_inputs`)."""

    def __init__(self, period: float, min_on: float):
        self.min_duty = float(min_on) / float(period)
        self.carry = np.zeros(2)

    def _duties(self, d: np.ndarray) -> np.ndarray:
        """Inlet and outlet duties (2 x n) as sent; updates the carry."""
        if self.carry.shape != d.shape:
            self.carry = np.zeros(d.shape)
        m = self.min_duty
        keep = (d <= 0.0) | (d >= m)
        want = d + self.carry
        out = np.where(want >= 0.5 * m, m, 0.0)  # the nearest realisable duty
        self.carry = np.where(keep, 0.0, want - out)
        return np.where(keep, d, out)

    def shape(self, command: Command) -> Command:
        """The command to send for one period."""
        u = command.as_array()
        d = self._duties(u[1:3].astype(float))
        return Command(float(u[0]), float(d[0]), float(d[1]))

    def shape_inputs(self, U: np.ndarray) -> np.ndarray:
        """The same for n chambers' plant inputs U (3 x n: speed, inlet, outlet), a new array."""
        U = np.array(U, dtype=float)
        U[1:3] = self._duties(U[1:3])
        return U
