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
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import casadi as ca
import numpy as np

from hbma_ctrl.core.codegen import compiled
from hbma_ctrl.core.params import Actuator, Pneumatics
from hbma_ctrl.core.units import mm
from hbma_ctrl.models.tables import PredictionModel

__all__ = ["ChamberBank", "BankSymbols", "TOPOLOGIES", "commands_from_inputs"]

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
        self.tables = PredictionModel(actuator, pneumatics, load_max=load_max, h_table_max=h_table_max)
        self.chamber = self.tables.chamber
        self.actuator = self.tables.actuator
        self.pneumatics = self.tables.pneumatics
        self.load_max = load_max
        self.h_table_max = h_table_max
        a = self.actuator
        x, W, b = ca.SX.sym("x"), ca.SX.sym("W"), ca.SX.sym("b")
        w = ca.SX.sym("w", 2)  # [supply a, outlet o]
        u = ca.vertcat(1.0, w[0], w[1])  # pump at full speed while the inlet is open, inlet duty a
        k, c = ca.SX.sym("k"), ca.SX.sym("c")
        self.symbols = BankSymbols(x, w, W, b, k, c)
        hx, p, lam = self.outputs_expr(x, W, k, c)
        q = self.chamber.net_flow(u, p, self.chamber.with_factors(self.chamber.params, b=b))
        self._xdot = ca.Function("xdot", [x, w, W, b, k, c], [q * a.R * a.T / (a.p_env * a.V0)])
        self.out = ca.Function("out", [x, W, k, c], [hx, p, lam], ["x", "W", "k", "c"], ["h", "p", "lam"])
        self._cache: dict = {}
        self.x_rest_max = -0.05  # the tables start here (scaled mass below ambient)

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
        xe = (x + 1) / c - 1
        tb = self.tables
        for _ in range(iters):
            p1 = tb.P_table(ca.vertcat(xe, Wk))
            xe = ((x + 1) - (k * p1 + pe) * (c - 1) / pe) * (p1 + pe) / (k * p1 + pe) - 1
        xw = ca.vertcat(xe, Wk)
        return tb.H_table(xw), k * tb.P_table(xw), tb.L_table(xw)

    def discrete_expr(self, dt: float, substeps: int = 1, method: str = "rk4"):
        """x+ (SX expression in the model's symbols) after dt s, rk4 or euler with inputs held."""
        x, w, W, b, k, c = self.symbols
        h = dt / substeps
        xn = x
        f = self._xdot
        for _ in range(substeps):
            if method == "euler":
                xn = xn + h * f(xn, w, W, b, k, c)
                continue
            k1 = f(xn, w, W, b, k, c)
            k2 = f(xn + h / 2 * k1, w, W, b, k, c)
            k3 = f(xn + h / 2 * k2, w, W, b, k, c)
            k4 = f(xn + h * k3, w, W, b, k, c)
            xn = xn + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        return xn

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
        and compiled by :func:`hbma_ctrl.core.codegen.compiled` (cached on disk by source hash; casadi's
        virtual machine without a compiler)."""
        key = ("map", id(fun), n, compile)
        if key not in self._cache:
            f = fun.map(n)
            if compile:
                f = compiled(f)
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

    def clip_load(self, W: np.ndarray) -> np.ndarray:
        """Loads clipped to the tables' range [1 mN, load_max] N."""
        return np.clip(np.asarray(W, dtype=float), 1e-3, self.load_max)
