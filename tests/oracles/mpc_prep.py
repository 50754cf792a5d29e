"""The NMPC's problem data from an estimate in Python: the oracle
:func:`hbma_ctrl.controllers.mpc_prep.problem_function` (which :meth:`hbma_ctrl.controllers.mpc.NMPC._problem`
calls compiled) is compared with. The load filter, ``PredictionModel``'s lift-off, path and reach, the clipped
targets and the integral action as the module docstring of :mod:`hbma_ctrl.controllers.mpc_prep` states
them, on the states an :class:`~hbma_ctrl.controllers.mpc.NMPC` keeps (read and advanced here)."""

from __future__ import annotations

import math

import numpy as np

from hbma_ctrl.controllers.mpc_settings import INTEGRAL_BAND, INTEGRAL_MAX
from hbma_ctrl.controllers.mpc_solvers import _Problem
from hbma_ctrl.core.interfaces import Estimate, Reference


def _load(nmpc, t: float, est: Estimate) -> float:
    """The load filter's next value (N), clipped to the model's range."""
    s = nmpc.settings
    F = float(est.F) if math.isfinite(est.F) else 0.0
    F = max(F, 0.0)
    resting = est.h < s.rest_height or "resting" in est.flags
    if nmpc._W is None:
        nmpc._W = F
    elif resting:
        # resting: the estimate's force is what the plate carries, a lower bound of the load
        nmpc._W = max(F, nmpc._W)
    else:
        dt = s.sample_period if nmpc._t_prev is None else max(t - nmpc._t_prev, 0.0)
        a = 1.0 if s.load_tau <= 0 else min(1.0, dt / s.load_tau)
        nmpc._W += a * (F - nmpc._W)
    return float(min(nmpc._W, s.load_max))


def _integrate(nmpc, t: float, h_est: float, target: float, clipped: bool) -> float:
    """The integral action's shift of the target, m: the height error integrated within INTEGRAL_BAND
    of the target, at most INTEGRAL_MAX either way, restarted when the target steps by more than the
    band, held while the target is clipped."""
    gain = nmpc.settings.integral_gain
    if gain <= 0.0:
        return 0.0
    if nmpc._int_target is None or abs(target - nmpc._int_target) > INTEGRAL_BAND:
        nmpc._int, nmpc._int_t = 0.0, t  # a new step: nothing owed yet
    err = target - h_est
    if abs(err) < INTEGRAL_BAND and not clipped:
        dt = max(t - nmpc._int_t, 0.0)
        nmpc._int = min(max(nmpc._int + gain * err * dt, -INTEGRAL_MAX), INTEGRAL_MAX)
    nmpc._int_target, nmpc._int_t = target, t
    return nmpc._int


def lift_off_x(m, W: float) -> float:
    """The state of PredictionModel m at which a load W (N) lifts off: the rest gauge pressure
    W / (pi r1^2) over p_env, W clipped to [0, load_max]."""
    Wc = min(max(float(W), 0.0), m.load_max)
    return float(Wc / (np.pi * m.actuator.r1 ** 2) / m.actuator.p_env)


def reachable_height(m, W: float, p_limit: float, lam_max: float, h_max: float) -> float:
    """Largest height (m) PredictionModel m reaches from rest under load W (N) along its load path
    without p > p_limit (Pa), lam > lam_max or h > h_max (m)."""
    p, lam = m._path_columns(W, "p_path", "lam_path")
    pth = {"h": m.grid.h_path, "p": p, "lam": lam}
    ok = (pth["p"] <= p_limit) & (pth["lam"] <= lam_max) & (pth["h"] <= h_max)
    if not ok[0]:
        return 0.0
    bad = np.nonzero(~ok)[0]
    if bad.size == 0:
        return float(min(pth["h"][-1], h_max))
    k = bad[0]
    # interpolate the first crossing of the limiting quantity
    h0, h1 = pth["h"][k - 1], pth["h"][k]
    fr = []
    for key, lim in (("p", p_limit), ("lam", lam_max), ("h", h_max)):
        v0, v1 = pth[key][k - 1], pth[key][k]
        if v1 > lim and v1 != v0:
            fr.append((lim - v0) / (v1 - v0))
    return float(h0 + (h1 - h0) * min(fr)) if fr else float(h0)


def problem_reference(nmpc, t: float, est: Estimate, ref: Reference, preview=None) -> _Problem:
    """What ``nmpc._problem`` returns (and records in ``nmpc.last``), computed in Python."""
    s, m = nmpc.settings, nmpc.model
    r = nmpc._target(est, ref)
    W = _load(nmpc, t, est)
    if est.h < s.rest_height:
        x0 = min(est.p / m.actuator.p_env, lift_off_x(m, W))
    else:
        x0 = m.x_at_height(est.h, W)
    h0, p0 = np.asarray(m.HP(float(x0), float(W)), dtype=float).ravel()
    # resting: the model's (virtual, <= 0) height is the better state; no height bias
    dh = 0.0 if est.h < s.rest_height else float(est.h - h0)
    dp = float(est.p - p0)
    p_lim = s.p_max - s.p_margin
    reach = reachable_height(m, W, p_lim - max(dp, 0.0), s.lam_max, s.h_max - max(dh, 0.0)) + dh
    N = s.horizon
    hi = max(min(reach, s.h_max), s.h_min)
    r_used = min(max(r, s.h_min), hi)
    if preview is not None and ref.height is not None:
        rs = np.full(N, r)
        pv = np.asarray(preview, dtype=float).ravel()[:N]
        rs[:pv.size] = pv
        rs[pv.size:] = pv[-1]
        r_c = np.clip(rs, s.h_min, hi)
    else:
        r_c = np.full(N, r_used)
    clipped = r_used != r
    if clipped:
        nmpc.clipped_count += 1
    shift = _integrate(nmpc, t, float(est.h), r_used, clipped)
    if shift != 0.0:
        r_c = np.clip(r_c + shift, s.h_min, hi)
    nmpc.last.update({"W": W, "x0": x0, "dh": dh, "dp": dp, "reference": r, "reference_used": r_used,
                      "integral_shift": shift, "reachable_height": reach, "target_clipped": clipped})
    return _Problem(x0, W, dh, dp, r_c, nmpc._u_prev.copy(), p_lim)
