"""Settings of the single-chamber NMPC, the valve-duty conversion and step-timing statistics (SI).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hbma_ctrl.core.interfaces import guard_margin_setting, p_max_setting, sample_period_setting
from hbma_ctrl.core.settings import Settings, check_range, setting
from hbma_ctrl.models.defaults import DEFAULT_MEMBRANE
from hbma_ctrl.models.reduced import MEMBRANES

#: the integral action works within this height error of the target, m, and shifts the target by at most INTEGRAL_MAX
INTEGRAL_BAND = 1e-3
INTEGRAL_MAX = 1e-3

_INPUTS = ("speed", "inlet", "outlet")
VARIANTS = ("rti_osqp", "rti_c_osqp", "rti_fn_osqp", "rti_fn_hpipm", "rti_fn_qrqp", "ipopt", "fatrop")

#: the cost's weights in the order the compiled solvers take them as an input (``rti_c_osqp``'s QP
#: data, fatrop's NLP parameters) rather than as constants: settings that differ only in them (a
#: tuning study's trials) share one generated library
WEIGHTS = ("w_height", "w_terminal", "w_rate[0]", "w_rate[1]", "w_rate[2]", "w_input[0]", "w_input[1]",
           "w_input[2]", "c_input[0]", "c_input[1]", "c_input[2]", "w_slack", "c_slack")


@dataclass
class MPCSettings(Settings):
    """Settings of :class:`~hbma_ctrl.controllers.mpc.NMPC` (SI; each field's unit, range and one-line doc
    are in its declaration).

    variant : 'rti_c_osqp' (real-time iteration, one OSQP QP per step, its data from one generated-C
        call, :mod:`hbma_ctrl.controllers.rti_c`), 'rti_osqp' (the same data Function on casadi's virtual
        machine: the reference path, equal to rounding, slower, `bench mpc`), 'rti_fn_osqp' / 'rti_fn_hpipm' /
        'rti_fn_qrqp' (the same RTI step as one casadi Function, :mod:`hbma_ctrl.controllers.rti_step`, its
        QP solved inside casadi), 'ipopt' or 'fatrop' (accurate: NLP to convergence).
    enforce_budget : off (the default: scenes, benches, tuning, code generation), no step is an overrun
        and no solver gets a wall-clock limit, so a simulation's results do not depend on the machine's
        load; the step times are still measured. The rig daemon sets it.
    membrane : the prediction model's tables (:class:`hbma_ctrl.models.tables.PredictionModel`).
    integral_gain : within ``INTEGRAL_BAND`` of the target the height error's integral times this
        shifts the target the QP tracks (at most ``INTEGRAL_MAX``; reset when the target steps by more
        than the band). Why: the MPC re-derives its state from the estimate every step, so a standing
        error the model cannot see (a pump that gives no flow at a low speed against a high back
        pressure, a valve that drops short openings) is never integrated otherwise.
    """

    WHERE = "mpc"

    variant: str = setting("rti_c_osqp", choices=VARIANTS,
                           doc="MPC: RTI + OSQP, its QP data as generated C (fast; rti_osqp: the same on casadi's virtual "
                               "machine, slower), the RTI step as one casadi Function with its QP solved by OSQP / HPIPM / qrqp "
                               "(rti_fn_*), or IPOPT / fatrop (accurate)")
    horizon: int = setting(20, integer=True, lo=2, hi=200, unit="steps", doc="MPC horizon N")
    sample_period: float = sample_period_setting()
    integrator: str = setting("rk4", choices=("rk4", "euler"), doc="MPC discretisation")
    substeps: int = setting(1, integer=True, lo=1, hi=20, unit="steps", doc="MPC integrator steps per interval")
    w_height: float = setting(1.0, lo=0.0, hi=1e9, unit="1/mm^2", doc="MPC weight on the height error per stage")
    w_terminal: float = setting(5.0, lo=0.0, hi=1e9, unit="1/mm^2", doc="MPC weight on the final height error")
    w_rate: tuple = setting((0.02, 0.002, 0.02), lo=0.0, hi=1e6, parts=_INPUTS, doc="MPC weights on input changes")
    w_input: tuple = setting((0.002, 0.0, 0.002), lo=0.0, hi=1e6, parts=_INPUTS, doc="MPC quadratic input weights")
    c_input: tuple = setting((0.02, 0.01, 0.02), lo=0.0, hi=1e6, parts=_INPUTS,
                             doc="MPC linear input costs: prefer idle, use the pump sparingly")
    w_slack: float = setting(1e3, lo=0.0, hi=1e9,
                             doc="quadratic penalty on constraint violation (slack in kPa / mm / 0.01 stretch)")
    c_slack: float = setting(1e3, lo=0.0, hi=1e9, doc="linear (exact) penalty on constraint violation")
    p_max: float = p_max_setting()
    p_margin: float = setting(1e3, lo=0.0, hi=1e6, unit="Pa", user="kPa",
                              doc="MPC: predicted pressure kept this far below p_max_kpa (at most p_max_kpa)")
    guard_margin: float = guard_margin_setting(0.5e3)
    lam_max: float = setting(1.5, lo=1.0, hi=5.0, lo_open=True, doc="MPC: stretch limit")
    h_min: float = setting(0.0, lo=0.0, hi=0.2, unit="m", doc="lowest height")
    h_max: float = setting(20e-3, lo=0.0, hi=0.2, lo_open=True, unit="m", user="mm", doc="MPC: height bound")
    u_max: tuple = setting((1.0, 1.0, 1.0), lo=0.0, hi=1.0, lo_open=True, parts=_INPUTS, doc="upper input bounds")
    du_max: tuple = setting((50.0, 100.0, 100.0), lo=0.0, hi=1e6, lo_open=True, unit="1/s", parts=_INPUTS,
                            doc="input rate limits")
    budget: float = setting(0.015, lo=0.0, hi=10.0, lo_open=True, unit="s", user="ms",
                            doc="MPC wall-clock budget per step (acts with enforce_budget; the rig daemon always "
                                "enforces it); OSQP stops at it")
    fallback_plan_steps: int = setting(10, integer=True, lo=0,
                                       doc="steps the shifted previous plan may stand in before the safe command")
    load_max: float = setting(10.0, lo=0.0, hi=200.0, lo_open=True, unit="N",
                              doc="largest load force the model covers (larger estimates are clipped, reported)")
    load_tau: float = setting(0.1, lo=0.0, hi=100.0, unit="s", doc="low-pass time constant of the estimated force")
    rest_height: float = setting(0.1e-3, lo=0.0, hi=0.01, unit="m",
                                 doc="below this estimated height the platform is taken as resting")
    rti_lin_floor: float = setting(0.25, lo=0.0, hi=1.0,
                                   doc="RTI: floor of the speed/inlet linearisation point (see module docstring)")
    rti_init_iterations: int = setting(5, integer=True, lo=1, hi=100, doc="RTI: QPs solved at the first step")
    qp_eps: float = setting(1e-4, lo=0.0, hi=1.0, lo_open=True, doc="OSQP absolute and relative tolerance")
    qp_max_iter: int = setting(300, integer=True, lo=1, doc="OSQP iteration limit")
    ipopt_max_iter: int = setting(100, integer=True, lo=1, doc="IPOPT iteration limit")
    codegen: bool = setting(True, doc="MPC: compile the RTI linearisation to C (falls back to casadi's virtual "
                                      "machine without a compiler)")
    fail_window: tuple | None = setting(None, lo=0.0, unit="s", parts=("t_start_s", "t_end_s"), key="fail_window_s",
                                        doc="MPC solves in this window fail (a fallback drill)")
    # repr=False: the stored reprs of the scenario goldens
    membrane: str = setting(DEFAULT_MEMBRANE, choices=MEMBRANES, repr=False,
                            doc="MPC prediction model's membrane law: cap (spherical cap) or exact (exact membrane tables)")
    integral_gain: float = setting(2.0, lo=0.0, hi=100.0, unit="1/s", repr=False, key="integral_gain_per_s",
                                   doc="MPC integral action on the height error near the target (0 = none)")
    enforce_budget: bool = setting(False, repr=False,
                                   doc="MPC: in a simulation, make a step slower than budget_ms an overrun (the "
                                       "supervisor's fallback), as in the rig daemon; off, results do not "
                                       "depend on the machine's load")

    def check_rules(self) -> None:
        self.within("p_margin", hi=self.p_max)
        self.within("guard_margin", hi=self.p_max)
        self.within("h_max", lo=self.h_min)
        if self.fail_window is not None and self.fail_window[0] > self.fail_window[1]:
            raise ValueError(f"mpc.fail_window = {self.fail_window!r} must be (t_start, t_end) with t_start <= t_end s")


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
