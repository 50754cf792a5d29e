"""The estimators' model: the quasi-static HBMA with the load as a state, as casadi Functions.

State ``x = [m, W]`` (SI: gas mass kg, load N), with the membrane shape ``s = (h1, h2)`` algebraic:

- contact (``pi r1^2 p_rest(m) > W``, ``p_rest = m R T / V0 - p_env``): ``G(h1, h2) = m R T`` and
  ``F(h1, h2) = W`` (SPEC 1-4), solved by Newton from a warm start (the previous shape). Free
  inflation is the contact branch with ``W = 0`` (then ``h2 = 0``); the formulas of SPEC 1-3 extend
  smoothly to small negative ``W`` (``h2 < 0``), so a load estimate near zero never hits a kink;
  reported ``h2`` and ``F`` are clipped at 0.
- resting (otherwise): the membrane is flat under the plate, ``V = V0``, ``p = p_rest(m)``, ``h = 0``.

The dynamics are the lead's quasi-static fidelity (:class:`hbma_ctrl.model.QuasiStatic`) with its
platform weight ``P["W"]`` replaced by the state ``W`` (a random walk, ``W' = 0``): the same
index-reduced ODE on ``[m, h1, h2]``, integrated by the simulator's fixed-step schemes ('euler' or
'rk4', ``nsub`` sub-steps per sample) and projected back onto the constraints after every sub-step,
exactly as :meth:`hbma_ctrl.model.Fidelity.step_function` does. The mode is fixed over a sample
(taken from the state at its start). The discrete map and its Jacobian ``A = dx+/dx`` come from one
casadi Function (algorithmic differentiation through the integrator and the Newton iterations), so
a predict step is a single call. The measurement Jacobian ``H = dp/dx`` is the implicit-function
derivative at the projected shape (exact where Newton has converged):
``d(h1, h2)/d(m, W) = J^-1 diag(R T, 1)`` with ``J = d(G, F)/d(h1, h2)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from hbma_ctrl import physics as ph
from hbma_ctrl.model import QuasiStatic, make_fidelity, shape_jacobian
from hbma_ctrl.params import Actuator, Platform, Pneumatics

__all__ = ["ObserverModel", "STATE_NAMES", "OUT_NAMES"]

STATE_NAMES = ("m", "W")
#: force, N, below which the membrane is taken as flat even without a load (about 200 Pa at r1 = 12.5 mm)
REST_EPS = 0.1
#: rows of the output vector of :meth:`ObserverModel.outputs`
OUT_NAMES = ("h1", "h2", "h", "F", "p", "rest", "det", "resid")


def _shape_newton(m, W, h1, h2, P, iters: int):
    """Newton on G(h1, h2) = m R T, F(h1, h2) = W from (h1, h2); Cramer's rule on the 2x2."""
    rt = P["R"] * P["T"]
    for _ in range(iters):
        G, F, J = shape_jacobian(h1, h2, P)
        r0, r1 = G - m * rt, F - W
        det = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
        sgn = ca.if_else(det >= 0, 1.0, -1.0)
        det = ca.if_else(ca.fabs(det) < 1e-12, sgn * 1e-12, det)
        d1 = (J[1, 1] * r0 - J[0, 1] * r1) / det
        d2 = (-J[1, 0] * r0 + J[0, 0] * r1) / det
        # keep the step inside the chart: at most half the cap height per iteration
        lim = 0.5 * ca.fmax(h1, 1e-4)
        sc = ca.fmin(1, lim / ca.fmax(ca.fmax(ca.fabs(d1), ca.fabs(d2)), 1e-30))
        h1, h2 = h1 - sc * d1, h2 - sc * d2
        h1 = ca.fmax(h1, 1e-7)
    return h1, h2


@dataclass
class _Syms:
    x: ca.SX
    s: ca.SX
    u: ca.SX
    theta: ca.SX
    P: dict


