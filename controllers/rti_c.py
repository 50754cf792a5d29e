"""The chamber RTI step with its QP data as ONE generated-C call and OSQP kept set up (``rti_c_osqp``).

Why: in the reference RTI path (``rti_osqp``, :class:`hbma_ctrl.controllers.mpc_solvers._RtiOsqp`) most of a
step is not the QP solve but building the QP around it: a casadi call with numpy arguments (tens
of microseconds) and some forty numpy operations on small arrays. Solving the QP inside casadi
(the ``rti_fn_*`` variants) is no faster, because casadi sets OSQP up again at every call.

This variant keeps what is fast in each: ONE Function maps (the parameters of the step, the
previous QP solution, shift or not) to everything OSQP's ``update`` takes (an SX plan and an SX
assembly around one mapped call of the node's linearisation, which C runs as a loop): the values of P and A
in OSQP's CSC data order (the patterns of the reference path), q, l, u and the primal warm start,
plus a finiteness flag. It is generated as C and compiled once (:func:`hbma_ctrl.core.codegen.compiled`,
cached on disk by source hash; casadi's virtual machine, with a one-line warning, without a
compiler) and called through preallocated buffers (:class:`hbma_ctrl.core.codegen.FastFunction`,
under a microsecond per call). The persistent OSQP solver is then updated in place and solved
warm-started, exactly as in the reference path, so the QP and its solution are the reference's (to
rounding).
"""

from __future__ import annotations

import math
import warnings

import casadi as ca
import numpy as np

from hbma_ctrl.controllers.mpc_settings import WEIGHTS, MPCSettings, weights_of
from hbma_ctrl.controllers.mpc_solvers import (OSQP_NO_TIME_LIMIT, _BudgetExceeded, _Problem, _RtiOsqp,
                                                _SolverFailure)
from hbma_ctrl.core.codegen import HOT_FLAGS, HOT_OPT, FastFunction, has_compiler
from hbma_ctrl.models.tables import PredictionModel

__all__ = ["qp_data_function"]

#: OSQP's infinity (its ``update`` clamps bounds to it; the generated data does the same)
_OSQP_INF = 1e30


def qp_data_function(rti: _RtiOsqp, looped: bool = True) -> ca.Function:
    """The QP data of one RTI step of ``rti`` (an :class:`_RtiOsqp`: its settings, stage and patterns).

    Inputs: ``par`` (8 + N: x0 (-), W (N), dh (m), dp (Pa), u_prev (3, -), p_lim (Pa), r (N stages, m)),
    ``z_prev`` (the previous QP solution in the pattern's variable layout), ``shift`` (1: a new step,
    the plan moves one stage; 0: another iteration at the same time), ``weights`` (:func:`weights_of`).
    Outputs: ``Px``, ``Ax`` (values
    in OSQP's CSC data order), ``q``, ``l``, ``u`` (QP units: mm, kPa, 1/100; bounds clamped to OSQP's
    infinity), ``z0`` (the primal warm start), ``ok`` (1 when the linearisation is finite).
    """
    N = rti.N
    SX = ca.SX
    par, zp, shift = SX.sym("par", 8 + N), SX.sym("z_prev", rti.nz), SX.sym("shift")
    wts = SX.sym("weights", len(WEIGHTS))
    Xb, Ub, Uext, Ulin = _plan(rti, par, zp, shift)
    W, dp = par[1], par[3]
    names = ["Px", "Ax", "q", "l", "u", "z0", "ok"]
    if not looped:
        lin = [rti.stage.lin(Xb[k], Uext[:, k], Ulin[:, k], W, dp) for k in range(N + 1)]
        rows = [ca.horzcat(*[ln[i] for ln in lin]) for i in range(9)]  # b: 3 x (N+1) as one row
        return ca.Function("rti_c_qp_data", [par, zp, shift, wts], _assemble(rti, par, wts, Xb, Ub, *rows),
                           ["par", "z_prev", "shift", "weights"], names,
                           {"cse": True})  # shared table look-ups (the nodes' first RK4 stage, p): 14 % less work
    # looped: the plan and the assembly as two SX Functions around ONE mapped call of the node's
    # linearisation, which C runs as a loop over the nodes (a twenty-first of the code)
    pre = ca.Function("rti_c_plan", [par, zp, shift], [Xb.T, Ub, Uext, Ulin])
    lin = rti.stage.lin
    ins = [SX.sym(lin.name_in(i), lin.sparsity_in(i)) for i in range(lin.n_in())]
    node = ca.Function("rti_c_node", ins, lin(*ins), lin.name_in(), lin.name_out(), {"cse": True})
    rows = [SX.sym(node.name_out(i), 1, node.nnz_out(i) * (N + 1)) for i in range(node.n_out())]
    Xr, Ubs = SX.sym("Xb", 1, N + 1), SX.sym("Ub", 3, N)
    post = ca.Function("rti_c_assemble", [par, wts, Xr, Ubs] + rows, _assemble(rti, par, wts, Xr.T, Ubs, *rows),
                       {"cse": True})
    MX = ca.MX
    par_m, zp_m, shift_m = MX.sym("par", 8 + N), MX.sym("z_prev", rti.nz), MX.sym("shift")
    wts_m = MX.sym("weights", len(WEIGHTS))
    Xm, Um, Uem, Ulm = pre(par_m, zp_m, shift_m)
    outs = node.map(N + 1)(Xm, Uem, Ulm, par_m[1], par_m[3])
    return ca.Function("rti_c_qp_data", [par_m, zp_m, shift_m, wts_m], post(par_m, wts_m, Xm, Um, *outs),
                       ["par", "z_prev", "shift", "weights"], names)



