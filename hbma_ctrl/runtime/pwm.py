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

from hbma_ctrl.core.interfaces import Command
from hbma_ctrl.core.params import check_range

__all__ = ["MinOnTime"]


class MinOnTime:
    """Error-diffusion shaping of the inlet and outlet duties for a minimum on-time (module doc).

    ``period``: the PWM period (the rig's sample period), s; ``min_on``: the valves' minimum
    opening, s, [0, period] (0: every duty passes unchanged). One chamber (:meth:`shape`) or n at
    once (:meth:`shape_inputs`, the robot's), each valve with its own carry.
    """

    def __init__(self, period: float, min_on: float):
        check_range("controller", "valve_min_on", min_on, 0.0, period, "s")
        self.min_duty = float(min_on) / float(period)
        self.carry = np.zeros(2)  # duty owed (+) or given in advance (-) per valve (2 x n for n chambers)

    @property
    def active(self) -> bool:
        """True when a minimum on-time is set."""
        return self.min_duty > 0.0

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
        """The command to send for one PWM period: duties each 0 or >= the minimum, averaging those
        asked for over the periods."""
        if not self.active:
            return command
        u = command.as_array()
        d = self._duties(u[1:3].astype(float))
        return Command(float(u[0]), float(d[0]), float(d[1]))

    def shape_inputs(self, U: np.ndarray) -> np.ndarray:
        """The same for n chambers' plant inputs U (3 x n: speed, inlet, outlet), a new array."""
        U = np.array(U, dtype=float)
        if self.active:
            U[1:3] = self._duties(U[1:3])
        return U

    def forget(self, valve: int, which: np.ndarray) -> None:
        """Drop the duty carried for ``valve`` (0 inlet, 1 outlet) of the chambers where ``which``
        (n,) is true: a trickle the caller decided not to send."""
        if self.carry.ndim == 2:
            self.carry[valve] = np.where(which, 0.0, self.carry[valve])
        elif bool(np.any(which)):
            self.carry[valve] = 0.0

    def reset(self) -> None:
        """Forget the carried duty."""
        self.carry = np.zeros_like(self.carry)

    def function(self, name: str = "pwm") -> ca.Function:
        """:meth:`shape` of one chamber as a casadi Function, for loops without Python:
        ``pwm(u[3], carry[2]) -> (u_sent[3], carry_next[2])``, the inlet and outlet duties' carry as
        :attr:`carry` holds it (the same operations, so the same bits; inactive: the command itself)."""
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
