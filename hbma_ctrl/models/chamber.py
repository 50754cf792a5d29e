"""The estimators' model: the reduced chamber with the load and three factors as states (casadi).

State ``x = [m, W, b, k, c]`` (SI: reduced gas mass kg, load N, pump-flow factor -, modulus factor
-, dead-volume factor -; the factors of :mod:`hbma_ctrl.models.reduced`); the chamber's volume at
rest is ``c V0`` and its gas mass ``c m`` (the state m is the gas mass referred to the nominal dead
volume: the flat membrane's pressure ``m R T / V0 - p_env`` does not depend on c, so c enters only
where the membrane moves or gas flows). The membrane shape ``s = (h1, h2)`` is algebraic (below, m
is the true gas mass c x[0]):

- contact (``pi r1^2 p_rest(m) > max(W, REST_EPS)``, ``p_rest = m R T / (c V0) - p_env``):
  ``G(h1, h2) = m R T`` and ``F(h1, h2) + EPS_K h2 = W`` (the quasi-static membrane model; EPS_K a
  tiny stiffness that fixes h2 = 0 where the pressure vanishes), solved by the casadi Newton
  :func:`hbma_ctrl.models.reduced.shape_newton` from a warm start (the previous shape). Free
  inflation is the contact branch with ``W = 0`` (then ``h2 = 0``).
- resting (otherwise, or forced by the filter's sticky rest mode, input ``hold``): the membrane is
  flat under the plate, ``V = c V0``, ``p = p_rest(m)``, ``h = 0``.

The dynamics are the quasi-static fidelity (:class:`hbma_ctrl.models.fidelity.QuasiStatic`) with
its platform weight replaced by the state ``W`` (random walks: ``W' = b' = k' = c' = 0``): the same
index-reduced ODE on ``[m, h1, h2]``, integrated by the simulator's fixed-step schemes ('euler' or
'rk4', ``nsub`` sub-steps per sample) and projected back onto the constraints after every
sub-step, as :meth:`hbma_ctrl.models.fidelity.Fidelity.step_function` does. The mode is fixed over
a sample. One casadi Function gives the discrete map, its Jacobian ``A = dx+/dx`` (algorithmic
differentiation through the integrator, each stage's shape by the implicit-function rule rather than
through the Newton iterations: :meth:`ObserverModel._ift_jacobian`), ``H = dp/dx`` and the covariance
prediction ``sym(A P A^T + Q)``; another the Joseph-form update; a third the outputs (h1, h2, h, F,
p) with their Jacobian by the implicit-function rule (``dh/dx = -r_h^-1 r_x`` for the constraint
residual r) and covariance ``D P D^T``. All are compiled to C (:mod:`hbma_ctrl.core.codegen`).

The membrane law (``membrane``): the spherical cap (docs/concepts/model.md §1, §3) or the exact axisymmetric
membrane (docs/concepts/model.md §9) as the same tabulated ratios to the cap in the (h1, h2) chart as an exact
rig (:class:`hbma_ctrl.models.fidelity_exact.ExactQuasiStatic`): pressure, volume, contact force and the
flat point all come from the chamber's ``law``, so the Newton projection, the dynamics and the
Jacobians (by AD through the bspline interpolants) are those of the exact membrane, in one model.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import casadi as ca
import numpy as np

from hbma_ctrl.core.params import Actuator, Pneumatics
from hbma_ctrl.models.fidelity import fixed_step, shape_jacobian
from hbma_ctrl.models.reduced import (
    ReducedChamber,
    constraint_jacobian,
    constraint_residual,
    shape_newton,
    solve_2x2,
)

__all__ = ["ObserverModel", "STATE_NAMES", "OUT_NAMES", "min_pivot"]

#: the load W may go below zero: the physics sees max(W, 0) (a dead zone), so near no load the
#: estimate is not pushed up by clipping (a clipped random walk drifts to a phantom load that
#: bends a free cap into a contact shape)
STATE_NAMES = ("m", "W", "b", "k", "c")
NX = len(STATE_NAMES)
#: force, N, below which the membrane is taken as flat even without a load (about 200 Pa at r1 = 12.5 mm)
REST_EPS = 0.1
#: rows of the output vector of :attr:`ObserverModel.outputs`
OUT_NAMES = ("h1", "h2", "h", "F", "p", "rest", "det", "resid")

#: state scales used by the covariance floor: gas mass (kg), load (N), flow, modulus and
#: dead-volume factors (-)
STATE_SCALE = np.array([1e-6, 1.0, 1.0, 1.0, 1.0])


def min_pivot(P, floor):
    """Smallest LDL^T pivot of P / (s s^T) - floor I (s = STATE_SCALE): > 0 iff every eigenvalue
    of the scaled P exceeds the floor. Closed form for the small state, no branches."""
    n = P.shape[0]
    M = P / ca.DM(np.outer(STATE_SCALE, STATE_SCALE)) - floor * ca.SX.eye(n)
    L = [[None] * n for _ in range(n)]
    d = []
    for j in range(n):
        dj = M[j, j] - sum(L[j][k] ** 2 * d[k] for k in range(j))
        d.append(dj)
        for i in range(j + 1, n):
            L[i][j] = (M[i, j] - sum(L[i][k] * L[j][k] * d[k] for k in range(j))) / dj
    out = d[0]
    for v in d[1:]:
        out = ca.fmin(out, v)
    return out


@dataclass
class _Syms:
    x: ca.SX
    s: ca.SX
    u: ca.SX
    theta: ca.SX
    P: dict
    Pbase: dict


class ObserverModel:
    """Casadi Functions of the estimators' model for one actuator and pneumatics (nominal values).

    Parameters
    ----------
    actuator, pneumatics : the nominal (believed) parameters, SI.
    dt : sample period, s; integrator : 'euler' | 'rk4'; nsub : sub-steps per sample;
    newton : Newton iterations of the shape projection per sub-step;
    membrane : 'cap' | 'exact', the membrane law (module docstring; ignored when ``chamber`` is given).
    jacobian : how the predict's A = dx+/dx treats the shape: 'ift' (default) as the constraint's
        implicit function at each integrator stage (:meth:`_ift_jacobian`), 'ad' by differentiating
        through the Newton iterates and the shape rates (the same where the projection has converged;
        about 30 % more instructions in the predict, the exact law's second derivatives).
    """

    def __init__(self, actuator: Actuator, pneumatics: Pneumatics, dt: float, integrator: str = "rk4",
                 nsub: int = 2, newton: int = 2, chamber: ReducedChamber | None = None, membrane: str = "cap",
                 jacobian: str = "ift"):
        if integrator not in ("euler", "rk4"):
            raise ValueError(f"estimator.integrator = '{integrator}': allowed euler, rk4")
        if jacobian not in ("ift", "ad"):
            raise ValueError(f"jacobian = '{jacobian}': allowed ift, ad")
        self.jacobian = jacobian
        self.chamber = chamber or ReducedChamber(actuator, pneumatics, membrane)
        self.membrane = self.chamber.membrane
        self.dt, self.integrator, self.nsub, self.newton = float(dt), integrator, int(nsub), int(newton)
        self._bind()
        self._build()

    def _bind(self) -> None:
        """Numeric parameters of the bound chamber (the casadi Functions take theta as an input)."""
        ch = self.chamber
        self.theta = ch.theta
        self.actuator = ch.actuator
        self.area = ch.area
        self.rt = ch.rt
        self.m_env = ch.x_scale  # gas mass at rest, unpressurised, kg

    def rebind(self, actuator: Actuator, pneumatics: Pneumatics) -> "ObserverModel":
        """This model for another actuator of the same material family and compressor map: the
        casadi Functions are shared, the numeric parameters are the new ones (self if unchanged)."""
        chamber = self.chamber.rebind(actuator, pneumatics)
        if chamber is self.chamber:
            return self
        om = copy.copy(self)
        om.chamber = chamber
        om._bind()
        return om

    # --- symbolic pieces ----------------------------------------------------------------------
    def _with_state(self, P: dict, x) -> dict:
        """Parameters as the state sees them: load W, pump-flow factor b, modulus factor k, dead
        volume c V0; ``P["m"]`` is the true gas mass c x[0]."""
        P = self.chamber.with_factors(P, b=x[2], k=x[3], c=x[4])
        P["W"] = ca.fmax(x[1], 0)  # dead zone: see STATE_NAMES
        P["m"] = x[0] * x[4]
        return P

    def _syms(self) -> _Syms:
        x = ca.SX.sym("x", NX)
        s = ca.SX.sym("s", 2)
        u = ca.SX.sym("u", 3)
        theta, P = self.chamber.symbols()
        return _Syms(x, s, u, theta, self._with_state(P, x), P)

    @staticmethod
    def _p_rest(m, P: dict):
        """The flat membrane's gauge pressure (Pa) for gas mass m (kg): the gas law in the dead volume."""
        return m * (P["R"] * P["T"]) / P["V0"] - P["p_env"]

    def _project(self, m, W, h1, h2, P, iters, hold):
        """(h1, h2, rest) for state (m, W) from the guess (h1, h2); hold > 0.5 forces rest (hold
        ``True``: the flat membrane itself, rest a constant 1, no projection in the graph)."""
        p_rest = self._p_rest(m, P)
        hf = self.chamber.fidelity.flat_h1(p_rest, P)
        if hold is True:
            return hf, hf, ca.SX(1.0)
        # below REST_EPS the membrane counts as flat even without a load (the origin is singular)
        rest = ca.logic_or(ca.pi * P["r1"] ** 2 * p_rest <= ca.fmax(W, REST_EPS), hold > 0.5)
        # leaving rest (guess flat) starts from the flat membrane; Newton on the contact branch
        c1, c2 = shape_newton(m, W, h1, h2, P, iters, self.chamber.law)
        return ca.if_else(rest, hf, c1), ca.if_else(rest, hf, c2), rest

    def _ift_jacobian(self, y: _Syms, P: dict, mode, stages: list):
        """dx+/dx of the predict with each stage's shape differentiated as the constraint's implicit
        function of the stage's gas mass and the state (``dh/d(m, x) = -r_h^-1 r_(m, x)``), not through
        the Newton iterates and the index-reduced shape rates (SX).

        Only the gas mass moves: m+ = m + dt sum(w_i q(p(h_i), u; P)). The stages' shapes h_i sit on the
        constraint r(h; m, P) = [G - m R T, F + EPS_K h2 - W] = 0 up to the integrator's error, so their
        derivative is the implicit function's; the rates through the Newton iterates and the stages'
        h' = J^-1 [q R T, 0] needed the law's second derivatives (for the exact membrane, the tables
        inside the Jacobian of a Jacobian: most of the predict). The same sum is built over fresh
        symbols for each stage's shape, its ``J = r_h`` and its residual ``r0``: the stage's shape is
        ``h_i + J^-1 (r0 - r(h_i; m_i, P))``, whose value is h_i; differentiated, then the symbols
        substituted by the predict's own values. Resting, the pressure is the flat chamber's, as in
        the dynamics."""
        law = self.chamber.law

        def residual(G, F, h2, mv):
            return ca.vertcat(*constraint_residual(G, F, h2, mv, P["W"], P))

        n = len(stages)
        Hs, Js, R0 = ca.SX.sym("Hs", 2, n), ca.SX.sym("Js", 4, n), ca.SX.sym("R0", 2, n)
        dt = self.dt / self.nsub
        w, a = ([1.0], [0.0]) if self.integrator == "euler" else ([1 / 6, 1 / 3, 1 / 3, 1 / 6], [0.0, 0.5, 0.5, 1.0])
        m = P["m"]
        i, vals = 0, []
        for _ in range(self.nsub):
            acc, k = 0, 0
            for ws, as_ in zip(w, a):
                mi = m + as_ * dt * k
                Gs, Fs, _ = shape_jacobian(Hs[0, i], Hs[1, i], P, law)  # (its Jacobian unused: not in the graph)
                rr = R0[:, i] - residual(Gs, Fs, Hs[1, i], mi)
                hi = Hs[:, i] + ca.vertcat(*solve_2x2(ca.reshape(Js[:, i], 2, 2), rr[0], rr[1]))
                k = self.chamber.rhs(ca.vertcat(mi, hi), y.u, P, mode)[0]
                acc = acc + ws * k
                xs = stages[i]
                G, F, Jv = constraint_jacobian(xs[1], xs[2], P, law)
                vals.append((xs[1:], ca.vec(Jv), residual(G, F, xs[2], xs[0])))
                i += 1
            m = m + dt * acc
        mn = ca.vertcat(m / y.x[4], y.x[1:])
        A = ca.jacobian(mn, y.x)
        syms = [Hs[:, j] for j in range(n)] + [Js[:, j] for j in range(n)] + [R0[:, j] for j in range(n)]
        subs = [v[0] for v in vals] + [v[1] for v in vals] + [v[2] for v in vals]
        return ca.substitute([A], syms, subs)[0]

    def _meas(self, x, h1, h2, rest, Pbase):
        """Outputs and their Jacobian wrt x at a projected shape (implicit-function rule).

        On the contact branch r(h, x) = [G(h; x) - m R T, F(h; x) - W] = 0 gives
        dh/dx = -r_h^-1 r_x and d(out)/dx = out_x + out_h dh/dx.
        """
        xs = ca.SX.sym("xs", NX)
        hs = ca.SX.sym("hs", 2)
        P = self._with_state(Pbase, xs)
        rt = P["R"] * P["T"]
        area = ca.pi * P["r1"] ** 2
        p_c, V_c, _, a2 = self.chamber.law(hs[0], hs[1], P)
        G = (p_c + P["p_env"]) * V_c
        F = ca.pi * a2 * p_c
        r = ca.vertcat(*constraint_residual(G, F, hs[1], P["m"], P["W"], P))
        o_c = ca.vertcat(hs[0], hs[1], hs[0] - hs[1], F, p_c)
        r_h = ca.jacobian(r, hs)
        det = r_h[0, 0] * r_h[1, 1] - r_h[0, 1] * r_h[1, 0]
        dh = -ca.solve(r_h, ca.jacobian(r, xs))
        D_c = ca.jacobian(o_c, xs) + ca.mtimes(ca.jacobian(o_c, hs), dh)
        p_rest = self._p_rest(P["m"], P)
        hf = self.chamber.fidelity.flat_h1(p_rest, P)
        # flat under a plate: h = 0; with no plate to rest on (W -> 0, below REST_EPS) the membrane
        # is a free cap of height hf -- blended linearly in W so the Jacobian stays finite
        free = 1 - ca.fmin(P["W"] / REST_EPS, 1)
        # (if_else, not a product: hf' is unbounded at zero pressure, and inf * 0 is NaN)
        h_free = ca.if_else(free > 0, hf * free, 0)
        o_r = ca.vertcat(hf, hf - h_free, h_free, area * p_rest, p_rest)
        D_r = ca.jacobian(o_r, xs)
        resid = ca.fabs(G - P["m"] * rt) / (P["m"] * rt) + ca.fabs(F - P["W"]) / (ca.fabs(xs[1]) + 0.1)
        rs = ca.SX.sym("rest")
        o = ca.if_else(rs > 0.5, o_r, o_c)
        D = ca.if_else(rs > 0.5, D_r, D_c)
        extra = ca.vertcat(rs, det, ca.if_else(rs > 0.5, 0, resid))
        out = ca.vertcat(o, extra)
        return ca.substitute([out, D[4, :], D], [xs, hs, rs], [x, ca.vertcat(h1, h2), rest])

    def _predict(self, held: bool) -> tuple[ca.Function, ca.Function]:
        """The predict Function (signature below) and the UKF's propagate (the same step without
        Jacobians); ``held``: built for hold = 1 (a resting step), the flat membrane's graph alone (the
        input ``hold`` then unused): the full Functions' values at hold = 1, A to rounding (casadi
        differentiates the smaller graph in another order)."""
        y = self._syms()
        hold = ca.SX.sym("hold")
        mode_in = True if held else hold
        P = y.P
        m, W, c = P["m"], P["W"], y.x[4]
        h1, h2, rest = self._project(m, W, y.s[0], y.s[1], P, self.newton + 1, mode_in)
        mode = ca.if_else(rest, 0.0, 1.0)
        x3 = ca.vertcat(m, h1, h2)
        h = self.dt / self.nsub
        rhs = self.chamber.rhs
        stages = []  # the shapes the stages' flows were evaluated at, for the Jacobian below

        def f(x3s):
            stages.append(x3s)
            return rhs(x3s, y.u, P, mode)

        for _ in range(self.nsub):
            x3 = fixed_step(f, x3, h, 1, self.integrator)
            a, b, _ = self._project(x3[0], W, x3[1], x3[2], P, self.newton, mode_in)
            x3 = ca.vertcat(x3[0], a, b)
        xn = ca.vertcat(x3[0] / c, y.x[1], y.x[2], y.x[3], y.x[4])
        A = self._ift_jacobian(y, P, mode, stages) if self.jacobian == "ift" else ca.jacobian(xn, y.x)
        # the predicted shape as the next warm start; re-projected at the predicted state
        h1n, h2n, restn = self._project(x3[0], W, x3[1], x3[2], P, self.newton, mode_in)
        outn, Hn, _ = self._meas(xn, h1n, h2n, restn, y.Pbase)
        # covariance: P+ = sym(A P A^T + Q), Q = diag((rel |dm|)^2 + qm, qW, qb, qk, qc); qv = [rel,
        # qm, qW, qb, qk, qc, floor]; piv = smallest LDL pivot of P+/scale^2 - floor I (> 0: floor holds)
        Pc = ca.SX.sym("P", NX, NX)
        qv = ca.SX.sym("qv", NX + 2)
        Q = ca.diag(ca.vertcat((qv[0] * (xn[0] - y.x[0])) ** 2 + qv[1], qv[2:NX + 1]))
        Pn = ca.mtimes([A, Pc, A.T]) + Q
        Pn = 0.5 * (Pn + Pn.T)
        tag = "_rest" if held else ""
        predict = ca.Function(
            "ekf_predict" + tag, [y.x, y.s, y.u, y.theta, hold, Pc, qv],
            [ca.densify(e) for e in (xn, A, ca.vertcat(h1n, h2n), outn, Hn, Pn, min_pivot(Pn, qv[NX + 1]))],
            ["x", "s", "u", "theta", "hold", "P", "qv"],
            ["x_next", "A", "s_next", "y", "H", "P_next", "piv"])
        # a step without Jacobians for sigma points (UKF): (x, s, u) -> (x+, s+, y+)
        propagate = ca.Function("ukf_propagate" + tag, [y.x, y.s, y.u, y.theta, hold],
                                [ca.densify(e) for e in (xn, ca.vertcat(h1n, h2n), outn)],
                                ["x", "s", "u", "theta", "hold"], ["x_next", "s_next", "y"])
        return predict, propagate

    def _outputs(self, held: bool) -> ca.Function:
        """The outputs at an arbitrary state (posterior) from a warm start; ``held`` as in :meth:`_predict`."""
        y2 = self._syms()
        hold2 = ca.SX.sym("hold")
        a, b, r = self._project(y2.P["m"], y2.P["W"], y2.s[0], y2.s[1], y2.P, self.newton + 1,
                                True if held else hold2)
        out2, H2, D2 = self._meas(y2.x, a, b, r, y2.Pbase)
        P2 = ca.SX.sym("P", NX, NX)
        C2 = ca.mtimes([D2, P2, D2.T])
        return ca.Function("ekf_outputs_rest" if held else "ekf_outputs", [y2.x, y2.s, y2.theta, hold2, P2],
                           [ca.densify(e) for e in (ca.vertcat(a, b), out2, H2, D2, 0.5 * (C2 + C2.T))],
                           ["x", "s", "theta", "hold", "P"], ["s_out", "y", "H", "D", "C"])

    def _build(self) -> None:
        self.predict, self.propagate = self._predict(False)
        #: the predict and the outputs of a resting step (hold = 1): the same values, without the
        #: contact branch's shape projection (most of the full Functions' work)
        self.predict_rest = self._predict(True)[0]
        self.outputs = self._outputs(False)
        self.outputs_rest = self._outputs(True)
        # Joseph-form scalar update: K = keep * P H^T / S, P+ = (I - K H) P (I - K H)^T + R K K^T;
        # keep (0/1 per state) holds states out of an update (Schmidt's consider states: the
        # Joseph form is the exact covariance for any gain)
        xu = ca.SX.sym("x", NX)
        keep = ca.SX.sym("keep", NX)
        Pu = ca.SX.sym("P", NX, NX)
        Hu = ca.SX.sym("H", 1, NX)
        nu = ca.SX.sym("innov")
        Ru = ca.SX.sym("R")
        fl = ca.SX.sym("floor")
        PHt = ca.mtimes(Pu, Hu.T)
        Su = ca.mtimes(Hu, PHt) + Ru
        K = keep * PHt / Su  # a scalar S: the "solve" is this division (S > 0 checked by the caller)
        IKH = ca.SX.eye(NX) - ca.mtimes(K, Hu)
        Pp = ca.mtimes([IKH, Pu, IKH.T]) + Ru * ca.mtimes(K, K.T)
        Pp = 0.5 * (Pp + Pp.T)
        self.update = ca.Function("kf_update", [xu, Pu, Hu, nu, Ru, fl, keep],
                                  [ca.densify(e) for e in (xu + K * nu, Pp, Su, min_pivot(Pp, fl))],
                                  ["x", "P", "H", "innov", "R", "floor", "keep"],
                                  ["x_post", "P_post", "S", "piv"])
        # the flat membrane's pressure at a state, as the outputs' resting branch computes it (the same
        # expression: the same bits), without the shape projection the outputs evaluate
        y3 = self._syms()
        self.flat_pressure = ca.Function("ekf_flat_pressure", [y3.x, y3.theta], [self._p_rest(y3.P["m"], y3.P)],
                                         ["x", "theta"], ["p_rest"])

    # --- numeric helpers ----------------------------------------------------------------------
    def gas_mass(self, p: float, h1: float = 0.0, h2: float = 0.0) -> float:
        """Gas mass (kg) at gauge pressure p (Pa) in the nominal chamber with shape (h1, h2) (m)."""
        return self.chamber.gas_mass(p, h1, h2)
