"""do-mpc's moving-horizon estimator on the chamber MHE's problem: a benchmark-only reference.

do-mpc is an optional extra (``pip install hbma-ctrl[bench]``), imported here only. The adapter
states the problem of :class:`hbma_ctrl.estimators.mhe.MHE` in do-mpc's terms: the same discrete
model (the EKF's, :func:`hbma_ctrl.estimators.mhe.lean_model`; the shape's warm start carried as two
more states without noise), the same window, the load and the three factors as estimated parameters
within their bounds, the pressure reading with the EKF's measurement noise, the gas mass at least the
ambient's. What do-mpc does differently, stated: the gas mass carries the EKF's process noise at every
node (the MHE's window follows the model from its first state), its arrival cost has fixed weights
(the prior's covariance at the start, never updated), every sample is a full IPOPT solve, the
commands are measured inputs (do-mpc's way: a measurement of u with a tight weight) and a
saturated reading is taken as the range itself (no censoring).
"""

from __future__ import annotations

import time
import warnings

import casadi as ca
import numpy as np

from hbma_ctrl.core import interrupt
from hbma_ctrl.core.extras import dompc_available
from hbma_ctrl.estimators.common import FACTOR_RANGE
from hbma_ctrl.estimators.ekf_step import observer_model
from hbma_ctrl.estimators.mhe import MHE, MHESettings, lean_model
from hbma_ctrl.estimators.mhe_problem import lean_meas
from hbma_ctrl.models.actuation import CommandTiming

__all__ = ["DoMPCMHE", "compare_dompc"]


class DoMPCMHE:
    """do-mpc's MHE (IPOPT per sample) on the chamber MHE's problem (module docstring), SI.

    ``start(x, P, shape)`` sets the prior (the EKF's posterior: state [m, W, b, k, c], covariance,
    shape warm start); ``step(z, u) -> (h, p, x)`` adds one sample (the reading z in Pa, the command
    acting over the period) and returns the newest node's height (m), pressure (Pa) and state;
    ``last_step_s`` its wall time."""

    def __init__(self, actuator, pneumatics, settings: MHESettings):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            import do_mpc
        self.s = s = settings.validate()
        om = observer_model(actuator, pneumatics, s)
        self.om = om
        pred, _ = lean_model(om)
        meas = lean_meas(om)
        theta = ca.DM(np.asarray(om.theta, dtype=float))
        mdl = do_mpc.model.Model("discrete", "SX")
        m = mdl.set_variable("_x", "m")
        h1w = mdl.set_variable("_x", "h1w")
        h2w = mdl.set_variable("_x", "h2w")
        u = mdl.set_variable("_u", "u", (3, 1))
        par = [mdl.set_variable("_p", n) for n in ("W", "b", "k", "c")]
        x5 = ca.vertcat(m, *par)
        sh = ca.vertcat(h1w, h2w)
        xn, _, sn = pred(x5, sh, u, theta)
        _, y, _, _ = meas(x5, sh, theta)
        self._scale = 1e-6  # the gas mass in mg inside do-mpc (IPOPT's scaling)
        mdl.set_meas("p", y[4], meas_noise=True)
        mdl.set_meas("u_meas", u, meas_noise=False)
        mdl.set_rhs("m", xn[0], process_noise=True)
        mdl.set_rhs("h1w", sn[0], process_noise=False)
        mdl.set_rhs("h2w", sn[1], process_noise=False)
        mdl.setup()
        mhe = do_mpc.estimator.MHE(mdl, ["W", "b", "k", "c"])
        mhe.settings.n_horizon = s.horizon
        mhe.settings.t_step = s.sample_period
        mhe.settings.meas_from_data = True
        mhe.settings.store_full_solution = False
        # IPOPT as the MHE's own reference runs it: a limited-memory Hessian (the exact one takes second
        # derivatives through the shape's Newton projection, NaN at the flat membrane)
        mhe.settings.nlpsol_opts = {"ipopt.print_level": 0, "print_time": 0, "ipopt.sb": "yes",
                                    "ipopt.max_iter": s.ipopt_iter, "ipopt.hessian_approximation": "limited-memory"}
        mhe.scaling["_x", "m"] = self._scale
        self.mdl, self.mhe = mdl, mhe
        self._timing = CommandTiming(s.sample_period, s.valve_delay, s.sensor_delay)
        self.last_step_s = 0.0

    def start(self, x: np.ndarray, P: np.ndarray, shape: np.ndarray, u_hist: list) -> None:
        """Set the fixed arrival weights from the prior (x, P), the warm start, and the commands sent so far."""
        s, mhe = self.s, self.mhe
        Pd = np.diag(P)
        R = s.noise_std ** 2 + (s.model_rel_std * 2e4) ** 2
        q = (s.flow_rel_std * 2e-8) ** 2 + s.mass_std_abs ** 2 * s.sample_period
        P_x = np.diag([1.0 / Pd[0], 1e-6, 1e-6])
        P_p = np.diag(1.0 / np.maximum(Pd[1:], 1e-12))
        P_v = np.diag([1.0 / R])
        P_w = np.diag([1.0 / q])
        mhe.set_default_objective(P_x, P_v, P_p, P_w)
        mhe.bounds["lower", "_p_est", "W"] = 0.0
        mhe.bounds["upper", "_p_est", "W"] = s.load_max
        for n in ("b", "k", "c"):
            mhe.bounds["lower", "_p_est", n] = FACTOR_RANGE[0]
            mhe.bounds["upper", "_p_est", n] = FACTOR_RANGE[1]
        mhe.bounds["lower", "_x", "m"] = self.om.m_env
        mhe.setup()
        mhe.x0 = np.array([x[0], shape[0], shape[1]])
        mhe.p_est0 = np.asarray(x[1:], dtype=float)
        mhe.set_initial_guess()
        for u in u_hist:
            self._timing.acting(u, 0 if u is u_hist[0] else 1)

    def step(self, z: float, u: np.ndarray) -> tuple:
        """One sample: the reading z (Pa; None: the last prediction's pressure, do-mpc needs a number) and
        the command held over the period."""
        t0 = time.perf_counter()
        s = self.s
        ua = self._timing.acting(u, 1) if self._timing.active else u
        zz = min(float(z), s.sensor_range) if z is not None and np.isfinite(z) else 0.0
        y = np.concatenate([[zz], ua]).reshape(-1, 1)
        x = np.asarray(self.mhe.make_step(y)).ravel()
        self.last_step_s = time.perf_counter() - t0
        return x


