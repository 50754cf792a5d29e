"""The robot's chamber bank: the reduced chamber model mapped over n chambers, for the robot's EKF
bank and NMPC (SI).

Every robot chamber is the reduced chamber of :mod:`hbma_ctrl.models.reduced` on its equilibrium
tables (:class:`hbma_ctrl.models.tables.PredictionModel`): the state is the scaled gas mass
``x = m R T / (p_env V0) - 1`` and, for a dead load ``W`` (N), the height ``H(x, W)``, the pressure
``Pp(x, W)`` and the stretch ``L(x, W)`` come from the tabulated equilibrium manifold. The gas mass
grows monotonically along every load path, also past the balloon limit point (the pressure falls
there, ``G = (p + p_env) V`` does not): that is why a model on the gas mass can hold a chamber on
the far branch.

The load of chamber i is its share of the robot's weight (and tip load) from
:func:`hbma_ctrl.robot.statics.load_sharing`, recomputed by the caller every control period from
the estimated heights: the model's ``W`` therefore lags the shape by one period (10 ms; the layers
are light and the motion slow, so the lag is far below the load's own uncertainty).

On top of the tables:

- the three chamber factors, estimated by the EKF bank and passed to the NMPC (offset-free
  prediction): ``b`` multiplies the pump flow, ``k`` the membrane modulus and ``c`` the dead volume
  (:meth:`ChamberBank.outputs_expr` maps the nominal tables onto a chamber with k and c exactly for
  a neo-Hookean-type membrane, without new tables);
- the command parametrisation of the pneumatic topology. Each chamber has two decision inputs
  ``w = [a, o]``: its supply ``a`` and its outlet duty ``o`` (0-1). In both topologies ``a`` is
  the inlet valve's duty with the pump at full speed, ``u = [1, a, o]``: the inflow is then linear
  in ``a`` at every pressure. (Metering by pump speed instead has a dead zone: below the speed
  whose stall pressure is the chamber pressure the pump delivers nothing, the linearisation at a
  small speed has zero gain and the RTI never starts pumping on the far branch.) 'per_chamber'
  (one compressor per chamber): chamber i's pump runs while its inlet is open; 'shared' (one
  compressor feeding every chamber through its inlet valve): the pump runs at full speed while
  any chamber draws. The chambers share the pump's flow; as long as the inlet duties sum to at
  most 1 per instant, each chamber gets ``a`` times the pump's flow at its own pressure (the
  manifold model of the robot rig), so the only coupling is the linear budget ``sum_i a_i <= 1``
  -- the NMPC carries it as one constraint row per stage.
- batched (casadi ``map``) discrete steps and their Jacobians for a whole bank of chambers.
- compressor speed as a decision (:meth:`ChamberBank.valve_inputs`): the NMPC plans the supply ``a``
  as a full-speed duty (the linear parametrisation above); what is sent throttles the pump so that
  the plant's inflow is the planned one, ``q(speed, p) inlet = a q(1, p)`` at the chamber's pressure
  p, instead of running the pump at full speed whenever an inlet is open. per_chamber: the speed is
  the lowest that delivers ``a q(1, p)`` (the map inverted at p) with the inlet fully open, but not
  below the speed whose stall pressure is ``STALL_MARGIN`` above p (the inlet duty meters the rest);
  shared: one speed for the pump, the lowest at which every drawing chamber's inlet duty
  ``a_i q(1, p_i) / q(speed, p_i)`` is at most 1 and the duties sum to at most 1 (the manifold's
  budget). The flow the plant gets at p is the one the NMPC assumes (it keeps planning in ``a``);
  at another pressure it is not: the map's relative slope ``-dq/dp / q = 1 / (p_stall(s) - p)`` is
  steeper at a low speed than at full speed, so a pressure estimate off by dp makes the throttled
  inflow off by about ``dp (1 / (p_stall(s) - p) - 1 / (p_stall(1) - p))`` (10 %/kPa with the stall
  6 kPa above p; the pressure's own rise within a period changes it < 1 %). Measured in closed
  loop (2-layer sequence) the estimate's pressure error is 72 Pa std and the rig gets the planned
  flow at its true pressure within 0.5 % (std 0.5 %), so the EKF bank keeps predicting with ``a``.
  It can predict with what was sent, ``u = [speed, inlet, outlet]`` (:meth:`ChamberBank.discrete_expr`
  with ``plant_inputs``; :class:`hbma_ctrl.estimators.robot_ekf.ChamberEKFBank` takes 3 x n
  inputs), exact whatever the pressure error; on the shared pump that delayed the release of the
  cautious supply cap (its modulus factor's std): 0.252 against 0.218 mm over seeds 1-8 (7 worse).
  Throttling costs no tracking the seeds resolve: the sequence's settled height RMSE is set by
  when the cautious cap of the chamber climbing to 8 mm, past its limit point, lets go (0.05-0.36 mm
  from seed to seed; the held chambers stay within 0.01-0.015 mm, median). Seeds 1-5, full speed /
  throttled: 0.285 / 0.293 mm per_chamber (mean pump speed 0.27 / 0.19), 0.280 / 0.274 mm shared
  (0.99 / 0.84); the slow test ``test_a_throttled_pump_tracks_as_well_as_full_speed_over_five_seeds``
  measures it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import casadi as ca
import numpy as np

from hbma_ctrl.core.codegen import HOT_FLAGS, HOT_OPT, compiled, is_finite, is_nan
from hbma_ctrl.core.params import Actuator, Pneumatics
from hbma_ctrl.core.physics import load_compressor_table
from hbma_ctrl.core.units import mm
from hbma_ctrl.models.fidelity import fixed_step
from hbma_ctrl.models.tables import PredictionModel

__all__ = ["ChamberBank", "BankSymbols", "TOPOLOGIES", "commands_from_inputs", "PumpMap", "throttled_inputs_function",
           "STALL_MARGIN"]

TOPOLOGIES = ("per_chamber", "shared")


class BankSymbols(NamedTuple):
    """The symbols of one chamber's expressions: scaled gas mass x (-), decisions w = [a, o] (0-1),
    load W (N), pump-flow factor b, modulus factor k, dead-volume factor c (-)."""

    x: ca.SX
    w: ca.SX
    W: ca.SX
    b: ca.SX
    k: ca.SX
    c: ca.SX


def commands_from_inputs(a: np.ndarray, o: np.ndarray, topology: str) -> np.ndarray:
    """Per-chamber decisions (supply a, outlet o; each (n,), 0-1) -> plant inputs U (3 x n).

    per_chamber: [speed 1 while a > 0 (else 0), inlet duty a, outlet o]; shared: [pump speed 1 while
    any inlet is open (else 0), inlet duty a, outlet o] (the same speed in every column: one pump).
    """
    a = np.clip(np.asarray(a, dtype=float), 0.0, 1.0)
    o = np.clip(np.asarray(o, dtype=float), 0.0, 1.0)
    a = np.where(a < 1e-4, 0.0, a)
    o = np.where(o < 1e-4, 0.0, o)
    if topology == "per_chamber":
        return np.vstack([(a > 0).astype(float), a, o])
    if topology == "shared":
        s = 1.0 if np.any(a > 0) else 0.0
        return np.vstack([np.full(a.shape, s), a, o])
    raise ValueError(f"robot.topology = '{topology}': allowed {', '.join(TOPOLOGIES)}")


class PumpMap:
    """The compressor map q(speed, p) (kg/s, before flow_scale) as its table: grid speeds (0-1), gauge
    pressures (Pa) and flows q (n_speeds, n_pressures), read bilinearly by
    :func:`throttled_inputs_function`."""

    def __init__(self, path):
        self.speeds, self.pressures, self.q = load_compressor_table(path)


#: the throttled pump keeps its stall pressure at least this far above the chamber's, Pa: near stall
#: the flow falls steeply with the back pressure (q ~ 1 - p / p_stall), so a pressure error of a
#: few hundred Pa would be a large flow error; the inlet duty meters the rest
STALL_MARGIN = 10e3


def _map_row(pump: PumpMap, p):
    """The map's flows at every grid speed (a list) at one pressure p (casadi expression), pressures
    clipped to the grid, bilinear in the pressure (the interval by comparisons), floored at 0."""
    pg, q = pump.pressures, pump.q
    pc = ca.fmin(ca.fmax(p, pg[0]), pg[-1])
    j = 0
    for g in pg[1:]:
        j = j + (pc >= g)
    j = ca.fmin(ca.fmax(j, 0), pg.size - 2)
    fs = [(pc - pg[i]) / (pg[i + 1] - pg[i]) for i in range(pg.size - 1)]  # the fraction in each interval
    row = []
    for si in range(q.shape[0]):
        v = 0
        for i, f in enumerate(fs):
            v = v + ca.if_else(j == i, q[si, i] * (1 - f) + q[si, i + 1] * f, 0)
        row.append(ca.fmax(v, 0.0))
    return row


def _flow_on(pump: PumpMap, Q: list, speed):
    """The flow on one row Q of :func:`_map_row` (list over the grid speeds) at a speed (expression)."""
    sg = pump.speeds
    sp = ca.fmin(ca.fmax(speed, sg[0]), sg[-1])
    k = 0
    for g in sg[1:]:
        k = k + (sp >= g)
    k = ca.fmin(ca.fmax(k, 0), sg.size - 2)
    v = 0
    for i in range(sg.size - 1):
        f = (sp - sg[i]) / (sg[i + 1] - sg[i])
        v = v + ca.if_else(k == i, Q[i] * (1 - f) + Q[i + 1] * f, 0)
    return v


def _speed_on(pump: PumpMap, Q: list, qt):
    """The lowest speed (0-1) whose flow on row Q (made non-decreasing in speed) reaches the target
    flow qt: 1 where full speed falls short (or qt is NaN), 0 for no flow (expression)."""
    sg = pump.speeds
    Qm, m = [], None
    for v in Q:  # non-decreasing in speed
        m = v if m is None else ca.fmax(m, v)
        Qm.append(m)
    k = 0
    for v in Qm:
        k = k + (v < qt)
    k = ca.if_else(is_nan(qt), sg.size, k)
    kk = ca.fmin(ca.fmax(k, 1), sg.size - 1)
    out = 0
    for i in range(1, sg.size):
        q0, q1 = Qm[i - 1], Qm[i]
        out = out + ca.if_else(kk == i, sg[i - 1] + (sg[i] - sg[i - 1]) * (qt - q0) / ca.fmax(q1 - q0, 1e-300), 0)
    out = ca.if_else(k >= sg.size, 1.0, ca.if_else(k == 0, sg[0], out))
    return ca.fmin(ca.fmax(ca.if_else(qt <= 0.0, 0.0, out), 0.0), 1.0)


def throttled_inputs_function(pump: PumpMap, n: int, topology: str, stall_margin: float = STALL_MARGIN,
                              name: str = "valve_inputs") -> ca.Function:
    """Per-chamber decisions (supply a as a full-speed inlet duty, outlet o; n each, 0-1) at gauge
    pressures p (n) Pa -> plant inputs U (3 x n) with the compressor throttled so that each inflow is
    ``a q(1, p)`` (module docstring), the speed never below the one whose stall pressure is
    ``stall_margin`` Pa above p; chambers the full-speed pump cannot feed at their pressure keep
    ``[1, a]``. ONE casadi Function ``valve_inputs(a[n], o[n], p[n]) -> U[3 x n]`` (the map's
    intervals found by comparisons, a shared pump's speed by 16 bisections; per-chamber pumps, one
    chamber's Function mapped over the n, which builds n times faster)."""
    if topology not in TOPOLOGIES:
        raise ValueError(f"robot.topology = '{topology}': allowed {', '.join(TOPOLOGIES)}")
    if topology == "per_chamber" and n > 1:
        one = throttled_inputs_function(pump, 1, topology, stall_margin, f"{name}_one").map(n)
        a, o, p = (ca.MX.sym(v, n) for v in "aop")
        return ca.Function(name, [a, o, p], [one(a.T, o.T, p.T)], ["a", "o", "p"], ["U"])
    SX = ca.SX
    a_in, o_in, p_in = SX.sym("a", n), SX.sym("o", n), SX.sym("p", n)
    a = [ca.fmin(ca.fmax(a_in[i], 0.0), 1.0) for i in range(n)]
    o = [ca.fmin(ca.fmax(o_in[i], 0.0), 1.0) for i in range(n)]
    a = [ca.if_else(v < 1e-4, 0.0, v) for v in a]
    o = [ca.if_else(v < 1e-4, 0.0, v) for v in o]
    any_a = 0
    for v in a:
        any_a = ca.logic_or(any_a, v > 0)
    if topology == "shared":
        tot = 0
        for v in a:
            tot = tot + v
        a = [ca.if_else(tot > 1.0, v / tot, v) for v in a]  # the manifold's budget
        speed0 = [ca.if_else(any_a, 1.0, 0.0)] * n
    else:
        speed0 = [ca.if_else(v > 0, 1.0, 0.0) for v in a]
    p = [ca.if_else(is_finite(p_in[i]), p_in[i], 0.0) for i in range(n)]
    Q = [_map_row(pump, pi) for pi in p]
    q1 = [_flow_on(pump, Qi, 1.0) for Qi in Q]
    feed = [ca.logic_and(a[i] > 0, q1[i] > 0) for i in range(n)]
    if stall_margin > 0:
        s_min = [_speed_on(pump, _map_row(pump, p[i] + stall_margin), 1e-12) for i in range(n)]
    else:
        s_min = [SX(0.0)] * n
    if topology == "per_chamber":
        speed, inlet = [], []
        for i in range(n):
            sp = ca.fmax(_speed_on(pump, Q[i], a[i] * q1[i]), s_min[i])
            q_s = _flow_on(pump, Q[i], sp)
            speed.append(ca.if_else(feed[i], sp, speed0[i]))
            inlet.append(ca.if_else(feed[i], ca.fmin(a[i] * q1[i] / ca.fmax(q_s, 1e-300), 1.0), a[i]))
    else:
        any_feed = 0
        for f in feed:
            any_feed = ca.logic_or(any_feed, f)
        target = [a[i] * q1[i] for i in range(n)]

        def duties(sv):
            out = []
            for i in range(n):
                q = _flow_on(pump, Q[i], sv)
                out.append(ca.if_else(q > 0, target[i] / ca.fmax(q, 1e-300), ca.inf))
            return out

        def fits(d):  # every fed chamber's duty finite and their sum at most 1
            ok, tot = 1, 0
            for i in range(n):
                ok = ca.logic_and(ok, ca.logic_or(ca.logic_not(feed[i]), is_finite(d[i])))
                tot = tot + ca.if_else(feed[i], d[i], 0.0)
            return ca.logic_and(ok, tot <= 1.0)

        lo = -ca.inf
        for i in range(n):
            lo = ca.fmax(lo, ca.if_else(feed[i], ca.fmax(_speed_on(pump, Q[i], target[i]), s_min[i]), -ca.inf))
        hi = SX(1.0)
        lo_b = lo
        for _ in range(16):  # the duties' sum falls with the speed: bisection on [lo, 1]
            mid = 0.5 * (lo_b + hi)
            good = fits(duties(mid))
            lo_b, hi = ca.if_else(good, lo_b, mid), ca.if_else(good, mid, hi)
        s = ca.if_else(fits(duties(lo)), lo, hi)
        d = duties(s)
        speed = [ca.if_else(any_feed, s, speed0[i]) for i in range(n)]
        inlet = [ca.if_else(ca.logic_and(any_feed, feed[i]), ca.fmin(d[i], 1.0), a[i]) for i in range(n)]
    U = ca.vertcat(ca.horzcat(*speed), ca.horzcat(*inlet), ca.horzcat(*o))
    return ca.Function(name, [a_in, o_in, p_in], [U], ["a", "o", "p"], ["U"], {"cse": True})


class ChamberBank:
    """The reduced chamber on its tables, with its factors; batched functions for n chambers.

    actuator, pneumatics : the nominal chamber and supply (never the rig's mismatched ones).
    topology : 'per_chamber' | 'shared' (see module doc).
    load_max : largest chamber load the tables cover, N; h_table_max : largest height, m.
    """

    def __init__(self, actuator: Actuator, pneumatics: Pneumatics, topology: str = "per_chamber",
                 load_max: float = 2.0, h_table_max: float = mm(14.0)):
        if topology not in TOPOLOGIES:
            raise ValueError(f"robot.topology = '{topology}': allowed {', '.join(TOPOLOGIES)}")
        self.topology = topology
        # the robot's chambers are the cap (its rig has no exact membrane yet, docs/concepts/truth.md)
        self.tables = PredictionModel(actuator, pneumatics, load_max=load_max, h_table_max=h_table_max,
                                      membrane="cap")
        self.chamber = self.tables.chamber
        self.actuator = self.tables.actuator
        self.pneumatics = self.tables.pneumatics
        self.load_max = load_max
        self.h_table_max = h_table_max
        x, W, b = ca.SX.sym("x"), ca.SX.sym("W"), ca.SX.sym("b")
        w = ca.SX.sym("w", 2)  # [supply a, outlet o]
        u = ca.SX.sym("u", 3)  # the plant's inputs [speed, inlet duty, outlet duty]
        k, c = ca.SX.sym("k"), ca.SX.sym("c")
        self.symbols = BankSymbols(x, w, W, b, k, c)
        self.u = u
        hx, p, lam = self.outputs_expr(x, W, k, c)
        q = self.chamber.net_flow(u, p, self.chamber.with_factors(self.chamber.params, b=b))
        self._xdot_u = ca.Function("xdot_u", [x, u, W, b, k, c], [self.x_of_mass(q)])
        # the decisions: pump at full speed while the inlet is open, inlet duty a
        self._xdot = ca.Function("xdot", [x, w, W, b, k, c],
                                 [self._xdot_u(x, ca.vertcat(1.0, w[0], w[1]), W, b, k, c)])
        self.out = ca.Function("out", [x, W, k, c], [hx, p, lam], ["x", "W", "k", "c"], ["h", "p", "lam"])
        self._cache: dict = {}

    @property
    def pump(self) -> PumpMap:
        """The compressor map of the nominal pneumatics (loaded once)."""
        if "pump" not in self._cache:
            self._cache["pump"] = PumpMap(self.pneumatics.csv_path)
        return self._cache["pump"]

    def x_of_mass(self, m):
        """A gas mass (or mass flow) m, kg (kg/s), in the scaled mass's units, p_env V0 / (R T) (the
        state's ``x = m R T / (p_env V0) - 1`` without its offset); numbers or SX."""
        a = self.actuator
        return m * a.R * a.T / (a.p_env * a.V0)

    def height_drop_function(self) -> ca.Function:
        """height_drop(x, W, k, c, dm) -> m: the height one chamber loses when gas mass dm (kg) leaves
        it, the model's height at (x, W, k, c) less the one at x less dm (casadi, cached)."""
        def build() -> ca.Function:
            xs, ws, ks, cs, ms = (ca.SX.sym(s) for s in ("x", "W", "k", "c", "dm"))
            drop = self.outputs_expr(xs, ws, ks, cs)[0] - self.outputs_expr(xs - self.x_of_mass(ms), ws, ks, cs)[0]
            return ca.Function("height_drop", [xs, ws, ks, cs, ms], [drop])

        return self.cached("height_drop", build)

    def open_flows_function(self) -> ca.Function:
        """open_flows(p, b) -> (q_in, q_out) kg/s: the mass flows a supply a = 1 (the full-speed pump
        through an open inlet) and an outlet o = 1 (fully open) pass at gauge pressure p (Pa) with
        pump-flow factor b, as the bank's model has them: a decision (a, o) passes a and o times these
        (casadi, cached)."""
        def build() -> ca.Function:
            pp, bb = ca.SX.sym("p"), ca.SX.sym("b")
            P = self.chamber.with_factors(self.chamber.params, b=bb)
            return ca.Function("open_flows", [pp, bb], [self.chamber.net_flow(ca.DM([1.0, 1.0, 0.0]), pp, P),
                                                      -self.chamber.net_flow(ca.DM([0.0, 0.0, 1.0]), pp, P)])

        return self.cached("open_flows", build)

    def valve_inputs(self, a: np.ndarray, o: np.ndarray, p: np.ndarray, throttle: bool = True) -> np.ndarray:
        """Plant inputs U (3 x n) for decisions a, o (n,) at gauge pressures p (n,) Pa: the compressor
        throttled to the planned flow (:func:`throttled_inputs_function`, built once per n), or with
        ``throttle`` False full speed while an inlet is open (:func:`commands_from_inputs`)."""
        if not throttle:
            return commands_from_inputs(a, o, self.topology)
        n = np.size(a)
        f = self.cached(("valve_inputs", n), lambda: throttled_inputs_function(self.pump, n, self.topology))
        return np.asarray(f(a, o, p), dtype=float)

    @property
    def x_max(self) -> float:
        """Largest scaled gas mass the tables cover (-)."""
        return float(self.tables.grid.x[-1])

    def cached(self, key, build: Callable[[], ca.Function]) -> ca.Function:
        """The Function ``build()`` made once per model and key (a role's step, say)."""
        if key not in self._cache:
            self._cache[key] = build()
        return self._cache[key]

    # --- building blocks -------------------------------------------------------------------------
    def outputs_expr(self, x, W, k, c=1.0, iters: int = 3):
        """(h, p, lam) of a chamber whose membrane modulus is k times nominal and whose dead volume
        is c times nominal (SX expressions; x is the gas mass in units of the NOMINAL p_env V0 / RT).

        For a neo-Hookean-type membrane the pressure of a given shape scales with the modulus, so a
        chamber of modulus k under load W has the shape of a nominal chamber under W / k at k times
        its pressure. Its gas is ``(x + 1) p_env V0 = (p + p_env)(c V0 + Vcap)``; the nominal table's
        (x1, p1) at the same shape give ``Vcap / V0 = (x1 + 1) p_env / (p1 + p_env) - 1``, so
        ``x1 + 1 = [(x + 1) - (k p1 + p_env)(c - 1) / p_env] (p1 + p_env) / (k p1 + p_env)``, solved
        by a fixed-point iteration (a contraction for the modest k, c of a mismatch). Resting
        chambers come out exact (p = p_env ((x + 1) / c - 1) for any k).
        """
        pe = self.actuator.p_env
        Wk = W / k
        tb = self.tables
        # the iterate is kept on the tables (zero outside their grid): from a start past the top (a dead
        # volume below nominal) it would otherwise read p1 = 0 and never come back; a chamber whose gas
        # is past the top reads the top's shape (the estimator flags it, ChamberEKFBank's ``beyond``)
        top = self.x_max
        xe = ca.fmin((x + 1) / c - 1, top)
        for _ in range(iters):
            p1 = tb.P_table(ca.vertcat(xe, Wk))
            xe = ca.fmin(((x + 1) - (k * p1 + pe) * (c - 1) / pe) * (p1 + pe) / (k * p1 + pe) - 1, top)
        xw = ca.vertcat(xe, Wk)
        return tb.H_table(xw), k * tb.P_table(xw), tb.L_table(xw)

    def x_top_expr(self, W, k, c=1.0):
        """The gas mass (units of the NOMINAL p_env V0 / RT) at which a chamber of modulus factor k and
        dead-volume factor c under load W reaches the top of the tables (their shape at ``x_max``):
        :meth:`outputs_expr`'s relation solved for x at x1 = x_max (SX). A larger dead volume holds
        more gas at the same shape, so the top in x moves with c."""
        pe = self.actuator.p_env
        p1 = self.tables.P_table(ca.vertcat(self.x_max, W / k))
        return (self.x_max + 1) * (k * p1 + pe) / (p1 + pe) + (k * p1 + pe) * (c - 1) / pe - 1

    def discrete_expr(self, dt: float, substeps: int = 1, method: str = "rk4", plant_inputs: bool = False):
        """x+ (SX expression in the model's symbols) after dt s, rk4 or euler with inputs held. With
        ``plant_inputs`` the input is ``self.u`` = [speed, inlet, outlet] (0-1: what the plant was sent,
        a throttled pump's speed included) instead of the decisions w = [a, o]."""
        x, w, W, b, k, c = self.symbols
        if plant_inputs:
            w = self.u
        f = self._xdot_u if plant_inputs else self._xdot
        return fixed_step(lambda xs: f(xs, w, W, b, k, c), x, dt, substeps, method)

    def linearisation(self, dt: float, substeps: int = 1, method: str = "rk4") -> ca.Function:
        """(x, w, W, b, k, c) -> (x+, dx+/dx, dx+/dw (1x2), h, dh/dx, p, dp/dx): one chamber, one stage."""
        key = ("lin", dt, substeps, method)
        if key not in self._cache:
            x, w, W, b, k, c = self.symbols
            xn = self.discrete_expr(dt, substeps, method)
            h, p, _ = self.outputs_expr(x, W, k, c)
            self._cache[key] = ca.Function(
                "lin", [x, w, W, b, k, c],
                [xn, ca.jacobian(xn, x), ca.jacobian(xn, w), h, ca.jacobian(h, x), p, ca.jacobian(p, x)])
        return self._cache[key]

    def mapped(self, fun: ca.Function, n: int, compile: bool = True) -> ca.Function:
        """fun mapped over n columns (cached per model); with ``compile`` the map is generated as C
        and compiled by :func:`hbma_ctrl.core.codegen.compiled` at its per-step flags (a map is one
        loop over the function: it compiles in a second; cached on disk by source hash; casadi's
        virtual machine without a compiler). The robot's EKF bank step, 9 chambers: 104 -> 90 us a
        call against -O1, bit-identical."""
        key = ("map", id(fun), n, compile)
        if key not in self._cache:
            f = fun.map(n)
            if compile:
                f = compiled(f, HOT_OPT, HOT_FLAGS)
            self._cache[key] = f
        return self._cache[key]

    # --- numeric helpers ---------------------------------------------------------------------------
    def x_at_height(self, h: np.ndarray, W: np.ndarray) -> np.ndarray:
        """States holding heights h (m) under loads W (N), elementwise (contact branch)."""
        h = np.atleast_1d(np.asarray(h, dtype=float))
        W = np.broadcast_to(np.asarray(W, dtype=float), h.shape)
        return np.array([self.tables.x_at_height(float(hi), float(wi)) for hi, wi in zip(h, W)])

    def pressure_at_height(self, h: np.ndarray, W: np.ndarray) -> np.ndarray:
        """Model pressure (Pa) at heights h (m) and loads W (N), elementwise."""
        h = np.atleast_1d(np.asarray(h, dtype=float))
        W = np.broadcast_to(np.asarray(W, dtype=float), h.shape)
        out = []
        for hi, wi in zip(h, W):
            pth = self.tables.path(float(wi))
            out.append(float(np.interp(hi, pth["h"], pth["p"])))
        return np.array(out)

    def peak(self, W: float) -> tuple[float, float]:
        """(height m, pressure Pa) of the balloon limit point along the load path at W (N)."""
        pth = self.tables.path(float(W))
        i = int(np.argmax(pth["p"]))
        return float(pth["h"][i]), float(pth["p"][i])

    def clip_load(self, W):
        """Loads clipped to the tables' range [1 mN, load_max] N (numpy, or a casadi expression for the
        generated steps)."""
        if isinstance(W, (ca.SX, ca.MX)):
            return ca.fmin(ca.fmax(W, 1e-3), self.load_max)
        return np.clip(np.asarray(W, dtype=float), 1e-3, self.load_max)
