"""Valve duties a solenoid valve with a minimum opening can realise (SI, no I/O).

Why: a valve driven by PWM at the sample period cannot open for less than its minimum on-time; a
shorter pulse is lost (or lengthened by the driver). Near a target the MPC asks for a trickle (an
inlet duty of 5 % = 0.5 ms at 10 ms) that such a valve never opens for: on the structured rig (2 ms
minimum) the 400 g membrane then sat 0.6 mm under its target with the MPC asking for the same lost
trickle every period. :class:`MinOnTime` realises a small duty on average instead: each valve's
duty below the minimum is quantised to 0 or the minimum, carrying the difference to the next period
(first-order error diffusion, a sigma-delta modulator), so over a few periods the valve passes what
was asked. A duty of 0 or at least the minimum passes unchanged and clears the carry (a command to
shut stays shut: no pulse after a vent or a safety cut). The pump's speed is not a valve: unchanged.
"""

from __future__ import annotations

import numpy as np

from hbma_ctrl.core.interfaces import Command
from hbma_ctrl.core.params import check_range

__all__ = ["MinOnTime"]


class MinOnTime:
    """Error-diffusion shaping of the inlet and outlet duties for a minimum on-time (module doc).

    ``period``: the PWM period (the rig's sample period), s; ``min_on``: the valves' minimum
    opening, s, [0, period] (0: every duty passes unchanged).
    """

    def __init__(self, period: float, min_on: float):
        check_range("controller", "valve_min_on", min_on, 0.0, period, "s")
        self.min_duty = float(min_on) / float(period)
        self.carry = np.zeros(2)  # duty owed (+) or given in advance (-) per valve

    @property
    def active(self) -> bool:
        """True when a minimum on-time is set."""
        return self.min_duty > 0.0

    def shape(self, command: Command) -> Command:
        """The command to send for one PWM period: duties each 0 or >= the minimum, averaging those
        asked for over the periods."""
        if not self.active:
            return command
        u = command.as_array()
        m = self.min_duty
        for i in (1, 2):
            d = float(u[i])
            if d <= 0.0 or d >= m:
                self.carry[i - 1] = 0.0
                continue
            want = d + self.carry[i - 1]
            out = m if want >= 0.5 * m else 0.0  # the nearest realisable duty
            self.carry[i - 1] = want - out
            u[i] = out
        return Command(float(u[0]), float(u[1]), float(u[2]))

    def reset(self) -> None:
        """Forget the carried duty."""
        self.carry[:] = 0.0
