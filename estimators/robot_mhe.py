"""Moving-horizon estimation of the robot's chambers: the EKF bank's model and API over a window each (SI).

:class:`RobotMHE` is :class:`hbma_ctrl.estimators.robot_ekf.ChamberEKFBank` with a window per chamber on
top. Each window is the chamber MHE's problem (:mod:`hbma_ctrl.estimators.mhe_problem`) with a known
load (``known_load``): the load of each node is the one the robot's statics gave for that period (the
loop's ``W``, as the EKF bank takes it), the unknowns are the window's first gas mass and the pump,
modulus and dead-volume factors. The model is the bank's (:class:`hbma_ctrl.models.bank.ChamberBank`,
the reduced chamber on its tables, the same as the EKF bank's and the NMPC's), in the window's state
``(m, W, b, k, c)`` with ``m = y m_env`` (``y = (x + 1) / c`` the EKF bank's gas coordinate, m_env the
nominal dead volume's gas at ambient): :class:`BankWindowModel`.

All chambers' windows step as ONE call: the chamber MHE's packed step mapped over the n chambers,
compiled once per machine. The EKF bank runs beside them every period: it gives the estimate while a
window fills (the first N periods, after a restart of the loop's filters and after a late tick), it
starts each window (nodes and arrival cost from its posteriors) and it is the fallback of a chamber whose
step fails (a non-finite step, a QP solution off its bounds) or whose window's cost per reading exceeds
``reseed_cost``: that chamber's estimate is the EKF's and its window restarts from the EKF's posteriors,
counted per chamber (:attr:`RobotMHE.fallbacks`). The flags, the innovations (``r``, ``nis``: the
burst test's input) and the factors' spread (``k_std``: the cautious cap's) are the EKF bank's.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import replace

import casadi as ca
import numpy as np

from hbma_ctrl.core.codegen import HOT_FLAGS, HOT_OPT, FastFunction, casadi_lib_flags, compiled
from hbma_ctrl.core.validation import floats_or_nan
from hbma_ctrl.estimators.common import guard_cov
from hbma_ctrl.estimators.ekf_step import KIND_NONE, KIND_OK
from hbma_ctrl.estimators.mhe_problem import QP_LIBS, linearise_function, mhe_packed_function, window_layout
from hbma_ctrl.estimators.mhe_settings import MHESettings
from hbma_ctrl.estimators.robot_ekf import B_RANGE, C_RANGE, K_RANGE, ChamberEKFBank, ChamberEKFSettings
from hbma_ctrl.models.actuation import CommandTiming
from hbma_ctrl.models.bank import ChamberBank
from hbma_ctrl.models.chamber import NX

__all__ = ["RobotMHE", "BankWindowModel", "window_settings"]

#: the window's parts that do not move with its nodes (the parameters and the arrival cost)
_FIXED = ("th", "xbar", "P0")


class BankWindowModel:
    """The bank's chamber model (:class:`ChamberBank`) as the window problem's model: ``predict`` and
    ``outputs`` with the signatures of :class:`hbma_ctrl.models.chamber.ObserverModel`'s, in the state
    ``(m kg, W N, b, k, c)`` with ``m = y m_env`` (module doc). The bank has no membrane shape to warm
    start (its tables give the shape of (x, W)): the shape inputs pass through. Outputs (h1, h2, h, F,
    p, rest, det, resid) = (h, 0, h, W, p, 0, 0, 0): the pressure's model error (``model_rel_std``)
    counts at every pressure, as in the EKF bank. The predict is the EKF bank's discrete model on the
    plant's inputs [speed, inlet, outlet]."""

    def __init__(self, model: ChamberBank, dt: float):
        a = model.actuator
        self.bank = model
        self.m_env = a.p_env * a.V0 / (a.R * a.T)
        self.theta = np.zeros(1)
        self.factor_ranges = (B_RANGE, K_RANGE, C_RANGE)
        xs, _, W, b, k, c = model.symbols
        xn = model.discrete_expr(dt, plant_inputs=True)
        fx = ca.Function("bank_fx", [xs, model.u, W, b, k, c], [xn])
        x, s, u, th = ca.SX.sym("x", NX), ca.SX.sym("s", 2), ca.SX.sym("u", 3), ca.SX.sym("theta", 1)
        hold, P, qv = ca.SX.sym("hold"), ca.SX.sym("P", NX, NX), ca.SX.sym("qv", NX + 2)
        me = self.m_env
        Wc = model.clip_load(x[1])
        xb = x[4] * x[0] / me - 1  # the bank's scaled gas mass
        m_next = (fx(xb, u, Wc, x[2], x[3], x[4]) + 1) / x[4] * me
        x_next = ca.vertcat(m_next, x[1:])
        A = ca.jacobian(x_next, x)
        h, p, _ = model.outputs_expr(xb, Wc, x[3], x[4])
        y = ca.vertcat(h, 0.0, h, Wc, p, 0.0, 0.0, 0.0)
        H = ca.jacobian(p, x)
        D = ca.jacobian(y[:5], x)
        C = D @ P @ D.T
        zero = ca.DM.zeros(1)
        self.predict = ca.Function("bank_window_predict", [x, s, u, th, hold, P, qv],
                                   [ca.densify(e) for e in (x_next, A, s, y, H, P, zero)],
                                   ["x", "s", "u", "theta", "hold", "P", "qv"],
                                   ["x_next", "A", "s_next", "y", "H", "P_next", "piv"])
        self.outputs = ca.Function("bank_window_outputs", [x, s, th, hold, P],
                                   [ca.densify(e) for e in (s, y, H, D, 0.5 * (C + C.T))],
                                   ["x", "s", "theta", "hold", "P"], ["s_out", "y", "H", "D", "C"])
        self._h_max = ca.Function("bank_h_max", [th], [ca.DM(model.h_table_max)])

    def h_max_function(self) -> ca.Function:
        """theta -> the largest node height, m: the tables' top."""
        return self._h_max