def _plan(rti: _RtiOsqp, par, zp, shift) -> tuple:
    """The step's linearisation points from the previous solution (SX): states Xb (N+1), inputs Ub
    (3 x N), Uext (3 x (N+1), the last repeated) and Ulin (Uext with speed and inlet floored)."""
    N, fl = rti.N, rti.s.rti_lin_floor
    x0 = par[0]
    X = zp[rti.ix.tolist()]
    Uc = ca.fmin(ca.fmax(ca.reshape(zp[rti.iu.ravel().tolist()], 3, N), 0.0), 1.0)  # 3 x N, as solve() keeps
    # the plan shifted by one stage (the last repeated) on a new step; the first state is the estimate
    Xb = ca.vertcat(shift * x0 + (1 - shift) * X[0], shift * ca.vertcat(X[2:], X[N]) + (1 - shift) * X[1:])
    Ub = shift * ca.horzcat(Uc[:, 1:], Uc[:, N - 1]) + (1 - shift) * Uc
    Uext = ca.horzcat(Ub, Ub[:, N - 1])
    Ulin = ca.vertcat(ca.fmax(Uext[0, :], fl), ca.fmax(Uext[1, :], fl), Uext[2, :])
    return Xb, Ub, Uext, Ulin


def _assemble(rti: _RtiOsqp, par, wts, Xb, Ub, f, a, b, h, ch, p, cp, lam, cl) -> list:
    """OSQP's data from the nodes' linearisation (each output of ``_Stage.lin`` over the N+1 nodes as
    one row; b's three entries per node in a row) and the cost's weights ``wts`` (:data:`WEIGHTS`):
    [Px, Ax, q, l, u, z0, ok]."""
    s, N = rti.s, rti.N
    SX = ca.SX
    w_height, w_terminal, wr, wu, cu, w_slack, c_slack = (wts[0], wts[1], wts[2:5], wts[5:8], wts[8:11], wts[11],
                                                          wts[12])
    f, a, h, ch, p, cp, lam, cl = (ca.vec(v) for v in (f, a, h, ch, p, cp, lam, cl))
    b = ca.reshape(b, 3, N + 1).T  # (N+1) x 3
    x0, dh, dp = par[0], par[2], par[3]
    u_prev, p_lim, r = par[4:7], par[7], par[8:]
    # only what the QP uses: the last node's dynamics and the first node's outputs are never built
    ok = ca.logic_and(ca.logic_and(ca.sumsqr(f[:N]) < ca.inf, ca.sumsqr(b[:N, :]) < ca.inf),
                      ca.sumsqr(ch[1:]) < ca.inf)
    # --- P (entry order of the reference pattern), x diagonal from the Gauss-Newton height cost
    wk = ca.vertcat(0.0, ca.repmat(w_height, N - 1, 1), w_height + w_terminal)
    r_mm, dh_mm = ca.vertcat(r[0], r) * 1e3, dh * 1e3
    e = h - ch * Xb + dh_mm - r_mm
    Pv = ca.vertcat(*rti.p_values(wr, wu, w_slack))
    Pv[rti.P_x.tolist()] = 2 * wk * ch ** 2 + 1e-8
    q = SX.zeros(rti.nz)
    q[rti.ix.tolist()] = 2 * wk * ch * e
    for k in range(N):
        for i in range(3):
            q[int(rti.iu[k, i])] = cu[i] - 2 * wr[i] * u_prev[i] if k == 0 else cu[i]
    q[rti.isl.tolist()] = c_slack
    # --- A values
    Av = SX(rti.A_vals)
    Av[rti.A_dyn_a.tolist()] = -a[:N]
    for i in range(3):
        Av[rti.A_dyn_b[:, i].tolist()] = -b[:N, i]
    k1 = list(range(1, N + 1))
    Av[rti.A_soft[:, 0].tolist()] = cp[k1]
    Av[rti.A_soft[:, 1].tolist()] = cl[k1]
    Av[rti.A_soft[:, 2].tolist()] = ch[k1]
    if s.h_min > 0:
        Av[rti.A_soft[:, 3].tolist()] = -ch[k1]
    # --- bounds
    lo, up = SX(np.clip(rti.l0, -_OSQP_INF, _OSQP_INF)), SX(np.clip(rti.u0, -_OSQP_INF, _OSQP_INF))
    lo[rti.r_init] = x0
    up[rti.r_init] = x0
    c = f[:N] - a[:N] * Xb[:N] - ca.sum2(b[:N, :] * Ub.T)
    dyn = list(range(rti.r_dyn, rti.r_dyn + N))
    lo[dyn] = c
    up[dyn] = c
    umax = np.array(s.u_max, float)
    for i in range(3):
        lo[rti.r_box + i] = ca.fmax(0.0, u_prev[i] - float(rti.du[i]))
        up[rti.r_box + i] = ca.fmin(float(umax[i]), u_prev[i] + float(rti.du[i]))
    rs = (rti.r_soft + rti.n_soft * np.arange(N)).tolist()
    Xk1 = Xb[k1]
    up[rs] = p_lim * 1e-3 - dp * 1e-3 - (p[k1] - cp[k1] * Xk1)
    up[[j + 1 for j in rs]] = s.lam_max * 1e2 - (lam[k1] - cl[k1] * Xk1)
    up[[j + 2 for j in rs]] = s.h_max * 1e3 - dh_mm - (h[k1] - ch[k1] * Xk1)
    if s.h_min > 0:
        up[[j + 3 for j in rs]] = -(s.h_min * 1e3 - dh_mm - (h[k1] - ch[k1] * Xk1))
    lo, up = ca.fmax(lo, -_OSQP_INF), ca.fmin(up, _OSQP_INF)
    z0 = SX.zeros(rti.nz)
    z0[rti.ix.tolist()] = Xb
    z0[rti.iu.ravel().tolist()] = ca.vec(Ub)
    return [Pv[rti.P_perm.tolist()], Av[rti.A_perm.tolist()], q, lo, up, z0, ok]


