"""The NMPC's problem data from an estimate, as ONE casadi Function (``mpc_prep``).

The step's problem from the estimate (the load filter, the state and output biases at the estimate,
the reachable height along the load path, the clipped targets and the integral action) written once
in casadi, so that :meth:`hbma_ctrl.controllers.mpc.NMPC._problem` calls it compiled (tens of
microseconds of Python per step otherwise) and the generated C loop (:mod:`hbma_ctrl.app.codegen.chamber`)
runs the same Function. It rounds as the Python oracle does (``tests/oracles/mpc_prep.py``:
``np.interp``'s formula, the path's column blend), to 1e-12 of it::

    mpc_prep(h, p, F, resting, r[N], target, Wf, has_W, fail, cold, load_a, I, I_target, has_I, ctrl_dt)
      -> (x0, W, dh, dp, p_lim, r_c[N], Wf_next, has_W_next, run_cold, run_warm, I_next, I_target_next,
          has_I_next, reach, r_used, clipped)

``h``, ``p``, ``F``: the estimate (m, Pa, N; a non-finite F counts as 0); ``resting``: its flag; ``r``: the
horizon's targets (the preview, or the target repeated) and ``target`` the target now (m); ``Wf``,
``has_W``: the load filter's state and ``load_a`` = min(1, dt / load_tau) its gain; ``I``, ``I_target``,
``has_I``: the integral action's state and ``ctrl_dt`` the time since its last step (s); ``fail``: a step
in the fallback drill (nothing moves); ``cold``: the backend has no plan (the C loop's gates).
Outputs: the problem (x0, W (N), dh (m), dp (Pa), p_lim (Pa), r_c (m)), the states after the step,
the gates, and for the NMPC's report the reachable height (m), the target used (m) and whether it was
clipped.
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

from hbma_ctrl.controllers.mpc_settings import INTEGRAL_BAND, INTEGRAL_MAX, MPCSettings
from hbma_ctrl.core.codegen import is_finite
from hbma_ctrl.models.tables import PredictionModel

__all__ = ["problem_function", "np_interp", "PREP_OUT"]

#: the outputs of :func:`problem_function`, in order
PREP_OUT = ("x0", "W", "dh", "dp", "p_lim", "r_c", "Wf_next", "has_W_next", "run_cold", "run_warm", "I_next",
            "I_target_next", "has_I_next", "reach", "r_used", "clipped")


def np_interp(xq, xp: np.ndarray, fp):
    """``np.interp(xq, xp, fp)`` with numpy's own arithmetic (slope * (x - xp[j]) + fp[j], the node's
    value at a node, the end values outside), so the result rounds as the Python NMPC's does."""
    xp = np.asarray(xp, dtype=float)
    lo, hi = ca.DM(xp[:-1]), ca.DM(xp[1:])
    f0, f1 = fp[:-1], fp[1:]
    slope = (f1 - f0) / (hi - lo)
    inside = ca.logic_and(xq >= lo, xq < hi)
    val = ca.if_else(xq == lo, f0, slope * (xq - lo) + f0)
    mid = ca.sum1(ca.if_else(inside, val, 0))
    return ca.if_else(xq >= xp[-1], fp[-1], ca.if_else(xq < xp[0], fp[0], mid))


