"""A steady-state Kalman filter on the gas mass: the cheapest estimator of the bench's Pareto.

The EKF's model (:mod:`hbma_ctrl.models.chamber`) predicts the state each sample, but the gain is
fixed: python-control's :func:`control.dlqe` on the model linearised once, at the flat membrane
(half the sensor's range, pump running: where the pressure is stiffest in the gas mass, so the
fixed gain never over-corrects where the membrane moves), for the gas mass alone (process noise
``flow_rel_std`` of that period's flow, measurement noise ``noise_std``). The gauge pressure is kept
>= 0 (the gas mass at least the ambient's). The load and the pump, modulus and
dead-volume factors stay at their prior (a nominal load prior, or no load): nothing is learnt.
A missing reading or an outlier skips the correction; a saturated one corrects towards the range
only while the prediction is below it (the EKF's one-sided observation).
"""

from __future__ import annotations

import time

import numpy as np

from hbma_ctrl.core.codegen import HOT_FLAGS, HOT_OPT, FastFunction
from hbma_ctrl.core.interfaces import Command, Estimate, EstimatorBase
from hbma_ctrl.core.params import Actuator, Pneumatics
from hbma_ctrl.estimators.common import (
    MEAS_MISSING,
    MEAS_OK,
    MEAS_OUTLIER,
    MEAS_SATURATED,
    FilterSettings,
    classify_measurement,
    physical_reading_bounds,
)
from hbma_ctrl.estimators.ekf_reference import OUTPUT_KEYS
from hbma_ctrl.estimators.ekf_step import observer_model
from hbma_ctrl.estimators.mhe import lean_model
from hbma_ctrl.models.actuation import CommandTiming
from hbma_ctrl.models.chamber import NX, STATE_NAMES

__all__ = ["SteadyStateKF", "steady_gain"]


def steady_gain(A: float, C: float, q: float, r: float) -> float:
    """The steady-state Kalman gain of the correction x+ = x- + K (z - C x-) (kg / Pa) for x+ = A x + w,
    z = C x + v with var(w) = q, var(v) = r: :func:`control.dlqe`'s predictor gain L = A K over A."""
    import control

    L, _, _ = control.dlqe(np.array([[A]]), np.array([[1.0]]), np.array([[C]]), np.array([[q]]), np.array([[r]]))
    return float(np.asarray(L).ravel()[0]) / A


class SteadyStateKF(EstimatorBase):
    """Fixed-gain Kalman filter on the gas mass (module docstring); the EKF's step API. SI."""

    state_names = STATE_NAMES

    def __init__(self, actuator: Actuator, pneumatics: Pneumatics, settings: FilterSettings | None = None):
        self.settings = s = (settings or FilterSettings()).validate()
        om = observer_model(actuator, pneumatics, s)
        self.model = om
        pred, outs = lean_model(om)
        self._pred = FastFunction(pred, s.compile, HOT_OPT, HOT_FLAGS)
        self._outs = FastFunction(outs, s.compile, HOT_OPT, HOT_FLAGS)
        self.theta = np.asarray(om.theta, dtype=float)
        W = max(s.load_init, 0.0) if s.load_init is not None else 0.0
        self.x = np.array([om.m_env, W, s.flow_factor_init, s.modulus_init, s.dead_volume_init])
        self.s = np.zeros(2)
        self._timing = CommandTiming(s.sample_period, s.valve_delay, s.sensor_delay)
        self._bounds = physical_reading_bounds(s.sensor_range, s.reading_min, s.reading_max_rel)
        self.K = self._gain()
        self.t: float | None = None
        self.last_output_cov = np.zeros((5, 5))
        self.last_step_s = 0.0
        self.counts = {"missing": 0, "outliers_bound": 0, "saturated": 0}

    def _gain(self) -> float:
        """dlqe's gain at the linearisation point of the module docstring."""
        s, om = self.settings, self.model
        m = om.gas_mass(0.5 * s.sensor_range)
        x = self.x.copy()
        x[0] = m
        x[1] = s.load_max  # flat under the plate
        so, y, H, _ = (a.copy() for a in self._outs(x, np.zeros(2), self.theta, np.zeros((NX, NX))))
        xn, A, _ = (a.copy() for a in self._pred(x, so, np.array([1.0, 1.0, 0.0]), self.theta))
        dm = float(xn[0] - m)
        q = (s.flow_rel_std * dm) ** 2 + s.mass_std_abs ** 2 * s.sample_period
        r = s.noise_std ** 2
        return steady_gain(float(A[0]), float(H[0]), q, r)

    def step(self, t: float, measurement, applied_command: Command) -> Estimate:
        """Predict to t (s) with the command held since the last step, then correct with the fixed gain."""
        t_wall = time.perf_counter()
        s = self.settings
        t = float(t)
        u = applied_command.as_array() if isinstance(applied_command, Command) else \
            np.asarray(applied_command, dtype=float).reshape(3)
        kind = classify_measurement(measurement, s.sensor_range, *self._bounds)
        if kind != MEAS_OK:
            self.counts[{MEAS_OUTLIER: "outliers_bound", MEAS_MISSING: "missing", MEAS_SATURATED: "saturated"}[kind]] += 1
        if self.t is None:
            p0 = float(measurement) if kind == MEAS_OK else 0.0
            self.x[0] = self.model.gas_mass(max(p0, 0.0))
            self._timing.acting(u, 0)
            k = 0
        else:
            k = max(int(round((t - self.t) / s.sample_period)), 0)
        for _ in range(k):
            ua = self._timing.acting(u, 1) if self._timing.active else u
            xn, _, sn = self._pred(self.x, self.s, ua, self.theta)
            self.x[0] = xn[0]
            self.s[:] = sn
        so, y, _, _ = self._outs(self.x, self.s, self.theta, np.zeros((NX, NX)))
        p = float(y[4])
        if kind == MEAS_OK:
            nu = float(measurement) - p
        elif kind == MEAS_SATURATED and p < s.sensor_range:
            nu = s.sensor_range - p
        else:
            nu = 0.0
        if nu != 0.0:
            self.x[0] = max(self.x[0] + self.K * nu, self.model.m_env)
            so, y, _, _ = self._outs(self.x, so, self.theta, np.zeros((NX, NX)))
        self.s[:] = so
        self.t = t
        self.last_step_s = time.perf_counter() - t_wall
        e = object.__new__(Estimate)
        e.__dict__.update(t=t, h1=float(y[0]), h2=float(y[1]), h=float(y[2]), F=float(y[3]), p=float(y[4]),
                          mean=self.x.copy(), cov=np.zeros((NX, NX)), state_names=STATE_NAMES,
                          std=dict.fromkeys(OUTPUT_KEYS, 0.0), flags=frozenset({kind} if kind != MEAS_OK else ()))
        return e

    def stats(self) -> dict:
        """Counts since construction: ``missing``, ``outliers_bound``, ``saturated`` readings."""
        c = dict(self.counts)
        c["outliers"] = c["outliers_bound"]
        return c
