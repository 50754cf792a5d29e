"""The robot loop's blocks around its controller and supervisor in numpy: the oracles the Functions of
:mod:`hbma_ctrl.runtime.robot_step` (which :class:`hbma_ctrl.runtime.robot.RobotLoop` evaluates) are
compared with. SI units throughout."""

from __future__ import annotations

import numpy as np

from hbma_ctrl.runtime.robot_step import VENT_DEADBAND
from hbma_ctrl.runtime.safety import ZERO_TARGET, SupervisorSettings


def slew(goal: np.ndarray, h_est: np.ndarray, dt: float, prev: np.ndarray | None, rate: float) -> np.ndarray:
    """The targets this tick: ``goal`` without a rate; otherwise ``prev`` (the estimated heights, NaN
    as 0 and at least 0, when None) moved towards it by at most rate x dt, a zero target at once."""
    goal = np.asarray(goal, dtype=float)
    if rate <= 0.0:
        return goal
    start = np.maximum(np.nan_to_num(np.asarray(h_est, dtype=float)), 0.0) if prev is None else prev
    lim = rate * dt
    return np.where(goal <= ZERO_TARGET, goal, start + np.clip(goal - start, -lim, lim))


def vent_mask(settings: SupervisorSettings, target: np.ndarray) -> np.ndarray:
    """Chambers the supervisor's vent rule holds: a finite target at or below ``vent_height``."""
    if settings.vent_height is None:
        return np.zeros(np.size(target), dtype=bool)
    return np.isfinite(target) & (target <= settings.vent_height)


def stretch_over(settings: SupervisorSettings, stretch: np.ndarray) -> np.ndarray:
    """Chambers the stretch interlock holds: at or above ``stretch_max`` (NaN: not held)."""
    if settings.stretch_max is None:
        return np.zeros(np.size(stretch), dtype=bool)
    return np.asarray(stretch, dtype=float) >= settings.stretch_max


def peaks(model, W: np.ndarray, k: np.ndarray) -> np.ndarray:
    """The limit-point pressures (Pa) at the loads over the modulus factors, clipped to the tables."""
    return np.array([model.peak(w)[1] for w in model.clip_load(np.asarray(W) / np.asarray(k))])


def caps(settings: SupervisorSettings, cautious: tuple | None, est: dict, href: np.ndarray, sup_lost: np.ndarray,
         sup_burst: np.ndarray, peak: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(a_max, near): no supply budget where the vent rule or an interlock (stretch, lost estimate now
    or latched, burst latch) holds a chamber; the cautious cap where its estimated pressure is above
    the fraction of ``peak`` (Pa) times its modulus factor and that factor's std above the threshold."""
    held = vent_mask(settings, href) | stretch_over(settings, est["lam"]) | est["lost"] | sup_lost | sup_burst
    a_max = np.where(held, 0.0, 1.0)
    if cautious is None:
        return a_max, np.zeros(a_max.size, dtype=bool)
    near = (est["p"] > cautious[0] * est["k"] * peak) & (est["k_std"] > cautious[1])
    return np.where(near, np.minimum(a_max, cautious[2]), a_max), near


def open_flows(model, p: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mass flows (kg/s) a supply a = 1 and an outlet o = 1 pass at pressures p (Pa), flow factors b."""
    q_in, q_out = model.mapped(model.open_flows_function(), np.size(p))(p, b)
    return np.asarray(q_in).ravel(), np.asarray(q_out).ravel()


def height_drops(model, x: np.ndarray, W: np.ndarray, k: np.ndarray, c: np.ndarray, dm: np.ndarray) -> np.ndarray:
    """The height (m) each chamber loses when gas mass dm (kg) leaves it."""
    return np.asarray(model.mapped(model.height_drop_function(), np.size(x))(x, W, k, c, dm)).ravel()


def vent_pulse_drop(model, min_duty: float, period: float, est: dict, W: np.ndarray, q_out: np.ndarray) -> np.ndarray:
    """The height (m) one minimum opening of each chamber's outlet takes off at the estimate: the
    model's height at the gas mass x less the one at x less what that opening lets out (q_out, kg/s)."""
    return np.maximum(height_drops(model, est["x"], W, est["k"], est["c"], q_out * (min_duty * period)), 0.0)


def net_vents(model, min_duty: float, period: float, a: np.ndarray, o: np.ndarray, est: dict, W: np.ndarray,
              excess: np.ndarray, carry: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(a, o, carry) sent with a minimum opening of ``min_duty``: a vent shorter than it netted into
    the same chamber's supply at the estimated pressure, one left over dropped (its outlet's carry
    too) while the chamber is at most VENT_DEADBAND, or half of what one opening takes off, above
    its target (``excess``, m)."""
    small = (o > 0.0) & (o < min_duty)
    if not small.any():
        return a, o, carry
    q_in, q_out = open_flows(model, est["p"], est["b"])
    net = a * q_in - o * q_out
    ok = small & (a > 0.0) & (q_in > 0.0) & (q_out > 0.0)
    a = np.where(ok, np.maximum(net, 0.0) / np.where(ok, q_in, 1.0), a)
    o = np.where(ok, np.maximum(-net, 0.0) / np.where(ok, q_out, 1.0), o)
    short = (o > 0.0) & (o < min_duty)
    drop = short & ~(excess > VENT_DEADBAND)
    if (short & ~drop).any():
        drop |= short & ~(excess > 0.5 * vent_pulse_drop(model, min_duty, period, est, W, q_out))
    carry = np.array(carry, dtype=float)
    carry[1] = np.where(drop, 0.0, carry[1])
    return a, np.where(drop, 0.0, o), carry
