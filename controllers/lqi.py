"""LQI: linear-quadratic state feedback with integral action on the linearised chamber (SI).

The plant is the controllers' gas-mass model (:class:`hbma_ctrl.models.tables.PredictionModel`, the
casadi model the MPC and bang-bang use), linearised around the operating point that holds the target
height: the scaled gas mass ``x* = x(r, W)`` on the load path of the target height r under the
estimated load W. The operating point comes from the target, not from the estimate, because the
loop is to be linear around where it settles. The state now, x, is the model's at the estimated
height and contact force: on the membrane the contact force is the load; while the platform rests it
is the force the pressure holds up, and the model's state at zero height under that force is the
resting gas mass, so the feedback sees the gas build up before lift-off.

- ``A = dx+/dx`` with the valves closed (1: a closed chamber keeps its gas),
- ``B``: the command v moves ``v q_ref`` of gas per second (``q_ref``, the pump's full flow at zero
  gauge pressure), because the command is mapped to the inputs through the model's own pump and vent
  flows at the estimated pressure (below): the actuators' nonlinearity (the pump's dead band at high
  pressure, the vent's root law) is inverted statically, so the dynamics left to the gain are linear,
- ``C = dH/dx`` at x*, the height's sensitivity to the gas mass (what changes with the target).

The state is augmented with the integral of the height error, ``xi+ = xi + Ts (h - r)``, and
:func:`control.dlqr` gives the gain of ``v = -K [x - x*, xi]`` for the weights ``q_height`` (per mm^2
of height error), ``q_integral`` (per (mm s)^2) and ``r_command`` (per unit command^2), per sample.

Gain schedule: C falls sevenfold from a free membrane at 1 mm to one under 8 N at 15 mm, so one
linearisation is either sluggish high up or aggressive low down (designed at 8 mm, the linearised
loop's slowest pole ranges over 0.93 to 0.99 per 20 ms sample between 0.5 and 15 mm, a time constant
of 0.3 to 2 s). A and B do not depend on the operating point, so the gain is a function of C alone:
it is computed once on a grid of C over the tables' heights and loads and interpolated at the C of
the target under the estimated load (the slowest pole then stays at 0.97; interpolating the gains in
height and load instead, 16 x 6 points, left it between 0.95 and 0.98 where C bends between the grid's
points, near lift-off and under heavy loads).

The command's mapping follows the PID's: a positive v runs the compressor into the inlet, throttled
to pass ``v q_ref`` at the estimated pressure as the robot's valves are
(:func:`hbma_ctrl.models.bank.throttled_inputs_function`; fully open at full speed if the pump cannot),
a negative v opens the outlet at the duty that vents ``-v q_ref`` (at most fully open). The integral
stops while the command is saturated in the error's direction (anti-windup, as the PID). The pressure
guard and the step timing are the runtime's (``p_max``, ``guard_margin``), as for the PID.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import casadi as ca
import numpy as np

from hbma_ctrl.controllers.baselines import _target
from hbma_ctrl.core import units as U
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
from hbma_ctrl.models.bank import PumpMap, throttled_inputs_function
from hbma_ctrl.models.tables import PredictionModel

__all__ = ["LQISettings", "LQIController", "lqi_gain", "augmented"]

#: the gain schedule: dlqr's gain at _N_C slopes C, log-spaced over the slopes of _N_H target heights from
#: _H_LO (m) to the tables' top and _N_W loads from 0 to the tables' largest, widened by _C_PAD either way
_H_LO = 0.25e-3
_N_H = 24
_N_W = 11
_N_C = 40
_C_PAD = 1.25


@dataclass
class LQISettings(ControllerSettingsDefaults, Settings):
    """LQI on height (SI but the weights, which are per mm; each field's unit, range and one-line doc are
    in its declaration)."""

    WHERE = "lqi"

    sample_period: float = sample_period_setting()
    q_height: float = setting(1.0, lo=0.0, hi=1e6, unit="1/mm^2", doc="LQI weight on the height error per sample")
    q_integral: float = setting(2.0, lo=0.0, hi=1e6, lo_open=True, unit="1/(mm s)^2",
                                doc="LQI weight on the height error's integral per sample")
    r_command: float = setting(0.5, lo=0.0, hi=1e3, lo_open=True, unit="-",
                               doc="LQI weight on the command per sample (1 = the pump's full flow at 0 kPa)")
    p_max: float = p_max_setting()
    guard_margin: float = guard_margin_setting(1e3)

    def check_rules(self) -> None:
        self.within("guard_margin", hi=self.p_max)


def augmented(A: float, B: float, C: float, Ts: float) -> tuple[np.ndarray, np.ndarray]:
    """The scalar plant x+ = A x + B v, h = C x with the height error's integral xi+ = xi + Ts C x
    appended: (Aa 2x2, Ba 2x1), state [x, xi] (the units of C x times s for xi)."""
    return np.array([[A, 0.0], [Ts * C, 1.0]]), np.array([[B], [0.0]])


def lqi_gain(A: float, B: float, C: float, Ts: float, q_height: float, q_integral: float,
             r_command: float) -> np.ndarray:
    """The gain K (1 x 2) of v = -K [x, xi] from :func:`control.dlqr` on :func:`augmented`, cost per
    sample q_height (C x)^2 + q_integral xi^2 + r_command v^2 (C in the weights' length unit)."""
    import control

    Aa, Ba = augmented(A, B, C, Ts)
    K, _, _ = control.dlqr(Aa, Ba, np.diag([q_height * C ** 2, q_integral]), np.array([[r_command]]))
    return np.asarray(K, dtype=float).reshape(1, 2)


class LQIController(ControllerBase):
    """Gain-scheduled LQI on the estimated height (module docstring)."""

    def __init__(self, actuator: Actuator, pneumatics: Pneumatics, settings: LQISettings | None = None,
                 model: PredictionModel | None = None):
        self.settings = (settings or LQISettings()).validate()
        self.model = model or PredictionModel(actuator, pneumatics)
        self._flows()
        self._schedule()
        self.reset()

    def _flows(self) -> None:
        """The model's open flows (the full-speed pump into the open inlet, the open vent; kg/s) as one
        Function of the gauge pressure, the pump's throttling, and the discrete map's Jacobians."""
        md = self.model
        ch = md.chamber
        p = ca.SX.sym("p")
        self._open = ca.Function("lqi_open_flows", [p], [ch.net_flow(ca.DM([1.0, 1.0, 0.0]), p, ch.params),
                                                       -ch.net_flow(ca.DM([0.0, 0.0, 1.0]), p, ch.params)])
        self.q_ref = float(self._open(0.0)[0])
        # the robot's valves' mapping: speed (and inlet duty) that pass a share of the full-speed flow
        self._inputs = throttled_inputs_function(PumpMap(md.pneumatics.csv_path), 1, "per_chamber",
                                                 name="lqi_inputs")
        # x per kg of gas: the model's state is m R T / (p_env V0) - 1
        self._x_per_kg = md.RT / (md.actuator.p_env * md.actuator.V0)
        x, W = ca.SX.sym("x"), ca.SX.sym("W")
        xn = md.discrete(self.settings.sample_period)(x, ca.DM.zeros(3), W, 0.0)
        self._lin = ca.Function("lqi_lin", [x, W], [ca.jacobian(xn, x), ca.jacobian(md.H(x, W), x)])

    def linearise(self, h: float, W: float) -> tuple[float, float, float, float]:
        """(x*, A, B, C) at target height h (m) under load W (N): the operating point and the scalar
        plant of the module docstring (C in mm per unit x, the weights' unit)."""
        x = self.model.x_at_height(h, W)
        A, C = (float(v) for v in self._lin(x, W))
        B = self.settings.sample_period * self.q_ref * self._x_per_kg
        return x, A, B, U.to_mm(C)

    def _schedule(self) -> None:
        """dlqr's gain on the grid of slopes C (A and B do not depend on the operating point)."""
        s, md = self.settings, self.model
        Cs = [self.linearise(h, W)[3] for h in np.linspace(_H_LO, md.h_table_max, _N_H)
              for W in np.linspace(0.0, md.load_max, _N_W)]
        _, A, B, _ = self.linearise(_H_LO, 0.0)
        self._logC = np.linspace(np.log(min(Cs) / _C_PAD), np.log(max(Cs) * _C_PAD), _N_C)
        self._K = np.array([lqi_gain(A, B, float(np.exp(c)), s.sample_period, s.q_height, s.q_integral,
                                     s.r_command)[0] for c in self._logC])

    def gain(self, h: float, W: float, x: float | None = None) -> np.ndarray:
        """The scheduled gain (2,) at target height h (m) under load W (N) (``x``: its operating point when
        known): interpolated in log C, C the height's slope there, within the grid's range."""
        x = self.model.x_at_height(h, W) if x is None else x
        C = U.to_mm(float(self._lin(x, W)[1]))
        c = np.log(max(C, 1e-12))
        return np.array([np.interp(c, self._logC, self._K[:, i]) for i in range(2)])

    def reset(self) -> None:
        self._xi = 0.0
        self._t_prev = None
        self._h_prev = None
        self._hold = None
        self.last: dict = {}

    def _command(self, v: float, p: float) -> tuple[np.ndarray, bool, bool]:
        """The inputs for command v at gauge pressure p (Pa), and whether the pump or the vent saturated."""
        p = max(p, 0.0)
        q_in, q_out = (float(f) for f in self._open(p))
        q = v * self.q_ref
        if q > 0:
            a = 1.0 if q_in <= 0 else q / q_in
            return np.asarray(self._inputs(min(a, 1.0), 0.0, p), dtype=float).ravel(), a >= 1.0, False
        if q < 0:
            o = 1.0 if q_out <= 0 else -q / q_out
            return np.array([0.0, 0.0, min(o, 1.0)]), False, o >= 1.0
        return np.zeros(3), False, False

    def step(self, t: float, estimate: Estimate, reference: Reference,
             preview: Sequence[float] | None = None) -> Command:
        """Command for the next period from the estimated height, pressure and load against the target;
        no ``preview`` (``accepts_preview`` is False: the runtime never passes one)."""
        s, md = self.settings, self.model
        t = check_time(t, "lqi.step")
        h = float(estimate.h) if np.isfinite(estimate.h) else (self._h_prev or 0.0)
        r = _target(self, reference, h)
        dt = s.sample_period if self._t_prev is None else max(t - self._t_prev, 1e-6)
        p = float(estimate.p) if np.isfinite(estimate.p) else 0.0
        # the contact force is the load while the platform rides on the membrane and the force the
        # pressure holds up while it rests, so the model's state at (h, F) is the resting gas mass there
        W = min(max(float(estimate.F), 0.0), md.load_max) if np.isfinite(estimate.F) else 0.0
        x_op = md.x_at_height(r, W)
        dx = md.x_at_height(max(h, 0.0), W) - x_op
        K = self.gain(r, W, x_op)
        v = float(-K[0] * dx - K[1] * self._xi)
        cmd, pump_sat, vent_sat = self._command(v, p)
        e = h - r
        if not ((pump_sat and e < 0) or (vent_sat and e > 0)):
            self._xi += U.to_mm(e) * dt
        self._h_prev, self._t_prev = h, t
        self.last = {"reference_used": r, "command": v, "status": "ok"}
        return Command(*(float(c) for c in cmd))

    def stats(self) -> dict:
        """What the controller reports itself (timing, fallbacks and guard counts come from the runtime)."""
        return {"variant": "lqi", "horizon": None, "fallbacks": 0, "target_clipped_steps": 0}

