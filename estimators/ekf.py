"""Extended Kalman filter: membrane shape and contact force from the chamber pressure alone.

State ``x = [m, W]``: the gas mass (kg) and the load on the membrane (N), a random walk. Why:

- The gas mass is the plant's own drift-free differential state (SPEC 4); the flow model (pump
  map, valves) drives it directly, so the commands enter the filter where they act.
- The shape ``(h1, h2)`` is not a state: given (m, W) it is fixed by the gas law and the contact
  condition (``G(h1, h2) = m R T``, ``F(h1, h2) = W``) or, when ``pi r1^2 p_rest(m) <= W``, the
  membrane rests flat. Carrying h1, h2 as filter states would give a covariance of rank 2 in a 4-d
  space (two exact constraints), which the update cannot keep consistent. They are outputs, with
  their covariance mapped through the implicit-function Jacobian.
- The load W is unknown to the user, piecewise constant (put on, taken off): a random walk.
  ``W = F`` in steady contact; ``W = 0`` is free inflation (h2 = 0).
- No flow-bias or modulus state: a flow bias is not separable from the dead-volume error (both
  change dp/dt per unit command) and a modulus state is not separable from the load (both change
  the pressure of a given gas mass), so they would add unobservable directions; their effect is
  covered by process noise on m (``flow_rel_std``) and by the measurement model error
  (``model_rel_std``), see :mod:`estimators.observability`.

What pressure alone tells (see :mod:`estimators.observability`): resting flat, only m is known
(``W`` is unobservable, only ``W >= pi r1^2 p``); in contact or free inflation both m and W are
observable while gas flows, and W is not when nothing flows (every (m, W) pair on a level set of
p is then an equilibrium). The filter therefore holds W at the lift-off bound while resting (the
least load consistent with the flat membrane, so lift-off is tracked without delay, and h = 0 is
right either way) and lets the random walk carry W when the flow stops.

Measurements: a missing or non-finite reading skips the update (flag ``missing``); a saturated
reading (>= sensor range) is a one-sided observation ``p >= range``: if the prediction is below
the range, an update towards the range with ``saturation_std``; otherwise no update (flag
``saturated``). Numerics: Joseph-form update, gains by solves, covariance symmetrised with an
eigenvalue floor after every predict and update (:mod:`estimators.common`). No global state; the
filter is deterministic.
"""

from __future__ import annotations

import math

import numpy as np

from hbma_ctrl.interfaces import Command, Estimate
from hbma_ctrl.params import Actuator, Pneumatics

from .common import (MEAS_MISSING, MEAS_SATURATED, FilterSettings, classify_measurement, guard_cov,
                     joseph_update)
from .fastcall import FastFunction
from .model import OUT_NAMES, STATE_NAMES, ObserverModel

__all__ = ["EKF", "EKFSettings", "OUTPUT_KEYS"]

#: outputs whose covariance the filters report (rows of ``output_cov``)
OUTPUT_KEYS = ("h1", "h2", "h", "F", "p")
_Y = {n: i for i, n in enumerate(OUT_NAMES)}


class EKFSettings(FilterSettings):
    """EKF settings: the fields of :class:`estimators.common.FilterSettings` (documented there)."""


_MODEL_CACHE: dict = {}


def observer_functions(actuator: Actuator, pneumatics: Pneumatics, s: FilterSettings):
    """(ObserverModel, fast predict, fast outputs, fast propagate), shared per configuration."""
    key = (type(actuator.material), str(pneumatics.csv_path), s.sample_period, s.integrator, s.nsub,
           s.newton, s.compile)
    if key not in _MODEL_CACHE:
        om = ObserverModel(actuator, pneumatics, s.sample_period, s.integrator, s.nsub, s.newton)
        _MODEL_CACHE[key] = (om, om.predict, om.outputs, om.propagate)
    om0, fp, fo, fq = _MODEL_CACHE[key]
    # the parameters (theta) differ per actuator: the numeric model is cheap, Functions are shared
    om = om0 if np.array_equal(om0.theta, om0.fid.space.values(actuator, pneumatics)) else \
        _rebind(om0, actuator, pneumatics)
    return om, FastFunction(fp, s.compile), FastFunction(fo, s.compile), FastFunction(fq, s.compile)


