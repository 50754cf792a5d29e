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

import casadi as ca
import numpy as np

from hbma_ctrl.core.codegen import FastFunction
from hbma_ctrl.core.interfaces import Command
from hbma_ctrl.core.params import check_range

__all__ = ["MinOnTime"]


class MinOnTime:
    """Error-diffusion shaping of the inlet and outlet duties for a minimum on-time (module doc).

    ``period``: the PWM period (the rig's sample period), s; ``min_on``: the valves' minimum
    opening, s, [0, period] (0: every duty passes unchanged). One chamber (:meth:`shape`) or n at
    once (:meth:`shape_inputs`, the robot's), each valve with its own carry. Each call evaluates
    :meth:`function` (mapped over the chambers): the block a generated loop runs.
    """

    def __init__(self, period: float, min_on: float):
        check_range("controller", "valve_min_on", min_on, 0.0, period, "s")
        self.min_duty = float(min_on) / float(period)
        self.carry = np.zeros(2)  # duty owed (+) or given in advance (-) per valve (2 x n for n chambers)
        self._fns: dict = {}

    @property
    def active(self) -> bool:
        """True when a minimum on-time is set."""
        return self.min_duty > 0.0

    def _send(self, u: np.ndarray) -> np.ndarray:
        """Plant inputs u (3,) or (3 x n) as sent (a new array); updates the carry (2,) or (2 x n)."""
        cols = u.shape[1:]
        if self.carry.shape != (2, *cols):
            self.carry = np.zeros((2, *cols))
        if cols not in self._fns:
            # the map expanded to one expression graph: a third of the mapped call's time on casadi's machine
            self._fns[cols] = FastFunction(self.function().map(cols[0]).expand() if cols else self.function(),
                                           compile=False)
        sent, carry = self._fns[cols](u, self.carry)
        self.carry = carry.reshape(self.carry.shape, order="F").copy()
        return sent.reshape(u.shape, order="F").copy()

    def shape(self, command: Command) -> Command:
        """The command to send for one PWM period: duties each 0 or >= the minimum, averaging those
        asked for over the periods."""
        if not self.active:
            return command
        return Command(*(float(v) for v in self._send(command.as_array().astype(float))))

    def shape_inputs(self, U: np.ndarray) -> np.ndarray:
        """The same for n chambers' plant inputs U (3 x n: speed, inlet, outlet), a new array."""
        U = np.asarray(U, dtype=float)
        return self._send(U) if self.active else U.copy()

    def function(self, name: str = "pwm") -> ca.Function:
        """:meth:`shape` of one chamber as a casadi Function: ``pwm(u[3], carry[2]) -> (u_sent[3],
        carry_next[2])``, the inlet and outlet duties' carry as :attr:`carry` holds it (inactive: the
        command itself)."""
        u, carry = ca.SX.sym("u", 3), ca.SX.sym("carry", 2)
        if not self.active:
            return ca.Function(name, [u, carry], [u, carry], ["u", "carry"], ["u_sent", "carry_next"])
        m = self.min_duty
        sent, nxt = [u[0]], []
        for i in range(2):
            d = u[1 + i]
            keep = ca.logic_or(d <= 0.0, d >= m)
            want = d + carry[i]
            out = ca.if_else(want >= 0.5 * m, m, 0.0)
            nxt.append(ca.if_else(keep, 0.0, want - out))
            sent.append(ca.if_else(keep, d, out))
        return ca.Function(name, [u, carry], [ca.vertcat(*sent), ca.vertcat(*nxt)], ["u", "carry"],
                           ["u_sent", "carry_next"])
