"""The moving-horizon estimator's window problem as casadi Functions: the real-time step and the IPOPT reference.

The window at the step of sample k holds the nodes ``j = 0 .. N`` (N = ``horizon``), node j at sample
``k - N + j``. The unknowns are the window's first state ``x_0 = (m_0, theta)``, theta = (W, b, k, c)
the load and the pump-flow, modulus and dead-volume factors of :mod:`hbma_ctrl.models.chamber`,
constant over the window. Every later node's gas mass follows from them by the EKF's discrete model
(single shooting): ``m_(j+1) = f(m_j, theta, u_j)``, so the problem has five unknowns whatever N is.
The mass flow's model error, which the EKF carries as process noise, is taken up by the flow and
dead-volume factors over the window and by the arrival cost's random walk between windows.

Measurement-to-state indexing: the reading taken at sample ``k - N + j`` constrains node j for
``j = 1 .. N``; node 0's reading is already in the arrival cost. The command applied over the period
ending at node ``j + 1`` drives the interval from node j to node j + 1.

The cost (every term a squared residual):

- arrival: ``(x_0 - xbar)^T P0^-1 (x_0 - xbar)``, (xbar, P0) updated by one EKF step at every step
  from the arrival itself, linearised along the window (node 0's interval and node 1's reading), so
  the arrival mean is the lagged EKF's, which has not seen the window's readings;
- the readings ``(p(x_j) - z_j)^2 / R_j`` (R the EKF's: ``noise_std`` and, in contact,
  ``model_rel_std`` of the pressure). A saturated reading only says ``p >= range`` (a one-sided
  residual with ``saturation_std``); a missing reading or an outlier has none; residuals beyond
  ``huber`` sigmas weigh as Huber's loss.

Hard constraints: the shape follows from (m, W) by the model's projection (``0 <= h2 <= h1``,
``h >= 0``); ``W >= 0`` (so the contact force is >= 0); the first node's gas mass at least the ambient's
(the gauge pressure is >= 0; the later nodes follow the model, whose vent stops at the ambient); the factors in :data:`hbma_ctrl.estimators.common.FACTOR_RANGE`; every
node's height at most :data:`H_MAX_REL` r1.

Known load (``known_load=True``): the load is not an unknown but an input series ``WL`` (N + 1, N),
one per node, as the robot's statics give it (:mod:`hbma_ctrl.estimators.robot_mhe`). Node j's
reading is modelled at ``WL_j`` and the interval ending at node j is predicted at ``WL_j``; the
unknowns that remain are the first gas mass and the three factors (the load's column of every
linearisation is zero and its step is held at 0, so the window's load plays no part in the
least-squares problem, its arrival update or its covariance).

The window's model (``om``) is the chamber's :class:`hbma_ctrl.models.chamber.ObserverModel` or any
object with the same ``predict`` and ``outputs`` Functions, ``theta`` and ``m_env``; it may name its
own ``factor_ranges`` (three (lo, hi) pairs, default :data:`FACTOR_RANGE`) and ``h_max_function()``
(theta -> the largest node height, m; default :data:`H_MAX_REL` r1).

The real-time step (:func:`mhe_step_function`) is one Gauss-Newton step: the model is linearised
afresh at the newest ``relinearise`` intervals and nodes, the older keep their stored linearisation
(:data:`LIN_NAMES`, corrected to first order at the iterate). Along the window the linearised
recursion gives every node's gas mass, pressure and height as an affine function of the five
unknowns (their sensitivities propagated by the rows of d m_next / d x), so the step is a dense
five-variable least-squares problem with box bounds (and a trust region) and one linear row per node
for the height, solved by casadi's conic interface (``qp_solver``).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from hbma_ctrl.estimators.common import FACTOR_RANGE, FilterSettings
from hbma_ctrl.estimators.ekf_step import KIND_OK, KIND_SATURATED
from hbma_ctrl.estimators.mhe_settings import MHESettings
from hbma_ctrl.models.chamber import NX, STATE_SCALE, ObserverModel, min_pivot

__all__ = ["mhe_step_function", "linearise_function", "mhe_nlp", "lean_model", "lean_meas", "LIN_NAMES", "STEP_IN", "STEP_OUT",
           "TRUST", "H_MAX_REL", "state_bounds", "window_layout", "mhe_packed_function", "PACKED_OUT", "scales", "fresh_nodes", "QP_LIBS", "BOUND_TOL", "LEVENBERG"]

#: libraries a QP solver's generated C links (shipped inside the casadi package; qrqp's C is self-contained)
QP_LIBS = {"daqp": ["-ldaqp"], "osqp": ["-losqp"], "qrqp": []}
#: the largest change of one Gauss-Newton step, per unknown in the scaled coordinates (gas mass in
#: mg, load N, factors): the model switches between resting and contact inside a step, where its
#: linearisation is one-sided; a bounded step keeps one sample's iteration on the branch it started on
TRUST = (0.3, 1.0, 0.02, 0.02, 0.02)
#: the height of a node is at most H_MAX_REL r1: the membrane's far branch (past the pressure's maximum)
#: reaches any low pressure with a large enough cap, so readings near zero after a fast vent could be
#: explained by a cap growing without bound instead of the flat membrane; the protocol's caps stay below
#: 1.8 r1 (the 7.5 mm, 2 mm chamber with 200 g at full speed)
H_MAX_REL = 2.5
#: stands for an infinite constraint bound where the QP solver needs a finite one (scaled units)
_BIG = 1e6
#: the height rows are met with this margin (mm), beyond the QP solver's feasibility tolerance
ROW_MARGIN = 1e-5
#: a QP solution may leave its bounds by this much (scaled units) and still be used
BOUND_TOL = 1e-6
#: Levenberg term on the Gauss-Newton Hessian (scaled units): keeps it regular where an unknown is
#: not observed over the window (the load of a resting membrane has its arrival cost alone)
LEVENBERG = 1e-9

#: inputs and outputs of the step Function (see :func:`mhe_step_function`)
STEP_IN = ("M", "th", "S", "U", "Z", "kinds", "xbar", "P0", "theta", "fresh")
#: the stored linearisation, inputs after STEP_IN and outputs (``name_next``) after STEP_OUT
LIN_NAMES = ("XI", "FM", "AR", "XM", "PV", "HR", "HV", "DH", "RS")
STEP_OUT = ("M_next", "th_next", "S_next", "xbar_next", "P0_next", "est", "C", "cov", "status", "cost",
            "n_active")


def scales() -> np.ndarray:
    """The state's scales (kg, N, -, -, -): the unknowns are solved for in these units."""
    return np.asarray(STATE_SCALE, dtype=float)


