"""The parts of :meth:`hbma_ctrl.runtime.robot.RobotLoop.tick` around its controller and supervisor as
casadi Functions: the loop evaluates them each tick, a generated robot loop emits them (SI).

- :func:`slew_function`: the targets this tick: each chamber's target moves towards its goal at most
  ``target_rate`` x dt, from the estimated height at the first tick; a zero target (the vent rule)
  applies at once.
- :func:`caps_function`: the supply bound the NMPC gets per chamber (``a_max``): 0 where the
  supervisor's vent rule or an interlock holds the chamber (the stretch at its limit, a lost
  estimate, a burst), and the cautious cap (``RobotLoop.cautious``) while a chamber's estimated
  pressure is above a fraction of its estimated limit-point pressure and its modulus factor is still
  uncertain. The limit-point pressures are refreshed where asked (every tenth tick in the loop) at
  the loads over the modulus factors (the tables' load path's peak, :func:`peak_function`).
- :func:`net_vents_function`: with a minimum valve opening, a vent shorter than it netted into the
  same chamber's supply, and one left over dropped unless the chamber is high enough above its
  target (:data:`VENT_DEADBAND`, and half the height one minimum opening takes off), the outlets'
  carried duty forgotten where one is dropped.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from hbma_ctrl.core.codegen import is_finite, is_nan
from hbma_ctrl.models.bank import ChamberBank
from hbma_ctrl.runtime.safety import ZERO_TARGET

__all__ = ["slew_function", "caps_function", "peak_function", "net_vents_function", "VENT_DEADBAND"]

#: with a minimum valve opening, a vent shorter than it is sent (as the minimum opening every few
#: periods) only while the chamber's estimated height is more than this above its target, m. One 2 ms
#: vent takes 0.4-0.8 mm off a chamber on its far branch at 39 kPa: held at its target by trickle
#: vents, it dipped that much several times a second (robot_bending on the structured rig, seeds
#: 0-5: 35 of 42 segments settled, most at the end of their 4 s). With the netting into the supply
#: and this band: 42 of 42 at 0.10, 0.15 and 0.25 mm, 37 of 42 with the netting and no band. The band
#: is also at least half the height one minimum opening takes off (net_vents_function): a vent is
#: sent only when it brings the chamber nearer its target
VENT_DEADBAND = 0.15e-3


def slew_function(n: int, target_rate: float, name: str = "slew") -> ca.Function:
    """slew(goal[n], prev[n], h_est[n], first, dt) -> href[n] (m, m/s, s): ``prev`` the last tick's
    targets, ignored at the ``first`` tick (then the estimated heights, NaN as 0, below 0 as 0)."""
    goal, prev, h = (ca.SX.sym(s, n) for s in ("goal", "prev", "h_est"))
    first, dt = ca.SX.sym("first"), ca.SX.sym("dt")
    if target_rate <= 0.0:
        return ca.Function(name, [goal, prev, h, first, dt], [goal], ["goal", "prev", "h_est", "first", "dt"], ["href"])
    h0 = ca.fmax(_nan_to_zero(h), 0.0)
    start = ca.if_else(first != 0, h0, prev)
    lim = target_rate * dt
    out = start + ca.fmin(ca.fmax(goal - start, -lim), lim)
    return ca.Function(name, [goal, prev, h, first, dt], [ca.if_else(goal <= ZERO_TARGET, goal, out)],
                       ["goal", "prev", "h_est", "first", "dt"], ["href"])


def _nan_to_zero(v):
    """np.nan_to_num on heights: NaN -> 0, +-inf -> the largest finite double (as numpy)."""
    big = np.finfo(float).max
    return ca.if_else(is_nan(v), 0.0, ca.fmin(ca.fmax(v, -big), big))


def peak_function(model: ChamberBank, name: str = "peak_pressure") -> ca.Function:
    """peak(W) -> the pressure of the limit point along the load path at W (N; clipped to the tables'
    loads), Pa: the largest of the path's pressures, its columns blended at W as the tables' path()."""
    W = ca.SX.sym("W")
    (p,) = model.tables.path_columns_expr(W, "p_path")
    return ca.Function(name, [W], [ca.mmax(p)], ["W"], ["p_peak"])


def caps_function(model: ChamberBank, n: int, cautious: tuple | None, vent_height: float | None,
                  stretch_max: float | None, name: str = "caps") -> ca.Function:
    """caps(W[n], k[n], p[n], k_std[n], href[n], lam[n], lost[n], sup_lost[n], sup_burst[n], peak[n], refresh)
        -> (a_max[n], near[n], peak_next[n])

    W the loads (N), k and k_std the modulus factors and their std, p the estimated pressures (Pa),
    href the targets (m), lam the estimated stretches, lost the lost estimates, sup_lost / sup_burst
    the supervisor's latches (0-1). No supply budget where the vent rule holds (a finite target at or
    below ``vent_height``, m) or an interlock does (``lam`` at or above ``stretch_max``, a lost
    estimate or latch, a burst latch); None = no such rule. ``peak`` the limit-point pressures kept
    (Pa), recomputed at the loads over the factors (clipped to the tables) where ``refresh`` is 1.
    ``cautious`` = (pressure fraction, k std, duty) as :class:`~hbma_ctrl.runtime.robot.RobotLoop`'s,
    None = no cap (near 0)."""
    SX = ca.SX
    names = ("W", "k", "p", "k_std", "href", "lam", "lost", "sup_lost", "sup_burst", "peak")
    W, k, p, ks, href, lam, lost, sup_lost, sup_burst, peak = (SX.sym(s, n) for s in names)
    refresh = SX.sym("refresh")
    pk = peak_function(model).map(n)
    fresh = ca.vec(pk(ca.vec(model.clip_load(W / k)).T))
    peak_next = ca.if_else(refresh != 0, fresh, peak) if cautious is not None else peak
    held = ca.logic_or(ca.logic_or(lost != 0, sup_lost != 0), sup_burst != 0)
    if vent_height is not None:
        held = ca.logic_or(held, ca.logic_and(is_finite(href), href <= vent_height))
    if stretch_max is not None:
        held = ca.logic_or(held, lam >= stretch_max)  # (NaN compares false: not held)
    a_max = ca.if_else(held, 0.0, 1.0)
    near = SX.zeros(n)
    if cautious is not None:
        c0, c1, c2 = (float(v) for v in cautious)
        near = ca.logic_and(p > c0 * k * peak_next, ks > c1)
        a_max = ca.if_else(near, ca.fmin(a_max, c2), a_max)
    return ca.Function(name, [W, k, p, ks, href, lam, lost, sup_lost, sup_burst, peak, refresh],
                       [a_max, near, peak_next], [*names, "refresh"], ["a_max", "near", "peak_next"])


def net_vents_function(model: ChamberBank, n: int, min_duty: float, period: float,
                       name: str = "net_vents") -> ca.Function:
    """net_vents(a[n], o[n], p[n], b[n], excess[n], x[n], W[n], k[n], c[n], carry[2 x n])
        -> (a_sent[n], o_sent[n], carry_next[2 x n])

    The short vents for a minimum opening of ``min_duty`` (of the period, s): the decisions
    (a, o), the estimated pressures p (Pa), pump-flow factors b, heights above the targets ``excess``
    (m), gas masses x, loads W (N) and factors k, c (for the height one minimum opening takes off),
    and the minimum on-time's carry (inlet row 0, outlet row 1: the outlet's is forgotten where a
    short vent is dropped).

    A vent shorter than the opening is netted into the same chamber's supply (the same net flow at
    p); one left over is dropped while the chamber is at most :data:`VENT_DEADBAND` above its
    target, or at most half the height one minimum opening takes off (the model's height at x less
    the one at the mass that opening lets out): a vent that would overshoot the target by more than
    it corrects is not sent. Why: holding a chamber the NMPC pumps and vents at once, a vent trickle
    reaches the valve as one minimum opening every few periods
    (:class:`~hbma_ctrl.runtime.pwm.MinOnTime`), a height step of 0.4-0.8 mm on a far-branch
    chamber; the pump's flow, a speed, can be trimmed by any amount."""
    SX = ca.SX
    a, o, p, b, ex, x, W, k, c = (SX.sym(s, n) for s in ("a", "o", "p", "b", "excess", "x", "W", "k", "c"))
    carry = SX.sym("carry", 2, n)
    flows, drop_fn = model.open_flows_function(), model.height_drop_function()
    md = float(min_duty)
    a_out, o_out, c_out = [], [], []
    any_small = 0
    for i in range(n):
        any_small = ca.logic_or(any_small, ca.logic_and(o[i] > 0.0, o[i] < md))
    for i in range(n):
        q_in, q_out = flows(p[i], b[i])
        small = ca.logic_and(o[i] > 0.0, o[i] < md)
        net = a[i] * q_in - o[i] * q_out
        ok = ca.logic_and(ca.logic_and(small, a[i] > 0.0), ca.logic_and(q_in > 0.0, q_out > 0.0))
        ai = ca.if_else(ok, ca.fmax(net, 0.0) / ca.if_else(ok, q_in, 1.0), a[i])
        oi = ca.if_else(ok, ca.fmax(-net, 0.0) / ca.if_else(ok, q_out, 1.0), o[i])
        short = ca.logic_and(oi > 0.0, oi < md)
        drop = ca.logic_and(short, ca.logic_not(ex[i] > VENT_DEADBAND))
        pulse = ca.fmax(drop_fn(x[i], W[i], k[i], c[i], q_out * (md * period)), 0.0)
        drop = ca.logic_or(drop, ca.logic_and(short, ca.logic_not(ex[i] > 0.5 * pulse)))
        # nothing changes on a tick without a short vent (the loop returns before its flows)
        a_out.append(ca.if_else(any_small, ai, a[i]))
        o_out.append(ca.if_else(any_small, ca.if_else(drop, 0.0, oi), o[i]))
        c_out.append(ca.vertcat(carry[0, i], ca.if_else(ca.logic_and(any_small, drop), 0.0, carry[1, i])))
    return ca.Function(name, [a, o, p, b, ex, x, W, k, c, carry],
                       [ca.vertcat(*a_out), ca.vertcat(*o_out), ca.horzcat(*c_out)],
                       ["a", "o", "p", "b", "excess", "x", "W", "k", "c", "carry"], ["a_sent", "o_sent", "carry_next"])