def compare_dompc(trial, rec, settings: MHESettings, steps: int) -> dict:
    """do-mpc's MHE and :class:`~hbma_ctrl.estimators.mhe.MHE` over the same ``steps`` samples of one rig
    run (after the window fills; both started from the EKF's posterior there): median step times (us),
    their ratio ``dompc_mhe_over_mhe_speed`` (do-mpc's median over the MHE's), and both pressure
    estimates' RMS difference (Pa) as a check that they solve the same problem. Each of do-mpc's steps
    (seconds each) is preceded by :func:`hbma_ctrl.core.interrupt.check`."""
    N = settings.horizon
    mhe = MHE(trial.actuator, trial.pneumatics, settings)
    K = len(rec.t)
    start = N + 1
    stop = min(start + steps, K)
    u0 = np.zeros(3)
    ts_mhe, p_mhe = [], []
    for k in range(stop):
        e = mhe.step(rec.t[k], rec.meas[k], rec.u[k - 1] if k > 0 else u0)
        if k == start - 1:
            # the prior do-mpc starts from: the window's arrival cost (the EKF's posterior at node 0)
            prior = (mhe.xbar.copy(), mhe.P0.copy(), mhe.S[:, 0].copy())
            first = k - N
        if k >= start:
            ts_mhe.append(mhe.last_step_s)
            p_mhe.append(e.p)
    d = DoMPCMHE(trial.actuator, trial.pneumatics, settings)
    meas = lean_meas(d.om)
    d.start(*prior, [rec.u[j - 1] if j > 0 else u0 for j in range(first + 1)])
    ts_d, p_d = [], []
    for k in range(first + 1, stop):
        interrupt.check()
        x = d.step(rec.meas[k], rec.u[k - 1])
        if k >= start:
            ts_d.append(d.last_step_s)
            xs = np.concatenate([[x[0]], np.asarray(d.mhe._p_est0.cat).ravel()])
            p_d.append(float(meas(xs, x[1:3], d.om.theta)[1][4]))
    med_m, med_d = float(np.median(ts_mhe)) * 1e6, float(np.median(ts_d)) * 1e6
    return {"dompc_mhe_step_us_median": med_d, "dompc_compare_mhe_step_us_median": med_m,
            "dompc_mhe_over_mhe_speed": med_d / med_m, "dompc_steps": len(ts_d),
            "dompc_vs_mhe_pressure_rms_pa": float(np.sqrt(np.mean((np.array(p_d) - np.array(p_mhe)) ** 2)))}