def _rebind(om0: ObserverModel, actuator: Actuator, pneumatics: Pneumatics) -> ObserverModel:
    om = object.__new__(ObserverModel)
    om.__dict__.update(om0.__dict__)
    om.theta = om0.fid.space.values(actuator, pneumatics)
    om.actuator = actuator
    om.area = float(np.pi * actuator.r1 ** 2)
    om.rt = actuator.R * actuator.T
    om.m_env = actuator.p_env * actuator.V0 / om.rt
    return om


class EKF:
    """Extended Kalman filter on ``x = [m, W]`` (see module docstring). SI throughout.

    ``step(t, measurement, applied_command) -> Estimate``: predicts over the periods since the
    last step with ``applied_command`` (the command held since then), then updates with the
    pressure reading (Pa). The first call initialises the state from the reading (membrane flat,
    load ``load_init``). ``reset(t, mean, cov)`` sets the state explicitly.
    After each step: ``last_nis`` (None without a normal update), ``last_output_cov`` (covariance
    of ``OUTPUT_KEYS``), ``last_step_s`` (wall time of the step).
    """

    state_names = STATE_NAMES

    def __init__(self, actuator: Actuator, pneumatics: Pneumatics, settings: FilterSettings | None = None):
        self.settings = (settings or EKFSettings()).validate()
        actuator.validate()
        pneumatics.validate()
        self.model, self._pred, self._outf, _ = observer_functions(actuator, pneumatics, self.settings)
        self.theta = np.asarray(self.model.theta, dtype=float)
        self.x: np.ndarray | None = None
        self.P: np.ndarray | None = None
        self.s = np.zeros(2)  # shape warm start (h1, h2)
        self.t: float | None = None
        self.last_nis: float | None = None
        self.last_innovation: float | None = None
        self.last_output_cov = np.zeros((5, 5))
        self.last_step_s = 0.0
        self._p_pred = 0.0
        self._H = np.zeros(2)
        self._cusum = 0.0
        self._changed = False

    # --- state handling -----------------------------------------------------------------------
    def reset(self, t: float, mean, cov=None, shape=None) -> None:
        """Set the state [m (kg), W (N)] and covariance at time t (s); shape = warm start (m)."""
        s = self.settings
        self.x = np.array(mean, dtype=float).reshape(2)
        self.P = np.diag([s.mass_init_std ** 2, s.load_init_std ** 2]) if cov is None else \
            np.array(cov, dtype=float).reshape(2, 2)
        self.P = guard_cov(self.P, s.cov_floor)
        self.t = float(t)
        self.s = np.zeros(2) if shape is None else np.array(shape, dtype=float).reshape(2)
        self._refresh_prediction()

    def _refresh_prediction(self) -> None:
        out = self._outf(self.x, self.s, self.theta)
        self.s = out[0].copy()
        self._p_pred = float(out[1][_Y["p"]])
        self._H = out[2].copy()

    def _init_from(self, t: float, z: float, kind: str) -> None:
        s = self.settings
        p0 = float(z) if kind == "ok" else (s.sensor_range if kind == MEAS_SATURATED else 0.0)
        m0 = (max(p0, 0.0) + self.model.actuator.p_env) * self.model.actuator.V0 / self.model.rt
        self.reset(t, [m0, s.load_init])

    # --- the filter ---------------------------------------------------------------------------
    def _predict(self, u: np.ndarray) -> None:
        s = self.settings
        out = self._pred(self.x, self.s, u, self.theta)
        A = self._pred.dense(1)
        xn = out[0].copy()
        if not np.all(np.isfinite(xn)) or not np.all(np.isfinite(A)):
            # the projection failed (e.g. across a fold): hold the state, widen the covariance
            xn, A = self.x.copy(), np.eye(2)
            self.P = self.P + np.diag([(1e-7) ** 2, s.load_std ** 2])
        else:
            self.s = out[2].copy()
            y = out[3]
            self._p_pred = float(y[_Y["p"]])
            self._H = out[4].copy()
        dt = s.sample_period
        q_abs = abs(xn[0] - self.x[0]) / dt  # net flow over the period, kg/s
        Qm = (s.flow_rel_std * q_abs * dt) ** 2 + s.mass_std_abs ** 2 * dt
        Q = np.diag([Qm, s.load_std ** 2 * dt])
        self.x = xn
        self.P = guard_cov(A @ self.P @ A.T + Q, s.cov_floor)

    def _update(self, z: float, R: float) -> None:
        innov = z - self._p_pred
        x, P, S, _ = joseph_update(self.x, self.P, self._H, innov, R)
        self.x, self.P = x, guard_cov(P, self.settings.cov_floor)
        self.last_innovation = innov
        self.last_nis = innov * innov / S
        # load-change detector: CUSUM of the NIS excess
        s = self.settings
        self._cusum = max(0.0, self._cusum + self.last_nis - s.change_drift)
        if self._cusum > s.change_threshold:
            self._cusum = 0.0
            self.P[1, 1] += s.change_std ** 2
            self._changed = True

    def _meas_var(self, p: float) -> float:
        s = self.settings
        return s.noise_std ** 2 + (s.model_rel_std * max(p, 0.0)) ** 2

    def step(self, t: float, measurement, applied_command: Command) -> Estimate:
        """Advance to time t (s) with the command held since the last step, then update."""
        import time

        t_wall = time.perf_counter()
        s = self.settings
        kind = classify_measurement(measurement, s.sensor_range)
        flags = set()
        self._changed = False
        if kind != "ok":
            flags.add(kind)
        if self.x is None:
            self._init_from(t, measurement, kind)
            k = 0
        else:
            k = int(round((t - self.t) / s.sample_period))
            if k < 0:
                raise ValueError(f"estimator.step: t = {t} s is before the last step's {self.t} s")
        u = applied_command.as_array() if isinstance(applied_command, Command) else \
            np.asarray(applied_command, dtype=float).reshape(3)
        for _ in range(k):
            self._predict(u)
        self.t = float(t)
        self.last_nis = None
        self.last_innovation = None
        if kind == "ok":
            self._update(float(measurement), self._meas_var(self._p_pred))
        elif kind == MEAS_SATURATED and self._p_pred < s.sensor_range:
            # one-sided: the true pressure is at least the range; pull the prediction up to it
            self._update(s.sensor_range, s.saturation_std ** 2 + self._meas_var(s.sensor_range))
            self.last_nis = None
        if self._changed:
            flags.add("load_change")
        est = self._finish(flags)
        self.last_step_s = time.perf_counter() - t_wall
        return est

    def _finish(self, flags: set) -> Estimate:
        s = self.settings
        # keep the load inside its bounds
        if not s.load_min <= self.x[1] <= s.load_max:
            self.x[1] = min(max(self.x[1], s.load_min), s.load_max)
            flags.add("clamped")
        out = self._outf(self.x, self.s, self.theta)
        y = out[1]
        if y[_Y["rest"]] > 0.5:
            # resting flat: only W >= pi r1^2 p is known; hold W at that bound (see docstring)
            flags.add("resting")
            bound = self.model.area * float(y[_Y["p"]])
            self.x[1] = max(bound, s.load_min)
            P = self.P.copy()
            P[0, 1] = P[1, 0] = 0.0
            P[1, 1] = s.load_rest_std ** 2
            self.P = guard_cov(P, s.cov_floor)
            self._cusum = 0.0
            # the outputs of a flat membrane do not depend on W: no re-evaluation needed
        if y[_Y["resid"]] > 1e-3 or not np.all(np.isfinite(y)):
            flags.add("not_converged")
        self.s = out[0].copy()
        self._p_pred = float(y[_Y["p"]])
        self._H = out[2].copy()
        D = self._outf.dense(3)
        C = D @ self.P @ D.T
        self.last_output_cov = 0.5 * (C + C.T)
        std = {k: math.sqrt(max(C[i, i], 0.0)) for i, k in enumerate(OUTPUT_KEYS)}
        h1, h2 = float(y[_Y["h1"]]), float(y[_Y["h2"]])
        return Estimate(t=self.t, h1=h1, h2=max(h2, 0.0), h=float(y[_Y["h"]]), F=max(float(y[_Y["F"]]), 0.0),
                        p=float(y[_Y["p"]]), mean=self.x.copy(), cov=self.P.copy(),
                        state_names=self.state_names, std=std, flags=frozenset(flags))
