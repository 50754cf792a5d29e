"""Nonlinear MPC of one chamber's membrane height: IPOPT / fatrop (accurate) or RTI (fast), one API.

The optimal control problem (both variants solve the same one)
--------------------------------------------------------------
State: the scaled gas mass x of :class:`hbma_ctrl.models.tables.PredictionModel` (one state; the
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
``rti_c_osqp``: real-time iteration. ONE casadi Function (:func:`hbma_ctrl.controllers.rti_c.qp_data_function`,
generated as C, called through preallocated buffers) linearises the dynamics and the outputs along
the shifted previous solution (one mapped call over the N+1 nodes) and returns the QP's data (P and
A values in OSQP's CSC order, q, l, u, the warm start); one sparse QP with a fixed pattern is
updated in place (never re-setup) and solved by OSQP, warm-started. The pump flow is bilinear in
speed and inlet duty; at a plan with the pump off its Jacobian vanishes, so the linearisation point
of speed and inlet is floored at ``rti_lin_floor`` (the affine term stays exact at the plan).
``rti_osqp``: the same, the Function on casadi's virtual machine (the reference path, slower).

``rti_fn_hpipm``, ``rti_fn_osqp``, ``rti_fn_qrqp``: the same real-time iteration as ONE casadi
Function (:func:`hbma_ctrl.controllers.rti_step.rti_step_function`: shift, linearisation, QP data, QP solved
inside casadi by HPIPM / OSQP / qrqp, first input), called once per step through preallocated
buffers; the ``codegen`` command generates C from exactly this Function. Its QP is written
stage-wise (the previous input as a state, the limits of stage k+1 through the dynamics on stage
k), which has the same optimum and lets HPIPM use the OCP structure.
``fatrop``: the IPOPT variant's NLP in the same stage form, solved by fatrop (casadi ``nlpsol``,
structure detected; with ``codegen`` the whole solver generated as C and built once per machine).

Valve duty -> on/off. A duty d in [0, 1] is a PWM command: the valve is held open for d * T_pwm of
each PWM period T_pwm (``duty_to_on_time``); the averaged flow is d times the open flow, which is
what the model uses. On-times shorter than the valve's minimum switching time are rounded to 0 or
T_pwm (whichever is nearer) by the valve driver, not by the MPC.

Embedding. ``step(t, estimate, reference) -> Command`` never raises on a numerical failure: on a
solver failure or, with ``enforce_budget`` set (a real-time loop: the rig daemon), a wall-clock
overrun (``budget``) it reports the failure in ``step_status`` (a
:class:`~hbma_ctrl.core.interfaces.StepStatus`, its text in ``last["status"]``: 'failed: ...' /
'overrun...'; 'ok' otherwise) and returns :data:`SAFE_COMMAND`; ``plan`` holds the
solved input sequence (N, 3) of an ok step, the late solution of an overrun, or None. The safety
policy (replaying the last good plan, then the safe command; the pressure guard) and the step
timing live in :mod:`hbma_ctrl.runtime` (``ChamberLoop``, ``Supervisor``), which hands the command
it finally sent back through :meth:`NMPC.applied` (the rate terms of the next step start from it).
A cold start (the first step, or the first after a failure: the RTI solves ``rti_init_iterations``
QPs then) is exempt from the budget: a daemon calls ``step`` once before its loop starts to warm up.
No global state: everything lives on the instance.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import casadi as ca
import numpy as np
import osqp

from hbma_ctrl.core.codegen import HOT_FLAGS, HOT_OPT, FastFunction
from hbma_ctrl.core.interfaces import (
    SAFE_COMMAND,
    STEP_OK,
    Command,
    ControllerBase,
    Estimate,
    Reference,
    SolveStatus,
    StepStatus,
)
from hbma_ctrl.core.loopgen import LogColumn, Part, Stage
from hbma_ctrl.core.params import Actuator, Pneumatics
from hbma_ctrl.core.validation import finite_or_nan
from hbma_ctrl.models.tables import PredictionModel

__all__ = ["MPCSettings", "NMPC", "VARIANTS", "duty_to_on_time"]

from hbma_ctrl.controllers.mpc_settings import (
    VARIANTS,
    MPCSettings,
    duty_to_on_time,
)
from hbma_ctrl.controllers.mpc_solvers import (
    qp_time_limit,
    _BudgetExceeded,
    _Fatrop,
    _Ipopt,
    _Problem,
    _SolverFailure,
)
from hbma_ctrl.controllers.mpc_prep import problem_function
from hbma_ctrl.controllers.rti_c import _RtiOsqp
from hbma_ctrl.controllers.rti_step import _RtiFunction


#: a step that solved after its budget: not sent, its solution kept as the plan
_LATE = StepStatus(SolveStatus.OVERRUN)


def _finite(value) -> bool:
    return not math.isnan(finite_or_nan(value))


def _check_inputs(t, reference, preview) -> None:
    """ValueError naming ``t``, ``reference.height`` or ``preview[j]`` when not a finite number (a bad
    input from a live stream is refused, not solved with)."""
    if not _finite(t):
        raise ValueError(f"mpc.step: t = {t!r} must be a finite time (s)")
    h = getattr(reference, "height", reference)
    if h is not None and not _finite(h):
        raise ValueError(f"mpc.step: reference.height = {h!r} must be a finite number (m) or None (hold)")
    if preview is not None:
        # the runtime's preview is a list of floats: checked in C-level passes (about 1 us, the loop
        # below 7 us at N = 20); anything else is checked element by element
        if type(preview) is list and set(map(type, preview)) == {float} and all(map(math.isfinite, preview)):
            return
        for j, v in enumerate(np.ravel(np.asarray(preview, dtype=object))):
            if not _finite(v):
                raise ValueError(f"mpc.step: preview[{j}] = {v!r} must be a finite height (m)")


class NMPC(ControllerBase):
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
        self.model = model or PredictionModel(actuator, pneumatics, load_max=s.load_max, membrane=s.membrane)
        # the step's problem data, compiled at the per-step level (-O3: 10 -> 6 us a call, same bits)
        self._prep = FastFunction(problem_function(self.model, s), compile=s.codegen, opt=HOT_OPT, flags=HOT_FLAGS)
        if s.variant in ("rti_osqp", "rti_c_osqp"):
            self.backend = _RtiOsqp(self.model, s, compile=s.variant == "rti_c_osqp")
        elif s.variant.startswith("rti_fn_"):
            self.backend = _RtiFunction(self.model, s, s.variant[len("rti_fn_"):])
        elif s.variant == "fatrop":
            self.backend = _Fatrop(self.model, s)
        else:
            self.backend = _Ipopt(self.model, s)
        self.reset()

    def reset(self) -> None:
        """Forget the plan, the load filter and the statistics."""
        self.backend.reset()
        self._u_prev = np.zeros(3)
        self._W = None
        self._t_prev = None
        self.plan = None  # (N, 3): this step's solved inputs, an overrun's late solution, or None
        self._hold = None
        self.clipped_count = 0
        self.step_status = STEP_OK
        self.last = {}
        self._int, self._int_target, self._int_t = 0.0, None, None  # integral action (settings doc)

    # --- helpers ---------------------------------------------------------------------------------
    def _target(self, est: Estimate, ref: Reference) -> float:
        """The target now (m): the reference's, or without one the height held since it went (the
        estimate's when it went). _SolverFailure when the estimate's h or p is not finite."""
        for name in ("h", "p"):
            if not math.isfinite(getattr(est, name)):
                raise _SolverFailure(f"estimate.{name} is not finite")
        if ref.height is None:
            if self._hold is None:
                self._hold = float(est.h)
            return self._hold
        self._hold = None
        return float(ref.height)

    def _problem(self, t: float, est: Estimate, ref: Reference, preview=None) -> _Problem:
        """The step's problem from the estimate: one call of the compiled ``mpc_prep``
        (:func:`hbma_ctrl.controllers.mpc_prep.problem_function`) on the filter and integral states kept here."""
        s = self.settings
        r = self._target(est, ref)
        prep = self._prep
        inp = prep.inp
        if preview is not None and ref.height is not None:
            N = s.horizon
            pv = np.asarray(preview, dtype=float).ravel()[:N]
            if pv.size == 0 or not np.all(np.isfinite(pv)):
                raise ValueError("mpc.step: preview must be a non-empty sequence of finite heights (m)")
            rin = inp[4]
            rin[:pv.size] = pv
            rin[pv.size:] = pv[-1]
        else:
            inp[4][:] = r
        inp[0][0], inp[1][0], inp[2][0] = est.h, est.p, est.F
        inp[3][0] = 1.0 if "resting" in est.flags else 0.0
        inp[5][0] = r
        if self._W is None:
            inp[7][0] = 0.0
        else:
            inp[6][0], inp[7][0] = self._W, 1.0
            dt = s.sample_period if self._t_prev is None else max(t - self._t_prev, 0.0)
            inp[10][0] = 1.0 if s.load_tau <= 0 else min(1.0, dt / s.load_tau)
        if self._int_target is None:
            inp[13][0] = 0.0
        else:
            inp[11][0], inp[12][0], inp[13][0] = self._int, self._int_target, 1.0
            inp[14][0] = max(t - self._int_t, 0.0)
        (x0, W, dh, dp, p_lim, r_c, Wf, _, _, _, I1, I_t, _, reach, r_used, clipped) = prep.eval()
        self._W = float(Wf[0])
        if s.integral_gain > 0.0:
            self._int, self._int_target, self._int_t = float(I1[0]), float(I_t[0]), t
        clipped = bool(clipped[0])
        if clipped:
            self.clipped_count += 1
        x0, W, dh, dp = float(x0[0]), float(W[0]), float(dh[0]), float(dp[0])
        self.last.update({"W": W, "x0": x0, "dh": dh, "dp": dp, "reference": r,
                          "reference_used": float(r_used[0]), "integral_shift": self._int if s.integral_gain > 0.0
                          else 0.0, "reachable_height": float(reach[0]), "target_clipped": clipped})
        return _Problem(x0, W, dh, dp, r_c.copy(), self._u_prev.copy(), float(p_lim[0]))

    def _in_fail_window(self, t: float) -> bool:
        fw = self.settings.fail_window
        return fw is not None and fw[0] <= t <= fw[1]

    # --- the step -------------------------------------------------------------------------------
    #: the scene passes the future targets (``preview``) to controllers that take them
    accepts_preview = True

    def step(self, t: float, estimate: Estimate, reference: Reference, preview=None) -> Command:
        """One control step: the command to hold for the next sample period (never raises on a
        numerical failure: it reports it in ``step_status``, see the module docstring). A bad
        input (non-finite t, reference height or preview) is a ValueError naming it.

        ``preview``: optional targets (m) at t + k * sample_period, k = 1..N (fewer: the last one
        holds); without it the current target holds over the horizon.
        """
        s = self.settings
        t_start = time.perf_counter()
        _check_inputs(t, reference, preview)
        status = STEP_OK
        cmd = SAFE_COMMAND.as_array()
        try:
            if self._in_fail_window(t):
                raise _SolverFailure("injected failure (fail_window)")
            pr = self._problem(t, estimate, reference, preview)
            cold = self.backend.X is None
            X, U = self.backend.solve(pr)
            # the wall clock decides only in a real-time loop (enforce_budget); a simulation's step
            # is never an overrun, so its results do not depend on the machine's load
            if s.enforce_budget and not cold and time.perf_counter() - t_start > s.budget:
                status = _LATE
                self.plan = U.copy()  # the late solution: the supervisor's plan for the next failure
            else:
                cmd = U[0].copy()
                self.plan = U.copy()
        except _BudgetExceeded as exc:
            status = StepStatus(SolveStatus.OVERRUN, str(exc))
            self.plan = None
        except _SolverFailure as exc:
            status = StepStatus(SolveStatus.FAILED, str(exc))
            self.plan = None
            self.backend.reset()
        elapsed = time.perf_counter() - t_start
        cmd = np.minimum(np.maximum(cmd, 0.0), 1.0)  # a new array (np.clip's wrapper costs 1-3 us more)
        # a caller that does not report the command it sent (applied) gets this one as the previous input
        self._u_prev = cmd
        self._t_prev = t
        self.step_status = status
        self.last.update({"status": str(status), "iterations": self.backend.iterations, "solve_ms": elapsed * 1e3})
        return Command(float(cmd[0]), float(cmd[1]), float(cmd[2]))

    #: failures are reported in ``step_status`` (the runtime's supervisor counts them per cause)
    reports_failures = True

    def set_enforce_budget(self, on: bool) -> None:
        """Act on the wall-clock budget from the next step on (a real-time loop) or not (a replay of a
        daemon's run, whose own machine's load must not change a decision): ``settings.enforce_budget``
        and OSQP's time limit with it. IPOPT's wall-time cap is fixed when its solver is built."""
        s = replace(self.settings, enforce_budget=bool(on)).validate()
        self.settings = self.backend.s = s
        solver = getattr(self.backend, "solver", None)
        if isinstance(solver, osqp.OSQP):  # the RTI + OSQP variants keep one OSQP set up
            solver.update_settings(time_limit=qp_time_limit(s))

    def applied(self, command: Command | np.ndarray) -> None:
        """The command actually sent (after the supervisor): the next step's input rates start from it."""
        a = command.as_array() if isinstance(command, Command) else np.asarray(command, dtype=float)
        self._u_prev = a.reshape(3).copy()

    # --- a generated loop ------------------------------------------------------------------------
    def stages(self, t: np.ndarray, every: int, command: str = "u") -> Part:
        """The NMPC in a generated loop (:mod:`hbma_ctrl.core.loopgen`) over the tick times ``t`` (s), a
        step every ``every`` ticks: its problem data (``mpc_prep``, the Function :meth:`_problem` calls),
        the cold-start guess, the RTI step Function (``rti_init_iterations`` unshifted calls on a cold
        start, stopping at a failure, as the backend solves; one shifted call after), and ``mpc_done``:
        whether the step solved (``ok``; a step in ``fail_window`` never does) and the next one starts cold.
        Reads the estimate (``est_h``, ``est_p``, ``est_F``, ``resting``), the targets (``target``, the
        horizon's ``ref``) and the command held (``command``); writes ``u0``, the plan ``U_guess`` and
        ``status``. ValueError naming the setting for a variant with no step Function or an enforced
        wall-clock budget."""
        s = self.settings
        if not isinstance(self.backend, _RtiFunction):
            raise ValueError(f"[controller] variant = '{s.variant}': only the rti_fn_* variants (the RTI step as "
                             "one Function) generate a loop")
        if s.enforce_budget:
            raise ValueError("[controller] enforce_budget = true: an enforced wall-clock budget depends on the "
                             "machine's clock; set it to false to generate the loop")
        rti, N = self.backend.function, s.horizon
        nz, nc = self.backend.nz, self.backend.nc
        x0, up, status, fail = ca.SX.sym("x0"), ca.SX.sym("u_prev", 3), ca.SX.sym("status"), ca.SX.sym("fail")
        # the backend without a plan: the estimate held, the last command repeated, zero duals
        cold = ca.Function("mpc_cold", [x0, up], [ca.repmat(x0, N + 1, 1), ca.repmat(up, 1, N), ca.SX.zeros(nz),
                                                  ca.SX.zeros(nc)],
                           ["x0", "u_prev"], ["X_guess", "U_guess", "lam_x_guess", "lam_a_guess"])
        ok = ca.logic_and(status == 0, fail == 0)
        done = ca.Function("mpc_done", [status, fail], [ok, 1 - ok], ["status", "fail"], ["ok", "cold"])
        signals = {"Wf": [0.0], "has_W": [0.0], "x0": [0.0], "W": [0.0], "dh": [0.0], "dp": [0.0], "p_lim": [0.0],
                   "r_c": np.zeros(N), "X_guess": np.zeros(N + 1), "U_guess": np.zeros(3 * N), "lam_x": np.zeros(nz),
                   "lam_a": np.zeros(nc), "u0": np.zeros(3), "status": [0.0], "qp_residual": [0.0], "qp_cost": [0.0],
                   "shift0": [0.0], "shift1": [1.0], "cold": [1.0], "ok": [0.0], "run_cold": [0.0], "run_warm": [0.0],
                   "fail": [0.0], "load_a": [0.0], "I": [0.0], "I_target": [0.0], "has_I": [0.0],
                   "ctrl_dt": [s.sample_period]}
        rti_in = ["x0", "W", "dh", "dp", command, "p_lim", "r_c", "X_guess", "U_guess", "lam_x", "lam_a"]
        rti_out = ["u0", "X_guess", "U_guess", "lam_x", "lam_a", "status", "qp_residual", "qp_cost"]
        stages = [
            Stage(problem_function(self.model, s), ["est_h", "est_p", "est_F", "resting", "ref", "target", "Wf",
                                                    "has_W", "fail", "cold", "load_a", "I", "I_target", "has_I",
                                                    "ctrl_dt"],
                  ["x0", "W", "dh", "dp", "p_lim", "r_c", "Wf", "has_W", "run_cold", "run_warm", "I", "I_target",
                   "has_I", None, None, None], every=every),
            Stage(cold, ["x0", command], ["X_guess", "U_guess", "lam_x", "lam_a"], every=every, gate="run_cold"),
            Stage(rti, rti_in + ["shift0"], rti_out, every=every, gate="run_cold", repeat=s.rti_init_iterations,
                  stop_on="status", fails_to="status"),
            Stage(rti, rti_in + ["shift1"], rti_out, every=every, gate="run_warm", fails_to="status"),
            Stage(done, ["status", "fail"], ["ok", "cold"], every=every)]
        t = np.asarray(t, dtype=float)
        fw = s.fail_window  # the fallback drill: every solve in [t0, t1] is treated as failed
        fails = np.zeros(t.size) if fw is None else ((t >= fw[0]) & (t <= fw[1])).astype(float)
        # the load filter's gain from the time since the last step, as _problem rounds it
        dts = [s.sample_period if k < every else max(t[k] - t[k - every], 0.0) for k in range(t.size)]
        load_a = np.array([1.0 if s.load_tau <= 0 else min(1.0, d / s.load_tau) for d in dts])
        solver = s.variant[len("rti_fn_"):]
        return Part(stages, signals, {"fail": fails, "load_a": load_a}, [LogColumn("mpc_status", "status")],
                    {"controller": f"RTI NMPC (hbma_ctrl.controllers.rti_step), N = {N}, QP {solver}, every {every} "
                                   "rig periods"})

    # --- reporting -------------------------------------------------------------------------------
    def stats(self) -> dict:
        """Variant, horizon and clipped-target count since the last reset (timing and fallbacks are
        counted by :mod:`hbma_ctrl.runtime`); for the rti_fn_* variants how the step runs."""
        out = {"variant": self.settings.variant, "horizon": self.settings.horizon,
               "target_clipped_steps": int(self.clipped_count)}
        if hasattr(self.backend, "mode"):  # the one-Function RTI: generated C, C parts, or casadi's VM
            out["rti_step_mode"] = self.backend.mode
        return out
