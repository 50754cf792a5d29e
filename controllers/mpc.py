"""Nonlinear MPC of one chamber's membrane height: IPOPT (accurate) or RTI + OSQP (fast), one API.

The optimal control problem (both variants solve the same one)
--------------------------------------------------------------
State: the scaled gas mass x of :class:`controllers.prediction.PredictionModel` (one state; the
shape follows from the equilibrium manifold, so resting, lift-off, contact and free inflation are
one smooth model). Inputs u = [compressor speed, inlet duty, outlet duty], each in [0, 1].
Parameters per step: the initial state, the load W (N, from the estimate's contact force), output
biases d_h, d_p (estimate minus model at the initial state: offset-free tracking under model
mismatch), the reference, the previous command.

    min  sum_k w_h (h_k - r)^2 + w_N (h_N - r)^2                   (h in mm)
         + sum_k w_du |u_k - u_{k-1}|^2 + w_u |u_k|^2 + c_u . u_k
         + sum_k w_s s_k^2 + c_s s_k
    s.t. x_{k+1} = F(x_k, u_k; W, d_p)         (RK4 or Euler over one sample period)
         0 <= u_k <= u_max, |u_k - u_{k-1}| <= du_max dt, speed_k <= inlet_k
         p_k + d_p <= p_max - p_margin + s_k   (kPa)     lam_k <= lam_max + s_k (1/100)
         h_min - s_k <= h_k <= h_max + s_k     (mm)      s_k >= 0   (lower bound only if h_min > 0)

"speed <= inlet" says the compressor never runs into a closed inlet (the pump flow is
``inlet * q(speed, p)``; pumping against a shut valve only stalls it). The state constraints are
soft (exact-penalty slack), so the problem is feasible from any state. Below lift-off the
model's height is a virtual negative height (:class:`PredictionModel`), which keeps a gradient
towards pumping when the platform rests; the height bias is zero while resting, e.g. after a disturbance
pushed the pressure above the limit. A target above what is reachable within p_max and lam_max is
clipped to the reachable height (the load path of the current load) and reported in ``stats()``.

Variants (``MPCSettings.variant``)
----------------------------------
``ipopt``: multiple shooting NLP solved to convergence by IPOPT, warm-started with the shifted
previous solution: the accurate reference, 5-30 ms per step.
``rti_osqp``: real-time iteration. One casadi Function (``map`` over the N+1 nodes, optionally
compiled to C) returns the discrete dynamics, their Jacobians and the linearised outputs along the
shifted previous solution; one sparse QP with a fixed pattern is updated in place (``update``: q, l,
u, Px, Ax; never re-setup) and solved by OSQP, warm-started. The pump flow is bilinear in speed and
inlet duty; at a plan with the pump off its Jacobian vanishes, so the linearisation point of speed
and inlet is floored at ``rti_lin_floor`` (the affine term stays exact at the plan).

Valve duty -> on/off. A duty d in [0, 1] is a PWM command: the valve is held open for d * T_pwm of
each PWM period T_pwm (``duty_to_on_time``); the averaged flow is d times the open flow, which is
what the model uses. On-times shorter than the valve's minimum switching time are rounded to 0 or
T_pwm (whichever is nearer) by the valve driver, not by the MPC.

Embedding. ``step(t, estimate, reference) -> Command`` never raises on a numerical failure: on a
solver failure or a wall-clock overrun (``budget``) it returns the previous plan shifted by one step
(for at most ``fallback_plan_steps`` steps), and after that :data:`SAFE_COMMAND` (compressor off,
outlet open). A cold start (the first step, or the first after a failure: the RTI solves
``rti_init_iterations`` QPs then) is exempt from the budget: a daemon calls ``step`` once before
its loop starts to warm up. Every fallback is counted; ``stats()`` has per-step solve timing. A pressure guard
overrides any command that would pump above ``p_max - guard_margin`` (counted separately). No
global state: everything lives on the instance.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass, fields

import casadi as ca
import numpy as np
import scipy.sparse as sp

from hbma_ctrl.interfaces import SAFE_COMMAND, Command, Estimate, Reference
from hbma_ctrl.params import Actuator, Pneumatics, check_range
from hbma_ctrl.validation import did_you_mean

from .prediction import PredictionModel

__all__ = ["MPCSettings", "NMPC", "VARIANTS", "duty_to_on_time", "timing_stats"]

VARIANTS = ("rti_osqp", "ipopt")


@dataclass
class MPCSettings:
    """Settings of :class:`NMPC` (SI; one docstring line per field).

    Fields
    ------
    variant : 'rti_osqp' (fast: one QP per step) or 'ipopt' (accurate: NLP to convergence).
    horizon : number of shooting intervals N, [2, 200].
    sample_period : controller period and shooting interval, s, (0, 1].
    integrator : 'rk4' or 'euler' for the discrete dynamics.
    substeps : integrator steps per shooting interval, [1, 20].
    w_height : weight on the height error, per mm^2 per stage.
    w_terminal : weight on the final height error, per mm^2.
    w_rate : weights on the input changes (speed, inlet, outlet), per step.
    w_input : quadratic weights on the inputs (speed, inlet, outlet).
    c_input : linear costs on the inputs (speed, inlet, outlet): prefer idle, use the pump sparingly.
    w_slack : quadratic penalty on constraint violation (slack in kPa / mm / 0.01 stretch).
    c_slack : linear (exact) penalty on constraint violation.
    p_max : gauge pressure limit, Pa, (0, 1e6].
    p_margin : the MPC keeps its predicted pressure this far below p_max, Pa.
    guard_margin : the pressure guard cuts the pump when the estimate is this close to p_max, Pa.
    lam_max : stretch limit (-), (1, 5].
    h_min, h_max : height bounds, m.
    u_max : upper input bounds (speed, inlet, outlet), each in (0, 1].
    du_max : input rate limits (speed, inlet, outlet), 1/s.
    budget : wall-clock budget of one step, s; a slower solve is an overrun (fallback).
    fallback_plan_steps : how many steps the shifted previous plan may stand in before the safe command.
    load_max : largest load force the model covers, N (larger estimates are clipped, reported).
    load_tau : time constant of the low-pass on the estimate's contact force, s.
    rest_height : below this estimated height the platform is taken as resting, m.
    rti_lin_floor : RTI only: floor of the speed/inlet linearisation point (see module docstring).
    rti_init_iterations : RTI only: QPs solved at the first step (cold start).
    qp_eps : OSQP absolute and relative tolerance.
    qp_max_iter : OSQP iteration limit.
    ipopt_max_iter : IPOPT iteration limit.
    codegen : compile the RTI linearisation Function to C with the system compiler (about 20 %
        faster steps; +0.6 s at construction; falls back to casadi's virtual machine without a compiler).
    fail_window : (t_start, t_end) s in which every solve is treated as failed (a fallback drill);
        None = never.
    """

    variant: str = "rti_osqp"
    horizon: int = 20
    sample_period: float = 0.02
    integrator: str = "rk4"
    substeps: int = 1
    w_height: float = 1.0
    w_terminal: float = 5.0
    w_rate: tuple = (0.02, 0.002, 0.02)
    w_input: tuple = (0.002, 0.0, 0.002)
    c_input: tuple = (0.02, 0.01, 0.02)
    w_slack: float = 1e3
    c_slack: float = 1e3
    p_max: float = 35e3
    p_margin: float = 1e3
    guard_margin: float = 0.5e3
    lam_max: float = 1.5
    h_min: float = 0.0
    h_max: float = 20e-3
    u_max: tuple = (1.0, 1.0, 1.0)
    du_max: tuple = (50.0, 100.0, 100.0)
    budget: float = 0.015
    fallback_plan_steps: int = 10
    load_max: float = 10.0
    load_tau: float = 0.1
    rest_height: float = 0.1e-3
    rti_lin_floor: float = 0.25
    rti_init_iterations: int = 5
    qp_eps: float = 1e-4
    qp_max_iter: int = 300
    ipopt_max_iter: int = 100
    codegen: bool = True
    fail_window: tuple | None = None

    def validate(self) -> "MPCSettings":
        """Check every field; raise ValueError naming the field and its allowed range."""
        if self.variant not in VARIANTS:
            hint = did_you_mean(str(self.variant), VARIANTS)
            raise ValueError(f"mpc.variant = '{self.variant}'{hint}; allowed: {', '.join(VARIANTS)}")
        if not isinstance(self.horizon, int) or isinstance(self.horizon, bool) or not 2 <= self.horizon <= 200:
            raise ValueError(f"mpc.horizon = {self.horizon!r} must be an integer in [2, 200]")
        check_range("mpc", "sample_period", self.sample_period, 0.0, 1.0, "s", lo_open=True)
        if self.integrator not in ("rk4", "euler"):
            raise ValueError(f"mpc.integrator = '{self.integrator}': allowed rk4, euler")
        if not isinstance(self.substeps, int) or not 1 <= self.substeps <= 20:
            raise ValueError(f"mpc.substeps = {self.substeps!r} must be an integer in [1, 20]")
        for name in ("w_height", "w_terminal", "w_slack", "c_slack"):
            check_range("mpc", name, getattr(self, name), 0.0, 1e9)
        for name in ("w_rate", "w_input", "c_input"):
            v = tuple(getattr(self, name))
            if len(v) != 3:
                raise ValueError(f"mpc.{name} must have 3 entries (speed, inlet, outlet), got {len(v)}")
            for i, x in enumerate(v):
                check_range("mpc", f"{name}[{i}]", float(x), 0.0, 1e6)
        check_range("mpc", "p_max", self.p_max, 0.0, 1e6, "Pa", lo_open=True)
        check_range("mpc", "p_margin", self.p_margin, 0.0, self.p_max, "Pa")
        check_range("mpc", "guard_margin", self.guard_margin, 0.0, self.p_max, "Pa")
        check_range("mpc", "lam_max", self.lam_max, 1.0, 5.0, lo_open=True)
        check_range("mpc", "h_min", self.h_min, 0.0, 0.2, "m")
        check_range("mpc", "h_max", self.h_max, self.h_min, 0.2, "m", lo_open=True)
        if len(tuple(self.u_max)) != 3 or len(tuple(self.du_max)) != 3:
            raise ValueError("mpc.u_max and mpc.du_max must have 3 entries (speed, inlet, outlet)")
        for i, x in enumerate(self.u_max):
            check_range("mpc", f"u_max[{i}]", float(x), 0.0, 1.0, lo_open=True)
        for i, x in enumerate(self.du_max):
            check_range("mpc", f"du_max[{i}]", float(x), 0.0, 1e6, "1/s", lo_open=True)
        check_range("mpc", "budget", self.budget, 0.0, 10.0, "s", lo_open=True)
        if not isinstance(self.fallback_plan_steps, int) or self.fallback_plan_steps < 0:
            raise ValueError(f"mpc.fallback_plan_steps = {self.fallback_plan_steps!r} must be an integer >= 0")
        check_range("mpc", "load_max", self.load_max, 0.0, 200.0, "N", lo_open=True)
        check_range("mpc", "load_tau", self.load_tau, 0.0, 100.0, "s")
        check_range("mpc", "rest_height", self.rest_height, 0.0, 0.01, "m")
        check_range("mpc", "rti_lin_floor", self.rti_lin_floor, 0.0, 1.0)
        if not isinstance(self.rti_init_iterations, int) or not 1 <= self.rti_init_iterations <= 100:
            raise ValueError(f"mpc.rti_init_iterations = {self.rti_init_iterations!r} must be in [1, 100]")
        check_range("mpc", "qp_eps", self.qp_eps, 0.0, 1.0, lo_open=True)
        if not isinstance(self.qp_max_iter, int) or self.qp_max_iter < 1:
            raise ValueError(f"mpc.qp_max_iter = {self.qp_max_iter!r} must be an integer >= 1")
        if not isinstance(self.ipopt_max_iter, int) or self.ipopt_max_iter < 1:
            raise ValueError(f"mpc.ipopt_max_iter = {self.ipopt_max_iter!r} must be an integer >= 1")
        if self.fail_window is not None:
            fw = tuple(self.fail_window)
            if len(fw) != 2 or not (0 <= fw[0] <= fw[1]):
                raise ValueError(f"mpc.fail_window = {self.fail_window!r} must be (t_start, t_end) with 0 <= t_start <= t_end s")
        return self


def duty_to_on_time(duty: float, pwm_period: float, min_on: float = 0.0) -> float:
    """Valve open time (s) per PWM period for a relaxed duty in [0, 1].

    On-times shorter than ``min_on`` (the valve's switching time) round to 0 or, when the off-time
    would be shorter than ``min_on``, to the full period.
    """
    check_range("duty_to_on_time", "duty", duty, 0.0, 1.0)
    check_range("duty_to_on_time", "pwm_period", pwm_period, 0.0, 10.0, "s", lo_open=True)
    on = duty * pwm_period
    if on < min_on:
        return 0.0 if on < 0.5 * min_on else min_on
    if pwm_period - on < min_on:
        return pwm_period
    return on


def timing_stats(ms: list | np.ndarray) -> dict:
    """Median, 99th percentile and max of per-step times (ms); NaN when empty."""
    a = np.asarray(ms, dtype=float)
    if a.size == 0:
        return {"median": float("nan"), "p99": float("nan"), "max": float("nan"), "n": 0}
    return {"median": float(np.median(a)), "p99": float(np.percentile(a, 99)), "max": float(a.max()),
            "n": int(a.size)}


class _SolverFailure(RuntimeError):
    pass


class _BudgetExceeded(_SolverFailure):
    """The solver stopped at its time limit (the step's budget): counted as an overrun."""


@dataclass
class _Problem:
    """Per-step parameters of the OCP (scaled units: h in mm, p in kPa)."""

    x0: float
    W: float
    dh: float  # m
    dp: float  # Pa
    r: np.ndarray  # m, target at stages 1..N (clipped)
    u_prev: np.ndarray
    p_lim: float  # Pa, on the model pressure + dp


class _Stage:
    """Discrete dynamics and outputs shared by both variants (casadi)."""

    def __init__(self, model: PredictionModel, s: MPCSettings):
        self.F = model.discrete(s.sample_period, s.integrator, s.substeps)
        x, W, dp = ca.SX.sym("x"), ca.SX.sym("W"), ca.SX.sym("dp")
        u = ca.SX.sym("u", 3)
        ulin = ca.SX.sym("ulin", 3)
        xn = self.F(x, u, W, dp)
        h = model.H(x, W) * 1e3  # mm
        p = model.Pp(x, W) * 1e-3  # kPa (model, without bias)
        lam = model.L(x, W) * 1e2  # 1/100
        # dynamics value at the plan, Jacobians at the (floored) linearisation point
        xl = self.F(x, ulin, W, dp)
        self.lin = ca.Function(
            "lin", [x, u, ulin, W, dp],
            [xn, ca.jacobian(xl, x), ca.jacobian(xl, ulin), h, ca.jacobian(h, x), p, ca.jacobian(p, x),
             lam, ca.jacobian(lam, x)],
            ["x", "u", "ulin", "W", "dp"], ["f", "a", "b", "h", "ch", "p", "cp", "lam", "cl"])
        self.out = ca.Function("out", [x, W], [h, p, lam])


def _compile(fun: ca.Function, tag: str) -> ca.Function:
    """Generate C for ``fun``, compile it with the system cc and load it (falls back to fun)."""
    d = tempfile.mkdtemp(prefix="hbma_mpc_")
    src = f"{tag}.c"
    cg = ca.CodeGenerator(src, {"with_header": False})
    cg.add(fun)
    cg.generate(d + os.sep)  # a directory prefix: no chdir (process-wide state)
    lib = os.path.join(d, f"{tag}.so")
    try:
        subprocess.run(["cc", "-O2", "-fPIC", "-shared", os.path.join(d, src), "-o", lib, "-lm"],
                       check=True, capture_output=True, timeout=120)
        ext = ca.external(fun.name(), lib)
    except (OSError, subprocess.SubprocessError, RuntimeError):
        return fun
    finally:
        shutil.rmtree(d, ignore_errors=True)  # the loaded library stays mapped
    return ext


class _RtiOsqp:
    """Real-time iteration: one sparse QP per step, fixed pattern, OSQP updated in place."""

    def __init__(self, model: PredictionModel, s: MPCSettings):
        import osqp

        self.s, self.model = s, model
        N = self.N = s.horizon
        self.stage = _Stage(model, s)
        lin = self.stage.lin.map(N + 1)
        self.lin = _compile(lin, f"lin_map{N}") if s.codegen else lin
        # variable layout
        self.ix = np.arange(N + 1)
        self.iu = (N + 1) + np.arange(3 * N).reshape(N, 3)
        self.isl = (N + 1) + 3 * N + np.arange(N)  # slack of stage k+1
        self.nz = (N + 1) + 4 * N
        self._build_pattern()
        self.solver = osqp.OSQP()
        self.solver.setup(self.P, np.zeros(self.nz), self.A, self.l0, self.u0, verbose=False,
                          eps_abs=s.qp_eps, eps_rel=s.qp_eps, max_iter=s.qp_max_iter, polishing=False,
                          warm_starting=True, adaptive_rho=True, time_limit=s.budget)
        self.X = None
        self.U = None
        self.iterations = 0

    # --- QP pattern ----------------------------------------------------------------------------
    def _build_pattern(self) -> None:
        s, N = self.s, self.N
        ix, iu, isl = self.ix, self.iu, self.isl
        # P (upper triangle): x diag (varies), u block tridiagonal (constant), slack diag (constant)
        Pr, Pc, Pv = [], [], []
        for k in range(N + 1):
            Pr.append(ix[k]); Pc.append(ix[k]); Pv.append(0.0)  # noqa: E702
        self.P_x = np.arange(N + 1)
        wr, wu = np.array(s.w_rate, float), np.array(s.w_input, float)
        for k in range(N):
            for i in range(3):
                nd = 2 if k < N - 1 else 1  # u_k appears in (u_k - u_{k-1}) and (u_{k+1} - u_k)
                Pr.append(iu[k, i]); Pc.append(iu[k, i]); Pv.append(2 * wr[i] * nd + 2 * wu[i] + 1e-8)  # noqa: E702
                if k > 0:
                    Pr.append(iu[k - 1, i]); Pc.append(iu[k, i]); Pv.append(-2 * wr[i])  # noqa: E702
        for k in range(N):
            Pr.append(isl[k]); Pc.append(isl[k]); Pv.append(2 * s.w_slack)  # noqa: E702
        self.P, self.P_perm = _csc_with_perm(Pr, Pc, self.nz)
        self.P_vals = np.array(Pv)
        # A rows
        Ar, Ac, Av = [], [], []
        row = 0

        def add(r, c, v):
            Ar.append(r); Ac.append(c); Av.append(v)  # noqa: E702

        self.r_init = row
        add(row, ix[0], 1.0)
        row += 1
        self.r_dyn = row
        self.A_dyn_a, self.A_dyn_b = [], []
        for k in range(N):
            add(row, ix[k + 1], 1.0)
            self.A_dyn_a.append(len(Av)); add(row, ix[k], 0.0)  # noqa: E702
            for i in range(3):
                self.A_dyn_b.append(len(Av)); add(row, iu[k, i], 0.0)  # noqa: E702
            row += 1
        self.r_box = row
        for k in range(N):
            for i in range(3):
                add(row, iu[k, i], 1.0)
                row += 1
        self.r_rate = row
        for k in range(1, N):
            for i in range(3):
                add(row, iu[k, i], 1.0); add(row, iu[k - 1, i], -1.0)  # noqa: E702
                row += 1
        self.r_pump = row  # inlet - speed >= 0
        for k in range(N):
            add(row, iu[k, 1], 1.0); add(row, iu[k, 0], -1.0)  # noqa: E702
            row += 1
        self.r_soft = row  # per stage k = 1..N: p, lam, h_hi, h_lo
        self.A_soft = []
        for k in range(N):
            idx = []
            for _ in range(4):
                idx.append(len(Av)); add(row, ix[k + 1], 0.0)  # noqa: E702
                add(row, isl[k], -1.0)
                row += 1
            self.A_soft.append(idx)
        self.r_slack = row
        for k in range(N):
            add(row, isl[k], 1.0)
            row += 1
        self.nc = row
        self.A, self.A_perm = _csc_with_perm(Ar, Ac, self.nz, self.nc)
        self.A_vals = np.array(Av)
        self.A_dyn_a, self.A_dyn_b = np.array(self.A_dyn_a), np.array(self.A_dyn_b).reshape(N, 3)
        self.A_soft = np.array(self.A_soft)
        inf = np.inf
        self.l0 = np.full(self.nc, -inf)
        self.u0 = np.full(self.nc, inf)
        self.l0[self.r_init] = self.u0[self.r_init] = 0.0
        self.l0[self.r_dyn:self.r_dyn + N] = self.u0[self.r_dyn:self.r_dyn + N] = 0.0
        umax = np.array(s.u_max, float)
        self.l0[self.r_box:self.r_box + 3 * N] = 0.0
        self.u0[self.r_box:self.r_box + 3 * N] = np.tile(umax, N)
        du = np.array(s.du_max, float) * s.sample_period
        self.du = du
        self.l0[self.r_rate:self.r_rate + 3 * (N - 1)] = -np.tile(du, N - 1)
        self.u0[self.r_rate:self.r_rate + 3 * (N - 1)] = np.tile(du, N - 1)
        self.l0[self.r_pump:self.r_pump + N] = 0.0
        self.l0[self.r_slack:self.r_slack + N] = 0.0

    # --- one step -------------------------------------------------------------------------------
    def reset(self) -> None:
        self.X = None
        self.U = None

    def solve(self, pr: _Problem) -> tuple[np.ndarray, np.ndarray]:
        N, s = self.N, self.s
        if self.X is None:
            Xb = np.full(N + 1, pr.x0)
            Ub = np.tile(pr.u_prev, (N, 1))
            iters = s.rti_init_iterations
            self.solver.update_settings(time_limit=1e3)  # cold start: exempt from the budget
        else:
            Xb = np.r_[pr.x0, self.X[2:], self.X[-1]]
            Ub = np.vstack([self.U[1:], self.U[-1:]])
            iters = 1
        try:
            for _ in range(iters):
                Xb, Ub = self._qp(pr, Xb, Ub)
        finally:
            if iters > 1:
                self.solver.update_settings(time_limit=s.budget)
        self.X, self.U = Xb, Ub
        return Xb, Ub

    def _qp(self, pr: _Problem, Xb: np.ndarray, Ub: np.ndarray):
        N, s = self.N, self.s
        Uext = np.vstack([Ub, Ub[-1:]])
        Ulin = Uext.copy()
        fl = s.rti_lin_floor
        Ulin[:, 0] = np.maximum(Ulin[:, 0], fl)
        Ulin[:, 1] = np.maximum(Ulin[:, 1], fl)
        res = self.lin(Xb[None, :], Uext.T, Ulin.T, pr.W, pr.dp)
        f, a, b, h, ch, p, cp, lam, cl = (np.asarray(v) for v in res)
        f, a, h, ch, p, cp, lam, cl = (v.ravel() for v in (f, a, h, ch, p, cp, lam, cl))
        b = b.reshape(3, N + 1, order="F") if b.shape[0] == 3 else b.reshape(N + 1, 3).T
        if not (np.all(np.isfinite(f)) and np.all(np.isfinite(b)) and np.all(np.isfinite(ch))):
            raise _SolverFailure("non-finite linearisation")
        # P: x diagonal from the Gauss-Newton height cost
        wk = np.full(N + 1, s.w_height)
        wk[0] = 0.0
        wk[N] += s.w_terminal
        r_mm, dh_mm = np.r_[pr.r[0], pr.r] * 1e3, pr.dh * 1e3
        e = h - ch * Xb + dh_mm - r_mm  # h_k(x) + dh - r = ch x + e
        Pv = self.P_vals.copy()
        Pv[self.P_x] = 2 * wk * ch ** 2 + 1e-8
        q = np.zeros(self.nz)
        q[self.ix] = 2 * wk * ch * e
        wr = np.array(s.w_rate, float)
        q[self.iu[0]] += -2 * wr * pr.u_prev
        q[self.iu] += np.array(s.c_input, float)[None, :]
        q[self.isl] = s.c_slack
        # A values
        Av = self.A_vals.copy()
        Av[self.A_dyn_a] = -a[:N]
        Av[self.A_dyn_b] = -b[:, :N].T
        k1 = np.arange(1, N + 1)
        Av[self.A_soft[:, 0]] = cp[k1]
        Av[self.A_soft[:, 1]] = cl[k1]
        Av[self.A_soft[:, 2]] = ch[k1]
        Av[self.A_soft[:, 3]] = -ch[k1]
        lo, up = self.l0.copy(), self.u0.copy()
        lo[self.r_init] = up[self.r_init] = pr.x0
        # x_{k+1} - a x_k - b u_k = f - a xb - b ub
        c = f[:N] - a[:N] * Xb[:N] - np.einsum("ik,ki->k", b[:, :N], Ub)
        lo[self.r_dyn:self.r_dyn + N] = up[self.r_dyn:self.r_dyn + N] = c
        # first input: box intersected with the rate limit from the applied command
        umax = np.array(s.u_max, float)
        lo[self.r_box:self.r_box + 3] = np.maximum(0.0, pr.u_prev - self.du)
        up[self.r_box:self.r_box + 3] = np.minimum(umax, pr.u_prev + self.du)
        rs = self.r_soft + 4 * np.arange(N)
        up[rs] = pr.p_lim * 1e-3 - pr.dp * 1e-3 - (p[k1] - cp[k1] * Xb[k1])
        up[rs + 1] = s.lam_max * 1e2 - (lam[k1] - cl[k1] * Xb[k1])
        up[rs + 2] = s.h_max * 1e3 - dh_mm - (h[k1] - ch[k1] * Xb[k1])
        if s.h_min > 0:  # (below lift-off H is a virtual negative height: no bound at h_min = 0)
            up[rs + 3] = -(s.h_min * 1e3 - dh_mm - (h[k1] - ch[k1] * Xb[k1]))
        self.solver.update(q=q, l=lo, u=up, Px=Pv[self.P_perm], Ax=Av[self.A_perm])
        z0 = np.zeros(self.nz)
        z0[self.ix] = Xb
        z0[self.iu] = Ub
        self.solver.warm_start(x=z0)
        r = self.solver.solve(raise_error=False)
        self.iterations = int(r.info.iter)
        if "time limit" in r.info.status:
            raise _BudgetExceeded("osqp: time limit (budget) reached")
        usable = r.info.status in ("solved", "solved inaccurate") or (
            r.info.status == "maximum iterations reached" and r.info.prim_res < 1e-3)
        if not usable or r.x is None or not np.all(np.isfinite(r.x)):
            raise _SolverFailure(f"osqp: {r.info.status}")
        z = r.x
        return z[self.ix].copy(), np.clip(z[self.iu], 0.0, 1.0)


class _Ipopt:
    """Multiple-shooting NLP, IPOPT to convergence, warm-started with the shifted solution."""

    def __init__(self, model: PredictionModel, s: MPCSettings):
        self.s, self.model = s, model
        N = self.N = s.horizon
        self.stage = _Stage(model, s)
        F = self.stage.F
        X = ca.SX.sym("X", N + 1)
        U = ca.SX.sym("U", 3, N)
        S = ca.SX.sym("S", N)
        par = ca.SX.sym("par", 8 + N)  # x0, W, dh(mm), dp(Pa), u_prev(3), p_lim(kPa), r(mm, N stages)
        x0, W, dh, dp = par[0], par[1], par[2], par[3]
        u_prev, p_lim, rr = par[4:7], par[7], par[8:]
        J = 0
        g, lbg, ubg = [X[0] - x0], [0.0], [0.0]
        wr, wu, cu = (ca.DM(list(v)) for v in (s.w_rate, s.w_input, s.c_input))
        du = np.array(s.du_max, float) * s.sample_period
        for k in range(N):
            g.append(X[k + 1] - F(X[k], U[:, k], W, dp))
            lbg.append(0.0); ubg.append(0.0)  # noqa: E702
            d = U[:, k] - (u_prev if k == 0 else U[:, k - 1])
            J += ca.dot(wr, d ** 2) + ca.dot(wu, U[:, k] ** 2) + ca.dot(cu, U[:, k])
            g.append(d)
            lbg += list(-du); ubg += list(du)  # noqa: E702
            g.append(U[1, k] - U[0, k])
            lbg.append(0.0); ubg.append(ca.inf)  # noqa: E702
            h, p, lam = self.stage.out(X[k + 1], W)
            w = s.w_height + (s.w_terminal if k == N - 1 else 0.0)
            J += w * (h + dh - rr[k]) ** 2 + s.w_slack * S[k] ** 2 + s.c_slack * S[k]
            lo_h = (s.h_min * 1e3 - h - dh, 0.0 if s.h_min > 0 else ca.inf)
            for expr, ub in ((p + dp * 1e-3 - p_lim, 0.0), (lam - s.lam_max * 1e2, 0.0),
                             (h + dh - s.h_max * 1e3, 0.0), lo_h):
                g.append(expr - S[k])
                lbg.append(-ca.inf); ubg.append(ub)  # noqa: E702
        z = ca.vertcat(X, ca.vec(U), S)
        self.nz = z.shape[0]
        nlp = {"x": z, "p": par, "f": J, "g": ca.vertcat(*g)}
        opts = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
                "ipopt.max_iter": s.ipopt_max_iter, "ipopt.tol": 1e-6,
                "ipopt.warm_start_init_point": "yes", "ipopt.mu_init": 1e-3,
                "ipopt.max_wall_time": max(10 * s.budget, 0.5), "error_on_fail": False}
        self.solver = ca.nlpsol("mpc_ipopt", "ipopt", nlp, opts)
        self.lbg, self.ubg = np.array(lbg, float), np.array(ubg, float)
        umax = np.array(s.u_max, float)
        self.lbz = np.r_[np.full(N + 1, -0.5), np.zeros(3 * N), np.zeros(N)]
        self.ubz = np.r_[np.full(N + 1, 50.0), np.tile(umax, N), np.full(N, np.inf)]
        self.X = self.U = self.S = None
        self.lam_g = None
        self.iterations = 0

    def reset(self) -> None:
        self.X = self.U = self.S = None
        self.lam_g = None

    def solve(self, pr: _Problem):
        N = self.N
        if self.X is None:
            Xb, Ub, Sb = np.full(N + 1, pr.x0), np.tile(pr.u_prev, (N, 1)), np.zeros(N)
        else:
            Xb = np.r_[pr.x0, self.X[2:], self.X[-1]]
            Ub = np.vstack([self.U[1:], self.U[-1:]])
            Sb = np.r_[self.S[1:], self.S[-1]]
        z0 = np.r_[Xb, Ub.ravel(), Sb]
        par = np.r_[pr.x0, pr.W, pr.dh * 1e3, pr.dp, pr.u_prev, pr.p_lim * 1e-3, pr.r * 1e3]
        kw = {}
        if self.lam_g is not None:
            kw["lam_g0"] = self.lam_g
        sol = self.solver(x0=z0, p=par, lbx=self.lbz, ubx=self.ubz, lbg=self.lbg, ubg=self.ubg, **kw)
        st = self.solver.stats()
        self.iterations = int(st.get("iter_count", 0))
        if not st.get("success", False):
            raise _SolverFailure(f"ipopt: {st.get('return_status')}")
        z = np.asarray(sol["x"]).ravel()
        self.lam_g = np.asarray(sol["lam_g"]).ravel()
        self.X = z[:N + 1]
        self.U = np.clip(z[N + 1:N + 1 + 3 * N].reshape(N, 3), 0.0, 1.0)
        self.S = z[N + 1 + 3 * N:]
        return self.X, self.U


def _csc_with_perm(rows, cols, n, m=None):
    """CSC matrix with the given pattern and the permutation from entry order to CSC data order."""
    m = n if m is None else m
    nnz = len(rows)
    M = sp.csc_matrix((np.arange(1, nnz + 1, dtype=float), (rows, cols)), shape=(m, n))
    M.sort_indices()
    if M.nnz != nnz:
        raise RuntimeError("QP pattern has duplicate entries")
    perm = M.data.astype(int) - 1
    M.data = np.ones(nnz) * 1e-12
    return M, perm


class NMPC:
    """Nonlinear MPC of one chamber's height (see module docstring). SI throughout.

    Parameters
    ----------
    actuator, pneumatics : the nominal actuator and pneumatics (the controller's model).
    settings : :class:`MPCSettings`.
    model : an already built :class:`PredictionModel` of the same actuator (shared to save the
        table build), or None.
    """

    def __init__(self, actuator: Actuator, pneumatics: Pneumatics, settings: MPCSettings | None = None,
                 model: PredictionModel | None = None):
        self.settings = s = (settings or MPCSettings()).validate()
        self.model = model or PredictionModel(actuator, pneumatics, load_max=s.load_max)
        self.backend = _RtiOsqp(self.model, s) if s.variant == "rti_osqp" else _Ipopt(self.model, s)
        self.reset()

    def reset(self) -> None:
        """Forget the plan, the load filter and the statistics."""
        self.backend.reset()
        self._u_prev = np.zeros(3)
        self._W = None
        self._t_prev = None
        self._plan = None  # (U, age)
        self._streak = 0
        self._hold = None
        self.solve_ms: list = []
        self.solve_cpu_ms: list = []  # thread CPU time: what other load on the machine does not inflate
        self.fallbacks = {"solver_failed": 0, "overrun": 0, "shifted_plan": 0, "safe_command": 0}
        self.guard_count = 0
        self.clipped_count = 0
        self.last = {}

    # --- helpers ---------------------------------------------------------------------------------
    def _load(self, t: float, est: Estimate) -> float:
        s = self.settings
        F = float(est.F) if np.isfinite(est.F) else 0.0
        F = max(F, 0.0)
        resting = est.h < s.rest_height or "resting" in est.flags
        if self._W is None:
            self._W = F
        elif resting:
            # resting: the estimate's force is what the plate carries, a lower bound of the load
            self._W = max(F, self._W)
        else:
            dt = s.sample_period if self._t_prev is None else max(t - self._t_prev, 0.0)
            a = 1.0 if s.load_tau <= 0 else min(1.0, dt / s.load_tau)
            self._W += a * (F - self._W)
        return float(min(self._W, s.load_max))

    def _problem(self, t: float, est: Estimate, ref: Reference, preview=None) -> _Problem:
        s, m = self.settings, self.model
        for name in ("h", "p"):
            if not np.isfinite(getattr(est, name)):
                raise _SolverFailure(f"estimate.{name} is not finite")
        W = self._load(t, est)
        if est.h < s.rest_height:
            x0 = min(est.p / self.model.actuator.p_env, m.lift_off_x(W))
        else:
            x0 = m.x_at_height(est.h, W)
        h0, p0 = (float(v) for v in np.asarray(m.HP(x0, W)).ravel())
        # resting: the model's (virtual, <= 0) height is the better state; no height bias
        dh = 0.0 if est.h < s.rest_height else float(est.h - h0)
        dp = float(est.p - p0)
        if ref.height is None:
            if self._hold is None:
                self._hold = float(est.h)
            r = self._hold
        else:
            self._hold = None
            r = float(ref.height)
        p_lim = s.p_max - s.p_margin
        reach = m.reachable_height(W, p_lim - max(dp, 0.0), s.lam_max, s.h_max - max(dh, 0.0)) + dh
        N = s.horizon
        rs = np.full(N, r)
        if preview is not None and ref.height is not None:
            pv = np.asarray(preview, dtype=float).ravel()[:N]
            if pv.size == 0 or not np.all(np.isfinite(pv)):
                raise ValueError("mpc.step: preview must be a non-empty sequence of finite heights (m)")
            rs[:pv.size] = pv
            rs[pv.size:] = pv[-1]
        hi = max(min(reach, s.h_max), s.h_min)
        r_c = np.clip(rs, s.h_min, hi)
        clipped = bool(np.clip(r, s.h_min, hi) != r)
        if clipped:
            self.clipped_count += 1
        self.last.update({"W": W, "x0": x0, "dh": dh, "dp": dp, "reference": r,
                          "reference_used": float(np.clip(r, s.h_min, hi)),
                          "reachable_height": reach, "target_clipped": clipped})
        return _Problem(x0, W, dh, dp, r_c, self._u_prev.copy(), p_lim)

    def _in_fail_window(self, t: float) -> bool:
        fw = self.settings.fail_window
        return fw is not None and fw[0] <= t <= fw[1]

    def _guard(self, cmd: np.ndarray, est: Estimate) -> np.ndarray:
        s = self.settings
        p = est.p if np.isfinite(est.p) else s.p_max
        if p >= s.p_max - s.guard_margin and (cmd[0] > 0 or cmd[2] < 1.0):
            self.guard_count += 1
            cmd = cmd.copy()
            cmd[0] = 0.0
            cmd[1] = 0.0
            if p >= s.p_max - 0.5 * s.guard_margin:
                cmd[2] = 1.0
        return cmd

    # --- the step -------------------------------------------------------------------------------
    #: the scene passes the future targets (``preview``) to controllers that take them
    accepts_preview = True

    def step(self, t: float, estimate: Estimate, reference: Reference, preview=None) -> Command:
        """One control step: the command to hold for the next sample period (never raises on a
        numerical failure; see the module docstring for the fallback chain).

        ``preview``: optional targets (m) at t + k * sample_period, k = 1..N (fewer: the last one
        holds); without it the current target holds over the horizon.
        """
        s = self.settings
        t_start = time.perf_counter()
        c_start = time.thread_time()
        status = "ok"
        try:
            if self._in_fail_window(t):
                raise _SolverFailure("injected failure (fail_window)")
            pr = self._problem(t, estimate, reference, preview)
            cold = self.backend.X is None
            X, U = self.backend.solve(pr)
            elapsed = time.perf_counter() - t_start
            if elapsed > s.budget and not cold:
                status = "overrun"
                self.fallbacks["overrun"] += 1
                cmd = self._fallback(U)
            else:
                cmd = U[0].copy()
                self._plan = (U.copy(), 0)
                self._streak = 0
        except _BudgetExceeded as exc:
            status = f"overrun: {exc}"
            self.fallbacks["overrun"] += 1
            cmd = self._fallback(None)
        except _SolverFailure as exc:
            status = f"failed: {exc}"
            self.fallbacks["solver_failed"] += 1
            self.backend.reset()
            cmd = self._fallback(None)
        elapsed = time.perf_counter() - t_start
        self.solve_ms.append(elapsed * 1e3)
        self.solve_cpu_ms.append((time.thread_time() - c_start) * 1e3)
        cmd = self._guard(np.clip(cmd, 0.0, 1.0), estimate)
        self._u_prev = cmd.copy()
        self._t_prev = t
        self.last.update({"status": status, "iterations": self.backend.iterations, "solve_ms": elapsed * 1e3})
        return Command(float(cmd[0]), float(cmd[1]), float(cmd[2]))

    def _fallback(self, late_plan: np.ndarray | None) -> np.ndarray:
        s = self.settings
        self._streak += 1
        cmd = None
        if self._plan is not None and self._streak <= s.fallback_plan_steps:
            U, age = self._plan
            if age + 1 < len(U):
                self._plan = (U, age + 1)
                cmd = U[age + 1].copy()
        if late_plan is not None:
            # the late solution is next step's plan (its first move is already missed)
            self._plan = (late_plan.copy(), 0)
        if cmd is None:
            self.fallbacks["safe_command"] += 1
            return SAFE_COMMAND.as_array()
        self.fallbacks["shifted_plan"] += 1
        return cmd

    # --- reporting -------------------------------------------------------------------------------
    def stats(self) -> dict:
        """Timing (ms) and fallback counts since the last reset."""
        t = timing_stats(self.solve_ms)
        c = timing_stats(self.solve_cpu_ms)
        n_fb = self.fallbacks["shifted_plan"] + self.fallbacks["safe_command"]
        return {"variant": self.settings.variant, "horizon": self.settings.horizon,
                "solve_ms_median": t["median"], "solve_ms_p99": t["p99"], "solve_ms_max": t["max"],
                "solve_cpu_ms_median": c["median"], "solve_cpu_ms_p99": c["p99"],
                "steps": t["n"], "fallbacks": int(n_fb), "fallback_detail": dict(self.fallbacks),
                "guard_activations": int(self.guard_count), "target_clipped_steps": int(self.clipped_count)}


def settings_fields() -> list[str]:
    """Names of the MPCSettings fields (for docs and scenario parsing)."""
    return [f.name for f in fields(MPCSettings)]
