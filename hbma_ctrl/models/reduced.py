"""The reduced chamber model: one chamber reduced to its gas mass, with the pump (SI).

Under a dead load W (or none) the membrane is quasi-static: the gas mass m and the load fix the
shape (h1, h2) through the gas law ``G(h1, h2) = (p + p_env) V = m R T`` and the contact condition
``F(h1, h2) = W`` (the paper's quasi-static HBMA model); the gas mass integrates the net flow of
the pump and the valves. Three factors describe how a real chamber differs from the nominal one:

- ``b`` multiplies the compressor map (``P["flow_scale"]``),
- ``k`` every modulus of the material (moduli enter the pressure linearly, so ``p = k p_nominal``
  at a given shape),
- ``c`` the dead volume (``P["V0"]``).

:class:`ReducedChamber` binds the parameters once from an :class:`Actuator` and
:class:`Pneumatics` and offers the pieces every role evaluates: the factored parameters, the flow,
the casadi Newton shape solve (:func:`shape_newton`) and the numeric shape solver. The roles build
on it: the estimators' casadi model (:class:`hbma_ctrl.models.chamber.ObserverModel`), the
equilibrium tables of the controllers (:class:`hbma_ctrl.models.tables.PredictionModel`) and the
robot's mapped chamber banks (:class:`hbma_ctrl.models.bank.ChamberBank`).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from hbma_ctrl.core import physics as ph
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.models.fidelity import QuasiStatic, cap_law, make_fidelity, shape_jacobian
from hbma_ctrl.models.fidelity_exact import make_exact_loaded
from hbma_ctrl.models.shape import ShapeSolver

__all__ = ["ReducedChamber", "shape_newton", "constraint_jacobian", "constraint_residual", "solve_2x2", "EPS_K", "FACTOR_NAMES", "MEMBRANES", "law_key"]

#: membrane laws a reduced chamber can use: the spherical cap (docs/concepts/model.md §1, §3) or the exact
#: axisymmetric membrane's flat-plate contact in the cap's chart (docs/concepts/model.md §9)
MEMBRANES = ("cap", "exact")

#: the three chamber factors: pump flow, modulus, dead volume (-)
FACTOR_NAMES = ("b", "k", "c")
#: a tiny contact stiffness, N/m, regularising F(h1, h2) = W where the pressure vanishes (at W = 0
#: and p -> 0 any h2 would do; with it h2 = 0): 1 N/m is below 1 % of dF/dh2 at working pressures
EPS_K = 1.0


def law_key(actuator: Actuator, pneumatics: Pneumatics, membrane: str) -> tuple:
    """What a model's casadi Functions depend on beyond the material family: the membrane law and, for
    'exact', its table (one per material shape: two Mooney-Rivlin chambers with other C2/C1 ratios
    need two), for caches of built Functions."""
    if membrane == "cap":
        return ("cap",)
    fid = make_exact_loaded("quasi_static", actuator.material, str(pneumatics.csv_path))
    return ("exact", id(fid))  # the fidelity is cached (kept alive) per material shape: its id is stable


def constraint_jacobian(h1, h2, P: dict, law=cap_law):
    """G (J), F (N) and the Jacobian in (h1, h2) of the shape's constraint [G - m R T, F + EPS_K h2 - W]
    at chart (h1, h2) (m): :func:`hbma_ctrl.models.fidelity.shape_jacobian` with the regularising
    EPS_K on the force row."""
    G, F, J = shape_jacobian(h1, h2, P, law)
    J = ca.SX(J)
    J[1, 1] = J[1, 1] + EPS_K
    return G, F, J


def constraint_residual(G, F, h2, m, W, P: dict) -> tuple:
    """The shape's constraint [G - m R T, F + EPS_K h2 - W] (J, N) from G (J) and F (N) at h2 (m), gas
    mass m (kg) and load W (N): the gas law and the force balance, zero on the shape."""
    return G - m * (P["R"] * P["T"]), F + EPS_K * h2 - W


def solve_2x2(J, r0, r1) -> tuple:
    """J^-1 [r0, r1] by Cramer's rule for a 2 x 2 J, |det J| held at 1e-12 or more (its sign kept):
    the shape Newton's step and the implicit-function rule's (SX)."""
    det = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
    sgn = ca.if_else(det >= 0, 1.0, -1.0)
    det = ca.if_else(ca.fabs(det) < 1e-12, sgn * 1e-12, det)
    return (J[1, 1] * r0 - J[0, 1] * r1) / det, (-J[1, 0] * r0 + J[0, 0] * r1) / det


def shape_newton(m, W, h1, h2, P: dict, iters: int, law=cap_law):
    """Casadi Newton on ``G(h1, h2) = m R T``, ``F(h1, h2) + EPS_K h2 = W`` from (h1, h2) (m).

    m gas mass (kg), W load (N), P the (symbolic) parameters; Cramer's rule on the 2x2, a step
    limited to half the cap height so the iterate stays in the chart. Symbolic throughout, so the
    estimators differentiate through it. ``law(h1, h2, P) -> (p, V, lam, a2)`` is the membrane law
    (the cap's by default; a fidelity's ``contact_law``).
    """
    for _ in range(iters):
        G, F, J = constraint_jacobian(h1, h2, P, law)
        d1, d2 = solve_2x2(J, *constraint_residual(G, F, h2, m, W, P))
        # keep the step inside the chart: at most half the cap height per iteration
        lim = 0.5 * ca.fmax(h1, 1e-4)
        sc = ca.fmin(1, lim / ca.fmax(ca.fmax(ca.fabs(d1), ca.fabs(d2)), 1e-30))
        h1, h2 = h1 - sc * d1, h2 - sc * d2
        h1 = ca.fmax(h1, 1e-7)
    return h1, h2


class ReducedChamber:
    """One chamber's reduced model with its nominal parameters bound (SI).

    actuator, pneumatics : the nominal (believed) chamber and supply, never a rig's mismatched ones.
    membrane : the membrane law, one of :data:`MEMBRANES`: 'cap' (default) or 'exact' (the quasi-static
        fidelity on the exact flat-plate contact tables, :func:`hbma_ctrl.models.fidelity_exact.make_exact_loaded`:
        the same law as an exact rig, built once per material and cached on disk).

    Attributes: ``membrane``, ``law`` (the fidelity's ``contact_law(h1, h2, P) -> (p, V, lam, a2)``), ``fidelity`` (the quasi-static plant model the dynamics come from), ``space`` (its
    parameter layout), ``theta`` (parameter vector), ``params`` (the same as a dict of floats),
    ``rt`` = R T (J/kg), ``area`` = pi r1^2 (m^2), ``x_scale`` = p_env V0 / (R T) (kg: the gas
    mass of the unpressurised dead volume), ``shapes`` (the numeric :class:`ShapeSolver`, on the cap's law
    whatever ``membrane``: the controllers' tables use it).
    """

    def __init__(self, actuator: Actuator, pneumatics: Pneumatics, membrane: str = "cap"):
        if membrane not in MEMBRANES:
            raise ValueError(f"membrane = '{membrane}': allowed {', '.join(MEMBRANES)}")
        self.actuator = actuator
        self.pneumatics = pneumatics
        self.membrane = membrane
        csv = str(pneumatics.csv_path)
        self.fidelity: QuasiStatic = (make_exact_loaded("quasi_static", actuator.material, csv) if membrane == "exact"
                                      else make_fidelity("quasi_static", actuator.material, csv))
        self.law = self.fidelity.contact_law
        self.space = self.fidelity.space
        self.theta = self.space.values(actuator, pneumatics, Platform())
        self.params = {n: float(v) for n, v in zip(self.space.names, self.theta)}
        self.rt = actuator.R * actuator.T
        self.area = float(np.pi * actuator.r1 ** 2)
        self.x_scale = actuator.p_env * actuator.V0 / self.rt
        self.shapes = ShapeSolver(self.space, self.theta)

    def rebind(self, actuator: Actuator, pneumatics: Pneumatics) -> "ReducedChamber":
        """This model for another actuator of the same material family and compressor map (self if
        the parameters are the same)."""
        if np.array_equal(self.theta, self.space.values(actuator, pneumatics, Platform())):
            return self
        return ReducedChamber(actuator, pneumatics, self.membrane)

    # --- symbolic pieces -----------------------------------------------------------------------
    def symbols(self) -> tuple[ca.SX, dict]:
        """Parameters as a symbolic vector theta and a dict of its named entries."""
        return self.space.symbols()

    @staticmethod
    def with_factors(P: dict, b=None, k=None, c=None) -> dict:
        """Parameters P with the pump-flow factor b, modulus factor k and dead-volume factor c
        applied (each optional, symbolic or float; the load and gas mass are the caller's)."""
        P = dict(P)
        if b is not None:
            P["flow_scale"] = P["flow_scale"] * b
        if k is not None:
            P["material"] = P["material"].scaled(k)
        if c is not None:
            P["V0"] = P["V0"] * c
        return P

    def net_flow(self, u, p, P: dict):
        """Net mass flow into the chamber (kg/s) for inputs u = [speed, inlet, outlet] (0-1) at
        gauge pressure p (Pa), with parameters P."""
        q, _, _ = ph.net_flow(u, p, P, self.fidelity.table)
        return q

    def rhs(self, x3, u, P: dict, mode):
        """Index-reduced quasi-static dynamics of ``[m, h1, h2]`` (kg, m, m); mode 0 resting, 1 contact."""
        return self.fidelity.rhs(x3, u, P, mode)

    # --- numeric helpers -------------------------------------------------------------------------
    def gas_mass(self, p: float, h1: float = 0.0, h2: float = 0.0) -> float:
        """Gas mass (kg) at gauge pressure p (Pa) in the nominal chamber with shape (h1, h2) (m)."""
        P = dict(self.params)
        P["material"] = self.actuator.material
        V = float(self.law(h1, h2, P)[1])
        return (p + self.actuator.p_env) * V / self.rt