def window_settings(s: ChamberEKFSettings, model: ChamberBank, horizon: int = 20, **kw) -> MHESettings:
    """The windows' settings from the EKF bank's (the same sample period, noise, pressure model error,
    sensor range and random walks; the gas's process noise as the window's mass flow error and random
    walk) and the window's own (``horizon`` samples, ``kw``: :class:`MHESettings` fields)."""
    a = model.actuator
    me = a.p_env * a.V0 / (a.R * a.T)
    dt = s.sample_period
    base = MHESettings(sample_period=dt, noise_std=s.noise_std, model_rel_std=s.model_rel_std,
                       sensor_range=s.sensor_range, flow_rel_std=min(s.x_rel_std, 1.0),
                       mass_std_abs=min(s.x_abs_std * me / math.sqrt(dt), 1e-5), flow_factor_std=s.b_rate_std,
                       modulus_std=s.k_rate_std, dead_volume_std=s.c_rate_std, load_max=model.load_max,
                       horizon=horizon, valve_delay=s.valve_delay, sensor_delay=s.sensor_delay)
    return replace(base, **kw).validate()


_CACHE: dict = {}


class RobotMHE:
    """n chamber windows over the EKF bank (see module doc), with :class:`ChamberEKFBank`'s API:
    ``step(z, w, W, steps=1)`` -> the same dict of (n,) arrays, ``reset``, ``rest_state``, ``gas_mass``,
    ``stats`` (the bank's counts, ``mhe_steps``, ``fallbacks`` and ``fallbacks_per_chamber``).

    model, n, settings : as the bank's. horizon : samples per window. window : more
    :class:`MHESettings` fields of the windows (``reseed_cost``, ``huber``, ``qp_solver``, ``compile``).
    """

    def __init__(self, model: ChamberBank, n: int, settings: ChamberEKFSettings | None = None,
                 horizon: int = 20, **window):
        self.ekf = ChamberEKFBank(model, n, settings)
        self.settings = self.ekf.settings
        self.model = model
        self.n = n
        self.window = ws = window_settings(self.settings, model, horizon, **window)
        self.N = N = int(ws.horizon)
        self.om = om = BankWindowModel(model, ws.sample_period)
        key = (id(model), repr(ws), n)
        if key not in _CACHE:
            packed = mhe_packed_function(om, ws, known_load=True).map(n)
            lin = linearise_function(om, N, known_load=True)
            if ws.compile:
                flags = list(HOT_FLAGS) + casadi_lib_flags(QP_LIBS[ws.qp_solver])
                packed = compiled(packed, HOT_OPT, flags,
                                  notice=f"compiling the robot MHE step ({n} chambers, N = {N}) once for this machine ...")
            _CACHE[key] = (packed, lin)
        packed, lin = _CACHE[key]
        self._fn = FastFunction(packed, False)
        self._lin = lin
        self._lay = window_layout(N, known_load=True)
        self._size = sum(r * c for _, (r, c) in self._lay)
        self._off = {}
        i = 0
        for name, (r, c) in self._lay:
            self._off[name] = (i, r, c)
            i += r * c
        #: the windows, one column per chamber (column-major parts, :func:`window_layout`)
        self.win = np.zeros((self._size, n), order="F")
        self._timing = CommandTiming(ws.sample_period, self.settings.valve_delay, self.settings.sensor_delay)
        self._filled = np.zeros(n, dtype=int)
        self._hist: deque = deque(maxlen=N + 1)  # the EKF's (X, P) over the windows' samples
        self.fallbacks = np.zeros(n, dtype=int)
        self.counts = {"mhe_steps": 0, "reseeds": 0, "restarts": 0}
        self.last: dict = {}
        self.last_status = np.full(n, -1)
        self.last_cost = np.full(n, np.nan)

    # --- the bank's API -----------------------------------------------------------------------
    @property
    def X(self):
        """The EKF bank's state (4, n) (the windows' companion)."""
        return self.ekf.X

    @property
    def P(self):
        """The EKF bank's covariance (16, n)."""
        return self.ekf.P

    @property
    def resets(self) -> int:
        """Diverged EKF filters restarted (the bank's count)."""
        return self.ekf.resets

    @property
    def max_steps(self) -> int:
        """The most periods one step predicts over (the bank's)."""
        return self.ekf.max_steps

    def rest_state(self, p0) -> np.ndarray:
        """:meth:`ChamberEKFBank.rest_state`."""
        return self.ekf.rest_state(p0)

    gas_mass = staticmethod(ChamberEKFBank.gas_mass)

    def reset(self, p0, mask=None) -> None:
        """Restart the filters (all, or those in ``mask``) at rest from readings p0 (n,) Pa; their windows
        fill again from the restarted EKF's estimates."""
        self.ekf.reset(p0, mask)
        m = np.ones(self.n, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
        self._filled[m] = 0

    def stats(self) -> dict:
        """The EKF bank's counts, ``mhe_steps`` (chamber steps the windows gave), ``fallbacks`` (chamber
        steps the EKF gave after a failed window step or a window cost above ``reseed_cost``, of which
        ``reseeds`` the latter), ``fallbacks_per_chamber`` and ``restarts`` (late ticks: every window
        refilled)."""
        c = self.ekf.stats()
        c.update(self.counts)
        c["fallbacks"] = int(self.fallbacks.sum())
        c["fallbacks_per_chamber"] = [int(v) for v in self.fallbacks]
        return c

    # --- the window ---------------------------------------------------------------------------
    def _part(self, name: str, cols=slice(None)) -> np.ndarray:
        i, r, c = self._off[name]
        return self.win[i:i + r * c, cols]

    def _push(self, cols: np.ndarray, ua: np.ndarray, zf: np.ndarray, code: np.ndarray, W: np.ndarray) -> None:
        """Shift the windows of chambers ``cols`` by one sample (as the packed step does inside)."""
        N = self.N
        for name, (r, c) in self._lay:
            if name in _FIXED:
                continue
            i = self._off[name][0]
            a = self.win[i:i + r * c]
            blk = r if c > 1 else 1  # column-major: one node or interval is a block of r entries
            a[:-blk, cols] = a[blk:, cols]
        U = self._part("U")
        U[3 * (N - 1):, cols] = ua[:, cols]
        self._part("Z")[N - 1, cols] = zf[cols]
        self._part("kinds")[N - 1, cols] = code[cols]
        self._part("WL")[N, cols] = W[cols]

    def _start(self, cols: np.ndarray) -> None:
        """The windows of ``cols`` from the EKF's posteriors over their samples: nodes, parameters, the
        arrival cost at node 0 (the load's row decoupled: it is known), the whole linearisation."""
        N, me = self.N, self.om.m_env
        Xs = np.array([h[0] for h in self._hist])  # (N + 1, 4, n)
        Ps = np.array([h[1] for h in self._hist])  # (N + 1, 16, n)
        lo = [r[0] for r in self.om.factor_ranges]
        hi = [r[1] for r in self.om.factor_ranges]
        for i in cols:
            M = np.maximum(Xs[:, 0, i] * me, me)
            WL = self._part("WL", i)
            th = np.concatenate([[WL[N]], np.clip(Xs[-1, 1:, i], lo, hi)])
            self._part("M", i)[:] = M
            self._part("th", i)[:] = th
            self._part("S", i)[:] = 0.0
            x0 = Xs[0, :, i]
            self._part("xbar", i)[:] = [max(x0[0] * me, me), WL[0], *x0[1:]]
            P4 = Ps[0, :, i].reshape(4, 4, order="F")
            T = np.diag([me, 1.0, 1.0, 1.0])
            P5 = np.zeros((NX, NX))
            idx = [0, 2, 3, 4]
            P5[np.ix_(idx, idx)] = T @ P4 @ T
            P5[1, 1] = 1.0
            self._part("P0", i)[:] = guard_cov(P5, self.window.cov_floor).ravel(order="F")
            U = self._part("U", i).reshape(3, N, order="F")
            out = self._lin(M, th, np.zeros((2, N + 1)), U, self.om.theta, WL)
            for name, o in zip(("XI", "FM", "AR", "XM", "PV", "HR", "HV", "DH", "RS"), out):
                self._part(name, i)[:] = np.asarray(o).ravel(order="F")

    def step(self, z, w, W, steps: int = 1) -> dict:
        """One period (see :meth:`ChamberEKFBank.step`): the EKF bank steps, then every full window takes
        one step in one mapped call; a chamber's failed step falls back to the EKF's estimate."""
        n, N, me = self.n, self.N, self.om.m_env
        est = dict(self.ekf.step(z, w, W, steps))
        Wv = self.model.clip_load(np.asarray(W, dtype=float).reshape(n))
        wv = np.asarray(w, dtype=float)
        if wv.size == 2 * n:
            wv = np.vstack([np.ones((1, n)), wv.reshape(2, n)])
        wv = wv.reshape(3, n)
        k = int(steps)
        ua = self._timing.acting(wv, k) if self._timing.active else wv
        if k > 1:  # a late tick: the windows have no readings of the missed periods; they refill
            self._filled[:] = 0
            self.counts["restarts"] += 1
        zf = np.where(est["used"], floats_or_nan(z, n), 0.0)
        code = np.where(est["used"], float(KIND_OK), float(KIND_NONE))
        self._hist.append((self.ekf.X.copy(), self.ekf.P.copy()))
        filling = self._filled <= N
        full = ~filling
        if filling.any():
            cols = np.nonzero(filling)[0]
            self._push(cols, ua, zf, code, Wv)
            self._filled[cols] += 1
            ready = cols[self._filled[cols] == N + 1]
            if ready.size and len(self._hist) == N + 1:
                self._start(ready)
        self.last_status[:] = -1
        if full.any():
            smp = np.vstack([ua, zf, code, Wv])
            out = self._fn(self.win, smp, np.zeros((1, n)))
            status = out[8]
            cost = out[9]
            ok = full & (status == 0)
            if self.window.reseed_cost > 0:
                high = ok & (cost > self.window.reseed_cost * N)
                self.counts["reseeds"] += int(high.sum())
                ok &= ~high
            bad = full & ~ok
            win_next = out[11].reshape(n, self._size).T
            # failed windows shift without the step (their nodes are restarted from the EKF below)
            self.win[:, ok] = win_next[:, ok]
            if bad.any():
                cols = np.nonzero(bad)[0]
                self._push(cols, ua, zf, code, Wv)
                self.fallbacks[cols] += 1
                if len(self._hist) == N + 1:
                    self._start(cols)
            if ok.any():
                self.counts["mhe_steps"] += int(ok.sum())
                self.last_status[ok] = 0
                self.last_cost[ok] = cost[ok]
                e5 = out[5].reshape(n, 5).T
                x5 = out[13].reshape(n, NX).T
                sd = out[14].reshape(n, 5).T
                xb = x5[4] * x5[0] / me - 1
                row = lambda v: ca.DM(v[ok]).T  # noqa: E731
                lam = np.asarray(self.model.out(row(xb), row(Wv), row(x5[3]), row(x5[4]))[2], dtype=float).ravel()
                piv_low = ok & (out[12] <= 0.0)
                for i in np.nonzero(piv_low)[0]:
                    P0 = self._part("P0", i)
                    P0[:] = guard_cov(P0.reshape(NX, NX, order="F"), self.window.cov_floor).ravel(order="F")
                for key, v in (("x", xb), ("b", x5[2]), ("k", x5[3]), ("c", x5[4]), ("h", np.maximum(e5[2], 0.0)),
                               ("p", e5[4]), ("h_std", sd[2])):
                    a = np.array(est[key], dtype=float)
                    a[ok] = v[ok]
                    est[key] = a
                lam_all = np.array(est["lam"], dtype=float)
                lam_all[ok] = lam
                est["lam"] = lam_all
        est["mhe"] = self.last_status == 0
        self.last = est
        return est
