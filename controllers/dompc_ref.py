"""do-mpc solving the same OCP as :class:`hbma_ctrl.controllers.mpc.NMPC`: a benchmark-only reference.

do-mpc is an optional extra (``pip install hbma-ctrl[bench]``); it is imported lazily here and
nowhere else, so the package runs without it. The adapter uses the very same discrete model
(:meth:`PredictionModel.discrete`), horizon, weights, input bounds, ``speed <= inlet`` and the soft
pressure / stretch / height limits, and the same preprocessing of the estimate (load filter,
initial state, output biases, target clipping) as the NMPC, so only the transcription and the
solver differ. Differences that remain, stated: do-mpc's soft constraints carry a linear slack
penalty only, and it has no input-rate bounds (the NMPC's defaults are not binding at 20 ms).
"""

from __future__ import annotations

import time
import warnings

import casadi as ca
import numpy as np

from hbma_ctrl.controllers.mpc import NMPC
from hbma_ctrl.controllers.mpc_settings import MPCSettings, timing_stats
from hbma_ctrl.core.extras import dompc_available
from hbma_ctrl.core.interfaces import SAFE_COMMAND, Command, ControllerBase, Estimate, Reference
from hbma_ctrl.core.params import Actuator, Pneumatics
from hbma_ctrl.models.tables import PredictionModel

__all__ = ["DoMPCController"]


