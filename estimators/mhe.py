"""Moving-horizon estimation of one chamber: the EKF's model and step API over a window of samples.

:class:`MHE` keeps the window (the last N samples' commands, readings and kinds, the nodes' gas
masses and shape warm starts, the window's parameters, the arrival cost and the stored
linearisation) and calls the window's problem once per sample: the real-time step or the IPOPT
reference of :mod:`hbma_ctrl.estimators.mhe_problem` (the unknowns, cost, constraints and arrival
update are described there), with its settings in :mod:`hbma_ctrl.estimators.mhe_settings`.

Solvers (``solver``):

- 'rti' (default): real-time iteration, one Gauss-Newton step per sample as ONE casadi Function
  (:func:`hbma_ctrl.estimators.mhe_problem.mhe_step_function`), compiled to C once per machine, as
  the EKF's step (:func:`hbma_ctrl.core.codegen.compiled`).
- 'ipopt': the full nonlinear least-squares problem solved by IPOPT at every sample (the reference;
  the same cost, constraints and arrival update). Slow.

Until the window is full (the first N samples) and on a failed step (a non-finite linearisation,
a QP solution off its bounds, an IPOPT failure) the chamber EKF of :mod:`hbma_ctrl.estimators.ekf` gives
the estimate, started from the MHE's last estimate; :meth:`MHE.stats` counts ``fallbacks``.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import replace as dc_replace

import numpy as np

from hbma_ctrl.core.codegen import HOT_FLAGS, HOT_OPT, FastFunction, casadi_lib_flags, compiled
from hbma_ctrl.core.interfaces import Command, Estimate, EstimatorBase
from hbma_ctrl.core.params import Actuator, Pneumatics
from hbma_ctrl.estimators.common import (
    MEAS_MISSING,
    MEAS_OK,
    MEAS_OUTLIER,
    MEAS_SATURATED,
    FilterSettings,
    classify_measurement,
    guard_cov,
    physical_reading_bounds,
)
from hbma_ctrl.estimators.ekf import EKF, EKFSettings
from hbma_ctrl.estimators.ekf_reference import OUTPUT_KEYS
from hbma_ctrl.estimators.ekf_step import KIND_NONE, KIND_OK, KIND_SATURATED, observer_model
from hbma_ctrl.estimators.mhe_problem import (
    H_MAX_REL,
    LEVENBERG,
    LIN_NAMES,
    QP_LIBS,
    TRUST,
    lean_model,
    mhe_packed_function,
    linearise_function,
    mhe_nlp,
    mhe_step_function,
    scales,
    state_bounds,
    window_layout,
)
from hbma_ctrl.estimators.mhe_settings import QP_SOLVERS, SOLVERS, MHESettings
from hbma_ctrl.models.actuation import CommandTiming
from hbma_ctrl.models.chamber import NX, STATE_NAMES, ObserverModel

__all__ = ["MHE", "MHESettings", "mhe_step_function", "linearise_function", "LIN_NAMES", "mhe_nlp", "TRUST", "H_MAX_REL",
           "SOLVERS", "QP_SOLVERS", "constraint_violations", "lean_model"]

_KIND = {MEAS_OK: KIND_OK, MEAS_SATURATED: KIND_SATURATED}
_RESTING = frozenset({"resting"})
_NO_FLAGS: frozenset = frozenset()
#: the companion EKF's flags that restart the window when the load is unknown (MHE._ekf_events)
_EKF_RESTARTS = frozenset({"lift_off", "load_change", "load_excess", "lift_off_ratio"})


def constraint_violations(h1, h2, h, F, W, tol: float = 1e-9) -> int:
    """Steps (entries) whose estimate breaks a hard constraint of the chamber: h < 0, h2 < 0,
    h2 > h1, F < 0 (m, N; beyond ``tol``) or a negative load state W (N; the EKF's state may be)."""
    h1, h2, h, F, W = (np.asarray(v, dtype=float) for v in (h1, h2, h, F, W))
    bad = (h < -tol) | (h2 < -tol) | (h2 > h1 + tol) | (F < -tol) | (W < -tol)
    return int(np.sum(bad))


_STEP_CACHE: dict = {}
#: the settings the step Function depends on (a trial's own load prior must not build another one)
_STEP_KEYS = ("relinearise", "huber", "noise_std", "model_rel_std", "sensor_range", "saturation_std", "flow_rel_std", "mass_std_abs",
              "load_std", "flow_factor_std", "modulus_std", "dead_volume_std", "cov_floor", "load_max",
              "sample_period", "horizon", "solver", "qp_solver", "ipopt_iter", "compile")


def _compiled_step(om: ObserverModel, s: MHESettings, key: tuple) -> FastFunction:
    if key not in _STEP_CACHE:
        fun = mhe_packed_function(om, s)
        flags = list(HOT_FLAGS) + casadi_lib_flags(QP_LIBS[s.qp_solver])
        done = compiled(fun, HOT_OPT, flags, notice=f"compiling the MHE step (N = {s.horizon}) once for this "
                                                     "machine ...") if s.compile else fun
        _STEP_CACHE[key] = done
    return FastFunction(_STEP_CACHE[key], False)


def _within_bounds(e: Estimate) -> Estimate:
    """The EKF's estimate within the MHE's hard constraints: its load state at least zero (the EKF's
    own may dip below: its dead zone), and the shape's ``0 <= h2 <= h1``, ``h >= 0``, ``F >= 0`` (an
    EKF step whose shape iteration did not converge, flag ``not_converged``, may leave them)."""
    h2 = min(max(e.h2, 0.0), max(e.h1, 0.0))
    if e.mean[1] >= 0.0 and h2 == e.h2 and e.h >= 0.0 and e.F >= 0.0:
        return e
    mean = e.mean
    if mean[1] < 0.0:
        mean = mean.copy()
        mean[1] = 0.0
    return dc_replace(e, mean=mean, h2=h2, h=max(e.h, 0.0), F=max(e.F, 0.0))


def _estimate(t, est, mean, cov, std, flags) -> Estimate:
    e = object.__new__(Estimate)
    e.__dict__.update(t=t, h1=est[0], h2=est[1], h=est[2], F=est[3], p=est[4], mean=mean, cov=cov,
                      state_names=STATE_NAMES, std=std, flags=flags)
    return e


class MHE(EstimatorBase):
    """Moving-horizon estimator of one chamber on the EKF's model (see module docstring). SI throughout.

    ``step(t, measurement, applied_command) -> Estimate`` as :meth:`hbma_ctrl.estimators.ekf.EKF.step`;
    the estimate is the window's newest node. Diagnostics after a step: ``last_output_cov`` (the
    covariance of ``OUTPUT_KEYS``), ``last_step_s``, ``last_cost`` (the window's cost), ``last_status``
    (0 ok; 1, 2 a failed step: see :func:`mhe_step_function`; -1 the EKF's estimate: window filling or
    fallback); :meth:`stats` counts ``fallbacks``, ``mhe_steps`` and the readings' kinds.
    """

    state_names = STATE_NAMES

    def __init__(self, actuator: Actuator, pneumatics: Pneumatics, settings: FilterSettings | None = None):
        s = settings if isinstance(settings, MHESettings) else MHESettings(**_fields(settings)) \
            if settings is not None else MHESettings()
        self.settings = s = s.validate()
        actuator.validate()
        pneumatics.validate()
        self.model = om = observer_model(actuator, pneumatics, s)
        self.theta = np.asarray(om.theta, dtype=float)
        self.N = N = int(s.horizon)
        ekf_fields = {k: v for k, v in _fields(s).items() if k in _fields(EKFSettings())}
        self.ekf = EKF(actuator, pneumatics, EKFSettings(**ekf_fields))
        self._timing = CommandTiming(s.sample_period, s.valve_delay, s.sensor_delay)
        self._bounds = physical_reading_bounds(s.sensor_range, s.reading_min, s.reading_max_rel)
        key = (id(om.predict), tuple(getattr(s, n) for n in _STEP_KEYS))
        if s.solver == "rti":
            self._fn = _compiled_step(om, s, key)
            self._nlp = None
            lk = ("lin", id(om.predict), N, s.compile)
            if lk not in _STEP_CACHE:
                fun = linearise_function(om, N)
                _STEP_CACHE[lk] = compiled(fun, HOT_OPT, HOT_FLAGS) if s.compile else fun
            self._lin_fn = FastFunction(_STEP_CACHE[lk], False)
            # the window lives in the step's input buffer: the step shifts and updates it in one call
            self._win = self._fn.inp[0]
            self._fn.inp[2][:] = self.theta
            self._smp = np.zeros(5)  # the newest sample: acting command, reading, its kind
        else:
            self._fn = None
            if key not in _NLP_CACHE:
                pred, outs = lean_model(om)
                _NLP_CACHE[key] = (mhe_nlp(om, s), FastFunction(pred, s.compile, HOT_OPT, HOT_FLAGS),
                                   FastFunction(outs, s.compile, HOT_OPT, HOT_FLAGS))
            self._nlp, self._pred1, self._out1 = _NLP_CACHE[key]
            self._win = np.zeros(sum(r * c for _, (r, c) in window_layout(N)))
        self._lo, self._hi = state_bounds(om, s)
        # the window (views into one flat vector, :func:`hbma_ctrl.estimators.mhe_problem.window_layout`):
        # nodes' masses, the parameters, shapes, the commands acting over the intervals, readings, kinds,
        # the arrival cost and the stored linearisation
        views, flat, i = {}, {}, 0
        for name, (r, c) in window_layout(N):
            flat[name] = v = self._win[i:i + r * c]
            views[name] = v if c == 1 else v.reshape((r, c), order="F")
            i += r * c
        self.M, self.th, self.S, self.U = views["M"], views["th"], views["S"], views["U"]
        self.Z, self.kinds, self.xbar, self.P0 = views["Z"], views["kinds"], views["xbar"], views["P0"]
        self.lin = [flat[n] for n in LIN_NAMES]
        self.th[:] = 1.0
        self.kinds[:] = float(KIND_NONE)
        self.P0[:] = np.eye(NX)
        self._filled = 0  # samples seen (the window is full from N + 1 on)
        self._hist: deque = deque(maxlen=N + 1)  # the EKF's (posterior x, P, shape) over the window's samples
        self.t: float | None = None
        self.last_output_cov = np.zeros((5, 5))
        self.last_step_s = 0.0
        self.last_cost = float("nan")
        self.last_status = -1
        self.last_active = 0
        self._ekf_est: Estimate | None = None
        self.counts = {"fallbacks": 0, "reseeds": 0, "mhe_steps": 0, "missing": 0, "outliers_bound": 0, "saturated": 0,
                       "time_jumps": 0}
        self._k_max = max(1, int(round(s.max_gap / s.sample_period)))
        self._last: Estimate | None = None

    # --- the step -----------------------------------------------------------------------------
    def step(self, t: float, measurement, applied_command: Command) -> Estimate:
        """Advance to time t (s) with the command held since the last step, then estimate from the window
        (one Gauss-Newton step or an IPOPT solve). Missing periods (a late tick) enter the window as
        samples without a reading; a gap longer than ``max_gap`` keeps ``max_gap`` of them (flag
        ``time_jump``). ValueError when t is not a finite time or goes backwards."""
        t_wall = time.perf_counter()
        s = self.settings
        t = self.ekf._check_time(t) if self.t is None else _check_time(t, self.t)
        kind = classify_measurement(measurement, s.sensor_range, *self._bounds)
        flags: set = set()
        if kind != MEAS_OK:
            flags.add(kind)
            key = {MEAS_OUTLIER: "outliers_bound", MEAS_MISSING: "missing", MEAS_SATURATED: "saturated"}[kind]
            self.counts[key] += 1
        u = applied_command.as_array() if isinstance(applied_command, Command) else \
            np.asarray(applied_command, dtype=float).reshape(3)
        if self.t is None:
            k = 0
        else:
            k = int(round((t - self.t) / s.sample_period))
            if k > self._k_max:
                k = self._k_max
                flags.add("time_jump")
                self.counts["time_jumps"] += 1
        if k == 0 and self._last is not None:
            # no period passed: nothing to add to the window
            self.t = t
            self.last_step_s = time.perf_counter() - t_wall
            return self._last
        est = None
        for i in range(max(k, 1)):
            last = i == max(k, 1) - 1
            z = measurement if last else None
            kd = kind if last else MEAS_MISSING
            est = self._one(t - (max(k, 1) - 1 - i) * s.sample_period, z, kd, u, k > 0)
        if flags:
            est = dc_replace(est, flags=frozenset(est.flags | flags))
        self.t = t
        self._last = est
        self.last_step_s = time.perf_counter() - t_wall
        return est

    def _one(self, t: float, z, kind: str, u: np.ndarray, advance: bool) -> Estimate:
        s, N = self.settings, self.N
        ua = self._timing.acting(u, 1 if advance else 0) if self._timing.active else u
        code = _KIND.get(kind, KIND_NONE)
        zf = float(z) if code == KIND_OK else 0.0
        if self._filled <= N or self._fn is None:
            self._push(ua, zf, code)
        else:
            # the compiled step shifts the window itself (_solve pushes when the step is not taken)
            self._sample = (ua, zf, code)
        if self._filled <= N or s.companion_ekf:
            e = self.ekf.step(t, z, u)
            self._hist.append((self.ekf.x.copy(), self.ekf.P.copy(), self.ekf.s.copy()))
            self._ekf_est = e
        elif self.ekf._timing.active:
            self.ekf._timing.acting(u, 1)  # the fallback's command history stays current
        if self._filled <= N:
            # the window fills: the EKF's estimate, its posteriors kept as the window's start
            self._filled += 1
            if self._filled == N + 1:
                self._start_window()
            self.last_status = -1
            return _within_bounds(e)
        # node N is new: the step predicts it from node N - 1
        return self._solve(t, z, u)

    def _push(self, ua: np.ndarray, zf: float, code: int) -> None:
        """Shift the window by one sample: drop node 0, the oldest interval and reading."""
        self.U[:, :-1] = self.U[:, 1:]
        self.U[:, -1] = ua
        self.Z[:-1] = self.Z[1:]
        self.Z[-1] = zf
        self.kinds[:-1] = self.kinds[1:]
        self.kinds[-1] = code
        self.M[:-1] = self.M[1:]
        self.S[:, :-1] = self.S[:, 1:]
        if self._fn is not None:
            # the stored linearisation moves with its nodes (column-major: a column is a block of rows)
            for a in self.lin:
                r = a.size // self.N
                a[:-r] = a[r:]

    def _start_window(self) -> None:
        """The window's nodes from the EKF's posteriors over its samples, the arrival cost from the
        EKF's posterior at node 0, the parameters from its latest."""
        hist = list(self._hist)
        xs = [h[0] for h in hist]
        self.M[:] = [x[0] for x in xs]
        self.S[:] = np.array([h[2] for h in hist]).T
        self.th[:] = np.clip(xs[-1][1:], *[b[1:] for b in state_bounds(self.model, self.settings)])
        x0, P0, _ = hist[0]
        self.xbar[:] = x0
        self.P0[:] = guard_cov(P0, self.settings.cov_floor)
        if self._fn is not None:
            # the whole window linearised once (the step then re-linearises its newest nodes only)
            out = self._lin_fn(self.M, self.th, self.S, self.U, self.theta)
            for a, o in zip(self.lin, out):
                a[:] = o

    def _solve(self, t: float, z, u) -> Estimate:
        s = self.settings
        if self._fn is not None:
            ua, zf, code = self._sample
            if self._ekf_events():
                self._push(ua, zf, code)
                return self._reseed()
            smp = self._smp
            smp[0], smp[1], smp[2] = ua.tolist()
            smp[3], smp[4] = zf, code
            out = self._fn(None, smp)  # None: the window already in the step's input buffer
            status = int(out[8][0])
            if status != 0:
                self._push(ua, zf, code)
            else:
                self._win[:] = out[11]  # the next window: shifted, the step's nodes, arrival, linearisation
                if out[12][0] <= 0.0:
                    self.P0[:] = guard_cov(self.P0, s.cov_floor)
                self.last_cost = float(out[9][0])
                self.last_active = int(out[10][0])
                if self._reseed_due():
                    return self._reseed()
                return self._accept(t, out[5].tolist(), out[6].reshape(5, 5, order="F").copy(),
                                    out[7].reshape(NX, NX, order="F").copy(), status, out[13].copy(),
                                    out[14].tolist())
        else:
            status = self._solve_ipopt()
            if status == 0:
                est = self._ipopt_outputs()
                if self._reseed_due():
                    return self._reseed()
                return self._accept(t, *est, status)
        if self.settings.companion_ekf:
            return self._reseed(failed=True)
        return self._fallback(t, z, u, status)

    def _ekf_events(self) -> bool:
        """With the load unknown (no ``load_init``), the companion EKF's detectors restart the window: a
        lift-off or a load change it declares (the window alone cannot see a lift-off: while the membrane
        rests the load is unobservable, and the flow and dead-volume factors take up the slower rise)."""
        e = self._ekf_est
        return (self.settings.companion_ekf and self.settings.load_init is None and e is not None
                and bool(e.flags & _EKF_RESTARTS))

    def _reseed_due(self) -> bool:
        """The window's cost per sample beyond ``reseed_cost`` with the companion EKF at hand: the window
        no longer explains its readings (a shape on the wrong branch of the pressure law)."""
        s = self.settings
        return s.companion_ekf and s.reseed_cost > 0 and self.last_cost > s.reseed_cost * self.N

    def _reseed(self, failed: bool = False) -> Estimate:
        """The window restarted from the companion EKF's posteriors over its samples; its estimate is the
        EKF's (flag ``mhe_fallback``, counted in ``fallbacks``; ``reseeds`` counts the restarts the
        window's cost or the EKF's detectors asked for)."""
        self.counts["fallbacks"] += 1
        if not failed:
            self.counts["reseeds"] += 1
        self.last_status = -1
        self._start_window()
        e = _within_bounds(self._ekf_est)
        return dc_replace(e, flags=frozenset(e.flags | {"mhe_fallback"}))

    def _accept(self, t: float, est: list, C: np.ndarray, cov: np.ndarray, status: int,
                mean: np.ndarray | None = None, std: list | None = None) -> Estimate:
        # within the shape's constraints as the RTI step reports them (mhe_step_function's est)
        est = [est[0], min(max(est[1], 0.0), max(est[0], 0.0)), max(est[2], 0.0), max(est[3], 0.0), est[4]]
        self.counts["mhe_steps"] += 1
        self.last_status = status
        self.last_output_cov = C
        if mean is None:
            mean = np.concatenate([[self.M[-1]], self.th])
        if std is None:
            std = np.sqrt(np.maximum(np.diag(C), 0.0)).tolist()
        flags = _RESTING if est[2] <= 0.0 and est[3] <= 0.0 else _NO_FLAGS
        return _estimate(t, est, mean, cov, dict(zip(OUTPUT_KEYS, std)), flags)

    def _fallback(self, t: float, z, u, status: int) -> Estimate:
        """A failed step: the EKF from the last estimate (node N - 1 and the window's parameters, with the
        Gauss-Newton covariance of the last step), stepped with this sample; node N is its posterior."""
        self.counts["fallbacks"] += 1
        self.last_status = -1
        N = self.N
        last = self._last
        x = np.concatenate([[self.M[N - 1]], self.th])
        P = last.cov if last is not None and last.cov.shape == (NX, NX) else self.P0
        self.ekf.reset(t - self.settings.sample_period, x, guard_cov(P, self.settings.cov_floor),
                       shape=self.S[:, N - 1], resting=None)
        e = self.ekf.step(t, z, u)
        self.M[N] = self.ekf.x[0]
        self.th[:] = np.clip(self.ekf.x[1:], *[b[1:] for b in state_bounds(self.model, self.settings)])
        self.S[:, N] = self.ekf.s
        return dc_replace(_within_bounds(e), flags=frozenset(e.flags | {"mhe_fallback"}))

    # --- the IPOPT reference ------------------------------------------------------------------
    def _solve_ipopt(self) -> int:
        N = self.N
        # node N from node N - 1's prediction (the start's last node)
        x = np.concatenate([[self.M[N - 1]], self.th])
        r = self._pred1(x, self.S[:, N - 1], self.U[:, N - 1], self.theta)
        self.M[N] = r[0][0]
        self.S[:, N] = r[2]
        res = self._nlp(self.M, self.th, self.S, self.U, self.Z, self.kinds, self.xbar, self.P0, self.theta)
        M1, th1 = np.asarray(res[0]).ravel(), np.asarray(res[1]).ravel()
        if not (np.all(np.isfinite(M1)) and np.all(np.isfinite(th1))):
            return 1
        self.M[:], self.th[:] = M1, th1
        self.last_cost = float(res[2])
        return 0

    def _ipopt_outputs(self) -> tuple:
        """After an IPOPT solve: the shapes, the arrival update (linearised at the solution's window, as
        the RTI step's, from the arrival mean) and node N's outputs and covariance (the Gauss-Newton
        Hessian of the five unknowns at the solution)."""
        s, N = self.settings, self.N
        pred, outf = self._pred1, self._out1
        sc = scales()
        th = self.th
        sm = np.array([sc[0], 0.0, 0.0, 0.0, 0.0])  # d m_j / d z, z the scaled unknowns
        fac = np.concatenate([[0.0], sc[1:]])
        J = []
        A0 = xn0 = H1 = y1 = None
        for j in range(N + 1):
            x = np.concatenate([[self.M[j]], th])
            o = outf(x, self.S[:, j], self.theta, np.zeros((NX, NX)))
            self.S[:, j] = o[0]
            if j >= 1:
                if j == 1:
                    y1, H1 = o[1].copy(), o[2].copy()
                kd = self.kinds[j - 1]
                p = o[1][4]
                rest = o[1][5] > 0.5
                R = s.noise_std ** 2 + ((0.0 if rest else s.model_rel_std) * max(p, 0.0)) ** 2
                w = 1.0 / math.sqrt(R) if kd == KIND_OK else (
                    1.0 / math.sqrt(s.saturation_std ** 2 + R) if kd == KIND_SATURATED and p < s.sensor_range else 0.0)
                J.append(w * (o[2][0] * sm + o[2] * fac))
            if j < N:
                r = pred(x, self.S[:, j], self.U[:, j], self.theta)
                A = r[1].reshape(NX, NX, order="F")
                sm = A[0, 0] * sm + A[0] * fac
                if j == 0:
                    A0, xn0 = A.copy(), r[0].copy()
        J = np.array(J)
        Pinv = np.linalg.inv(self.P0 / np.outer(sc, sc))
        Hh = Pinv + J.T @ J + LEVENBERG * np.eye(5)
        TN = np.zeros((NX, 5))
        TN[0] = sm
        TN[1:, 1:] = np.diag(sc[1:])
        covN = TN @ np.linalg.solve(Hh, TN.T)
        covN = 0.5 * (covN + covN.T)
        xN = np.concatenate([[self.M[N]], th])
        o = outf(xN, self.S[:, N], self.theta, covN)
        est = o[1][:5].tolist()
        C = o[3].reshape(5, 5, order="F").copy()
        # arrival update from the arrival mean (EKF predict and Joseph update with node 1's reading)
        x0 = np.concatenate([[self.M[0]], th])
        Q = np.diag([(s.flow_rel_std * (xn0[0] - self.M[0])) ** 2 + s.walk_var()[0], *s.walk_var()[1:]])
        Pm = A0 @ self.P0 @ A0.T + Q
        kd = self.kinds[0]
        rest1 = y1[5] > 0.5
        R1 = s.noise_std ** 2 + ((0.0 if rest1 else s.model_rel_std) * max(y1[4], 0.0)) ** 2
        xm = xn0 + A0 @ (self.xbar - x0)
        p1 = y1[4] + H1 @ (xm - np.concatenate([[self.M[1]], th]))
        used = kd == KIND_OK or (kd == KIND_SATURATED and y1[4] < s.sensor_range)
        if kd == KIND_SATURATED:
            R1 = s.saturation_std ** 2 + s.noise_std ** 2 + ((0.0 if rest1 else s.model_rel_std) * s.sensor_range) ** 2
        z1 = s.sensor_range if kd == KIND_SATURATED else self.Z[0]
        if used:
            Sv = float(H1 @ Pm @ H1) + R1
            K = Pm @ H1 / Sv
            IKH = np.eye(NX) - np.outer(K, H1)
            Pm = IKH @ Pm @ IKH.T + R1 * np.outer(K, K)
            xm = xm + K * (z1 - p1)
        self.xbar[:] = xm
        self.P0[:] = guard_cov(0.5 * (Pm + Pm.T), s.cov_floor)
        return est, C, covN

    def stats(self) -> dict:
        """Counts since construction: ``fallbacks`` (steps the EKF gave after a failed MHE step),
        ``mhe_steps`` (steps the MHE gave), ``missing``, ``outliers_bound``, ``saturated`` readings and
        ``time_jumps``; ``outliers`` as the EKF's."""
        c = dict(self.counts)
        c["outliers"] = c["outliers_bound"]
        return c


_NLP_CACHE: dict = {}


def _fields(settings) -> dict:
    """A settings dataclass's fields as a dict (shallow)."""
    from dataclasses import fields as dc_fields

    return {f.name: getattr(settings, f.name) for f in dc_fields(settings)}


def _check_time(t, last: float) -> float:
    if type(t) is float and last - 1e-9 <= t < math.inf:
        return t
    try:
        tf = float(t)
    except (TypeError, ValueError):
        raise ValueError(f"estimator.step: t = {t!r} must be a finite time in s") from None
    if not math.isfinite(tf) or isinstance(t, (str, bytes, bool)):
        raise ValueError(f"estimator.step: t = {t!r} must be a finite time in s")
    if tf < last - 1e-9:
        raise ValueError(f"estimator.step: t = {tf} s is before the last step's {last} s (time must not go backwards)")
    return tf

