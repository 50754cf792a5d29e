"""The EKF's baselines in ``bench ekf``: the same filter on its reference path, and filterpy's EKF on
the same casadi model (SI).

- :class:`ReferenceEKF`: the EKF with separate predict, update and output calls and its detectors in
  Python at every step: the check that the compiled step changes time, not accuracy.
- :class:`FilterpyEKF`: :class:`filterpy.kalman.ExtendedKalmanFilter` driven by the EKF's model, without
  the EKF's own logic (detectors, gate, guards, delays): the library baseline.
"""

from __future__ import annotations

import math
import time

import numpy as np

from hbma_ctrl.core.interfaces import Command, Estimate, EstimatorBase
from hbma_ctrl.estimators.common import FilterSettings, classify_measurement, physical_reading_bounds
from hbma_ctrl.estimators.ekf import EKF, OUTPUT_KEYS
from hbma_ctrl.estimators.ekf_step import fast, observer_model
from hbma_ctrl.models.chamber import NX, STATE_NAMES

__all__ = ["ReferenceEKF", "FilterpyEKF"]


class ReferenceEKF(EKF):
    """The EKF on its reference path (separate predict, update and output calls, detectors in
    Python) for every step: the bench's check that the compiled step changes time, not accuracy."""

    compiled_step = False


class FilterpyEKF(EstimatorBase):
    """filterpy's :class:`~filterpy.kalman.ExtendedKalmanFilter` driven by the EKF's casadi model
    (the bench's library baseline, SI): the same compiled discrete map and its Jacobian A as F,
    the same process noise and measurement variance, H = dp/dx and the predicted pressure from the
    same model, the same output map; filterpy's own predict and update (inverse of S, Joseph form).
    What it lacks is the EKF's own logic: no sticky rest or lift-off detector (the model decides
    contact by the load state), no gate, no guards, no valve or sensor delays (the commands act at
    once). So that it can follow a load at all the load
    starts at the trial's nominal weight (known), one sigma 10 % + 0.01 N. Missing and out-of-range
    readings skip the update. It reports no ``last_innovation`` (None: the innovation test skips it)."""

    state_names = STATE_NAMES

    def __init__(self, actuator, pneumatics, settings: FilterSettings, load: float = 0.0):
        from filterpy.kalman import ExtendedKalmanFilter  # the bench's baseline only

        s = self.settings = settings.validate()
        self.model = observer_model(actuator, pneumatics, s)
        self._pred = fast(self.model.predict, s.compile)
        self._outf = fast(self.model.outputs, s.compile)
        self.theta = np.asarray(self.model.theta, dtype=float)
        self.kf = ExtendedKalmanFilter(dim_x=NX, dim_z=1)
        self.kf.predict_x = self._predict_x
        self._xn = np.zeros((NX, 1))
        self.load = float(load)
        self.s = np.zeros(2)
        self.t: float | None = None
        self.last_nis: float | None = None
        self.last_output_cov = np.zeros((5, 5))
        self.last_step_s = 0.0
        self._q = np.array(s.walk_var())
        self._qv = np.array([s.flow_rel_std, *self._q, s.cov_floor])
        self._bounds = physical_reading_bounds(s.sensor_range, s.reading_min, s.reading_max_rel)

    def _predict_x(self, u=0) -> None:
        self.kf.x = self._xn  # filterpy's hook: the model's map, computed with F by step()

    def step(self, t: float, measurement, applied_command: Command) -> Estimate:
        """Predict one period with the command held since the last step, update with the reading (Pa)."""
        t0 = time.perf_counter()
        s, kf = self.settings, self.kf
        kind = classify_measurement(measurement, s.sensor_range, *self._bounds)
        if self.t is None:
            act = self.model.actuator
            p0 = float(measurement) if kind == "ok" else 0.0
            kf.x = np.array([[(max(p0, 0.0) + act.p_env) * act.V0 / self.model.rt], [self.load], [1.0], [1.0],
                             [1.0]])
            var = s.prior_var()
            var[1] = (0.1 * self.load + 0.01) ** 2
            kf.P = np.diag(var)
        else:
            u = applied_command.as_array() if isinstance(applied_command, Command) else \
                np.asarray(applied_command, dtype=float).reshape(3)
            out = self._pred(kf.x.ravel(), self.s, u, self.theta, 0.0, kf.P, self._qv)
            self._xn = out[0].reshape(NX, 1).copy()
            kf.F = out[1].reshape(NX, NX, order="F").copy()
            q = self._q.copy()
            q[0] += (s.flow_rel_std * (self._xn[0, 0] - kf.x[0, 0])) ** 2
            kf.Q = np.diag(q)
            self.s = out[2].copy()
            kf.predict()
            self.last_nis = None
            if kind == "ok":
                H = out[4].reshape(1, NX).copy()
                p = float(out[3][4])
                R = s.noise_std ** 2 + (s.model_rel_std * max(p, 0.0)) ** 2
                kf.update(float(measurement), lambda x: H, lambda x: np.array([[p]]), R=R)
                self.last_nis = float(kf.y[0, 0] ** 2 / kf.S[0, 0])
        self.t = float(t)
        o = self._outf(kf.x.ravel(), self.s, self.theta, 0.0, kf.P)
        self.s = o[0].copy()
        y = o[1]
        C = o[4].reshape(5, 5, order="F").copy()
        d = (s.output_rel_std * y[:5]) ** 2
        d[4] = 0.0
        d[3] += s.force_std_floor ** 2
        C[np.diag_indices(5)] += d
        self.last_output_cov = C
        std = {k: math.sqrt(max(C[i, i], 0.0)) for i, k in enumerate(OUTPUT_KEYS)}
        est = Estimate(t=self.t, h1=float(y[0]), h2=max(float(y[1]), 0.0), h=float(y[2]), F=max(float(y[3]), 0.0),
                       p=float(y[4]), mean=kf.x.ravel().copy(), cov=kf.P.copy(), state_names=STATE_NAMES,
                       std=std, flags=frozenset())
        self.last_step_s = time.perf_counter() - t0
        return est