class _RtiC(_RtiOsqp):
    """RTI + OSQP with the QP data as one generated-C call (see the module docstring).

    The pattern, OSQP's setup and the acceptance of a solution are the reference path's; only
    how the data is computed differs. ``mode``: "c" (generated C) or "vm" (casadi's virtual machine:
    no compiler, or ``settings.codegen`` off).
    """

    COMPILE_LIN = False  # the QP data has the linearisation inside

    def __init__(self, model: PredictionModel, s: MPCSettings):
        super().__init__(model, s)
        fun = qp_data_function(self)
        compile_c = bool(s.codegen) and has_compiler()
        if s.codegen and not compile_c:
            warnings.warn("rti_c_osqp: no C compiler (cc, gcc, clang) found; the QP data runs on casadi's "
                          "virtual machine (slower, same results)", RuntimeWarning, stacklevel=2)
        self.data = FastFunction(fun, compile=compile_c, opt=HOT_OPT, flags=HOT_FLAGS)
        self.mode = "c" if self.data.fun is not fun else "vm"
        if compile_c and self.mode == "vm":
            warnings.warn("rti_c_osqp: the generated C did not compile; the QP data runs on casadi's "
                          "virtual machine (slower, same results)", RuntimeWarning, stacklevel=2)
        self._par = self.data.inp[0]  # written in place: passed as None (kept) to the call
        self._z, self._shift = self.data.inp[1], self.data.inp[2]
        self.data.inp[3][:] = weights_of(s)  # the settings' weights, for every call
        self._osqp = self.solver._solver  # the bound solver: update/solve without the wrapper's copies

    def solve(self, pr: _Problem) -> tuple[np.ndarray, np.ndarray]:
        """One RTI step (``rti_init_iterations`` unshifted QPs at a cold start): (X (N+1,), U (N, 3))."""
        s = self.s
        par = self._par
        par[0], par[1], par[2], par[3] = pr.x0, pr.W, pr.dh, pr.dp
        par[4:7] = pr.u_prev
        par[7] = pr.p_lim
        par[8:] = pr.r
        if self.X is None:
            z = self._z  # the data's z_prev buffer: the previous solution, or the cold start's guess
            z[:] = 0.0
            z[self.ix] = pr.x0
            z[self.iu] = pr.u_prev
            iters, shift = s.rti_init_iterations, 0.0
        else:
            iters, shift = 1, 1.0
        exempt = iters > 1 and s.enforce_budget  # a cold start is exempt from the budget
        if exempt:
            self.solver.update_settings(time_limit=OSQP_NO_TIME_LIMIT)
        try:
            for _ in range(iters):
                z = self._qp(shift)
                shift = 0.0
        finally:
            if exempt:
                self.solver.update_settings(time_limit=s.budget)
        self.X = z[self.ix]
        self.U = np.minimum(np.maximum(z[self.iu], 0.0), 1.0)  # (np.clip's wrapper costs 1-3 us more)
        return self.X, self.U

    def _qp(self, shift: float) -> np.ndarray:
        """One QP from the data buffers (par and z_prev already written); its solution, also left in
        z_prev for the next call."""
        self._shift[0] = shift
        Px, Ax, q, lo, up, z0, ok = self.data.eval()
        if ok[0] != 1.0:
            raise _SolverFailure("non-finite linearisation")
        osqp_ = self._osqp
        osqp_.update_data_vec(q=q, l=lo, u=up)
        osqp_.update_data_mat(P_x=Px, P_i=None, A_x=Ax, A_i=None)
        osqp_.warm_start(z0, None)
        osqp_.solve()
        info = osqp_.info
        self.iterations = int(info.iter)
        status = info.status
        if "time limit" in status:
            raise _BudgetExceeded("osqp: time limit (budget) reached")
        x = osqp_.solution.x
        usable = status in ("solved", "solved inaccurate") or (
            status == "maximum iterations reached" and info.prim_res < 1e-3)
        # x @ x is finite exactly when every entry is (short of an overflow at |x| ~ 1e154, itself a
        # failure): one BLAS call where np.all(np.isfinite(x)) costs two numpy calls and a wrapper
        if not usable or x is None or not math.isfinite(x @ x):
            raise _SolverFailure(f"osqp: {status}")
        self._z[:] = x
        return self._z
