"""A bank of per-chamber EKFs for the robot, stepped as one mapped casadi call (SI).

One filter per chamber, each from its own pressure sensor. State ``[x, b, k, c]``: the gas mass
``x`` (scaled by the NOMINAL ``p_env V0 / RT``, minus 1) of :class:`hbma_ctrl.models.bank.
ChamberBank`, and three slow random walks: the pump-flow factor ``b``, the membrane-modulus factor
``k`` and the dead-volume factor ``c`` (see :meth:`ChamberBank.outputs_expr`). The load ``W`` of
each chamber is not a state: the robot's statics give it (:func:`hbma_ctrl.robot.load_sharing` of
the estimated heights), one control period late.

Why separate filters rather than one joint filter: given the loads, the chambers' gas masses are
dynamically independent (each has its own valves and sensor; with the shared pump the manifold
model keeps each chamber's inflow its own duty times the pump flow), so a joint filter's
covariance would be block diagonal up to the load coupling, which enters through W and is small
against the parameter mismatch. Nine 4-state filters (one mapped call) cost a fraction of one
36-state filter's dense algebra.

Why k and c. Without k a softer rig membrane, whose pressure peaks lower, drags the filter back
onto the near branch as soon as the pressure falls past the (earlier, lower) true limit point:
the falling pressure is explained by less gas instead of by a far-branch membrane (first runs: a
-15 % modulus chamber estimated at 2.5 mm while it stood at 15 mm). Without c the larger dead volume
biases the height by the cap volume's share (-0.2 to -0.7 mm near 6 mm in the first 3-layer run).
What is observable when: at rest only ``(x + 1) / c`` (the pressure) and ``b / c`` (its rise per
command) are; k is not (a flat membrane's pressure does not depend on it). After lift-off the shape
of p(gas mass) and the peak value separate k and c. Near the limit point the pressure hardly
depends on the gas mass (dp/dx -> 0): there the filter leans on the flow model (the gas mass
integrates the commanded flow with the learnt b), which is what keeps the far branch observable at
all. Targets held on the near branch, below the peak, leave k and c partly unlearnt (a residual
height error of a few tenths of a mm is then possible).

All chambers are stepped by ONE call of the casadi ``map`` of the single-chamber step (predict with
rk4 + Jacobians, covariance predict, scalar Joseph update), so 9 filters cost about one call.
A missing (NaN) or saturated (>= sensor range) reading skips that chamber's update.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from hbma_ctrl.core.params import check_range
from hbma_ctrl.models.bank import ChamberBank

__all__ = ["ChamberEKFSettings", "ChamberEKFBank"]


@dataclass(frozen=True)
class ChamberEKFSettings:
    """Per-chamber EKF tuning (SI).

    sample_period : s; noise_std : sensor noise one sigma, Pa; model_rel_std : relative pressure
    model error (modulus mismatch), -; x_abs_std, x_rel_std : process noise of the scaled mass per
    step (absolute and relative to the predicted change); b_rate_std : random walk of the flow
    factor, 1/sqrt(s); b0, b0_std : initial flow factor and its sigma; k0_std, k_rate_std : initial
    sigma and random walk (1/sqrt(s)) of the modulus factor (prior 1); c0_std, c_rate_std : the same
    for the dead-volume factor (prior 1); sensor_range : Pa (readings at or above it are not used).
    """

    sample_period: float = 0.01
    noise_std: float = 200.0
    model_rel_std: float = 0.01
    x_abs_std: float = 2e-4
    x_rel_std: float = 0.1
    b_rate_std: float = 0.05
    b0: float = 1.0
    b0_std: float = 0.25
    k0_std: float = 0.15
    k_rate_std: float = 0.002
    c0_std: float = 0.25
    c_rate_std: float = 0.002
    sensor_range: float = 50e3

    def validate(self) -> "ChamberEKFSettings":
        check_range("robot_ekf", "sample_period", self.sample_period, 1e-4, 1.0, "s")
        check_range("robot_ekf", "noise_std", self.noise_std, 1.0, 1e4, "Pa")
        check_range("robot_ekf", "model_rel_std", self.model_rel_std, 0.0, 1.0)
        check_range("robot_ekf", "x_abs_std", self.x_abs_std, 0.0, 1.0)
        check_range("robot_ekf", "x_rel_std", self.x_rel_std, 0.0, 10.0)
        check_range("robot_ekf", "b_rate_std", self.b_rate_std, 0.0, 10.0)
        check_range("robot_ekf", "b0", self.b0, 0.5, 2.0)
        check_range("robot_ekf", "b0_std", self.b0_std, 0.0, 2.0)
        check_range("robot_ekf", "k0_std", self.k0_std, 0.0, 1.0)
        check_range("robot_ekf", "k_rate_std", self.k_rate_std, 0.0, 10.0)
        check_range("robot_ekf", "c0_std", self.c0_std, 0.0, 1.0)
        check_range("robot_ekf", "c_rate_std", self.c_rate_std, 0.0, 10.0)
        check_range("robot_ekf", "sensor_range", self.sensor_range, 1e3, 1e6, "Pa")
        return self


B_RANGE = (0.5, 2.0)
K_RANGE = (0.6, 1.6)
C_RANGE = (0.6, 1.8)


NS = 4  # [x, b, k, c]


def _step_function(model: ChamberBank, s: ChamberEKFSettings) -> ca.Function:
    """Single-chamber EKF step (X[4], P[16], w[2], W, z, use) -> (X+[4], P+[16], h, p, nis, h_std)."""
    xs, w, W, b, k, c = model.symbols
    xn = model.discrete_expr(s.sample_period)
    th = ca.vertcat(b, k, c)
    fx = ca.Function("fx", [xs, w, W, b, k, c], [xn, ca.jacobian(xn, xs), ca.jacobian(xn, th)])
    he, pe, _ = model.outputs_expr(xs, W, k, c)
    zv = ca.vertcat(xs, k, c)
    pj = ca.Function("pj", [xs, W, k, c], [pe, ca.jacobian(pe, zv), he, ca.jacobian(he, zv)])
    X = ca.SX.sym("X", NS)
    Pv = ca.SX.sym("P", NS * NS)
    wi = ca.SX.sym("wi", 2)
    Wi, z, use = ca.SX.sym("Wi"), ca.SX.sym("z"), ca.SX.sym("use")
    x_pred, Ax, Ath = fx(X[0], wi, Wi, X[1], X[2], X[3])
    A = ca.vertcat(ca.horzcat(Ax, Ath), ca.horzcat(ca.DM.zeros(3, 1), ca.DM.eye(3)))
    P = ca.reshape(Pv, NS, NS)
    dx = x_pred - X[0]
    Q = ca.diag(ca.vertcat(s.x_abs_std ** 2 + (s.x_rel_std * dx) ** 2, s.b_rate_std ** 2 * s.sample_period,
                           s.k_rate_std ** 2 * s.sample_period, s.c_rate_std ** 2 * s.sample_period))
    Pm = A @ P @ A.T + Q
    xm = ca.vertcat(x_pred, X[1], X[2], X[3])
    p_pred, dp, _, _ = pj(xm[0], Wi, xm[2], xm[3])
    Hx = ca.horzcat(dp[0], 0, dp[1], dp[2])
    R = s.noise_std ** 2 + (s.model_rel_std * p_pred) ** 2
    S = Hx @ Pm @ Hx.T + R
    K = Pm @ Hx.T / S * use
    innov = z - p_pred
    xp = xm + K * innov
    IKH = ca.DM.eye(NS) - K @ Hx
    Pp = IKH @ Pm @ IKH.T + K @ K.T * R
    Pp = 0.5 * (Pp + Pp.T)
    p_post, _, h, dh = pj(xp[0], Wi, xp[2], xp[3])
    G = ca.horzcat(dh[0], 0, dh[1], dh[2])
    return ca.Function("ekf_bank_step", [X, Pv, wi, Wi, z, use],
                       [xp, ca.reshape(Pp, NS * NS, 1), h, p_post, innov ** 2 / S * use,
                        ca.sqrt(ca.fmax(G @ Pp @ G.T, 0))])


class ChamberEKFBank:
    """n per-chamber EKFs stepped together (see module doc).

    ``step(z, w, W)``: z (n,) pressure readings Pa (NaN = missing), w (2, n) the decisions applied
    during the last period (supply, outlet; see :mod:`hbma_ctrl.models.bank`), W (n,) the loads N
    used over that period. Returns a dict of (n,) arrays: x, b, h (m, >= 0), p (Pa), h_std (m),
    nis, used (bool), and the factors b, k, c (-).
    """

    def __init__(self, model: ChamberBank, n: int, settings: ChamberEKFSettings | None = None):
        if not isinstance(n, int) or n < 1:
            raise ValueError(f"robot_ekf.n = {n!r} must be an integer >= 1")
        self.settings = (settings or ChamberEKFSettings()).validate()
        self.model = model
        self.n = n
        step = model.cached(("ekf", self.settings), lambda: _step_function(model, self.settings))
        self._fun = model.mapped(step, n)
        self.X = None
        self.P = None
        self.last: dict = {}
        self.resets = 0

    def reset(self, p0, mask=None) -> None:
        """Start the filters (all, or those in ``mask``) at rest from readings p0 (n,) Pa (a flat
        membrane: x = p / p_env, factors at their priors)."""
        if mask is not None and self.X is not None:
            keep_X, keep_P = self.X.copy(), self.P.copy()
            self.reset(p0)
            m = np.asarray(mask, dtype=bool)
            self.X = np.where(m[None, :], self.X, keep_X)
            self.P = np.where(m[None, :], self.P, keep_P)
            return
        p0 = np.nan_to_num(np.asarray(p0, dtype=float).reshape(self.n), nan=0.0)
        s = self.settings
        x0 = np.clip(p0 / self.model.actuator.p_env, -0.04, None)
        self.X = np.vstack([x0, np.full(self.n, s.b0), np.ones(self.n), np.ones(self.n)])
        sx = max(s.noise_std / self.model.actuator.p_env, 1e-3)
        # x and c enter the rest pressure as (x + 1) / c: start them correlated so that the first
        # reading pins (x + 1) / c, not x alone
        P0 = np.diag([sx ** 2 + s.c0_std ** 2, s.b0_std ** 2, s.k0_std ** 2, s.c0_std ** 2])
        P0[0, 3] = P0[3, 0] = s.c0_std ** 2
        P0 = P0.reshape(16, 1)
        self.P = np.repeat(P0, self.n, 1)

    def step(self, z, w, W) -> dict:
        z = np.asarray(z, dtype=float).reshape(self.n)
        if self.X is None:
            self.reset(z)
        s = self.settings
        use = (np.isfinite(z) & (z < s.sensor_range)).astype(float)
        zz = np.where(use > 0, z, 0.0)
        Wv = self.model.clip_load(np.asarray(W, dtype=float).reshape(self.n))
        out = self._fun(self.X, self.P, np.asarray(w, dtype=float).reshape(2, self.n), Wv[None, :],
                        zz[None, :], use[None, :])
        X = np.asarray(out[0])
        Pn = np.asarray(out[1])
        bad = ~(np.all(np.isfinite(X), 0) & np.all(np.isfinite(Pn), 0))
        self.resets += int(bad.sum())
        X[0] = np.clip(X[0], -0.04, self.model.x_max)
        X[1] = np.clip(X[1], *B_RANGE)
        X[2] = np.clip(X[2], *K_RANGE)
        X[3] = np.clip(X[3], *C_RANGE)
        self.X = X
        self.P = Pn
        if bad.any():  # a diverged filter restarts from its reading (counted in ``resets``)
            self.reset(zz, bad)
        self.last = {"x": X[0].copy(), "b": X[1].copy(), "k": X[2].copy(), "c": X[3].copy(),
                     "h": np.maximum(np.asarray(out[2]).ravel(), 0.0), "p": np.asarray(out[3]).ravel(),
                     "h_std": np.asarray(out[5]).ravel(),
                     "k_std": np.sqrt(np.maximum(self.P[2 * NS + 2], 0.0)), "nis": np.asarray(out[4]).ravel(), "used": use > 0}
        return self.last
