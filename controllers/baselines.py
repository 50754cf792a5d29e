"""Baselines with the controller step API, so the MPC's value is measured, not claimed (SI).

- :class:`PIDController`: PID on the estimated height; a positive output runs the compressor into
  the open inlet, a negative one opens the outlet. The pump is one-directional and the outlet only
  vents: two actuators for the two signs of one PID output.
- :class:`BangBangController`: what rigs use today: bang-bang pressure control with a hysteresis
  band around a pressure setpoint; the setpoint is the nominal model's equilibrium pressure at the
  target height and the estimated load (a static calibration map), so mismatch is not corrected.

Both propose commands only: the pressure guard and the step timing are applied by
:mod:`hbma_ctrl.runtime` (``ChamberLoop``, ``Supervisor``), the same for them as for the MPC.
``p_max`` and ``guard_margin`` stay in their settings: the bang-bang setpoint is capped by them and
the runtime builds the supervisor from them. They never fail.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hbma_ctrl.core.interfaces import (
    Command,
    ControllerBase,
    ControllerSettingsDefaults,
    Estimate,
    Reference,
    check_time,
    guard_margin_setting,
    p_max_setting,
    sample_period_setting,
)
from hbma_ctrl.core.params import Actuator, Pneumatics
from hbma_ctrl.core.settings import Settings, setting
from hbma_ctrl.models.tables import PredictionModel

__all__ = ["PIDSettings", "PIDController", "BangBangSettings", "BangBangController"]


def _target(ctrl: ControllerBase, reference: Reference, h: float) -> float:
    """The reference's height, or without one the height ``h`` (m) when it went, held since (kept on
    ``ctrl._hold``)."""
    if reference.height is None:
        if ctrl._hold is None:
            ctrl._hold = h
        return ctrl._hold
    ctrl._hold = None
    return float(reference.height)


@dataclass
class PIDSettings(ControllerSettingsDefaults, Settings):
    """PID on height (SI; each field's unit, range and one-line doc are in its declaration)."""

    WHERE = "pid"

    sample_period: float = sample_period_setting()
    kp: float = setting(1000.0, lo=0.0, hi=1e7, unit="1/m", user="1/mm", doc="PID proportional gain")
    ki: float = setting(200.0, lo=0.0, hi=1e7, unit="1/(m s)", user="1/(mm s)", doc="PID integral gain")
    kd: float = setting(20.0, lo=0.0, hi=1e7, unit="s/m", user="s/mm", doc="PID derivative gain (on the estimate)")
    d_tau: float = setting(0.05, lo=0.0, hi=10.0, unit="s", doc="low-pass time constant of the derivative")
    outlet_gain: float = setting(0.5, lo=0.0, hi=100.0,
                                 doc="scales the negative output into the outlet duty (the vent is stronger)")
    p_max: float = p_max_setting()
    guard_margin: float = guard_margin_setting(1e3)

    def check_rules(self) -> None:
        self.within("guard_margin", hi=self.p_max)


class PIDController(ControllerBase):
    """PID on the estimated height with anti-windup by conditional integration."""

    def __init__(self, actuator: Actuator | None = None, pneumatics: Pneumatics | None = None,
                 settings: PIDSettings | None = None):
        self.settings = (settings or PIDSettings()).validate()
        self.reset()

    def reset(self) -> None:
        self._i = 0.0
        self._h_prev = None
        self._d = 0.0
        self._t_prev = None
        self._hold = None
        self.last: dict = {}

    def step(self, t: float, estimate: Estimate, reference: Reference,
             preview: Sequence[float] | None = None) -> Command:
        """Command for the next period from the height error (estimate vs reference); no ``preview``
        (``accepts_preview`` is False: the runtime never passes one)."""
        s = self.settings
        t = check_time(t, "pid.step")
        h = float(estimate.h) if np.isfinite(estimate.h) else (self._h_prev or 0.0)
        r = _target(self, reference, h)
        dt = s.sample_period if self._t_prev is None else max(t - self._t_prev, 1e-6)
        e = r - h
        if self._h_prev is not None:
            raw = -(h - self._h_prev) / dt
            a = 1.0 if s.d_tau <= 0 else min(1.0, dt / s.d_tau)
            self._d += a * (raw - self._d)
        v = s.kp * e + s.ki * self._i + s.kd * self._d
        # integrate only while the output is not saturated in the direction of the error
        if not ((v >= 1.0 and e > 0) or (v <= -1.0 / max(s.outlet_gain, 1e-9) and e < 0)):
            self._i += e * dt
        if v > 0:
            cmd = np.array([min(v, 1.0), 1.0, 0.0])
        else:
            cmd = np.array([0.0, 0.0, min(-v * s.outlet_gain, 1.0)])
        self._h_prev, self._t_prev = h, t
        self.last = {"reference_used": r, "status": "ok"}
        return Command(*(float(c) for c in cmd))

    def stats(self) -> dict:
        """What the controller reports itself (timing, fallbacks and guard counts come from the runtime)."""
        return {"variant": "pid", "horizon": None, "fallbacks": 0, "target_clipped_steps": 0}


@dataclass
class BangBangSettings(ControllerSettingsDefaults, Settings):
    """Bang-bang pressure control with hysteresis (SI; each field's unit, range and one-line doc are in its
    declaration). The setpoint is capped at p_max - guard_margin."""

    WHERE = "bang_bang"

    sample_period: float = sample_period_setting()
    band: float = setting(500.0, lo=0.0, hi=1e5, unit="Pa", user="kPa", doc="bang-bang hysteresis half-band")
    speed: float = setting(1.0, lo=0.0, hi=1.0, lo_open=True, doc="compressor speed while pumping")
    p_max: float = p_max_setting()
    guard_margin: float = guard_margin_setting(1e3)
    load_max: float = setting(10.0, lo=0.0, hi=200.0, lo_open=True, unit="N", doc="largest load force of the static map")

    def check_rules(self) -> None:
        self.within("guard_margin", hi=self.p_max)


class BangBangController(ControllerBase):
    """Pump when p < setpoint - band, vent when p > setpoint + band, hold (all closed) between."""

    def __init__(self, actuator: Actuator, pneumatics: Pneumatics, settings: BangBangSettings | None = None,
                 model: PredictionModel | None = None):
        self.settings = (settings or BangBangSettings()).validate()
        self.model = model or PredictionModel(actuator, pneumatics, load_max=self.settings.load_max)
        self.reset()

    def reset(self) -> None:
        self._state = 0  # +1 pumping, -1 venting, 0 holding
        self._hold = None
        self.last: dict = {}

    def setpoint(self, h: float, W: float) -> float:
        """Static map: equilibrium gauge pressure (Pa) at height h (m) under load W (N)."""
        pth = self.model.path(W)
        if h <= 0:
            return 0.0
        return float(np.interp(h, pth["h"], pth["p"]))

    def step(self, t: float, estimate: Estimate, reference: Reference,
             preview: Sequence[float] | None = None) -> Command:
        """Hysteresis on the estimated pressure around the mapped setpoint; no ``preview``
        (``accepts_preview`` is False: the runtime never passes one)."""
        s = self.settings
        check_time(t, "bang_bang.step")
        r = _target(self, reference, estimate.h)
        W = max(float(estimate.F), 0.0) if np.isfinite(estimate.F) else 0.0
        p_set = min(self.setpoint(r, W), s.p_max - s.guard_margin - s.band)
        p = float(estimate.p) if np.isfinite(estimate.p) else s.p_max
        if p < p_set - s.band:
            self._state = 1
        elif p > p_set + s.band:
            self._state = -1
        elif (self._state == 1 and p >= p_set) or (self._state == -1 and p <= p_set):
            self._state = 0
        cmd = {1: np.array([s.speed, 1.0, 0.0]), -1: np.array([0.0, 0.0, 1.0]),
               0: np.zeros(3)}[self._state]
        self.last = {"reference_used": r, "pressure_setpoint": p_set, "status": "ok"}
        return Command(*(float(c) for c in cmd))

    def stats(self) -> dict:
        """What the controller reports itself (timing, fallbacks and guard counts come from the runtime)."""
        return {"variant": "bang_bang", "horizon": None, "fallbacks": 0, "target_clipped_steps": 0}
