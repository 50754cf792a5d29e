"""Moving-horizon estimation of one chamber: the EKF's model and step API over a window of samples.

The window at the step of sample k holds the nodes ``j = 0 .. N`` (N = ``horizon``), node j at
sample ``k - N + j``. The decision variables are the gas mass of every node and the window's
parameters ``theta = (W, b, k, c)`` (the load and the pump-flow, modulus and dead-volume factors of
:mod:`hbma_ctrl.models.chamber`), constant over the window: the membrane's stiffness factor k and the
load W are estimated from the window's data, no separate fit. Node j's state is ``x_j = (m_j, theta)``,
the EKF's state layout (:data:`hbma_ctrl.models.chamber.STATE_NAMES`).

Measurement-to-state indexing: the reading taken at sample ``k - N + j`` constrains node j, for
``j = 1 .. N`` (the newest reading, given to this step, constrains the newest node N, whose estimate
the step returns). Node 0's reading is already in the arrival cost. The command applied over the
period ending at node ``j + 1`` (the one handed to that step, acting through the modelled valve and
sensor delays as in the EKF) drives the shooting interval from node j to node j + 1.

The cost (multiple shooting, every term a squared residual):

- arrival: ``(x_0 - xbar)^T P0^-1 (x_0 - xbar)``, with (xbar, P0) updated by one EKF step at every
  step: from the arrival itself, linearised along the window (node 0's interval, ``P- = A P0 A^T + Q``,
  and a Joseph-form update with node 1's reading, its Jacobian and variance), so the arrival
  covariance follows the data (not a fixed weight) and the arrival mean is the lagged EKF's, which
  has not seen the window's readings (the window's node 0 has: as the next prior they would count
  twice);
- the shooting defects ``(f(x_j, u_j) - m_(j+1)) / sigma_j``, f the EKF's discrete model (the same
  casadi Function, :meth:`hbma_ctrl.models.chamber.ObserverModel._predict`), sigma_j the EKF's
  process noise of the gas mass (``flow_rel_std`` of the period's flow, ``mass_std_abs``);
- the readings ``(p(x_j) - z_j)^2 / R_j`` (R the EKF's: ``noise_std`` and, in contact,
  ``model_rel_std`` of the pressure). A saturated reading is censored: it says only ``p >= range``,
  the residual ``(p - range) / sigma`` (``saturation_std``) counts only while the model's pressure is
  below the range (a one-sided, hinge residual, as the EKF's one-sided update); a missing reading or
  an outlier has no residual.

Hard constraints: the shape follows from (m, W) by the model's projection, which keeps
``0 <= h2 <= h1`` and ``h = h1 - h2 >= 0`` for every state (resting: h1 = h2, the flat membrane);
the contact force is the load in contact, so ``F >= 0`` is the bound ``W >= 0`` on the decision
variable (the EKF lets its load state go below zero, :data:`hbma_ctrl.models.chamber.STATE_NAMES`), and
``pi r1^2 p`` while resting, so the gauge pressure is bounded below by 0 (every node's gas mass at
least the ambient's: nothing draws a vacuum); the factors stay in
:data:`hbma_ctrl.estimators.common.FACTOR_RANGE`; every node's height is at most :data:`H_MAX_REL` r1 (a
linearised row of the QP: the far branch of the pressure law would otherwise explain the readings of
a vented chamber by an ever larger cap). Lift-off and touch-down
are the model's complementarity (the membrane rests while ``pi r1^2 p <= W``), evaluated at every
node, so the window sees a lift-off at the sample where it happens.

Solvers (``solver``):

- 'rti' (default): real-time iteration, one Gauss-Newton step per sample as ONE casadi Function
  (:func:`mhe_step_function`): the window shifted by the caller, the model and its Jacobians at every
  node (the predict and outputs Functions ``map``-ped over the nodes), the residuals linearised, the
  constrained QP (Gauss-Newton Hessian, the bounds above and a trust region) solved by casadi's conic
  interface (``qp_solver``: 'qrqp', self-contained C, or 'osqp'), the arrival update and the newest
  node's outputs and covariance (the Gauss-Newton Hessian's inverse). Compiled to C once per machine,
  as the EKF's step (:func:`hbma_ctrl.core.codegen.compiled`).
- 'ipopt': the full nonlinear least-squares problem solved by IPOPT at every sample (the reference;
  the same cost, constraints and arrival update). Slow.

Until the window is full (the first N samples) and on a failed step (a non-finite linearisation,
a QP solution off its bounds, an IPOPT failure) the chamber EKF of :mod:`hbma_ctrl.estimators.ekf` gives
the estimate, started from the MHE's last estimate; :meth:`MHE.stats` counts ``fallbacks``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from dataclasses import replace as dc_replace

import casadi as ca
import numpy as np

from hbma_ctrl.core.codegen import HOT_FLAGS, HOT_OPT, FastFunction, casadi_lib_flags, compiled
from hbma_ctrl.core.interfaces import Command, Estimate, EstimatorBase
from hbma_ctrl.core.params import Actuator, Pneumatics
from hbma_ctrl.core.settings import setting
from hbma_ctrl.estimators.common import (
    FACTOR_RANGE,
    MEAS_MISSING,
    MEAS_OK,
    MEAS_OUTLIER,
    MEAS_SATURATED,
    FilterSettings,
    classify_measurement,
    guard_cov,
    physical_reading_bounds,
)
from hbma_ctrl.estimators.ekf import EKF, EKFSettings
from hbma_ctrl.estimators.ekf_reference import OUTPUT_KEYS
from hbma_ctrl.estimators.ekf_step import KIND_NONE, KIND_OK, KIND_SATURATED, observer_model
from hbma_ctrl.models.actuation import CommandTiming
from hbma_ctrl.models.chamber import NX, STATE_NAMES, STATE_SCALE, ObserverModel

__all__ = ["MHE", "MHESettings", "mhe_step_function", "linearise_function", "LIN_NAMES", "mhe_nlp", "TRUST", "H_MAX_REL", "SOLVERS", "QP_SOLVERS",
           "constraint_violations"]

SOLVERS = ("rti", "ipopt")
QP_SOLVERS = ("daqp", "qrqp", "osqp")
#: libraries a QP solver's generated C links (shipped inside the casadi package; qrqp's C is self-contained)
_QP_LIBS = {"daqp": ["-ldaqp"], "osqp": ["-losqp"], "qrqp": []}
#: the largest change of one Gauss-Newton step, per variable in the scaled coordinates (gas mass in
#: mg, load N, factors): the model switches between resting and contact inside a step, where its
#: linearisation is one-sided; a bounded step keeps one sample's iteration on the branch it started on
TRUST = (0.3, 1.0, 0.02, 0.02, 0.02)
#: the height of a node is at most H_MAX_REL r1: the membrane's far branch (past the pressure's maximum)
#: reaches any low pressure with a large enough cap, so readings near zero after a fast vent could be
#: explained by a cap growing without bound instead of the flat membrane; the protocol's caps stay below
#: 1.8 r1 (the 7.5 mm, 2 mm chamber with 200 g at full speed)
H_MAX_REL = 2.5
#: stands for an infinite constraint bound (m) where the QP solver needs a finite one
_BIG = 1e3
#: a QP solution may leave its bounds by this much (scaled units) and still be used
_BOUND_TOL = 1e-6
#: Levenberg term on the Gauss-Newton Hessian (scaled units): keeps it regular where a parameter is
#: not observed over the window (the load of a resting membrane has its arrival cost alone)
_LEVENBERG = 1e-9
_KIND = {MEAS_OK: KIND_OK, MEAS_SATURATED: KIND_SATURATED}
#: the companion EKF's flags that restart the window when the load is unknown (MHE._ekf_events)
_EKF_RESTARTS = frozenset({"lift_off", "load_change", "load_excess", "lift_off_ratio"})


@dataclass
class MHESettings(FilterSettings):
    """MHE settings: the EKF's (:class:`hbma_ctrl.estimators.common.FilterSettings`, the same model, noise and
    priors) and the window's."""

    horizon: int = setting(20, integer=True, lo=2, hi=200, unit="samples",
                           doc="MHE: samples in the window (readings constraining it)")
    solver: str = setting("rti", choices=SOLVERS,
                          doc="MHE: one Gauss-Newton step per sample as generated C (rti) or a full IPOPT solve (ipopt)")
    qp_solver: str = setting("daqp", choices=QP_SOLVERS, doc="MHE: the RTI step's QP solver (its C generated with the step)")
    huber: float = setting(3.0, lo=0.0, hi=100.0,
                           doc="MHE: readings beyond this many sigmas weigh as Huber's loss does (0: least squares)")
    relinearise: int = setting(2, integer=True, lo=0, hi=200, unit="nodes",
                               doc="MHE: the newest nodes linearised afresh each step, the older keep theirs (0: all)")
    companion_ekf: bool = setting(True, doc="MHE: run the EKF beside it every sample, to restart the window from")
    reseed_cost: float = setting(5.0, lo=0.0, hi=1e6,
                                 doc="MHE: restart the window from the EKF above this cost per sample (0: never)")
    ipopt_iter: int = setting(50, integer=True, lo=1, hi=10000, unit="iterations",
                              doc="MHE: IPOPT's iteration limit per sample (solver ipopt)")