class ObserverModel:
    """Casadi Functions of the estimators' model for one actuator and pneumatics (nominal values).

    Parameters
    ----------
    actuator, pneumatics : the nominal (believed) parameters, SI.
    dt : sample period, s; integrator : 'euler' | 'rk4'; nsub : sub-steps per sample;
    newton : Newton iterations of the shape projection per sub-step.
    """

    def __init__(self, actuator: Actuator, pneumatics: Pneumatics, dt: float, integrator: str = "rk4",
                 nsub: int = 2, newton: int = 2):
        if integrator not in ("euler", "rk4"):
            raise ValueError(f"estimator.integrator = '{integrator}': allowed euler, rk4")
        self.fid: QuasiStatic = make_fidelity("quasi_static", actuator.material, str(pneumatics.csv_path))
        self.theta = self.fid.space.values(actuator, pneumatics, Platform())
        self.actuator = actuator
        self.dt, self.integrator, self.nsub, self.newton = float(dt), integrator, int(nsub), int(newton)
        self.area = float(np.pi * actuator.r1 ** 2)
        self.rt = actuator.R * actuator.T
        self.m_env = actuator.p_env * actuator.V0 / self.rt  # gas mass at rest, unpressurised
        self._build()

    # --- symbolic pieces ----------------------------------------------------------------------
    def _syms(self) -> _Syms:
        x = ca.SX.sym("x", 2)
        s = ca.SX.sym("s", 2)
        u = ca.SX.sym("u", 3)
        theta, P = self.fid.space.symbols()
        P = dict(P)
        P["W"] = x[1]
        return _Syms(x, s, u, theta, P)

    def _project(self, m, W, h1, h2, P, iters):
        """(h1, h2, rest) for state (m, W) from the guess (h1, h2)."""
        rt = P["R"] * P["T"]
        p_rest = m * rt / P["V0"] - P["p_env"]
        # below REST_EPS the membrane counts as flat even without a load (the origin is singular)
        rest = ca.pi * P["r1"] ** 2 * p_rest <= ca.fmax(W, REST_EPS)
        hf = ph.flat_h1_from_pressure(p_rest, P)
        # leaving rest (guess flat) starts from the flat membrane; Newton on the contact branch
        c1, c2 = _shape_newton(m, W, h1, h2, P, iters)
        return ca.if_else(rest, hf, c1), ca.if_else(rest, hf, c2), rest

    def _meas(self, m, W, h1, h2, rest, P):
        """Outputs and their Jacobian wrt (m, W) at a projected shape (implicit-function rule)."""
        rt = P["R"] * P["T"]
        p_c = ph.pressure(h1, h2, P)
        p_rest = m * rt / P["V0"] - P["p_env"]
        p = ca.if_else(rest, p_rest, p_c)
        _, F, J = shape_jacobian(h1, h2, P)
        det = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
        G = ph.gas_pv(h1, h2, P)
        resid = ca.if_else(rest, 0, ca.fabs(G - m * rt) / (m * rt) + ca.fabs(F - W) / (ca.fabs(W) + 0.1))
        # d(h1, h2)/d(m, W) = J^-1 diag(RT, 1) on the contact branch
        Jinv = ca.vertcat(ca.horzcat(J[1, 1], -J[0, 1]), ca.horzcat(-J[1, 0], J[0, 0])) / det
        S = ca.mtimes(Jinv, ca.diag(ca.vertcat(rt, 1)))
        s1, s2 = ca.SX.sym("s1"), ca.SX.sym("s2")
        gp = ca.substitute(ca.gradient(ph.pressure(s1, s2, P), ca.vertcat(s1, s2)),
                           ca.vertcat(s1, s2), ca.vertcat(h1, h2))
        Hc = ca.mtimes(gp.T, S)  # dp/d(m, W)
        # flat membrane: h1 = h2 = flat(p_rest(m)); dp/dm = RT/V0
        ms = ca.SX.sym("ms")
        hf_m = ca.substitute(ca.jacobian(ph.flat_h1_from_pressure(ms * rt / P["V0"] - P["p_env"], P), ms),
                             ms, m)
        z = ca.SX(1, 1)
        H_p = ca.if_else(rest, ca.horzcat(rt / P["V0"], 0), Hc)
        # rows: h1, h2, h, F, p -> Jacobian (5 x 2)
        D_c = ca.vertcat(S[0, :], S[1, :], S[0, :] - S[1, :], ca.horzcat(0, 1), Hc)
        area = ca.pi * P["r1"] ** 2
        D_r = ca.vertcat(ca.horzcat(hf_m, 0), ca.horzcat(hf_m, 0), ca.horzcat(z, 0),
                         ca.horzcat(area * rt / P["V0"], 0), ca.horzcat(rt / P["V0"], 0))
        D = ca.if_else(rest, D_r, D_c)
        out = ca.vertcat(h1, h2, ca.if_else(rest, 0, h1 - h2), ca.if_else(rest, area * p_rest, F), p,
                         rest, det, resid)
        return out, H_p, D

    def _build(self) -> None:
        y = self._syms()
        m, W = y.x[0], y.x[1]
        P = y.P
        h1, h2, rest = self._project(m, W, y.s[0], y.s[1], P, self.newton + 1)
        mode = ca.if_else(rest, 0.0, 1.0)
        x3 = ca.vertcat(m, h1, h2)
        h = self.dt / self.nsub
        fid = self.fid
        for _ in range(self.nsub):
            if self.integrator == "euler":
                x3 = x3 + h * fid._rhs(x3, y.u, P, mode)
            else:
                k1 = fid._rhs(x3, y.u, P, mode)
                k2 = fid._rhs(x3 + h / 2 * k1, y.u, P, mode)
                k3 = fid._rhs(x3 + h / 2 * k2, y.u, P, mode)
                k4 = fid._rhs(x3 + h * k3, y.u, P, mode)
                x3 = x3 + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            a, b, _ = self._project(x3[0], W, x3[1], x3[2], P, self.newton)
            x3 = ca.vertcat(x3[0], a, b)
        xn = ca.vertcat(x3[0], W)
        A = ca.jacobian(xn, y.x)
        # the predicted shape as the next warm start; re-projected at the predicted state
        h1n, h2n, restn = self._project(xn[0], W, x3[1], x3[2], P, self.newton)
        outn, Hn, _ = self._meas(xn[0], W, h1n, h2n, restn, P)
        self.predict = ca.Function(
            "ekf_predict", [y.x, y.s, y.u, y.theta],
            [xn, A, ca.vertcat(h1n, h2n), outn, Hn], ["x", "s", "u", "theta"],
            ["x_next", "A", "s_next", "y", "H"])
        # outputs at an arbitrary state (posterior), from a warm start
        y2 = self._syms()
        a, b, r = self._project(y2.x[0], y2.x[1], y2.s[0], y2.s[1], y2.P, self.newton + 1)
        out2, H2, D2 = self._meas(y2.x[0], y2.x[1], a, b, r, y2.P)
        self.outputs = ca.Function("ekf_outputs", [y2.x, y2.s, y2.theta], [ca.vertcat(a, b), out2, H2, D2],
                                   ["x", "s", "theta"], ["s_out", "y", "H", "D"])
        # a step without Jacobians for sigma points (UKF): (x, s, u) -> (x+, s+, p+)
        self.propagate = ca.Function("ukf_propagate", [y.x, y.s, y.u, y.theta],
                                     [xn, ca.vertcat(h1n, h2n), outn[4]], ["x", "s", "u", "theta"],
                                     ["x_next", "s_next", "p"])

    # --- numeric helpers ----------------------------------------------------------------------
    def gas_mass(self, p: float, h1: float = 0.0, h2: float = 0.0) -> float:
        """Gas mass (kg) at gauge pressure p (Pa) in the nominal chamber with shape (h1, h2)."""
        P = {n: float(v) for n, v in zip(self.fid.space.names, self.theta)}
        P["material"] = self.actuator.material
        V = float(ph.geometry(h1, h2, P)["V"])
        return (p + self.actuator.p_env) * V / self.rt
