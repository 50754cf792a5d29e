"""The chamber NMPC's real-time-iteration step as ONE casadi Function (shift, linearisation, QP, solve).

:func:`rti_step_function` builds a Function that does everything one RTI step of
:class:`controllers.mpc.NMPC` does: it shifts the previous plan by one stage, linearises the
gas-mass dynamics and the outputs along it (the same ``_Stage.lin`` as the reference
``rti_osqp`` path), assembles the same sparse QP (cost, dynamics, input box and rates,
"speed <= inlet", soft pressure / stretch / height limits; see :mod:`controllers.mpc`), solves it
inside casadi through its conic interface (``qrqp``, ``hpipm``, ``osqp``, ``daqp``: the
``qp_solver`` argument) and returns the first input and the new plan. Everything is numeric, so the
Function can be code-generated to C (``qrqp`` generates self-contained C; ``hpipm`` needs the
hpipm/blasfeo headers and libraries shipped inside the casadi package; ``osqp`` those of OSQP)
and the Python controller calls exactly this Function (see ``controllers.mpc_solvers._RtiCompiled``).

Signature (N = ``settings.horizon``; every argument a dense column, SI unless said)
------------------------------------------------------------------------------------
Inputs:

============  =========  ===========================================================================
``x0``        1          initial state estimate: scaled gas mass (-)
``W``         1          load on the platform, N
``dh``        1          output bias of the height (estimate minus model), m
``dp``        1          output bias of the pressure, Pa
``u_prev``    3          command applied last period (speed, inlet, outlet), each in [0, 1]
``p_lim``     1          limit on the predicted pressure (model + dp), Pa
``r``         N          target heights at stages 1..N (already clipped to the reachable range), m
``X_guess``   N + 1      previous state plan (primal guess)
``U_guess``   3 x N      previous input plan (primal guess), column k = u_k
``shift``     1          1: a new step (the guess is shifted by one stage); 0: another iteration at
                         the same time (the guess is used as is; cold start)
============  =========  ===========================================================================

Outputs:

============  =========  ===========================================================================
``u0``        3          first input (speed, inlet, outlet) clipped to [0, 1]
``X_plan``    N + 1      new state plan (the next call's ``X_guess``)
``U_plan``    3 x N      new input plan, clipped to [0, 1] (the next call's ``U_guess``)
``status``    1          0: ok; 1: non-finite linearisation or solution; 2: the QP solution violates
                         its constraints by more than ``_RES_TOL`` (solver failure)
``residual``  1          largest constraint violation of the QP solution (QP units: kPa, mm, ...)
============  =========  ===========================================================================
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from controllers.mpc_settings import MPCSettings
from controllers.mpc_solvers import _Stage
from hbma_ctrl.models.tables import PredictionModel

__all__ = ["QP_SOLVERS", "rti_step_function"]

#: conic plugins the step can be built with (the first is the default)
QP_SOLVERS = ("qrqp", "hpipm", "osqp", "daqp")

_IN = ["x0", "W", "dh", "dp", "u_prev", "p_lim", "r", "X_guess", "U_guess", "shift"]
_OUT = ["u0", "X_plan", "U_plan", "status", "residual"]
#: largest constraint violation of a usable QP solution (QP units; as the OSQP path's acceptance)
_RES_TOL = 1e-3


def _solver_opts(qp_solver: str, s: MPCSettings) -> dict:
    if qp_solver == "qrqp":
        return {"print_iter": False, "print_header": False, "print_info": False, "error_on_fail": False,
                "max_iter": 1000}
    if qp_solver == "osqp":
        return {"osqp": {"verbose": False, "eps_abs": s.qp_eps, "eps_rel": s.qp_eps, "max_iter": s.qp_max_iter,
                         "polish": False}, "error_on_fail": False, "warm_start_primal": True}
    if qp_solver == "hpipm":
        return {"error_on_fail": False}
    return {"error_on_fail": False}


def rti_step_function(model: PredictionModel, settings: MPCSettings, qp_solver: str = "qrqp") -> ca.Function:
    """The RTI step of the chamber NMPC as one casadi Function (signature in the module docstring).

    ``model``: the controller's :class:`PredictionModel`; ``settings``: its :class:`MPCSettings`
    (validated here); ``qp_solver``: one of :data:`QP_SOLVERS`. ValueError on an unknown solver or
    one this casadi build lacks.
    """
    s = settings.validate()
    if qp_solver not in QP_SOLVERS:
        raise ValueError(f"rti_step.qp_solver = '{qp_solver}'; allowed: {', '.join(QP_SOLVERS)}")
    if not ca.has_conic(qp_solver):
        raise ValueError(f"rti_step.qp_solver = '{qp_solver}': this casadi build has no such conic plugin")
    N = s.horizon
    stage = _Stage(model, s)
    SX = ca.SX
    x0, W, dh, dp, p_lim, shift = (SX.sym(n) for n in ("x0", "W", "dh", "dp", "p_lim", "shift"))
    u_prev, r = SX.sym("u_prev", 3), SX.sym("r", N)
    Xg, Ug = SX.sym("X", N + 1), SX.sym("U", 3, N)
    # --- shift (shift = 1) or keep (shift = 0) the guess; the first state is always the estimate
    Xs = ca.vertcat(Xg[2:], Xg[N])
    Xb = ca.vertcat(x0, shift * Xs + (1 - shift) * Xg[1:])
    Ub = shift * ca.horzcat(Ug[:, 1:], Ug[:, N - 1]) + (1 - shift) * Ug
    # --- linearisation at the N + 1 nodes
    Uext = ca.horzcat(Ub, Ub[:, N - 1])
    fl = s.rti_lin_floor
    lin = [stage.lin(Xb[k], Uext[:, k], ca.vertcat(ca.fmax(Uext[0, k], fl), ca.fmax(Uext[1, k], fl), Uext[2, k]),
                     W, dp) for k in range(N + 1)]
    f, a, b, h, ch, p, cp, lam, cl = ([ln[i] for ln in lin] for i in range(9))
    # --- variables, as the reference path: z = [x_0..x_N, u_0..u_{N-1} (3 each), s_1..s_N]
    nx, nu = N + 1, 3 * N
    nz = nx + nu + N
    ix = list(range(nx))
    iu = [[nx + 3 * k + i for i in range(3)] for k in range(N)]
    isl = [nx + nu + k for k in range(N)]
    # --- cost 1/2 z'Hz + g'z
    wk = [0.0] + [s.w_height] * N
    wk[N] += s.w_terminal
    dh_mm = dh * 1e3
    r_mm = ca.vertcat(r[0], r) * 1e3
    H = SX(nz, nz)
    g = SX.zeros(nz)
    for k in range(nx):
        e = h[k] - ch[k] * Xb[k] + dh_mm - r_mm[k]
        H[ix[k], ix[k]] = 2 * wk[k] * ch[k] ** 2 + 1e-8
        g[ix[k]] = 2 * wk[k] * ch[k] * e
    wr, wu, cu = (np.array(v, float) for v in (s.w_rate, s.w_input, s.c_input))
    for k in range(N):
        nd = 2 if k < N - 1 else 1  # u_k appears in (u_k - u_{k-1}) and (u_{k+1} - u_k)
        for i in range(3):
            H[iu[k][i], iu[k][i]] = 2 * wr[i] * nd + 2 * wu[i] + 1e-8
            if k > 0:
                H[iu[k - 1][i], iu[k][i]] = -2 * wr[i]
                H[iu[k][i], iu[k - 1][i]] = -2 * wr[i]
            g[iu[k][i]] = cu[i] - (2 * wr[i] * u_prev[i] if k == 0 else 0.0)
    for k in range(N):
        H[isl[k], isl[k]] = 2 * s.w_slack
        g[isl[k]] = s.c_slack
    # --- simple bounds: x_0 fixed, u box (u_0 also within the rate limit of u_prev), s >= 0
    inf = ca.inf
    umax = np.array(s.u_max, float)
    du = np.array(s.du_max, float) * s.sample_period
    lbx = [x0] + [-inf] * N
    ubx = [x0] + [inf] * N
    for k in range(N):
        for i in range(3):
            lbx.append(ca.fmax(0.0, u_prev[i] - du[i]) if k == 0 else 0.0)
            ubx.append(ca.fmin(umax[i], u_prev[i] + du[i]) if k == 0 else umax[i])
    lbx += [0.0] * N
    ubx += [inf] * N
    # --- linear constraints lba <= A z <= uba
    rows, lba, uba = [], [], []

    def row(entries, lo, up):
        rows.append(entries)
        lba.append(lo)
        uba.append(up)

    for k in range(N):  # x_{k+1} - a x_k - b u_k = f - a xb - b ub
        c = f[k] - a[k] * Xb[k] - ca.mtimes(b[k], Ub[:, k])
        row([(ix[k + 1], 1.0), (ix[k], -a[k])] + [(iu[k][i], -b[k][i]) for i in range(3)], c, c)
    for k in range(1, N):
        for i in range(3):
            row([(iu[k][i], 1.0), (iu[k - 1][i], -1.0)], -du[i], du[i])
    for k in range(N):  # inlet - speed >= 0
        row([(iu[k][1], 1.0), (iu[k][0], -1.0)], 0.0, inf)
    for k in range(N):  # soft limits at stage k + 1
        j = k + 1
        row([(ix[j], cp[j]), (isl[k], -1.0)], -inf, p_lim * 1e-3 - dp * 1e-3 - (p[j] - cp[j] * Xb[j]))
        row([(ix[j], cl[j]), (isl[k], -1.0)], -inf, s.lam_max * 1e2 - (lam[j] - cl[j] * Xb[j]))
        row([(ix[j], ch[j]), (isl[k], -1.0)], -inf, s.h_max * 1e3 - dh_mm - (h[j] - ch[j] * Xb[j]))
        if s.h_min > 0:  # (below lift-off H is a virtual negative height: no bound at h_min = 0)
            row([(ix[j], -ch[j]), (isl[k], -1.0)], -inf, -(s.h_min * 1e3 - dh_mm - (h[j] - ch[j] * Xb[j])))
    nc = len(rows)
    A = SX(nc, nz)
    for rr, entries in enumerate(rows):
        for col, v in entries:
            A[rr, col] = v
    Hsp, Asp = H.sparsity(), A.sparsity()
    z0 = ca.vertcat(Xb, ca.vec(Ub), SX.zeros(N))
    lbx, ubx, lba, uba = (ca.vertcat(*v) for v in (lbx, ubx, lba, uba))
    ins = [x0, W, dh, dp, u_prev, p_lim, r, Xg, Ug, shift]
    data = ca.Function("rti_qp_data", ins, [H, g, A, lba, uba, lbx, ubx, z0, ca.vertcat(*f, *ch, *a, *cp)])
    post_z = SX.sym("z", nz)
    Xn = post_z[:nx]
    Un = ca.fmin(ca.fmax(ca.reshape(post_z[nx:nx + nu], 3, N), 0.0), 1.0)
    viol = ca.vertcat(ca.fmax(lbx - post_z, 0), ca.fmax(post_z - ubx, 0),
                      ca.fmax(lba - ca.mtimes(A, post_z), 0), ca.fmax(ca.mtimes(A, post_z) - uba, 0))
    # an infinite bound gives fmax(-inf, 0) = 0: only finite violations count
    res = ca.mmax(viol)
    chk = SX.sym("chk", 4 * (N + 1))
    finite = ca.logic_and(ca.sumsqr(post_z) < inf, ca.sumsqr(chk) < inf)
    status = ca.if_else(finite, ca.if_else(res <= _RES_TOL, 0.0, 2.0), 1.0)
    post = ca.Function("rti_post", [post_z, chk] + ins, [Un[:, 0], Xn, Un, status, res])
    # --- the MX wrapper: data -> conic -> post
    qp = ca.conic("rti_qp", qp_solver, {"h": Hsp, "a": Asp}, _solver_opts(qp_solver, s))
    mx = [ca.MX.sym(n, *v.shape) for n, v in zip(_IN, ins)]
    Hm, gm, Am, lbam, ubam, lbxm, ubxm, z0m, chkm = data(*mx)
    sol = qp(h=Hm, g=gm, a=Am, lba=lbam, uba=ubam, lbx=lbxm, ubx=ubxm, x0=z0m)
    outs = post(sol["x"], chkm, *mx)
    return ca.Function("rti_step", mx, list(outs), _IN, _OUT)