def constraint_violations(h1, h2, h, F, W, tol: float = 1e-9) -> int:
    """Steps (entries) whose estimate breaks a hard constraint of the chamber: h < 0, h2 < 0,
    h2 > h1, F < 0 (m, N; beyond ``tol``) or a negative load state W (N; the EKF's state may be)."""
    h1, h2, h, F, W = (np.asarray(v, dtype=float) for v in (h1, h2, h, F, W))
    bad = (h < -tol) | (h2 < -tol) | (h2 > h1 + tol) | (F < -tol) | (W < -tol)
    return int(np.sum(bad))


def _scales() -> np.ndarray:
    return np.asarray(STATE_SCALE, dtype=float)


def _bounds(om: ObserverModel, s: FilterSettings) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of (m, W, b, k, c) in SI: the gas mass at least the ambient's (the gauge pressure is >= 0:
    the pump fills, the outlet vents to ambient, nothing draws a vacuum; so the resting membrane's
    contact force pi r1^2 p is >= 0), W in [0, load_max], factors in FACTOR_RANGE."""
    lo = np.array([om.m_env, 0.0, FACTOR_RANGE[0], FACTOR_RANGE[0], FACTOR_RANGE[0]])
    hi = np.array([50.0 * om.m_env, s.load_max, FACTOR_RANGE[1], FACTOR_RANGE[1], FACTOR_RANGE[1]])
    return lo, hi


def _residual_terms(s: FilterSettings, N: int, M, th, fm, p, rest, Z, kinds, xbar, P0):
    """The window's scaled residual vector (arrival 5, defects N, readings N) at the nodes' gas
    masses M (N + 1), parameters th (4), the model's next masses fm (N) and pressures p, rest flags
    (N, nodes 1..N), readings Z and kinds (N); returns (r, weights-and-flags) as casadi expressions.
    The arrival term is whitened by the Cholesky-free form r0^T P0s^-1 r0 (returned separately)."""
    sc = _scales()
    x0s = ca.vertcat(M[0], th) / ca.DM(sc)
    r0 = x0s - xbar / ca.DM(sc)
    dm = fm - M[1:]
    sig2 = (s.flow_rel_std * (fm - M[:-1])) ** 2 + s.mass_std_abs ** 2 * s.sample_period + s.cov_floor * sc[0] ** 2
    rd = dm / ca.sqrt(sig2)
    ok = kinds == KIND_OK
    sat = kinds == KIND_SATURATED
    rel = ca.if_else(rest > 0.5, 0.0, s.model_rel_std)
    R = s.noise_std ** 2 + (rel * ca.fmax(p, 0.0)) ** 2
    R_sat = s.saturation_std ** 2 + s.noise_std ** 2 + (rel * s.sensor_range) ** 2
    w_sat = ca.logic_and(sat, p < s.sensor_range)
    rz = ca.if_else(ok, (p - Z) / ca.sqrt(R), ca.if_else(w_sat, (p - s.sensor_range) / ca.sqrt(R_sat), 0.0))
    wz = ca.if_else(ok, 1.0 / ca.sqrt(R), ca.if_else(w_sat, 1.0 / ca.sqrt(R_sat), 0.0))
    if s.huber > 0:
        # Huber's loss by reweighting: a residual beyond huber sigmas weighs as its linear branch (the
        # weight held over the step, as iteratively reweighted least squares does)
        hw = ca.sqrt(ca.fmin(1.0, s.huber / ca.fmax(ca.fabs(rz), 1e-12)))
        rz, wz = rz * hw, wz * hw
    return r0, rd, 1.0 / ca.sqrt(sig2), rz, wz, R, R_sat, ok, w_sat


_LEAN_CACHE: dict = {}


def lean_model(om: ObserverModel) -> tuple[ca.Function, ca.Function]:
    """The EKF's predict and outputs with the mode free (hold = 0: the state decides rest or contact)
    and only what the window needs: ``mhe_predict(x, s, u, theta) -> (x_next, A, s_next)`` and
    ``mhe_outputs(x, s, theta, P) -> (s_out, y, H, C)`` (the same expressions as the model's ``predict``
    and ``outputs``, :class:`hbma_ctrl.models.chamber.ObserverModel`, the parts not read left out,
    common subexpressions merged)."""
    key = id(om.predict)
    if key not in _LEAN_CACHE:
        x, sh, u = ca.SX.sym("x", NX), ca.SX.sym("s", 2), ca.SX.sym("u", 3)
        th = ca.SX.sym("theta", om.predict.size1_in(3))
        P = ca.SX.sym("P", NX, NX)
        qv = ca.DM.zeros(NX + 2)
        xn, A, sn, _, _, _, _ = om.predict.call([x, sh, u, th, 0.0, ca.DM.zeros(NX, NX), qv])
        pred = ca.Function("mhe_predict", [x, sh, u, th], [xn, A, sn], ["x", "s", "u", "theta"],
                           ["x_next", "A", "s_next"], {"cse": True})
        so, y, H, D, C = om.outputs.call([x, sh, th, 0.0, P])
        outs = ca.Function("mhe_outputs", [x, sh, th, P], [so, y, H, C], ["x", "s", "theta", "P"],
                           ["s_out", "y", "H", "C"], {"cse": True})
        meas = ca.Function("mhe_meas", [x, sh, th], [so, y, H, D[2, :]], ["x", "s", "theta"],
                           ["s_out", "y", "H", "Dh"], {"cse": True})
        _LEAN_CACHE[key] = (om.predict, pred, outs, meas)  # the model's Function kept: its id stays unique
    return _LEAN_CACHE[key][1:3]


def _model_maps(om: ObserverModel, N: int) -> tuple[ca.Function, ca.Function]:
    """(predict, outputs without their covariance) of :func:`lean_model`, mapped over N nodes."""
    pred, _ = lean_model(om)
    return pred.map(N), _LEAN_CACHE[id(om.predict)][3].map(N)


def _qv(s: FilterSettings) -> np.ndarray:
    return np.array([s.flow_rel_std] + s.walk_var() + [s.cov_floor])


#: inputs and outputs of the step Function (see :func:`mhe_step_function`)
STEP_IN = ("M", "th", "S", "U", "Z", "kinds", "xbar", "P0", "theta", "fresh")
#: the stored linearisation, inputs after STEP_IN and outputs (``name_next``) after STEP_OUT
LIN_NAMES = ("XI", "FM", "AR", "XM", "PV", "HR", "HV", "DH", "RS")
STEP_OUT = ("M_next", "th_next", "S_next", "xbar_next", "P0_next", "est", "C", "cov", "status", "cost",
            "n_active")


def mhe_step_function(om: ObserverModel, s: MHESettings) -> ca.Function:
    """One real-time iteration of the MHE as one casadi Function (numeric, C-generable).

    Inputs (SI; N = ``s.horizon``): ``M`` (N + 1) the nodes' gas masses (kg, reduced as the EKF's
    state), ``th`` (4) the window's (W, b, k, c), ``S`` (2 x (N + 1)) the nodes' shape warm starts
    (h1, h2, m), ``U`` (3 x N) the commands acting over the N intervals, ``Z`` (N) the readings of
    nodes 1..N (Pa) and ``kinds`` (N) their kinds (:data:`hbma_ctrl.estimators.ekf_step.KIND_OK`, ``KIND_NONE``,
    ``KIND_SATURATED``), ``xbar`` (5) and ``P0`` (5 x 5) the arrival cost's mean and covariance at
    node 0, ``theta`` the model's parameters, ``fresh`` 1 when node N is new (its gas mass is then
    predicted from node N - 1 before the step).

    Outputs: the nodes and parameters after the step, the shapes, the arrival cost of the next
    window's node 0 (this window's node 1), ``est`` = (h1, h2, h, F, p) at node N, C their
    covariance, ``cov`` the covariance of node N's state (5 x 5, from the Gauss-Newton Hessian),
    ``status`` (0 ok, 1 non-finite, 2 the QP solution off its bounds), ``cost`` (the window's cost
    before the step) and ``n_active`` (variables at a bound or at the trust region after the step).
    """
    s = s.validate()
    N = int(s.horizon)
    nt = int(np.asarray(om.theta).size)
    sc = _scales()
    lo, hi = _bounds(om, s)
    pred1, out1 = lean_model(om)
    MX = ca.MX
    M, th, S, U = MX.sym("M", N + 1), MX.sym("th", 4), MX.sym("S", 2, N + 1), MX.sym("U", 3, N)
    Z, kinds = MX.sym("Z", N), MX.sym("kinds", N)
    xbar, P0 = MX.sym("xbar", NX), MX.sym("P0", NX, NX)
    theta, fresh = MX.sym("theta", nt), MX.sym("fresh")
    # a new node N: its gas mass and shape from node N - 1's prediction
    xl = ca.vertcat(M[N - 1], th)
    xn_l, _, sn_l = pred1(xl, S[:, N - 1], U[:, N - 1], theta)
    mN = ca.if_else(fresh > 0.5, xn_l[0], M[N])
    sN = ca.if_else(fresh > 0.5, sn_l, S[:, N])
    M1 = ca.vertcat(M[:N], mN)
    S1 = ca.horzcat(S[:, :N], sN)
    X = ca.vertcat(M1.T, ca.repmat(th, 1, N + 1))  # 5 x (N + 1)
    TH = ca.repmat(theta, 1, N)
    # the stored linearisation of the intervals (points XI, values FM, rows AR of d m_next / d x) and of
    # the nodes 1..N (points XM, pressure PV, its row HR, height HV, its row DH, rest RS, shape SO)
    XI, FM, AR = MX.sym("XI", NX, N), MX.sym("FM", 1, N), MX.sym("AR", NX, N)
    XM, PV, HR = MX.sym("XM", NX, N), MX.sym("PV", 1, N), MX.sym("HR", NX, N)
    HV, DHs, RS = MX.sym("HV", 1, N), MX.sym("DH", NX, N), MX.sym("RS", 1, N)
    lin_in = [XI, FM, AR, XM, PV, HR, HV, DHs, RS]
    L = _fresh_nodes(s)
    pm_L, om_L = _model_maps(om, L)
    xnf, Af, _ = pm_L(X[:, N - L:N], S1[:, N - L:N], U[:, N - L:], TH[:, :L])
    sof, yf, Hf, Dhf = om_L(X[:, N - L + 1:], S1[:, N - L + 1:], TH[:, :L])
    old = N - L  # the nodes that keep their linearisation
    FMn = ca.horzcat(FM[:, :old], xnf[0, :])
    ARn = ca.horzcat(AR[:, :old], ca.reshape(Af[0, :], NX, L))
    XIn = ca.horzcat(XI[:, :old], X[:, old:N])
    PVn = ca.horzcat(PV[:, :old], yf[4, :])
    HRn = ca.horzcat(HR[:, :old], ca.reshape(Hf, NX, L))
    HVn = ca.horzcat(HV[:, :old], yf[2, :])
    DHn = ca.horzcat(DHs[:, :old], ca.reshape(Dhf, NX, L))
    RSn = ca.horzcat(RS[:, :old], yf[5, :])
    XMn = ca.horzcat(XM[:, :old], X[:, old + 1:])
    lin_out = [XIn, FMn, ARn, XMn, PVn, HRn, HVn, DHn, RSn]
    # the model at the iterate: the stored values corrected to first order (exact where just evaluated)
    fm_at = FMn + ca.sum1(ARn * (X[:, :N] - XIn))
    p_at = PVn + ca.sum1(HRn * (X[:, 1:] - XMn))
    h_at = HVn + ca.sum1(DHn * (X[:, 1:] - XMn))
    so = ca.horzcat(S1[:, 1:old + 1], sof)
    A0 = ca.vertcat(ARn[:, 0].T, ca.horzcat(MX.zeros(NX - 1, 1), MX.eye(NX - 1)))
    xn0 = ca.vertcat(fm_at[0], th)
    H1 = HRn[:, 0].T
    y1p, rest_at = p_at[0], RSn
    # --- the least-squares data as an SX Function (residuals, Jacobian, QP data)
    SXs = ca.SX
    sM, sth, sZ, sk = SXs.sym("M", N + 1), SXs.sym("th", 4), SXs.sym("Z", N), SXs.sym("kinds", N)
    sxb, sP0 = SXs.sym("xbar", NX), SXs.sym("P0", NX, NX)
    sfm, sA, sp, sH, srest = SXs.sym("fm", N), SXs.sym("A", NX, N), SXs.sym("p", N), SXs.sym("H", NX, N), \
        SXs.sym("rest", N)
    sDh, sh, shmax = SXs.sym("Dh", NX, N), SXs.sym("h", N), SXs.sym("hmax")
    r0, rd, wd, rz, wz, R, R_sat, ok, w_sat = _residual_terms(s, N, sM, sth, sfm, sp, srest, sZ, sk, sxb, sP0)
    n = N + 5
    # the Jacobians in the scaled variables z = [m_0..m_N, W, b, k, c] / scale (rows whitened)
    Jd = SXs.zeros(N, n)
    Jz = SXs.zeros(N, n)
    for j in range(N):
        Jd[j, j] = wd[j] * sA[0, j] * sc[0]  # d f_m(x_j) / d m_j (A's row of m)
        Jd[j, j + 1] = -wd[j] * sc[0]
        for i in range(4):
            Jd[j, N + 1 + i] = wd[j] * sA[1 + i, j] * sc[1 + i]
        Jz[j, j + 1] = wz[j] * sH[0, j] * sc[0]
        for i in range(4):
            Jz[j, N + 1 + i] = wz[j] * sH[1 + i, j] * sc[1 + i]
    Pinv = ca.inv(sP0 / ca.DM(np.outer(sc, sc)))
    Pinv = 0.5 * (Pinv + Pinv.T)
    E0 = SXs.zeros(NX, n)
    E0[0, 0] = 1.0
    for i in range(4):
        E0[1 + i, N + 1 + i] = 1.0
    Hq = ca.mtimes([E0.T, Pinv, E0]) + ca.mtimes(Jd.T, Jd) + ca.mtimes(Jz.T, Jz) + _LEVENBERG * SXs.eye(n)
    g = ca.mtimes(E0.T, ca.mtimes(Pinv, r0)) + ca.mtimes(Jd.T, rd) + ca.mtimes(Jz.T, rz)
    cost = 0.5 * (ca.mtimes([r0.T, Pinv, r0]) + ca.sumsqr(rd) + ca.sumsqr(rz))
    z = ca.vertcat(sM / sc[0], sth / ca.DM(sc[1:]))
    zlo = np.concatenate([[lo[0] / sc[0]] * (N + 1), lo[1:] / sc[1:]])
    zhi = np.concatenate([[hi[0] / sc[0]] * (N + 1), hi[1:] / sc[1:]])
    tr = np.concatenate([[TRUST[0]] * (N + 1), TRUST[1:]])
    lbx = ca.fmax(ca.DM(zlo) - z, -ca.DM(tr))
    ubx = ca.fmin(ca.DM(zhi) - z, ca.DM(tr))
    # a start outside its bounds (a prior off them) is brought back within one step
    lbx = ca.fmin(lbx, ubx)
    Hq = 0.5 * (Hq + Hq.T)
    # the height bound at nodes 1..N, linearised: h_j + dh_j/dz dz <= hmax
    Ah = SXs.zeros(N, n)
    for j in range(N):
        Ah[j, j + 1] = sDh[0, j] * sc[0]
        for i in range(4):
            Ah[j, N + 1 + i] = sDh[1 + i, j] * sc[1 + i]
    uba = shmax - sh
    data = ca.Function("mhe_qp_data", [sM, sth, sZ, sk, sxb, sP0, sfm, sA, sp, sH, srest, sDh, sh, shmax],
                       [Hq, g, lbx, ubx, cost, R, ca.if_else(ok, 1.0, ca.if_else(w_sat, 1.0, 0.0)), R_sat, Ah, uba],
                       ["M", "th", "Z", "kinds", "xbar", "P0", "fm", "A", "p", "H", "rest", "Dh", "h", "hmax"],
                       ["Hq", "g", "lbx", "ubx", "cost", "R", "used", "R_sat", "Ah", "uba"])
    hmax = _h_max(om)(theta)
    Hm, gm, lbm, ubm, costm, Rm, usedm, Rsatm, Ahm, ubam = data(M1, th, Z, kinds, xbar, P0, fm_at.T, ARn,
                                                               p_at.T, HRn, rest_at.T, DHn, h_at.T, hmax)
    Hsp = ca.Sparsity.dense(n, n)
    qp = ca.conic("mhe_qp", s.qp_solver, {"h": Hsp, "a": ca.Sparsity.dense(N, n)}, _qp_opts(s.qp_solver))
    # (a height already above the bound, a start off it, is brought down by at most the trust region)
    sol = qp(h=Hm, g=gm, lbx=lbm, ubx=ubm, a=Ahm, lba=-_BIG * MX.ones(N), uba=ca.fmax(ubam, ca.mtimes(Ahm, lbm)))
    dz = sol["x"]
    # --- after the step: nodes, arrival update, newest node's outputs and covariance
    znew_M = M1 + dz[:N + 1] * sc[0]
    th_new = th + dz[N + 1:] * ca.DM(sc[1:])
    off = ca.fmax(ca.fmax(ca.mmax(dz - ubm), ca.mmax(lbm - dz)),
                  ca.mmax(ca.mtimes(Ahm, dz) - ca.fmax(ubam, ca.mtimes(Ahm, lbm))) * 1e3)
    active = ca.sum1((dz - lbm <= 1e-9) + (ubm - dz <= 1e-9))
    x0o = ca.vertcat(M1[0], th)
    # arrival: the EKF's step from the arrival mean (not from the window's node 0, which already holds
    # the window's readings: taken as the next prior, they would count twice and drag the parameters
    # along), linearised along the window (node 0's interval and node 1's reading): predict with Q as
    # the EKF's, then the Joseph-form update with node 1's reading
    xm = xn0 + ca.mtimes(A0, xbar - x0o)
    dmq = fm_at[0] - M1[0]
    Q = ca.diag(ca.vertcat((s.flow_rel_std * dmq) ** 2 + s.walk_var()[0], *s.walk_var()[1:]))
    Pm = ca.mtimes([A0, P0, A0.T]) + Q
    p1 = y1p + ca.mtimes(H1, xm - X[:, 1])
    used1 = usedm[0]
    z1 = ca.if_else(kinds[0] == KIND_SATURATED, s.sensor_range, Z[0])
    R1 = ca.if_else(kinds[0] == KIND_SATURATED, Rsatm[0], Rm[0])
    Sv = ca.mtimes([H1, Pm, H1.T]) + R1
    K = used1 * ca.mtimes(Pm, H1.T) / Sv
    IKH = MX.eye(NX) - ca.mtimes(K, H1)
    Pp = ca.mtimes([IKH, Pm, IKH.T]) + R1 * ca.mtimes(K, K.T)
    Pp = 0.5 * (Pp + Pp.T)
    xbar_next = xm + K * (z1 - p1)
    # the newest node: its covariance from the Gauss-Newton Hessian (scaled), its outputs
    idx = [N, N + 1, N + 2, N + 3, N + 4]
    Eo = ca.DM.zeros(n, NX)
    for i, j in enumerate(idx):
        Eo[j, i] = 1.0
    Ci = ca.solve(Hm, Eo, "ldl")
    covN = ca.mtimes(Eo.T, Ci) * ca.DM(np.outer(sc, sc))
    covN = 0.5 * (covN + covN.T)
    xN = ca.vertcat(znew_M[N], th_new)
    s_out, yN, _, CN = out1(xN, so[:, N - 1], theta, covN)
    S_next = ca.horzcat(S1[:, 0], so[:, :N - 1], s_out)
    finite = _finite(ca.vertcat(dz, yN, ca.vec(Pp), xbar_next, ca.vec(covN)))
    status = ca.if_else(finite, ca.if_else(off <= _BOUND_TOL, 0.0, 2.0), 1.0)
    est = ca.vertcat(yN[0], yN[1], yN[2], yN[3], yN[4])
    return ca.Function("mhe_step", [M, th, S, U, Z, kinds, xbar, P0, theta, fresh] + lin_in,
                       [znew_M, th_new, S_next, xbar_next, Pp, est, CN, covN, status, costm, active] + lin_out,
                       list(STEP_IN) + list(LIN_NAMES), list(STEP_OUT) + [n + "_next" for n in LIN_NAMES])


def _fresh_nodes(s: "MHESettings") -> int:
    """The newest nodes the step linearises afresh (``relinearise``; 0: all N)."""
    return int(s.horizon) if s.relinearise == 0 else min(int(s.relinearise), int(s.horizon))


def linearise_function(om: ObserverModel, N: int) -> ca.Function:
    """The window's whole linearisation (the step's stored inputs :data:`LIN_NAMES`) at nodes M, th,
    shapes S and commands U: what the step keeps for the nodes it does not linearise afresh."""
    pred_map, out_map = _model_maps(om, N)
    nt = int(np.asarray(om.theta).size)
    M, th, S, U, theta = (ca.MX.sym(n, *sh) for n, sh in (("M", (N + 1, 1)), ("th", (4, 1)), ("S", (2, N + 1)),
                                                            ("U", (3, N)), ("theta", (nt, 1))))
    X = ca.vertcat(M.T, ca.repmat(th, 1, N + 1))
    TH = ca.repmat(theta, 1, N)
    xn, A, _ = pred_map(X[:, :N], S[:, :N], U, TH)
    _, y, H, Dh = out_map(X[:, 1:], S[:, 1:], TH)
    outs = [X[:, :N], xn[0, :], ca.reshape(A[0, :], NX, N), X[:, 1:], y[4, :], ca.reshape(H, NX, N), y[2, :],
            ca.reshape(Dh, NX, N), y[5, :]]
    return ca.Function("mhe_linearise", [M, th, S, U, theta], outs, ["M", "th", "S", "U", "theta"], list(LIN_NAMES))


def _h_max(om: ObserverModel) -> ca.Function:
    """theta -> the largest node height (m), :data:`H_MAX_REL` r1."""
    thp, Pd = om.chamber.symbols()
    return ca.Function("mhe_h_max", [thp], [H_MAX_REL * Pd["r1"]])


def _finite(e):
    return ca.fabs(ca.sum1(ca.sum2(e))) <= 1.7976931348623157e308


def _qp_opts(qp_solver: str) -> dict:
    if qp_solver == "daqp":
        return {"error_on_fail": False}
    if qp_solver == "qrqp":
        return {"print_iter": False, "print_header": False, "print_info": False, "error_on_fail": False,
                "max_iter": 200}
    return {"osqp": {"verbose": False, "eps_abs": 1e-8, "eps_rel": 1e-8, "max_iter": 4000, "polish": True},
            "error_on_fail": False}


_STEP_CACHE: dict = {}
#: the settings the step Function depends on (a trial's own load prior must not build another one)
_STEP_KEYS = ("relinearise", "huber", "noise_std", "model_rel_std", "sensor_range", "saturation_std", "flow_rel_std", "mass_std_abs",
              "load_std", "flow_factor_std", "modulus_std", "dead_volume_std", "cov_floor", "load_max",
              "sample_period", "horizon", "solver", "qp_solver", "ipopt_iter", "compile")


def _compiled_step(om: ObserverModel, s: MHESettings, key: tuple) -> FastFunction:
    if key not in _STEP_CACHE:
        fun = mhe_step_function(om, s)
        flags = list(HOT_FLAGS) + casadi_lib_flags(_QP_LIBS[s.qp_solver])
        done = compiled(fun, HOT_OPT, flags, notice=f"compiling the MHE step (N = {s.horizon}) once for this "
                                                     "machine ...") if s.compile else fun
        _STEP_CACHE[key] = done
    return FastFunction(_STEP_CACHE[key], False)


def mhe_nlp(om: ObserverModel, s: MHESettings) -> ca.Function:
    """The window's full problem for IPOPT as a Function of the step's inputs (:data:`STEP_IN`, with
    ``fresh`` = 0 and node N already predicted) -> (M, th, status 0 ok / 1 failed, cost): the same
    cost and bounds as :func:`mhe_step_function`, the model exact at every node (no linearisation),
    no trust region."""
    s = s.validate()
    N = int(s.horizon)
    nt = int(np.asarray(om.theta).size)
    sc = _scales()
    lo, hi = _bounds(om, s)
    pred_map, out_map = _model_maps(om, N)
    MX = ca.MX
    zv = MX.sym("z", N + 5)
    S, U, Z, kinds = MX.sym("S", 2, N + 1), MX.sym("U", 3, N), MX.sym("Z", N), MX.sym("kinds", N)
    xbar, P0, theta = MX.sym("xbar", NX), MX.sym("P0", NX, NX), MX.sym("theta", nt)
    M = zv[:N + 1] * sc[0]
    th = zv[N + 1:] * ca.DM(sc[1:])
    X = ca.vertcat(M.T, ca.repmat(th, 1, N + 1))
    TH = ca.repmat(theta, 1, N)
    xn = pred_map(X[:, :N], S[:, :N], U, TH)[0]
    y = out_map(X[:, 1:], S[:, 1:], TH)[1]
    hmax = _h_max(om)(theta)
    # the process noise's sigma at the window's start values (a parameter: the cost stays a sum of squares)
    fm0, Mpar = MX.sym("fm0", N), MX.sym("Mpar", N + 1)
    sig2 = (s.flow_rel_std * (fm0 - Mpar[:-1])) ** 2 + s.mass_std_abs ** 2 * s.sample_period + s.cov_floor * sc[0] ** 2
    rd = (xn[0, :].T - M[1:]) / ca.sqrt(sig2)
    ok = kinds == KIND_OK
    sat = kinds == KIND_SATURATED
    p = y[4, :].T
    rel = ca.if_else(y[5, :].T > 0.5, 0.0, s.model_rel_std)
    R = s.noise_std ** 2 + (rel * ca.fmax(p, 0.0)) ** 2
    R_sat = s.saturation_std ** 2 + s.noise_std ** 2 + (rel * s.sensor_range) ** 2
    rz = ca.if_else(ok, (p - Z) / ca.sqrt(R), ca.if_else(sat, ca.fmin(p - s.sensor_range, 0.0) / ca.sqrt(R_sat), 0.0))
    # Huber's loss (huber sigmas), the same as the RTI step's
    lz = rz ** 2 if s.huber <= 0 else ca.if_else(ca.fabs(rz) <= s.huber, rz ** 2,
                                                 2 * s.huber * ca.fabs(rz) - s.huber ** 2)
    x0s = ca.vertcat(M[0], th) / ca.DM(sc)
    r0 = x0s - xbar / ca.DM(sc)
    Pinv = ca.inv(P0 / ca.DM(np.outer(sc, sc)))
    f = 0.5 * (ca.mtimes([r0.T, Pinv, r0]) + ca.sumsqr(rd) + ca.sum1(lz))
    par = ca.vertcat(ca.vec(S), ca.vec(U), Z, kinds, xbar, ca.vec(P0), theta, fm0, Mpar)
    opts = {"ipopt": {"print_level": 0, "max_iter": s.ipopt_iter, "tol": 1e-8, "hessian_approximation": "limited-memory"},
            "print_time": False, "error_on_fail": False}
    solver = ca.nlpsol("mhe_ipopt", "ipopt", {"x": zv, "f": f, "p": par, "g": y[2, :].T - hmax}, opts)
    zlo = np.concatenate([[lo[0] / sc[0]] * (N + 1), lo[1:] / sc[1:]])
    zhi = np.concatenate([[hi[0] / sc[0]] * (N + 1), hi[1:] / sc[1:]])
    Min, thin = MX.sym("M", N + 1), MX.sym("th", 4)
    fm0in = MX.sym("fm0", N)
    z0 = ca.vertcat(Min / sc[0], thin / ca.DM(sc[1:]))
    sol = solver(x0=ca.fmin(ca.fmax(z0, zlo), zhi), lbx=zlo, ubx=zhi, lbg=-ca.inf, ubg=0.0,
                 p=ca.vertcat(ca.vec(S), ca.vec(U), Z, kinds, xbar, ca.vec(P0), theta, fm0in, Min))
    zs = sol["x"]
    return ca.Function("mhe_ipopt_step", [Min, thin, S, U, Z, kinds, xbar, P0, theta, fm0in],
                       [zs[:N + 1] * sc[0], zs[N + 1:] * ca.DM(sc[1:]), sol["f"]],
                       ["M", "th", "S", "U", "Z", "kinds", "xbar", "P0", "theta", "fm0"], ["M_next", "th_next", "cost"])


def _within_bounds(e: Estimate) -> Estimate:
    """The EKF's estimate with its load state at least zero (the MHE's bound; the EKF's own load state
    may dip below: its dead zone)."""
    if e.mean[1] >= 0.0:
        return e
    mean = e.mean.copy()
    mean[1] = 0.0
    return dc_replace(e, mean=mean)


def _estimate(t, est, mean, cov, std, flags) -> Estimate:
    e = object.__new__(Estimate)
    e.__dict__.update(t=t, h1=est[0], h2=est[1], h=est[2], F=est[3], p=est[4], mean=mean, cov=cov,
                      state_names=STATE_NAMES, std=std, flags=flags)
    return e


class MHE(EstimatorBase):
    """Moving-horizon estimator of one chamber on the EKF's model (see module docstring). SI throughout.

    ``step(t, measurement, applied_command) -> Estimate`` as :meth:`hbma_ctrl.estimators.ekf.EKF.step`;
    the estimate is the window's newest node. Diagnostics after a step: ``last_output_cov`` (the
    covariance of ``OUTPUT_KEYS``), ``last_step_s``, ``last_cost`` (the window's cost), ``last_status``
    (0 ok; 1, 2 a failed step: see :func:`mhe_step_function`; -1 the EKF's estimate: window filling or
    fallback); :meth:`stats` counts ``fallbacks``, ``mhe_steps`` and the readings' kinds.
    """

    state_names = STATE_NAMES

    def __init__(self, actuator: Actuator, pneumatics: Pneumatics, settings: FilterSettings | None = None):
        s = settings if isinstance(settings, MHESettings) else MHESettings(**_fields(settings)) \
            if settings is not None else MHESettings()
        self.settings = s = s.validate()
        actuator.validate()
        pneumatics.validate()
        self.model = om = observer_model(actuator, pneumatics, s)
        self.theta = np.asarray(om.theta, dtype=float)
        self.N = N = int(s.horizon)
        ekf_fields = {k: v for k, v in _fields(s).items() if k in _fields(EKFSettings())}
        self.ekf = EKF(actuator, pneumatics, EKFSettings(**ekf_fields))
        self._timing = CommandTiming(s.sample_period, s.valve_delay, s.sensor_delay)
        self._bounds = physical_reading_bounds(s.sensor_range, s.reading_min, s.reading_max_rel)
        key = (id(om.predict), tuple(getattr(s, n) for n in _STEP_KEYS))
        if s.solver == "rti":
            self._fn = _compiled_step(om, s, key)
            self._nlp = None
            lk = ("lin", id(om.predict), N, s.compile)
            if lk not in _STEP_CACHE:
                fun = linearise_function(om, N)
                _STEP_CACHE[lk] = compiled(fun, HOT_OPT, HOT_FLAGS) if s.compile else fun
            self._lin_fn = FastFunction(_STEP_CACHE[lk], False)
            self.lin = [np.zeros(self._fn.inp[len(STEP_IN) + i].size) for i in range(len(LIN_NAMES))]
        else:
            self._fn = None
            if key not in _NLP_CACHE:
                pred, outs = lean_model(om)
                _NLP_CACHE[key] = (mhe_nlp(om, s), FastFunction(pred, s.compile, HOT_OPT, HOT_FLAGS),
                                   FastFunction(outs, s.compile, HOT_OPT, HOT_FLAGS))
            self._nlp, self._pred1, self._out1 = _NLP_CACHE[key]
        self._qv = _qv(s)
        self._lo, self._hi = _bounds(om, s)
        # the window: nodes' masses, shapes, the commands acting over the intervals, readings, kinds
        self.M = np.zeros(N + 1)
        self.th = np.ones(4)
        self.S = np.zeros((2, N + 1))
        self.U = np.zeros((3, N))
        self.Z = np.zeros(N)
        self.kinds = np.full(N, float(KIND_NONE))
        self.xbar = np.zeros(NX)
        self.P0 = np.eye(NX)
        self._filled = 0  # samples seen (the window is full from N + 1 on)
        self._hist: list = []  # the EKF's (posterior x, P, shape) while the window fills
        self.t: float | None = None
        self.last_output_cov = np.zeros((5, 5))
        self.last_step_s = 0.0
        self.last_cost = float("nan")
        self.last_status = -1
        self.last_active = 0
        self._ekf_est: Estimate | None = None
        self.counts = {"fallbacks": 0, "reseeds": 0, "mhe_steps": 0, "missing": 0, "outliers_bound": 0, "saturated": 0,
                       "time_jumps": 0}
        self._k_max = max(1, int(round(s.max_gap / s.sample_period)))
        self._last: Estimate | None = None

    # --- the step -----------------------------------------------------------------------------
    def step(self, t: float, measurement, applied_command: Command) -> Estimate:
        """Advance to time t (s) with the command held since the last step, then estimate from the window
        (one Gauss-Newton step or an IPOPT solve). Missing periods (a late tick) enter the window as
        samples without a reading; a gap longer than ``max_gap`` keeps ``max_gap`` of them (flag
        ``time_jump``). ValueError when t is not a finite time or goes backwards."""
        t_wall = time.perf_counter()
        s = self.settings
        t = self.ekf._check_time(t) if self.t is None else _check_time(t, self.t)
        kind = classify_measurement(measurement, s.sensor_range, *self._bounds)
        flags: set = set()
        if kind != MEAS_OK:
            flags.add(kind)
            key = {MEAS_OUTLIER: "outliers_bound", MEAS_MISSING: "missing", MEAS_SATURATED: "saturated"}[kind]
            self.counts[key] += 1
        u = applied_command.as_array() if isinstance(applied_command, Command) else \
            np.asarray(applied_command, dtype=float).reshape(3)
        if self.t is None:
            k = 0
        else:
            k = int(round((t - self.t) / s.sample_period))
            if k > self._k_max:
                k = self._k_max
                flags.add("time_jump")
                self.counts["time_jumps"] += 1
        if k == 0 and self._last is not None:
            # no period passed: nothing to add to the window
            self.t = t
            self.last_step_s = time.perf_counter() - t_wall
            return self._last
        est = None
        for i in range(max(k, 1)):
            last = i == max(k, 1) - 1
            z = measurement if last else None
            kd = kind if last else MEAS_MISSING
            est = self._one(t - (max(k, 1) - 1 - i) * s.sample_period, z, kd, u, k > 0)
        if flags:
            est = dc_replace(est, flags=frozenset(est.flags | flags))
        self.t = t
        self._last = est
        self.last_step_s = time.perf_counter() - t_wall
        return est

    def _one(self, t: float, z, kind: str, u: np.ndarray, advance: bool) -> Estimate:
        s, N = self.settings, self.N
        ua = self._timing.acting(u, 1 if advance else 0) if self._timing.active else u
        code = _KIND.get(kind, KIND_NONE)
        zf = float(z) if code == KIND_OK else 0.0
        self._push(ua, zf, code)
        if self._filled <= N or s.companion_ekf:
            e = self.ekf.step(t, z, u)
            self._hist.append((self.ekf.x.copy(), self.ekf.P.copy(), self.ekf.s.copy()))
            del self._hist[:-(N + 1)]
            self._ekf_est = e
        elif self.ekf._timing.active:
            self.ekf._timing.acting(u, 1)  # the fallback's command history stays current
        if self._filled <= N:
            # the window fills: the EKF's estimate, its posteriors kept as the window's start
            self._filled += 1
            if self._filled == N + 1:
                self._start_window()
            self.last_status = -1
            return _within_bounds(e)
        # node N is new: the step predicts it from node N - 1
        return self._solve(t, z, u)

    def _push(self, ua: np.ndarray, zf: float, code: int) -> None:
        """Shift the window by one sample: drop node 0, the oldest interval and reading."""
        self.U[:, :-1] = self.U[:, 1:]
        self.U[:, -1] = ua
        self.Z[:-1] = self.Z[1:]
        self.Z[-1] = zf
        self.kinds[:-1] = self.kinds[1:]
        self.kinds[-1] = code
        self.M[:-1] = self.M[1:]
        self.S[:, :-1] = self.S[:, 1:]
        if self._fn is not None:
            # the stored linearisation moves with its nodes (column-major: a column is a block of rows)
            for a in self.lin:
                r = a.size // self.N
                a[:-r] = a[r:]

    def _start_window(self) -> None:
        """The window's nodes from the EKF's posteriors over its samples, the arrival cost from the
        EKF's posterior at node 0, the parameters from its latest."""
        xs = [h[0] for h in self._hist[-(self.N + 1):]]
        self.M[:] = [x[0] for x in xs]
        self.S[:] = np.array([h[2] for h in self._hist[-(self.N + 1):]]).T
        self.th[:] = np.clip(xs[-1][1:], *[b[1:] for b in _bounds(self.model, self.settings)])
        x0, P0, _ = self._hist[-(self.N + 1)]
        self.xbar[:] = x0
        self.P0[:] = guard_cov(P0, self.settings.cov_floor)
        if self._fn is not None:
            # the whole window linearised once (the step then re-linearises its newest nodes only)
            out = self._lin_fn(self.M, self.th, self.S, self.U, self.theta)
            for a, o in zip(self.lin, out):
                a[:] = o

    def _solve(self, t: float, z, u) -> Estimate:
        s, N = self.settings, self.N
        if self._ekf_events():
            return self._reseed()
        if self._fn is not None:
            fn = self._fn
            out = fn(self.M, self.th, self.S, self.U, self.Z, self.kinds, self.xbar, self.P0, self.theta, 1.0,
                     *self.lin)
            status = int(out[8][0])
            if status == 0:
                for a, o in zip(self.lin, out[len(STEP_OUT):]):
                    a[:] = o
                # within the bounds (the QP's solution may leave them by its tolerance, _BOUND_TOL)
                self.M[:] = np.maximum(out[0], self._lo[0])
                self.th[:] = np.clip(out[1], self._lo[1:], self._hi[1:])
                self.S[:] = out[2].reshape(2, N + 1, order="F")
                self.xbar[:] = out[3]
                self.P0[:] = guard_cov(out[4].reshape(NX, NX, order="F"), s.cov_floor)
                est = out[5].tolist()
                C = out[6].reshape(5, 5, order="F").copy()
                cov = out[7].reshape(NX, NX, order="F").copy()
                self.last_cost = float(out[9][0])
                self.last_active = int(out[10][0])
                if self._reseed_due():
                    return self._reseed()
                return self._accept(t, est, C, cov, status)
        else:
            status = self._solve_ipopt()
            if status == 0:
                est = self._ipopt_outputs()
                if self._reseed_due():
                    return self._reseed()
                return self._accept(t, *est, status)
        if self.settings.companion_ekf:
            return self._reseed(failed=True)
        return self._fallback(t, z, u, status)

    def _ekf_events(self) -> bool:
        """With the load unknown (no ``load_init``), the companion EKF's detectors restart the window: a
        lift-off or a load change it declares (the window alone cannot see a lift-off: while the membrane
        rests the load is unobservable, and the flow and dead-volume factors take up the slower rise)."""
        e = self._ekf_est
        return (self.settings.companion_ekf and self.settings.load_init is None and e is not None
                and bool(e.flags & _EKF_RESTARTS))

    def _reseed_due(self) -> bool:
        """The window's cost per sample beyond ``reseed_cost`` with the companion EKF at hand: the window
        no longer explains its readings (a shape on the wrong branch of the pressure law)."""
        s = self.settings
        return s.companion_ekf and s.reseed_cost > 0 and self.last_cost > s.reseed_cost * self.N

    def _reseed(self, failed: bool = False) -> Estimate:
        """The window restarted from the companion EKF's posteriors over its samples; its estimate is the
        EKF's (flag ``mhe_fallback``, counted in ``fallbacks``; ``reseeds`` counts the restarts the
        window's cost or the EKF's detectors asked for)."""
        self.counts["fallbacks"] += 1
        if not failed:
            self.counts["reseeds"] += 1
        self.last_status = -1
        self._start_window()
        e = _within_bounds(self._ekf_est)
        return dc_replace(e, flags=frozenset(e.flags | {"mhe_fallback"}))

    def _accept(self, t: float, est: list, C: np.ndarray, cov: np.ndarray, status: int) -> Estimate:
        # reported as the EKF reports them: h2, h and F at least 0 (the contact condition's tiny
        # regularising stiffness leaves F = -EPS_K h2, micronewtons, on a free cap)
        est = [est[0], max(est[1], 0.0), max(est[2], 0.0), max(est[3], 0.0), est[4]]
        self.counts["mhe_steps"] += 1
        self.last_status = status
        self.last_output_cov = C
        mean = np.concatenate([[self.M[-1]], self.th])
        std = dict(zip(OUTPUT_KEYS, np.sqrt(np.maximum(np.diag(C), 0.0)).tolist()))
        flags = {"resting"} if est[2] <= 0.0 and est[3] <= 0.0 else set()
        return _estimate(t, est, mean, cov, std, frozenset(flags))

    def _fallback(self, t: float, z, u, status: int) -> Estimate:
        """A failed step: the EKF from the last estimate (node N - 1 and the window's parameters, with the
        Gauss-Newton covariance of the last step), stepped with this sample; node N is its posterior."""
        self.counts["fallbacks"] += 1
        self.last_status = -1
        N = self.N
        last = self._last
        x = np.concatenate([[self.M[N - 1]], self.th])
        P = last.cov if last is not None and last.cov.shape == (NX, NX) else self.P0
        self.ekf.reset(t - self.settings.sample_period, x, guard_cov(P, self.settings.cov_floor),
                       shape=self.S[:, N - 1], resting=None)
        e = self.ekf.step(t, z, u)
        self.M[N] = self.ekf.x[0]
        self.th[:] = np.clip(self.ekf.x[1:], *[b[1:] for b in _bounds(self.model, self.settings)])
        self.S[:, N] = self.ekf.s
        return dc_replace(_within_bounds(e), flags=frozenset(e.flags | {"mhe_fallback"}))

    # --- the IPOPT reference ------------------------------------------------------------------
    def _solve_ipopt(self) -> int:
        N = self.N
        pred = self._pred1
        # node N from node N - 1's prediction, the process noise's sigma at the window's start values
        x = np.concatenate([[self.M[N - 1]], self.th])
        r = pred(x, self.S[:, N - 1], self.U[:, N - 1], self.theta)
        self.M[N] = r[0][0]
        self.S[:, N] = r[2]
        fm0 = np.empty(N)
        for j in range(N):
            x = np.concatenate([[self.M[j]], self.th])
            fm0[j] = pred(x, self.S[:, j], self.U[:, j], self.theta)[0][0]
        res = self._nlp(self.M, self.th, self.S, self.U, self.Z, self.kinds, self.xbar, self.P0, self.theta, fm0)
        M1, th1 = np.asarray(res[0]).ravel(), np.asarray(res[1]).ravel()
        if not (np.all(np.isfinite(M1)) and np.all(np.isfinite(th1))):
            return 1
        self._ipopt_prev = (self.M.copy(), self.th.copy())
        self.M[:], self.th[:] = M1, th1
        self.last_cost = float(res[2])
        return 0

    def _ipopt_outputs(self) -> tuple:
        """After an IPOPT solve: the shapes, the arrival update (linearised at the solution, as the RTI
        step's) and node N's outputs and covariance (the Gauss-Newton Hessian at the solution)."""
        s, N = self.settings, self.N
        pred, outf = self._pred1, self._out1
        sc = _scales()
        n = N + 5
        J = []
        A0 = xn0 = None
        H1 = y1 = None
        for j in range(N + 1):
            x = np.concatenate([[self.M[j]], self.th])
            o = outf(x, self.S[:, j], self.theta, np.zeros((NX, NX)))
            self.S[:, j] = o[0]
            if j == 1:
                y1, H1 = o[1].copy(), o[2].copy()
            if j >= 1:
                kd = self.kinds[j - 1]
                p = o[1][4]
                rest = o[1][5] > 0.5
                R = s.noise_std ** 2 + ((0.0 if rest else s.model_rel_std) * max(p, 0.0)) ** 2
                w = 1.0 / math.sqrt(R) if kd == KIND_OK else (
                    1.0 / math.sqrt(s.saturation_std ** 2 + R) if kd == KIND_SATURATED and p < s.sensor_range else 0.0)
                row = np.zeros(n)
                row[j] = w * o[2][0] * sc[0]
                row[N + 1:] = w * o[2][1:] * sc[1:]
                J.append(row)
            if j < N:
                r = pred(x, self.S[:, j], self.U[:, j], self.theta)
                A = r[1].reshape(NX, NX, order="F")
                sig = math.sqrt((s.flow_rel_std * (r[0][0] - self.M[j])) ** 2 + s.mass_std_abs ** 2 * s.sample_period
                                + s.cov_floor * sc[0] ** 2)
                row = np.zeros(n)
                row[j] = A[0, 0] / sig * sc[0]
                row[j + 1] = -sc[0] / sig
                row[N + 1:] = A[0, 1:] / sig * sc[1:]
                J.append(row)
                if j == 0:
                    A0, xn0 = A.copy(), r[0].copy()
        J = np.array(J)
        Pinv = np.linalg.inv(self.P0 / np.outer(sc, sc))
        E0 = np.zeros((NX, n))
        E0[0, 0] = 1.0
        E0[1:, N + 1:] = np.eye(4)
        Hh = E0.T @ Pinv @ E0 + J.T @ J + _LEVENBERG * np.eye(n)
        idx = [N, N + 1, N + 2, N + 3, N + 4]
        covN = np.linalg.inv(Hh)[np.ix_(idx, idx)] * np.outer(sc, sc)
        covN = 0.5 * (covN + covN.T)
        xN = np.concatenate([[self.M[N]], self.th])
        o = outf(xN, self.S[:, N], self.theta, covN)
        est = o[1][:5].tolist()
        C = o[3].reshape(5, 5, order="F").copy()
        # arrival update from the solution's node 0 (EKF predict and Joseph update with node 1's reading)
        Q = np.diag([(s.flow_rel_std * (xn0[0] - self.M[0])) ** 2 + s.walk_var()[0], *s.walk_var()[1:]])
        Pm = A0 @ self.P0 @ A0.T + Q
        kd = self.kinds[0]
        rest1 = y1[5] > 0.5
        R1 = s.noise_std ** 2 + ((0.0 if rest1 else s.model_rel_std) * max(y1[4], 0.0)) ** 2
        # from the arrival mean (the lagged EKF's), as the RTI step's
        xm = xn0 + A0 @ (self.xbar - np.concatenate([[self.M[0]], self.th]))
        p1 = y1[4] + H1 @ (xm - np.concatenate([[self.M[1]], self.th]))
        used = kd == KIND_OK or (kd == KIND_SATURATED and p1 < s.sensor_range)
        if kd == KIND_SATURATED:
            R1 = s.saturation_std ** 2 + s.noise_std ** 2 + ((0.0 if rest1 else s.model_rel_std) * s.sensor_range) ** 2
        z1 = s.sensor_range if kd == KIND_SATURATED else self.Z[0]
        if used:
            Sv = float(H1 @ Pm @ H1) + R1
            K = Pm @ H1 / Sv
            IKH = np.eye(NX) - np.outer(K, H1)
            Pm = IKH @ Pm @ IKH.T + R1 * np.outer(K, K)
            xm = xm + K * (z1 - p1)
        self.xbar[:] = xm
        self.P0[:] = guard_cov(0.5 * (Pm + Pm.T), s.cov_floor)
        return est, C, covN

    def stats(self) -> dict:
        """Counts since construction: ``fallbacks`` (steps the EKF gave after a failed MHE step),
        ``mhe_steps`` (steps the MHE gave), ``missing``, ``outliers_bound``, ``saturated`` readings and
        ``time_jumps``; ``outliers`` as the EKF's."""
        c = dict(self.counts)
        c["outliers"] = c["outliers_bound"]
        return c


_NLP_CACHE: dict = {}


def _fields(settings) -> dict:
    """A settings dataclass's fields as a dict (shallow)."""
    from dataclasses import fields as dc_fields

    return {f.name: getattr(settings, f.name) for f in dc_fields(settings)}


def _check_time(t, last: float) -> float:
    if type(t) is float and last - 1e-9 <= t < math.inf:
        return t
    try:
        tf = float(t)
    except (TypeError, ValueError):
        raise ValueError(f"estimator.step: t = {t!r} must be a finite time in s") from None
    if not math.isfinite(tf) or isinstance(t, (str, bytes, bool)):
        raise ValueError(f"estimator.step: t = {t!r} must be a finite time in s")
    if tf < last - 1e-9:
        raise ValueError(f"estimator.step: t = {tf} s is before the last step's {last} s (time must not go backwards)")
    return tf
