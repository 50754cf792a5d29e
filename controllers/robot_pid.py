"""Pressure-PID baseline for the robot: one PID per chamber on its measured pressure (SI).

The target height of each chamber is turned into a target pressure by the nominal model (the
pressure on the chamber's load path at that height, :meth:`hbma_ctrl.models.bank.ChamberBank.pressure_at_height`), and a
PID drives the measured pressure there: a positive output is the supply ``a`` (pump / inlet duty),
a negative one the outlet duty ``o``. Same decision interface as
:class:`hbma_ctrl.controllers.robot_mpc.RobotNMPC` and the same topologies.

What it cannot do, by construction: past the balloon limit point the pressure *falls* as the
membrane grows, so a target height on the far branch has a target pressure that is also met on the
near branch — the PID, rising from rest, stops there (a lower height); and if it were started on
the far branch, any pressure deficit makes it pump, which lowers the pressure further (positive
feedback: pressure control is unstable there). The closed-loop scenes show it beside the NMPC.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hbma_ctrl.core.interfaces import RobotControllerBase
from hbma_ctrl.core.settings import Settings, setting

__all__ = ["RobotPIDSettings", "RobotPressurePID"]


@dataclass(frozen=True)
class RobotPIDSettings(Settings):
    """The chambers' pressure PIDs (SI; each field's unit, range and one-line doc are in its declaration)."""

    WHERE = "robot_pid"

    kp: float = setting(1.0 / 8e3, lo=0.0, hi=1.0, unit="1/Pa", doc="proportional gain")
    ki: float = setting(1.0 / 8e3 / 0.4, lo=0.0, hi=1.0, unit="1/(Pa s)", doc="integral gain")
    kd: float = setting(0.0, lo=0.0, hi=1.0, unit="s/Pa", doc="derivative gain")
    sample_period: float = setting(0.01, lo=1e-4, hi=1.0, unit="s", doc="control period")
    deadband: float = setting(0.0, lo=0.0, hi=1e4, unit="Pa", doc="no action within this of the target pressure")


class RobotPressurePID(RobotControllerBase):
    """n pressure PIDs; ``step(p_meas, W, h_ref) -> (a, o)`` (see module doc): a
    :class:`~hbma_ctrl.core.interfaces.RobotReadingsController` that never fails and keeps no plan."""

    #: its step takes the pressure readings
    feedback = "readings"

    def __init__(self, model, n: int, settings: RobotPIDSettings | None = None):
        self.s = (settings or RobotPIDSettings()).validate()
        self.model = model
        self.n = n
        self.integ = np.zeros(n)
        self.prev_e = None

    def targets(self, W, h_ref) -> np.ndarray:
        """Target pressures (Pa) for target heights h_ref (m) under loads W (N)."""
        return self.model.pressure_at_height(np.asarray(h_ref, dtype=float).reshape(self.n),
                                             self.model.clip_load(W))

    def step(self, p_meas, W, h_ref):
        """Supply and outlet decisions (n,) each from the measured pressures (Pa), loads (N), targets (m)."""
        s = self.s
        p = np.nan_to_num(np.asarray(p_meas, dtype=float).reshape(self.n), nan=0.0)
        pref = self.targets(W, h_ref)
        e = pref - p
        e = np.where(np.abs(e) < s.deadband, 0.0, e)
        de = np.zeros(self.n) if self.prev_e is None else (e - self.prev_e) / s.sample_period
        self.prev_e = e
        v = s.kp * e + self.integ + s.kd * de
        # conditional integration (anti-windup): only while the output is not saturated that way
        grow = s.ki * e * s.sample_period
        sat = ((v >= 1) & (grow > 0)) | ((v <= -1) & (grow < 0))
        self.integ = np.where(sat, self.integ, np.clip(self.integ + grow, -1, 1))
        v = np.clip(v, -1, 1)
        a = np.maximum(v, 0.0)
        o = np.maximum(-v, 0.0)
        if self.model.topology == "shared" and a.sum() > 1:
            a = a / a.sum()
        return a, o