def problem_function(model: PredictionModel, s: MPCSettings) -> ca.Function:
    """The ``mpc_prep`` Function of the NMPC with settings ``s`` on its prediction model (module doc)."""
    g = model.grid
    N = s.horizon
    act = model.actuator
    MX = ca.MX
    h_est, p_est, F_est, rest_flag = MX.sym("h"), MX.sym("p"), MX.sym("F"), MX.sym("resting")
    r_in, Wf, has_W = MX.sym("r", N), MX.sym("Wf"), MX.sym("has_W")
    r_now = MX.sym("target")  # the target now; r_in the horizon's (the preview, or the target repeated)
    fail, cold_in, a = MX.sym("fail"), MX.sym("cold"), MX.sym("load_a")
    # --- the load filter (NMPC._load): dt is the controller period
    F = ca.if_else(is_finite(F_est), F_est, 0)
    F = ca.fmax(F, 0)
    resting_h = h_est < s.rest_height
    resting = ca.logic_or(resting_h, rest_flag != 0)
    Wf_new = ca.if_else(has_W == 0, F, ca.if_else(resting, ca.fmax(F, Wf), Wf + a * (F - Wf)))
    W = ca.fmin(Wf_new, s.load_max)
    # --- the load path at W (PredictionModel.path): linear in W between the grid's columns
    # one lookup and a two-column blend per table: (1 - s) A[:, j] + s A[:, j + 1], as path() rounds it
    x_path, p_path, l_path = model.path_columns_expr(W, "x_path", "p_path", "lam_path")
    hp = np.asarray(g.h_path, dtype=float)
    lift_x = ca.fmin(ca.fmax(W, 0.0), model.load_max) / (math.pi * act.r1 ** 2) / act.p_env
    x_at_h = np_interp(h_est, hp, x_path)
    x0 = ca.if_else(resting_h, ca.fmin(p_est / act.p_env, lift_x), x_at_h)
    hp0 = model.HP(x0, W)
    dh = ca.if_else(resting_h, 0, h_est - hp0[0])
    dp = p_est - hp0[1]
    p_lim = s.p_max - s.p_margin
    # --- the reachable height along the path: the first node past a limit, the crossing interpolated
    p_limit, h_lim = p_lim - ca.fmax(dp, 0), s.h_max - ca.fmax(dh, 0)
    hpd = ca.DM(hp)
    ok = ca.logic_and(ca.logic_and(p_path <= p_limit, l_path <= s.lam_max), hpd <= h_lim)
    bad = 1 - ok
    n = hp.size
    first = ca.logic_and(bad, ca.cumsum(bad) - bad == 0)[1:]  # the first bad node (none before it)
    fr = MX(ca.DM.inf(n - 1))
    for v, lim in ((p_path, p_limit), (l_path, s.lam_max), (hpd, h_lim)):
        v0, v1 = v[:-1], v[1:]
        cand = ca.if_else(ca.logic_and(v1 > lim, v1 != v0), (lim - v0) / (v1 - v0), ca.inf)
        fr = ca.fmin(fr, cand)
    h0n, h1n = hpd[:-1], hpd[1:]
    at = ca.if_else(fr < ca.inf, h0n + (h1n - h0n) * fr, h0n)
    reach_first = ca.sum1(ca.if_else(first, at, 0))
    any_bad = ca.sum1(bad[1:]) > 0
    reach = ca.if_else(ok[0] == 0, 0, ca.if_else(any_bad, reach_first, ca.fmin(hp[-1], h_lim))) + dh
    hi = ca.fmax(ca.fmin(reach, s.h_max), s.h_min)
    r_c = ca.fmin(ca.fmax(r_in, s.h_min), hi)
    r_used = ca.fmin(ca.fmax(r_now, s.h_min), hi)  # the target now as the NMPC clips it (_problem)
    # --- the integral action (NMPC._integrate) on the target now (not the preview's first): restarted
    # when it steps by more than the band; integrated within the band unless clipped; dt the controller
    # period (0 on a restart)
    I_in, I_tgt, has_I, dt_c = MX.sym("I"), MX.sym("I_target"), MX.sym("has_I"), MX.sym("ctrl_dt")
    target, clipped = r_used, r_used != r_now
    restart = ca.logic_or(has_I == 0, ca.fabs(target - I_tgt) > INTEGRAL_BAND)
    I0 = ca.if_else(restart, 0.0, I_in)
    err = target - h_est
    grow = ca.logic_and(ca.fabs(err) < INTEGRAL_BAND, ca.logic_not(clipped))
    I1 = ca.if_else(grow, ca.fmin(ca.fmax(I0 + s.integral_gain * err * ca.if_else(restart, 0.0, dt_c),
                                          -INTEGRAL_MAX), INTEGRAL_MAX), I0)
    if s.integral_gain <= 0:
        I1 = MX(0.0)
    r_c = ca.if_else(I1 != 0, ca.fmin(ca.fmax(r_c + I1, s.h_min), hi), r_c)
    # a step in the fail window (the drill) solves nothing and leaves the load filter as it was
    failing = fail != 0
    prep = ca.Function("mpc_prep", [h_est, p_est, F_est, rest_flag, r_in, r_now, Wf, has_W, fail, cold_in, a,
                                    I_in, I_tgt, has_I, dt_c],
                       [x0, W, dh, dp, MX(p_lim), r_c, ca.if_else(failing, Wf, Wf_new),
                        ca.if_else(failing, has_W, 1.0), ca.logic_and(cold_in != 0, ca.logic_not(failing)),
                        ca.logic_and(cold_in == 0, ca.logic_not(failing)),
                        ca.if_else(failing, I_in, I1), ca.if_else(failing, I_tgt, target),
                        ca.if_else(failing, has_I, 1.0), reach, r_used, clipped],
                       ["h", "p", "F", "resting", "r", "target", "Wf", "has_W", "fail", "cold", "load_a",
                        "I", "I_target", "has_I", "ctrl_dt"],
                       list(PREP_OUT))
    return prep
