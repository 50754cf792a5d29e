"""Settings of the single-chamber NMPC, the valve-duty conversion and step-timing statistics (SI).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hbma_ctrl.core.params import check_range
from hbma_ctrl.core.validation import did_you_mean
from hbma_ctrl.models.defaults import DEFAULT_MEMBRANE

#: the integral action works within this height error of the target, m, and shifts the target by at most INTEGRAL_MAX
INTEGRAL_BAND = 1e-3
INTEGRAL_MAX = 1e-3

VARIANTS = ("rti_osqp", "rti_c_osqp", "rti_fn_osqp", "rti_fn_hpipm", "rti_fn_qrqp", "ipopt", "fatrop")

#: the cost's weights in the order the compiled solvers take them as an input (``rti_c_osqp``'s QP
#: data, fatrop's NLP parameters) rather than as constants: settings that differ only in them (a
#: tuning study's trials) share one generated library
WEIGHTS = ("w_height", "w_terminal", "w_rate[0]", "w_rate[1]", "w_rate[2]", "w_input[0]", "w_input[1]",
           "w_input[2]", "c_input[0]", "c_input[1]", "c_input[2]", "w_slack", "c_slack")


@dataclass
class MPCSettings:
    """Settings of :class:`~hbma_ctrl.controllers.mpc.NMPC` (SI; one docstring line per field).

    Fields
    ------
    variant : 'rti_c_osqp' (the default: real-time iteration, one OSQP QP per step, its data from one
        generated-C call, :mod:`hbma_ctrl.controllers.rti_c`), 'rti_osqp' (the same QP built in numpy: the
        reference path, equal to rounding, two to three times slower, `bench mpc`), 'rti_fn_osqp' /
        'rti_fn_hpipm' / 'rti_fn_qrqp' (the same RTI step as one casadi Function,
        :mod:`hbma_ctrl.controllers.rti_step`, its QP solved inside casadi by OSQP / HPIPM / qrqp), 'ipopt' or
        'fatrop' (accurate: NLP to convergence).
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
    budget : wall-clock budget of one step, s; with ``enforce_budget`` a slower step is an overrun
        (fallback) and OSQP stops at it.
    enforce_budget : act on ``budget`` (a real-time loop: the rig daemon sets it). Off (the default:
        scenes, benches, tuning, code generation), no step is an overrun and no solver gets a
        wall-clock limit, so a simulation's results do not depend on the machine's load; the step
        times are still measured.
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
    membrane : membrane law of the prediction model's tables: 'cap' (spherical cap) or 'exact'
        (the exact membrane's, :class:`hbma_ctrl.models.tables.PredictionModel`; the default).
    integral_gain : integral action on the estimated height error, 1/s, [0, 100] (0 = none): within
        ``INTEGRAL_BAND`` of the target the error's integral times this shifts the target the QP
        tracks (at most ``INTEGRAL_MAX``; reset when the target steps by more than the band). Why:
        the MPC re-derives its state from the estimate every step, so a standing error the model
        cannot see (a pump that gives no flow at a low speed against a high back pressure, a valve
        that drops short openings) is never integrated: it plans the same useless trickle forever.
    """

    variant: str = "rti_c_osqp"
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
    membrane: str = field(default=DEFAULT_MEMBRANE, repr=False)  # repr: the stored reprs of the scenario goldens
    integral_gain: float = field(default=2.0, repr=False)
    enforce_budget: bool = field(default=False, repr=False)

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
        if not isinstance(self.enforce_budget, bool):
            raise ValueError(f"mpc.enforce_budget = {self.enforce_budget!r} must be true or false")
        if not isinstance(self.fallback_plan_steps, int) or self.fallback_plan_steps < 0:
            raise ValueError(f"mpc.fallback_plan_steps = {self.fallback_plan_steps!r} must be an integer >= 0")
        check_range("mpc", "load_max", self.load_max, 0.0, 200.0, "N", lo_open=True)
        check_range("mpc", "load_tau", self.load_tau, 0.0, 100.0, "s")
        check_range("mpc", "rest_height", self.rest_height, 0.0, 0.01, "m")
        check_range("mpc", "rti_lin_floor", self.rti_lin_floor, 0.0, 1.0)
        check_range("mpc", "integral_gain", self.integral_gain, 0.0, 100.0, "1/s")
        if not isinstance(self.rti_init_iterations, int) or not 1 <= self.rti_init_iterations <= 100:
            raise ValueError(f"mpc.rti_init_iterations = {self.rti_init_iterations!r} must be in [1, 100]")
        check_range("mpc", "qp_eps", self.qp_eps, 0.0, 1.0, lo_open=True)
        if not isinstance(self.qp_max_iter, int) or self.qp_max_iter < 1:
            raise ValueError(f"mpc.qp_max_iter = {self.qp_max_iter!r} must be an integer >= 1")
        if not isinstance(self.ipopt_max_iter, int) or self.ipopt_max_iter < 1:
            raise ValueError(f"mpc.ipopt_max_iter = {self.ipopt_max_iter!r} must be an integer >= 1")
        if self.membrane not in ("cap", "exact"):
            hint = did_you_mean(str(self.membrane), ("cap", "exact"))
            raise ValueError(f"mpc.membrane = '{self.membrane}'{hint}; allowed: cap, exact")
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


def weights_of(s: MPCSettings) -> np.ndarray:
    """Settings ``s``'s cost weights as the compiled solvers take them (:data:`WEIGHTS` order)."""
    return np.array([s.w_height, s.w_terminal, *s.w_rate, *s.w_input, *s.c_input, s.w_slack, s.c_slack], dtype=float)