def state_bounds(om: ObserverModel, s: FilterSettings) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of (m, W, b, k, c) in SI: the gas mass at least the ambient's (the gauge pressure is >= 0:
    the pump fills, the outlet vents to ambient, nothing draws a vacuum; so the resting membrane's
    contact force pi r1^2 p is >= 0), W in [0, load_max], factors in FACTOR_RANGE."""
    fr = getattr(om, "factor_ranges", None) or (FACTOR_RANGE,) * 3
    lo = np.array([om.m_env, 0.0] + [r[0] for r in fr])
    hi = np.array([50.0 * om.m_env, s.load_max] + [r[1] for r in fr])
    return lo, hi


def fresh_nodes(s: MHESettings) -> int:
    """The newest nodes the step linearises afresh (``relinearise``; 0: all N)."""
    return int(s.horizon) if s.relinearise == 0 else min(int(s.relinearise), int(s.horizon))


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


def lean_meas(om: ObserverModel) -> ca.Function:
    """The outputs of :func:`lean_model` without their covariance: ``mhe_meas(x, s, theta) -> (s_out,
    y, H, Dh)``, Dh the height's row of the outputs' Jacobian."""
    lean_model(om)
    return _LEAN_CACHE[id(om.predict)][3]


def _model_maps(om: ObserverModel, N: int) -> tuple[ca.Function, ca.Function]:
    """(predict, outputs without their covariance) of :func:`lean_model`, mapped over N nodes."""
    pred, _ = lean_model(om)
    return pred.map(N), lean_meas(om).map(N)


def _h_max(om: ObserverModel) -> ca.Function:
    """theta -> the largest node height (m), :data:`H_MAX_REL` r1 (or the model's own ``h_max_function``)."""
    if hasattr(om, "h_max_function"):
        return om.h_max_function()
    thp, Pd = om.chamber.symbols()
    return ca.Function("mhe_h_max", [thp], [H_MAX_REL * Pd["r1"]])


def _finite(e):
    return ca.fabs(ca.sum1(ca.sum2(e))) <= 1.7976931348623157e308


def _reading_terms(s: FilterSettings, p, rest, Z, kinds):
    """Per node: the whitened reading residual and its weight (1 / sigma, Huber-reweighted), the
    reading's variance R and the saturated reading's R_sat, and whether the reading counts."""
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
    used = ca.if_else(ok, 1.0, ca.if_else(w_sat, 1.0, 0.0))
    return rz, wz, R, R_sat, used


#: the unknowns with a known load: the load's entry of the state held out (its step 0)
_NO_LOAD = ca.DM([1.0, 0.0, 1.0, 1.0, 1.0])


def _condensed_data(om: ObserverModel, s: MHESettings, known_load: bool = False) -> ca.Function:
    """The five-unknown least-squares step from the window's linearisation (an SX Function): the
    Gauss-Newton Hessian and gradient in the scaled unknowns, their box (bounds within the trust
    region), the nodes' height rows (<= hmax, mm), the cost at the iterate, every node's gas mass and
    its sensitivity, the readings' variances."""
    N = int(s.horizon)
    sc = scales()
    lo, hi = state_bounds(om, s)
    SX = ca.SX
    m0, th, Z, kinds = SX.sym("m0"), SX.sym("th", 4), SX.sym("Z", N), SX.sym("kinds", N)
    xbar, P0 = SX.sym("xbar", NX), SX.sym("P0", NX, NX)
    FM, AR, XI = SX.sym("FM", N), SX.sym("AR", NX, N), SX.sym("XI", NX, N)
    PV, HR, XM = SX.sym("PV", N), SX.sym("HR", NX, N), SX.sym("XM", NX, N)
    HV, DH, RS = SX.sym("HV", N), SX.sym("DH", NX, N), SX.sym("RS", N)
    hmax = SX.sym("hmax")
    scth = ca.DM(sc[1:])
    # the window along the linearised recursion: node j's gas mass m_j and its row sm_j of
    # d m_j / d z (z the scaled unknowns); d theta / d z = diag(scales)
    m = m0
    sm = ca.horzcat(SX(sc[0]), SX.zeros(1, 4))
    ms, sms, ps, Jp, hs, Jh = [m], [sm], [], [], [], []
    for j in range(N):
        a = AR[:, j]
        m = FM[j] + a[0] * (m - XI[0, j]) + ca.dot(a[1:], th - XI[1:, j])
        sm = a[0] * sm + ca.horzcat(SX.zeros(1, 1), (a[1:] * scth).T)
        ms.append(m)
        sms.append(sm)
        hr, dh = HR[:, j], DH[:, j]
        dxm = ca.vertcat(m - XM[0, j], th - XM[1:, j])
        ps.append(PV[j] + ca.dot(hr, dxm))
        hs.append(HV[j] + ca.dot(dh, dxm))
        Jp.append(hr[0] * sm + ca.horzcat(SX.zeros(1, 1), (hr[1:] * scth).T))
        Jh.append(dh[0] * sm + ca.horzcat(SX.zeros(1, 1), (dh[1:] * scth).T))
    p, h = ca.vertcat(*ps), ca.vertcat(*hs)
    Mv, Sm = ca.vertcat(*ms), ca.vertcat(*sms)
    rz, wz, R, R_sat, used = _reading_terms(s, p, RS, Z, kinds)
    Jz = ca.vertcat(*Jp) * ca.repmat(wz, 1, 5)
    x0s = ca.vertcat(m0, th) / ca.DM(sc)
    r0 = x0s - xbar / ca.DM(sc)
    Pinv = ca.inv(P0 / ca.DM(np.outer(sc, sc)))
    Pinv = 0.5 * (Pinv + Pinv.T)
    Hq = Pinv + ca.mtimes(Jz.T, Jz) + LEVENBERG * SX.eye(5)
    Hq = 0.5 * (Hq + Hq.T)
    g = ca.mtimes(Pinv, r0) + ca.mtimes(Jz.T, rz)
    cost = 0.5 * (ca.mtimes([r0.T, Pinv, r0]) + ca.sumsqr(rz))
    zlo, zhi = lo / sc, hi / sc
    tr = ca.DM(TRUST)
    lbx = ca.fmax(ca.DM(zlo) - x0s, -tr)
    ubx = ca.fmin(ca.DM(zhi) - x0s, tr)
    # a start outside its bounds (a prior off them) is brought back within one step
    lbx = ca.fmin(lbx, ubx)
    if known_load:
        lbx, ubx = lbx * _NO_LOAD, ubx * _NO_LOAD
    # the height rows (mm: the QP solver's tolerances are absolute), met with ROW_MARGIN; a row the box
    # cannot meet is relaxed to the box's best (brought back over the next steps). The nodes' gas masses
    # need no rows: the model's vent stops at the ambient pressure, and the first node's is in the box
    A = ca.vertcat(*Jh) * 1e3
    best_hi = ca.sum2(ca.fmin(A * ca.repmat(lbx.T, N, 1), A * ca.repmat(ubx.T, N, 1)))
    lba = -_BIG * ca.DM.ones(N)
    uba = ca.fmax((hmax - h) * 1e3 - ROW_MARGIN, best_hi)
    return ca.Function("mhe_qp_data", [m0, th, Z, kinds, xbar, P0, FM, AR, XI, PV, HR, XM, HV, DH, RS, hmax],
                       [Hq, g, lbx, ubx, A, lba, uba, cost, Mv, Sm, R, used, R_sat],
                       ["m0", "th", "Z", "kinds", "xbar", "P0", "FM", "AR", "XI", "PV", "HR", "XM", "HV", "DH", "RS",
                        "hmax"],
                       ["Hq", "g", "lbx", "ubx", "A", "lba", "uba", "cost", "M", "Sm", "R", "used", "R_sat"],
                       {"cse": True})


def _nodes(M, th, WL):
    """The states (5 x nodes) of gas masses M (a row) and the window's th = (W, b, k, c); with a known
    load the nodes' own loads WL (a row) replace W."""
    n = M.size2()
    if WL is None:
        return ca.vertcat(M, ca.repmat(th, 1, n))
    return ca.vertcat(M, WL, ca.repmat(th[1:], 1, n))


def _without_load(a, known_load: bool):
    """Rows (5 x n) of a linearisation with the load's row zeroed when the load is known."""
    return a * ca.repmat(_NO_LOAD, 1, a.size2()) if known_load else a


def mhe_step_function(om: ObserverModel, s: MHESettings, known_load: bool = False) -> ca.Function:
    """One real-time iteration of the MHE as one casadi Function (numeric, C-generable).

    Inputs (SI; N = ``s.horizon``): ``M`` (N + 1) the nodes' gas masses (kg, reduced as the EKF's
    state), ``th`` (4) the window's (W, b, k, c), ``S`` (2 x (N + 1)) the nodes' shape warm starts
    (h1, h2, m), ``U`` (3 x N) the commands acting over the N intervals, ``Z`` (N) the readings of
    nodes 1..N (Pa) and ``kinds`` (N) their kinds (:data:`hbma_ctrl.estimators.ekf_step.KIND_OK`, ``KIND_NONE``,
    ``KIND_SATURATED``), ``xbar`` (5) and ``P0`` (5 x 5) the arrival cost's mean and covariance at
    node 0, ``theta`` the model's parameters, ``fresh`` 1 when node N is new (its gas mass is then
    predicted from node N - 1 before the step); then the stored linearisation (:data:`LIN_NAMES`).

    Outputs: the nodes (the recursion from the new first state) and parameters after the step, the
    shapes, the arrival cost of the next window's node 0 (this window's node 1), ``est`` = (h1, h2, h,
    F, p) at node N, C their covariance, ``cov`` the covariance of node N's state (5 x 5, from the
    Gauss-Newton Hessian), ``status`` (0 ok, 1 non-finite, 2 the QP solution off its bounds), ``cost``
    (the window's cost before the step) and ``n_active`` (unknowns at a bound or at the trust region
    after the step); then the linearisation to store (``name_next``).

    With ``known_load`` (module docstring) a last input ``WL`` (N + 1) gives the nodes' loads (N); th's
    load entry is then not used, and the outputs report node N's load WL_N.
    """
    s = s.validate()
    N = int(s.horizon)
    nt = int(np.asarray(om.theta).size)
    sc = scales()
    _, out1 = lean_model(om)
    MX = ca.MX
    M, th, S, U = MX.sym("M", N + 1), MX.sym("th", 4), MX.sym("S", 2, N + 1), MX.sym("U", 3, N)
    Z, kinds = MX.sym("Z", N), MX.sym("kinds", N)
    xbar, P0 = MX.sym("xbar", NX), MX.sym("P0", NX, NX)
    theta, fresh = MX.sym("theta", nt), MX.sym("fresh")
    WL = MX.sym("WL", N + 1) if known_load else None
    WLr = WL.T if known_load else None
    TH = ca.repmat(theta, 1, N)
    L = fresh_nodes(s)
    pm_L, om_L = _model_maps(om, L)
    # the newest L intervals linearised afresh; the last one's prediction is the new node N (its gas
    # mass and shape); the interval ending at node j is predicted at node j's load
    XL = _nodes(M[N - L:N].T, th, WLr[:, N - L + 1:] if known_load else None)
    xnf, Af, snf = pm_L(XL, S[:, N - L:N], U[:, N - L:], TH[:, :L])
    mN = ca.if_else(fresh > 0.5, xnf[0, L - 1], M[N])
    sN = ca.if_else(fresh > 0.5, snf[:, L - 1], S[:, N])
    M1 = ca.vertcat(M[:N], mN)
    S1 = ca.horzcat(S[:, :N], sN)
    X = _nodes(M1.T, th, WLr)  # 5 x (N + 1)
    # the intervals' points: each at the load of the node it ends at
    XIv = _nodes(M1[:N].T, th, WLr[:, 1:] if known_load else None)
    # the stored linearisation of the intervals (points XI, values FM, rows AR of d m_next / d x) and of
    # the nodes 1..N (points XM, pressure PV, its row HR, height HV, its row DH, rest RS)
    XI, FM, AR = MX.sym("XI", NX, N), MX.sym("FM", 1, N), MX.sym("AR", NX, N)
    XM, PV, HR = MX.sym("XM", NX, N), MX.sym("PV", 1, N), MX.sym("HR", NX, N)
    HV, DHs, RS = MX.sym("HV", 1, N), MX.sym("DH", NX, N), MX.sym("RS", 1, N)
    lin_in = [XI, FM, AR, XM, PV, HR, HV, DHs, RS]
    sof, yf, Hf, Dhf = om_L(X[:, N - L + 1:], S1[:, N - L + 1:], TH[:, :L])
    old = N - L  # the nodes that keep their linearisation
    FMn = ca.horzcat(FM[:, :old], xnf[0, :])
    ARn = ca.horzcat(AR[:, :old], _without_load(ca.reshape(Af[0, :], NX, L), known_load))
    XIn = ca.horzcat(XI[:, :old], XIv[:, old:N])
    PVn = ca.horzcat(PV[:, :old], yf[4, :])
    HRn = ca.horzcat(HR[:, :old], _without_load(ca.reshape(Hf, NX, L), known_load))
    HVn = ca.horzcat(HV[:, :old], yf[2, :])
    DHn = ca.horzcat(DHs[:, :old], _without_load(ca.reshape(Dhf, NX, L), known_load))
    RSn = ca.horzcat(RS[:, :old], yf[5, :])
    XMn = ca.horzcat(XM[:, :old], X[:, old + 1:])
    lin_out = [XIn, FMn, ARn, XMn, PVn, HRn, HVn, DHn, RSn]
    so = ca.horzcat(S1[:, 1:old + 1], sof)
    hmax = _h_max(om)(theta)
    data = _condensed_data(om, s, known_load)
    Hm, gm, lbm, ubm, Am, lbam, ubam, costm, Mv, Sm, Rm, usedm, Rsatm = data(
        M1[0], th, Z, kinds, xbar, P0, FMn.T, ARn, XIn, PVn.T, HRn, XMn, HVn.T, DHn, RSn.T, hmax)
    qp = ca.conic("mhe_qp", s.qp_solver, {"h": ca.Sparsity.dense(5, 5), "a": ca.Sparsity.dense(N, 5)},
                  _qp_opts(s.qp_solver))
    sol = qp(h=Hm, g=gm, lbx=lbm, ubx=ubm, a=Am, lba=lbam, uba=ubam)
    dz = sol["x"]
    # --- after the step: nodes, arrival update, newest node's outputs and covariance
    # within the bounds: the QP solution may leave them by its tolerance (a load of -1e-17 N puts the
    # model's contact on its regularised side)
    lo, hi = state_bounds(om, s)
    M_new = ca.fmax(Mv + ca.mtimes(Sm, dz), lo[0])
    th_new = ca.fmin(ca.fmax(th + dz[1:] * ca.DM(sc[1:]), ca.DM(lo[1:])), ca.DM(hi[1:]))
    # off the box (scaled units) or a height above its row (mm)
    off = ca.fmax(ca.fmax(ca.mmax(dz - ubm), ca.mmax(lbm - dz)), ca.mmax(ca.mtimes(Am, dz) - ubam))
    active = ca.sum1((dz - lbm <= 1e-9) + (ubm - dz <= 1e-9))
    # arrival: the EKF's step from the arrival mean (not from the window's node 0, which already holds
    # the window's readings: taken as the next prior, they would count twice and drag the parameters
    # along), linearised along the window (node 0's interval and node 1's reading): predict with Q as
    # the EKF's, then the Joseph-form update with node 1's reading
    x0o = ca.vertcat(M1[0], th)
    fm0 = FMn[0] + ca.dot(ARn[:, 0], x0o - XIn[:, 0])
    A0 = ca.vertcat(ARn[:, 0].T, ca.horzcat(MX.zeros(NX - 1, 1), MX.eye(NX - 1)))
    xn0 = ca.vertcat(fm0, th)
    H1 = HRn[:, 0].T
    x1o = ca.vertcat(M1[1], th)
    y1p = PVn[0] + ca.dot(HRn[:, 0], x1o - XMn[:, 0])
    xm = xn0 + ca.mtimes(A0, xbar - x0o)
    Q = ca.diag(ca.vertcat((s.flow_rel_std * (fm0 - M1[0])) ** 2 + s.walk_var()[0], *s.walk_var()[1:]))
    Pm = ca.mtimes([A0, P0, A0.T]) + Q
    p1 = y1p + ca.mtimes(H1, xm - x1o)
    z1 = ca.if_else(kinds[0] == KIND_SATURATED, s.sensor_range, Z[0])
    R1 = ca.if_else(kinds[0] == KIND_SATURATED, Rsatm[0], Rm[0])
    Sv = ca.mtimes([H1, Pm, H1.T]) + R1
    K = usedm[0] * ca.mtimes(Pm, H1.T) / Sv
    IKH = MX.eye(NX) - ca.mtimes(K, H1)
    Pp = ca.mtimes([IKH, Pm, IKH.T]) + R1 * ca.mtimes(K, K.T)
    Pp = 0.5 * (Pp + Pp.T)
    xbar_next = xm + K * (z1 - p1)
    # the newest node: x_N = (m_N, theta) is affine in the unknowns, its covariance T Hq^-1 T^T
    TN = ca.vertcat(Sm[N, :], ca.horzcat(MX.zeros(4, 1), ca.diag(ca.DM(sc[1:]))))
    covN = ca.mtimes([TN, ca.solve(Hm, TN.T, "ldl")])
    covN = 0.5 * (covN + covN.T)
    if known_load:
        th_new = ca.vertcat(WL[N], th_new[1:])
    xN = ca.vertcat(M_new[N], th_new)
    s_out, yN, _, CN = out1(xN, so[:, N - 1], theta, covN)
    S_next = ca.horzcat(S1[:, 0], so[:, :N - 1], s_out)
    finite = _finite(ca.vertcat(dz, yN, ca.vec(Pp), xbar_next, ca.vec(covN)))
    status = ca.if_else(finite, ca.if_else(off <= BOUND_TOL, 0.0, 2.0), 1.0)
    # within the shape's constraints: h2 in [0, h1], h and F at least 0 (the shape's projection from
    # its warm start leaves h2 within nanometres of 0 on a free cap, where the contact condition's
    # regularising stiffness makes F = EPS_K h2, micronewtons, and a few micrometres off a membrane
    # that is about flat)
    est = ca.vertcat(yN[0], ca.fmin(ca.fmax(yN[1], 0.0), ca.fmax(yN[0], 0.0)), ca.fmax(yN[2], 0.0),
                     ca.fmax(yN[3], 0.0), yN[4])
    extra = [WL] if known_load else []
    return ca.Function("mhe_step", [M, th, S, U, Z, kinds, xbar, P0, theta, fresh] + lin_in + extra,
                       [M_new, th_new, S_next, xbar_next, Pp, est, CN, covN, status, costm, active] + lin_out,
                       list(STEP_IN) + list(LIN_NAMES) + ["WL"] * known_load,
                       list(STEP_OUT) + [n + "_next" for n in LIN_NAMES])


def linearise_function(om: ObserverModel, N: int, known_load: bool = False) -> ca.Function:
    """The window's whole linearisation (the step's stored inputs :data:`LIN_NAMES`) at nodes M, th,
    shapes S and commands U (and, ``known_load``, the nodes' loads WL, N): what the step keeps for the
    nodes it does not linearise afresh."""
    pred_map, out_map = _model_maps(om, N)
    nt = int(np.asarray(om.theta).size)
    M, th, S, U, theta = (ca.MX.sym(n, *sh) for n, sh in (("M", (N + 1, 1)), ("th", (4, 1)), ("S", (2, N + 1)),
                                                            ("U", (3, N)), ("theta", (nt, 1))))
    WLc = ca.MX.sym("WL", N + 1)
    WL = WLc.T if known_load else None
    X = _nodes(M.T, th, WL)
    XI = _nodes(M[:N].T, th, WL[:, 1:] if known_load else None)
    TH = ca.repmat(theta, 1, N)
    xn, A, _ = pred_map(XI, S[:, :N], U, TH)
    _, y, H, Dh = out_map(X[:, 1:], S[:, 1:], TH)
    outs = [XI, xn[0, :], _without_load(ca.reshape(A[0, :], NX, N), known_load), X[:, 1:], y[4, :],
            _without_load(ca.reshape(H, NX, N), known_load), y[2, :],
            _without_load(ca.reshape(Dh, NX, N), known_load), y[5, :]]
    ins = [M, th, S, U, theta] + ([WLc] if known_load else [])
    return ca.Function("mhe_linearise", ins, outs, ["M", "th", "S", "U", "theta"] + ["WL"] * known_load,
                       list(LIN_NAMES))


def _qp_opts(qp_solver: str) -> dict:
    if qp_solver == "daqp":
        return {"error_on_fail": False}
    if qp_solver == "qrqp":
        return {"print_iter": False, "print_header": False, "print_info": False, "error_on_fail": False,
                "max_iter": 200}
    return {"osqp": {"verbose": False, "eps_abs": 1e-8, "eps_rel": 1e-8, "max_iter": 4000, "polish": True},
            "error_on_fail": False}


def mhe_nlp(om: ObserverModel, s: MHESettings, known_load: bool = False) -> ca.Function:
    """The window's full problem for IPOPT, ``(M, th, S, U, Z, kinds, xbar, P0, theta) -> (M_next,
    th_next, cost)``: the same unknowns, cost and bounds as :func:`mhe_step_function`, the model exact
    along the window (its recursion from the first state, no linearisation), no trust region; ``M``
    and ``th`` the start, ``S`` the shapes' warm starts. With ``known_load`` a last input ``WL``
    (N + 1) gives the nodes' loads, N, and th's load is held."""
    s = s.validate()
    N = int(s.horizon)
    nt = int(np.asarray(om.theta).size)
    sc = scales()
    lo, hi = state_bounds(om, s)
    pred1, _ = lean_model(om)
    meas = lean_meas(om)
    MX = ca.MX
    zv = MX.sym("z", 5)
    S, U, Z, kinds = MX.sym("S", 2, N + 1), MX.sym("U", 3, N), MX.sym("Z", N), MX.sym("kinds", N)
    xbar, P0, theta = MX.sym("xbar", NX), MX.sym("P0", NX, NX), MX.sym("theta", nt)
    WL = MX.sym("WL", N + 1)
    x0 = zv * ca.DM(sc)
    th = x0[1:]
    ms, ps, rests, hs = [x0[0]], [], [], []
    x = x0

    def at(m, j):  # node j's state
        return ca.vertcat(m, WL[j], th[1:]) if known_load else ca.vertcat(m, th)

    for j in range(N):
        xn = pred1(at(x[0], j + 1), S[:, j], U[:, j], theta)[0]
        x = at(xn[0], j + 1)
        ms.append(xn[0])
        y = meas(x, S[:, j + 1], theta)[1]
        ps.append(y[4])
        hs.append(y[2])
        rests.append(y[5])
    p, h = ca.vertcat(*ps), ca.vertcat(*hs)
    ok = kinds == KIND_OK
    sat = kinds == KIND_SATURATED
    rel = ca.if_else(ca.vertcat(*rests) > 0.5, 0.0, s.model_rel_std)
    R = s.noise_std ** 2 + (rel * ca.fmax(p, 0.0)) ** 2
    R_sat = s.saturation_std ** 2 + s.noise_std ** 2 + (rel * s.sensor_range) ** 2
    rz = ca.if_else(ok, (p - Z) / ca.sqrt(R), ca.if_else(sat, ca.fmin(p - s.sensor_range, 0.0) / ca.sqrt(R_sat), 0.0))
    # Huber's loss (huber sigmas), the same as the RTI step's
    lz = rz ** 2 if s.huber <= 0 else ca.if_else(ca.fabs(rz) <= s.huber, rz ** 2,
                                                 2 * s.huber * ca.fabs(rz) - s.huber ** 2)
    r0 = zv - xbar / ca.DM(sc)
    # the inverse as an SX Function: the whole problem expands to SX (evaluated much faster than MX)
    Ps = ca.SX.sym("P", NX, NX)
    Pinv = ca.Function("mhe_inv", [Ps], [ca.inv(Ps)])(P0 / ca.DM(np.outer(sc, sc)))
    f = 0.5 * (ca.mtimes([r0.T, Pinv, r0]) + ca.sum1(lz))
    Mv = ca.vertcat(*ms)
    hmax = _h_max(om)(theta)
    par = ca.vertcat(ca.vec(S), ca.vec(U), Z, kinds, xbar, ca.vec(P0), theta, WL)
    opts = {"ipopt": {"print_level": 0, "max_iter": s.ipopt_iter, "tol": 1e-8, "hessian_approximation": "limited-memory"},
            "print_time": False, "error_on_fail": False, "expand": True}
    solver = ca.nlpsol("mhe_ipopt", "ipopt", {"x": zv, "f": f, "p": par, "g": h - hmax},
                       opts)
    Min, thin, WLin = MX.sym("M", N + 1), MX.sym("th", 4), MX.sym("WL", N + 1)
    z0 = ca.vertcat(Min[0], thin) / ca.DM(sc)
    zlo, zhi = ca.DM(lo / sc), ca.DM(hi / sc)
    z0 = ca.fmin(ca.fmax(z0, zlo), zhi)
    if known_load:  # the load held where it starts
        zlo = ca.vertcat(zlo[0], z0[1], zlo[2:])
        zhi = ca.vertcat(zhi[0], z0[1], zhi[2:])
    WLv = WLin if known_load else ca.DM.zeros(N + 1)
    sol = solver(x0=z0, lbx=zlo, ubx=zhi, lbg=-ca.inf, ubg=0.0,
                 p=ca.vertcat(ca.vec(S), ca.vec(U), Z, kinds, xbar, ca.vec(P0), theta, WLv))
    zs = sol["x"]
    Msol = ca.Function("mhe_traj", [zv, S, U, theta, WL], [Mv])(zs, S, U, theta, WLv)
    extra = [WLin] if known_load else []
    return ca.Function("mhe_ipopt_step", [Min, thin, S, U, Z, kinds, xbar, P0, theta] + extra,
                       [Msol, zs[1:] * ca.DM(sc[1:]), sol["f"]],
                       ["M", "th", "S", "U", "Z", "kinds", "xbar", "P0", "theta"] + ["WL"] * known_load,
                       ["M_next", "th_next", "cost"])


def window_layout(N: int, known_load: bool = False) -> list[tuple[str, tuple[int, int]]]:
    """The window as one flat vector (each part column-major, in this order): the step's inputs
    :data:`STEP_IN` without ``theta`` and ``fresh``, then the stored linearisation :data:`LIN_NAMES`
    (then, ``known_load``, the nodes' loads ``WL``); (name, (rows, columns)) per part."""
    return [("M", (N + 1, 1)), ("th", (4, 1)), ("S", (2, N + 1)), ("U", (3, N)), ("Z", (N, 1)), ("kinds", (N, 1)),
            ("xbar", (NX, 1)), ("P0", (NX, NX)), ("XI", (NX, N)), ("FM", (1, N)), ("AR", (NX, N)), ("XM", (NX, N)),
            ("PV", (1, N)), ("HR", (NX, N)), ("HV", (1, N)), ("DH", (NX, N)), ("RS", (1, N))] + \
        [("WL", (N + 1, 1))] * known_load


#: outputs of the packed step (:func:`mhe_packed_function`): :data:`STEP_OUT`, then these
PACKED_OUT = STEP_OUT + ("window_next", "P0_pivot", "x_new", "std")


def mhe_packed_function(om: ObserverModel, s: MHESettings, known_load: bool = False) -> ca.Function:
    """:func:`mhe_step_function` on the window as one flat vector (:func:`window_layout`), shifted by
    one sample inside: ``(window, sample, theta) -> outputs`` (:data:`PACKED_OUT`), ``sample`` = (the
    command acting over the newest interval (3), the newest reading (Pa), its kind). ``window_next``
    is the next step's window; ``P0_pivot`` the next arrival covariance's smallest pivot above the
    floor (:func:`hbma_ctrl.models.chamber.min_pivot`: <= 0 when it needs the floor), ``x_new`` node
    N's state and ``std`` the outputs' standard deviations. With ``known_load`` the sample has a sixth
    entry, the newest node's load (N)."""
    s = s.validate()
    N = int(s.horizon)
    nt = int(np.asarray(om.theta).size)
    lay = window_layout(N, known_load)
    size = sum(r * c for _, (r, c) in lay)
    W, new, theta = ca.MX.sym("window", size), ca.MX.sym("sample", 5 + known_load), ca.MX.sym("theta", nt)
    parts, i = {}, 0
    for name, (r, c) in lay:
        parts[name] = ca.reshape(W[i:i + r * c], r, c)
        i += r * c

    def shifted(a, last):
        return ca.horzcat(a[:, 1:], last) if a.size2() > 1 else ca.vertcat(a[1:], last)

    win = dict(parts)
    win["M"] = ca.vertcat(parts["M"][1:], parts["M"][N])
    win["S"] = ca.horzcat(parts["S"][:, 1:], parts["S"][:, N])
    win["U"] = shifted(parts["U"], new[:3])
    win["Z"] = ca.vertcat(parts["Z"][1:], new[3])
    win["kinds"] = ca.vertcat(parts["kinds"][1:], new[4])
    for name in LIN_NAMES:
        a = parts[name]
        win[name] = ca.horzcat(a[:, 1:], a[:, N - 1])
    if known_load:
        win["WL"] = ca.vertcat(parts["WL"][1:], new[5])
    step = mhe_step_function(om, s, known_load)
    args = [win[n] for n in STEP_IN[:8]] + [theta, 1.0] + [win[n] for n in LIN_NAMES] + \
        ([win["WL"]] if known_load else [])
    out = step.call(args)
    res = dict(zip(list(STEP_OUT) + list(LIN_NAMES), out))
    nxt = {"M": res["M_next"], "th": res["th_next"], "S": res["S_next"], "U": win["U"], "Z": win["Z"],
           "kinds": win["kinds"], "xbar": res["xbar_next"], "P0": res["P0_next"]}
    nxt.update({n: res[n] for n in LIN_NAMES})
    if known_load:
        nxt["WL"] = win["WL"]
    W_next = ca.vertcat(*[ca.vec(nxt[n]) for n, _ in lay])
    Ps = ca.SX.sym("P", NX, NX)
    piv = ca.Function("mhe_pivot", [Ps], [min_pivot(Ps, s.cov_floor)])(res["P0_next"])
    x_new = ca.vertcat(res["M_next"][N], res["th_next"])
    std = ca.sqrt(ca.fmax(ca.diag(res["C"]), 0.0))
    return ca.Function("mhe_packed", [W, new, theta], list(out[:len(STEP_OUT)]) + [W_next, piv, x_new, std],
                       ["window", "sample", "theta"], list(PACKED_OUT))