class DoMPCController(ControllerBase):
    """The NMPC's OCP transcribed and solved by do-mpc (IPOPT), with the controller step API
    (:class:`~hbma_ctrl.core.interfaces.Controller`). It counts its failures itself (``fallbacks``) and
    sends the safe command for them: its ``step_status`` stays ok and it keeps no ``plan``."""

    def __init__(self, actuator: Actuator, pneumatics: Pneumatics, settings: MPCSettings | None = None,
                 model: PredictionModel | None = None):
        ok, why = dompc_available()
        if not ok:
            raise ImportError(why)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            import do_mpc
        self.settings = s = (settings or MPCSettings()).validate()
        # the NMPC provides the identical preprocessing of the estimate (never its solver here)
        self._pre = NMPC(actuator, pneumatics, s, model=model)
        pm = self._pre.model
        Fd = pm.discrete(s.sample_period, s.integrator, s.substeps)
        mdl = do_mpc.model.Model("discrete", "SX")
        x = mdl.set_variable("_x", "x")
        sp = mdl.set_variable("_u", "speed")
        inl = mdl.set_variable("_u", "inlet")
        out = mdl.set_variable("_u", "outlet")
        W = mdl.set_variable("_tvp", "W")
        dh = mdl.set_variable("_tvp", "dh")
        dp = mdl.set_variable("_tvp", "dp")
        r = mdl.set_variable("_tvp", "r")
        plim = mdl.set_variable("_tvp", "plim")

        u = ca.vertcat(sp, inl, out)
        mdl.set_rhs("x", Fd(x, u, W, dp))
        mdl.setup()
        # objective and constraints from the set-up model's own symbols
        x, W, dh, dp, r, plim = (mdl.x["x"], mdl.tvp["W"], mdl.tvp["dh"], mdl.tvp["dp"], mdl.tvp["r"],
                                 mdl.tvp["plim"])
        sp, inl, out = mdl.u["speed"], mdl.u["inlet"], mdl.u["outlet"]
        u = ca.vertcat(sp, inl, out)
        h = pm.H(x, W) * 1e3 + dh * 1e3
        p = pm.Pp(x, W) * 1e-3 + dp * 1e-3
        lam = pm.L(x, W) * 1e2
        mpc = do_mpc.controller.MPC(mdl)
        mpc.settings.n_horizon = s.horizon
        mpc.settings.t_step = s.sample_period
        mpc.settings.store_full_solution = False
        mpc.settings.nlpsol_opts = {"ipopt.print_level": 0, "ipopt.sb": "yes", "print_time": 0,
                                    "ipopt.max_iter": s.ipopt_max_iter}
        e = h - r * 1e3
        wu, cu = np.array(s.w_input), np.array(s.c_input)
        lterm = s.w_height * e ** 2 + sum(wu[i] * u[i] ** 2 + cu[i] * u[i] for i in range(3))
        mpc.set_objective(lterm=lterm, mterm=(s.w_height + s.w_terminal) * e ** 2)
        wr = np.array(s.w_rate)
        mpc.set_rterm(speed=float(wr[0]), inlet=float(wr[1]), outlet=float(wr[2]))
        for name, ub in zip(("speed", "inlet", "outlet"), s.u_max):
            mpc.bounds["lower", "_u", name] = 0.0
            mpc.bounds["upper", "_u", name] = float(ub)
        mpc.bounds["lower", "_x", "x"] = -0.5
        mpc.bounds["upper", "_x", "x"] = 50.0
        pen = float(s.c_slack)
        mpc.set_nl_cons("pump", sp - inl, ub=0.0)
        soft = {"p": p - plim * 1e-3, "lam": lam - s.lam_max * 1e2, "hmax": h - s.h_max * 1e3}
        if s.h_min > 0:
            soft["hmin"] = s.h_min * 1e3 - h
        for name, expr in soft.items():
            mpc.set_nl_cons(name, expr, ub=0.0, soft_constraint=True, penalty_term_cons=pen)
        tmpl = mpc.get_tvp_template()
        self._tvp = {"W": 0.0, "dh": 0.0, "dp": 0.0, "plim": s.p_max}
        self._r = np.zeros(s.horizon)

        def tvp_fun(t_now):
            # stage k's cost is on x_k, the NMPC's on x_{k+1} with r[k]: r at stage k is r[k - 1]
            for k in range(s.horizon + 1):
                for key, val in self._tvp.items():
                    tmpl["_tvp", k, key] = val
                tmpl["_tvp", k, "r"] = self._r[max(k - 1, 0)]
            return tmpl

        mpc.set_tvp_fun(tvp_fun)
        with warnings.catch_warnings():
            # do-mpc 5.1.2's setup (_check_validity) calls numpy on casadi values, for which casadi 3.8
            # prints a page-long FutureWarning in the middle of `bench mpc`'s table; it is about
            # do-mpc's code, and only that notice is silenced
            warnings.filterwarnings("ignore", message=r"\s*casadi: a numpy function was called on a casadi value",
                                    category=FutureWarning)
            mpc.setup()
        self.mpc = mpc
        self._started = False
        self.solve_ms: list = []
        self.solve_cpu_ms: list = []
        self.failures = 0
        self.last: dict = {}

    accepts_preview = True

    def step(self, t: float, estimate: Estimate, reference: Reference, preview=None) -> Command:
        """One do-mpc ``make_step`` on the NMPC's problem data (timed: the whole step)."""
        t0 = time.perf_counter()
        c0 = time.thread_time()
        try:
            pr = self._pre._problem(t, estimate, reference, preview)
            self._tvp.update({"W": pr.W, "dh": pr.dh, "dp": pr.dp, "plim": pr.p_lim})
            self._r = pr.r
            x0 = np.array([[pr.x0]])
            if not self._started:
                self.mpc.x0 = x0
                self.mpc.u0 = pr.u_prev.reshape(3, 1)
                self.mpc.set_initial_guess()
                self._started = True
            u = np.asarray(self.mpc.make_step(x0)).ravel()
            ok = bool(self.mpc.solver_stats.get("success", True)) and np.all(np.isfinite(u))
        except RuntimeError as exc:  # a casadi/IPOPT error inside make_step: count it, go safe
            ok, u = False, None
            self.last["error"] = str(exc)
        if not ok:
            self.failures += 1
            u = SAFE_COMMAND.as_array()
        u = np.clip(u, 0.0, 1.0)
        self._pre._u_prev = u.copy()
        self.solve_ms.append((time.perf_counter() - t0) * 1e3)
        self.solve_cpu_ms.append((time.thread_time() - c0) * 1e3)
        return Command(*(float(v) for v in u))

    def stats(self) -> dict:
        tt = timing_stats(self.solve_ms)
        cc = timing_stats(self.solve_cpu_ms)
        return {"variant": "do-mpc", "horizon": self.settings.horizon, "solve_ms_median": tt["median"],
                "solve_ms_p99": tt["p99"], "solve_ms_max": tt["max"], "steps": tt["n"],
                "solve_cpu_ms_median": cc["median"], "solve_cpu_ms_p99": cc["p99"],
                "fallbacks": int(self.failures), "guard_activations": 0, "target_clipped_steps": 0}
