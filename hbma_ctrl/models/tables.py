"""The controller's prediction model: one chamber reduced to its gas mass (SI).

Why one state. Under a dead load (or none) the membrane is quasi-static: for a given gas mass ``m``
and load ``W`` the shape (h1, h2) follows from the gas law ``G(h1, h2) = m R T`` and the contact
condition ``F(h1, h2) = W`` (:mod:`hbma_ctrl.models.reduced`, the paper's quasi-static model). Resting (the platform
sits on the rig until ``pi r1^2 p >= W``), lift-off, contact and free inflation (``W = 0``) are all
the same single-valued map ``m -> (h, p, lam)`` for the loads and heights of this actuator (checked
when the map is built: the gas mass grows monotonically along every load path, because the gas is
compressible even where the pressure passes its maximum). So the controller's state is the scaled
gas mass

    x = m R T / (p_env V0) - 1            (= gauge pressure / p_env while resting; 0 at ambient)

with ``x' = q(u, p) R T / (p_env V0)`` (``q`` from :func:`hbma_ctrl.core.physics.net_flow`, the same
compressor map and valves as the plant) and the outputs ``h = H(x, W)``, ``p = Pp(x, W)``,
``lam = L(x, W)`` from the equilibrium manifold, tabulated once per actuator from the membrane physics
on an (x, W) grid and interpolated by cubic B-splines (smooth, cheap, code-generable). The
singular points of the (h1, h2) chart (the flat origin for ``W = 0``, the lift-off kink) never
reach the optimiser: it only sees x.

Nothing here re-derives physics: the grid points are the contact shapes of the one shape solver
(:meth:`hbma_ctrl.models.shape.ShapeSolver.contact`).

Two membrane laws (``membrane``): ``"cap"`` (the spherical cap, docs/concepts/model.md §3) and ``"exact"``
(the default; the exact axisymmetric membrane, Model §9: the same tabulated law the rig and the
simulator's exact rung step with, :class:`hbma_ctrl.models.fidelity_exact.ExactQuasiStatic`'s
``contact_law``, imported, not re-derived). Both are evaluated in the cap's chart (h1, h2), so the
contact bisection, the load paths and the tables are the same code. The stretch ``lam`` (what
``lam_max`` limits) is the area-average stretch of the chart's shape (paper eq. 3) under both laws,
so a setting means the same for either; the exact membrane's largest stretch (on the plate, or at
the pole) is higher (1.51 against 1.29 at 8 mm under 400 g, r1 12.5 mm, t0 3 mm).
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from hbma_ctrl.core import physics as ph
from hbma_ctrl.core.params import Actuator, Pneumatics
from hbma_ctrl.models.defaults import DEFAULT_MEMBRANE
from hbma_ctrl.models.fidelity import fixed_step
from hbma_ctrl.models.fidelity_exact import make_exact_loaded
from hbma_ctrl.models.piecewise import PiecewiseCubic
from hbma_ctrl.models.reduced import MEMBRANES, ReducedChamber
from hbma_ctrl.models.shape import SHAPE_OUTPUTS, ShapeSolver

#: MEMBRANES (from :mod:`hbma_ctrl.models.reduced`): the membrane laws a prediction model can be
#: tabulated from, the same as the observer model's
__all__ = ["PredictionModel", "MEMBRANES", "exact_shape_function", "exact_shape_solver"]


def exact_shape_function(space: ph.ParamSpace, material, compressor_csv: str) -> ca.Function:
    """(h1, h2, theta) -> SHAPE_OUTPUTS with the exact membrane's law: the rig's exact quasi-static
    rung's ``contact_law`` (p, V; F = pi a^2 p) for ``material``'s shape, any modulus scale, r1 and
    t0 through theta (its table is built once per material shape, then cached on disk); ``lam`` the
    chart's area-average stretch, as the cap's (module docstring)."""
    law = make_exact_loaded("quasi_static", material, str(compressor_csv)).contact_law
    h1, h2 = ca.SX.sym("h1"), ca.SX.sym("h2")
    theta, P = space.symbols()
    p, V, _, a2 = law(h1, h2, P)
    lam = ph.geometry(h1, h2, P)["lam"]
    return ca.Function("exact_chamber", [h1, h2, theta], [p, ca.pi * a2 * p, lam, V, (p + P["p_env"]) * V],
                       ["h1", "h2", "theta"], list(SHAPE_OUTPUTS))


def exact_shape_solver(chamber: ReducedChamber) -> ShapeSolver:
    """A shape solver of ``chamber``'s nominal parameters with the exact membrane's law
    (:func:`exact_shape_function`)."""
    fun = exact_shape_function(chamber.space, chamber.actuator.material, str(chamber.pneumatics.csv_path))
    return ShapeSolver(chamber.space, chamber.theta, fun)


@dataclass(frozen=True)
class _Grid:
    x: np.ndarray  # scaled gas mass grid (-)
    W: np.ndarray  # load grid, N
    h: np.ndarray  # (nx, nW) height, m
    p: np.ndarray  # (nx, nW) gauge pressure, Pa
    lam: np.ndarray  # (nx, nW) stretch (-)
    h_path: np.ndarray  # heights along the load paths (contact branch), m
    x_path: np.ndarray  # (nh, nW) x along each load path
    p_path: np.ndarray  # (nh, nW)
    lam_path: np.ndarray  # (nh, nW)


#: how the tables are evaluated in the model's Functions (:meth:`PredictionModel.functions`)
TABLE_FORMS = ("bspline", "poly")


@dataclass(frozen=True)
class TableFunctions:
    """The prediction model's Functions in one table form (:meth:`PredictionModel.functions`): H, Pp,
    L, HP (x, W) -> height m, gauge pressure Pa, stretch -, (h, p); rhs (x, u, W, dp) -> xdot 1/s."""

    H: ca.Function
    Pp: ca.Function
    L: ca.Function
    HP: ca.Function
    rhs: ca.Function


class PredictionModel:
    """Gas-mass prediction model of one chamber for the MPC and the baselines (SI).

    Parameters
    ----------
    actuator, pneumatics : the nominal actuator (never the rig's mismatched one).
    load_max : largest load force the tables cover, N (loads above are clipped and reported).
    h_table_max : largest height the tables cover, m (default 1.4 r1).
    n_x, n_W, n_h : grid sizes.
    chamber : the :class:`ReducedChamber` to tabulate (built from actuator and pneumatics if None).
    membrane : the membrane law tabulated, 'cap' (spherical cap) or 'exact' (the exact membrane's
        tables, as the rig's ``membrane = "exact"``; the default, :mod:`hbma_ctrl.models.defaults`); see the
        module docstring.

    Attributes
    ----------
    chamber : the reduced chamber model the tables are of (parameters, flow, shape solver).
    membrane : 'cap' or 'exact'; shapes : the shape solver of that law the tables come from.
    H_table, P_table, L_table : the interpolants of ``vertcat(x, W)`` behind H, Pp, L.
    H, Pp, L : casadi Functions (x, W) -> height (m), gauge pressure (Pa), stretch (-); HP both. H is negative
        (virtual) below lift-off; the physical height is max(H, 0).
    rhs : casadi Function (x, u, W, dp) -> xdot (1/s); ``dp`` is a pressure bias (Pa) added to the
        model pressure in the valve/pump flows (offset-free prediction).
        These five evaluate the tables as bspline calls; :meth:`functions` gives them with the tables as
        inline polynomials (the same values to 1e-13), which the RTI and IPOPT controllers use.
    """

    def __init__(self, actuator: Actuator, pneumatics: Pneumatics, load_max: float = 10.0,
                 h_table_max: float | None = None, n_x: int = 140, n_W: int = 26, n_h: int = 160,
                 chamber: ReducedChamber | None = None, membrane: str = DEFAULT_MEMBRANE):
        if membrane not in MEMBRANES:
            raise ValueError(f"prediction.membrane = {membrane!r}: allowed {', '.join(MEMBRANES)}")
        self.membrane = membrane
        self.actuator = actuator.validate()
        self.pneumatics = pneumatics.validate()
        if not (0.0 < load_max <= 200.0):
            raise ValueError(f"prediction.load_max = {load_max!r} is out of range (0, 200] N")
        self.load_max = float(load_max)
        self.h_table_max = float(h_table_max if h_table_max is not None else 1.4 * actuator.r1)
        self.chamber = chamber or ReducedChamber(actuator, pneumatics)
        self.RT = self.chamber.rt
        self.theta = self.chamber.theta
        self.shapes = self.chamber.shapes if membrane == "cap" else exact_shape_solver(self.chamber)
        self.grid = self._tabulate(n_x, n_W, n_h)
        self._build_functions()

    # --- tables ----------------------------------------------------------------------------------
    def _tabulate(self, n_x: int, n_W: int, n_h: int) -> _Grid:
        a = self.actuator
        solver = self.shapes
        Wg = np.linspace(0.0, self.load_max, n_W)
        # denser near the lift-off point, where the map bends
        hg = self.h_table_max * np.linspace(0.0, 1.0, n_h) ** 1.5
        HH, WW = np.meshgrid(hg, Wg, indexing="ij")
        hf, Wf = HH.ravel(), WW.ravel()
        span = 4.0 * a.r1
        hi = hf + span
        if np.any(solver.eval(hi, hi - hf)["F"] < Wf):
            raise ValueError("prediction: load_max is beyond what the membrane can carry; lower it")
        # contact: h1 >= h with F(h1, h1 - h) = W; unloaded, the free cap (h1 = h)
        h1, _ = solver.contact(hf, Wf, span, unknown="h1")
        h1 = np.where(Wf > 0, h1, hf)
        y = solver.eval(h1, h1 - hf)
        p, lam = y["p"], y["lam"]
        G = (p + a.p_env) * y["V"]
        x_path = (G / (a.p_env * a.V0) - 1.0).reshape(HH.shape)
        p_path = p.reshape(HH.shape)
        lam_path = lam.reshape(HH.shape)
        if np.any(np.diff(x_path, axis=0) <= 0):
            raise ValueError("prediction: the gas mass does not grow along a load path (a snap-through "
                             "inside the table); lower load_max or h_table_max")
        xg = np.linspace(-0.05, float(x_path[-1].max()), n_x)
        H = np.zeros((n_x, n_W))
        Pg = np.zeros((n_x, n_W))
        Lg = np.zeros((n_x, n_W))
        for j in range(n_W):
            xp, hp, pp, lp = x_path[:, j], hg, p_path[:, j], lam_path[:, j]
            rest = xg < xp[0]
            # below lift-off the platform rests (h = 0); the table continues the height linearly
            # into negative "virtual" heights with the lift-off slope, so that an optimiser resting
            # far below lift-off still sees that pumping raises the height (a flat h = 0 would give
            # it no gradient). Callers clamp at 0 where a physical height is meant.
            slope = (hp[1] - hp[0]) / (xp[1] - xp[0])
            H[:, j] = np.where(rest, slope * (xg - xp[0]), _interp_extrap(xg, xp, hp))
            Pg[:, j] = np.where(rest, xg * a.p_env, _interp_extrap(xg, xp, pp))
            Lg[:, j] = np.where(rest, 1.0, _interp_extrap(xg, xp, lp))
        return _Grid(xg, Wg, H, Pg, Lg, hg, x_path, p_path, lam_path)

    def _build_functions(self) -> None:
        g = self.grid
        #: the tables as casadi interpolants of vertcat(x, W): height m, gauge pressure Pa, stretch -
        self.H_table = ca.interpolant("H", "bspline", [g.x, g.W], g.h.ravel(order="F"), {})
        self.P_table = ca.interpolant("Pp", "bspline", [g.x, g.W], g.p.ravel(order="F"), {})
        self.L_table = ca.interpolant("L", "bspline", [g.x, g.W], g.lam.ravel(order="F"), {})
        self._forms: dict = {}
        self._poly = None
        fns = self.functions("bspline")
        self.H, self.Pp, self.L, self.HP, self.rhs = fns.H, fns.Pp, fns.L, fns.HP, fns.rhs

    def functions(self, form: str = "bspline") -> "TableFunctions":
        """The model's Functions (H, Pp, L, HP, rhs: see the class doc) with the tables evaluated as
        ``form``: 'bspline' (casadi's interpolant calls: compact, what a JIT at every construction
        wants) or 'poly' (the same splines as their per-cell polynomials, inline arithmetic,
        :class:`hbma_ctrl.models.piecewise.PiecewiseCubic`: equal to 1e-13, and the Jacobians are
        arithmetic instead of interpolant calls, about half the cost in generated C and faster on
        casadi's virtual machine; built on first use, 0.2 s)."""
        if form not in TABLE_FORMS:
            raise ValueError(f"prediction.functions: form = {form!r}; allowed {', '.join(TABLE_FORMS)}")
        if form not in self._forms:
            x, W, dp = ca.SX.sym("x"), ca.SX.sym("W"), ca.SX.sym("dp")
            u = ca.SX.sym("u", 3)
            xw = ca.vertcat(x, W)
            if form == "bspline":
                h, p, lam = self.H_table(xw), self.P_table(xw), self.L_table(xw)
            else:
                if self._poly is None:
                    g = self.grid
                    self._poly = PiecewiseCubic("prediction_tables", [g.x, g.W], [g.h, g.p, g.lam])
                h, p, lam = self._poly(xw)
            q = self.chamber.net_flow(u, p + dp, self.chamber.params)
            self._forms[form] = TableFunctions(
                H=ca.Function("H", [x, W], [h]), Pp=ca.Function("Pp", [x, W], [p]),
                L=ca.Function("L", [x, W], [lam]), HP=ca.Function("HP", [x, W], [ca.vertcat(h, p)]),
                rhs=ca.Function("rhs", [x, u, W, dp], [q * self.RT / (self.actuator.p_env * self.actuator.V0)],
                                ["x", "u", "W", "dp"], ["xdot"]))
        return self._forms[form]

    # --- numeric helpers ---------------------------------------------------------------------------
    def discrete(self, dt: float, integrator: str = "rk4", substeps: int = 1, form: str = "bspline") -> ca.Function:
        """(x, u, W, dp) -> x+ after ``dt`` s with inputs held (fixed-step euler/rk4, SX graph); the tables
        evaluated as ``form`` (:meth:`functions`)."""
        if integrator not in ("rk4", "euler"):
            raise ValueError(f"mpc.integrator = '{integrator}': allowed rk4, euler")
        rhs = self.functions(form).rhs
        x, W, dp = ca.SX.sym("x"), ca.SX.sym("W"), ca.SX.sym("dp")
        u = ca.SX.sym("u", 3)
        xn = fixed_step(lambda xs: rhs(xs, u, W, dp), x, dt, substeps, integrator)
        return ca.Function("F", [x, u, W, dp], [xn], ["x", "u", "W", "dp"], ["x_next"])

    def x_at_height(self, h: float, W: float) -> float:
        """The state that holds height h (m) under load W (N) on the contact branch."""
        (x,) = self._path_columns(W, "x_path")
        return float(np.interp(h, self.grid.h_path, x))

    def _path_columns(self, W: float, *names: str) -> tuple[np.ndarray, ...]:
        """The named tables (``x_path``, ``p_path``, ``lam_path``) along the load path at W (N): each
        (1 - s) column j - 1 + s column j of the grid's, W clipped to [0, load_max]."""
        g = self.grid
        W = min(max(float(W), 0.0), self.load_max)
        j = min(max(int(np.searchsorted(g.W, W)), 1), len(g.W) - 1)
        s = (W - g.W[j - 1]) / (g.W[j] - g.W[j - 1])
        return tuple((1 - s) * A[:, j - 1] + s * A[:, j] for A in (getattr(g, nm) for nm in names))

    def path_columns_expr(self, W, *names: str) -> tuple:
        """:meth:`_path_columns` for a casadi expression W (N): each named table along the load path
        as one linear-interpolant lookup at W clipped to [0, load_max], the generated steps' form."""
        g = self.grid
        Wc = ca.fmin(ca.fmax(W, 0.0), self.load_max)
        return tuple(ca.interpolant(f"path_{nm}", "linear", [np.asarray(g.W, dtype=float)],
                                    np.asarray(getattr(g, nm), dtype=float).ravel(order="F"))(Wc) for nm in names)

    def path(self, W: float) -> dict:
        """Load path at load W (N): arrays h (m), x, p (Pa), lam along the contact branch."""
        x, p, lam = self._path_columns(W, "x_path", "p_path", "lam_path")
        return {"h": self.grid.h_path, "x": x, "p": p, "lam": lam}



def _interp_extrap(xq: np.ndarray, xp: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """np.interp with linear extrapolation at the upper end."""
    out = np.interp(xq, xp, fp)
    hi = xq > xp[-1]
    if hi.any():
        slope = (fp[-1] - fp[-2]) / (xp[-1] - xp[-2])
        out[hi] = fp[-1] + slope * (xq[hi] - xp[-1])
    return out
