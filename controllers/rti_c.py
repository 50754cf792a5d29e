"""The chamber NMPC's real-time iteration with OSQP kept set up (``rti_osqp``, ``rti_c_osqp``).

One sparse QP per step with a fixed pattern (:class:`_RtiOsqp`); ONE casadi Function
(:func:`qp_data_function`) maps (the parameters of the step, the previous QP solution, shift or not,
the cost's weights) to everything OSQP's ``update`` takes (an SX plan and an SX assembly around one
mapped call of the node's linearisation, which C runs as a loop): the values of P and A in OSQP's
CSC data order, q, l, u and the primal warm start, plus a finiteness flag. The persistent OSQP solver
is then updated in place (never set up again) and solved warm-started.

The two variants differ only in how that Function is evaluated. ``rti_c_osqp``: generated as C and
compiled once (:func:`hbma_ctrl.core.codegen.compiled`, cached on disk by source hash; casadi's
virtual machine, with a one-line warning, without a compiler) and called through preallocated
buffers (:class:`hbma_ctrl.core.codegen.FastFunction`, under a microsecond per call). ``rti_osqp``:
the same Function on casadi's virtual machine (the reference path, slower). Solving the QP inside
casadi (the ``rti_fn_*`` variants, :mod:`hbma_ctrl.controllers.rti_step`) is no faster, because
casadi sets OSQP up again at every call.
"""

from __future__ import annotations

import math
import warnings

import casadi as ca
import numpy as np
import osqp
import scipy.sparse as sp

from hbma_ctrl.controllers.mpc_settings import WEIGHTS, MPCSettings, weights_of
from hbma_ctrl.controllers.mpc_solvers import (OSQP_NO_TIME_LIMIT, Rows, _BudgetExceeded, _Problem,
                                                _SolverFailure, _Stage, mapped_function, sparse,
                                                qp_time_limit)
from hbma_ctrl.core.codegen import HOT_FLAGS, HOT_OPT, FastFunction, has_compiler
from hbma_ctrl.models.tables import PredictionModel

__all__ = ["qp_data_function"]

#: OSQP's step size rho, fixed, and how often it checks for termination (iterations), for the RTI QPs.
#: Its defaults (rho 0.1 adapted every 4 x 25 iterations, termination checked every 25) ran most
#: warm-started QPs to 25 iterations where 10 meet the same tolerances, and an adapted rho stays with
#: the solver into later QPs: the iteration counts then depended on the history (adapting every 20, 32
#: or 50 iterations gave a median of 25, every 40 or 48 one of 10-12). A fixed rho is the same every
#: step and needs no refactorisation inside a solve. Scanned in ``bench mpc``'s loop (N = 20, rho
#: fixed, checked every 5): median / mean iterations 10 / 42 at 0.01, 10 / 26 at 0.02, 10 / 23 at 0.03,
#: 15 / 26 at 0.05, 30 / 38 at 0.1, 75 / 93 at 0.3; at 0.03 checked every 2, 5, 10, 25: median 10, 10,
#: 10, 25 iterations, the step 0.27, 0.25, 0.25, 0.28 ms (the checks cost). ``bench loop --seeds 20``
#: passed 20/20, 17/20, 20/20 checked every 5 and 20/20, 19/20, 20/20 every 10 (OSQP's defaults:
#: 20/20, 19/20, 19/20); a QP stopped at 5 iterations is the least accurate within the tolerance
QP_RHO = 0.03
QP_CHECK_EVERY = 10
#: OSQP's Ruiz equilibration passes (its default 10). Each update of P and A re-scales the whole KKT
#: matrix before refactorising it: in ``bench mpc``'s loop (N = 20) the matrix update took 54 us with
#: 10 passes, 34 with 4, 30 with 3, 27 with 2, 23 with 1 and 16 with none, while the solve's median
#: iterations stayed at 10 from 2 passes up; with 1 or none most QPs ran to the iteration limit (300).
#: 4 keeps two passes of margin; ``bench loop --seeds 20`` passed 20/20, 19/20, 20/20 as with 10.
QP_SCALING = 4


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
    par, zp, shift = ca.SX.sym("par", 8 + N), ca.SX.sym("z_prev", rti.nz), ca.SX.sym("shift")
    wts = ca.SX.sym("weights", len(WEIGHTS))
    Xb, Ub, Uext, Ulin = _plan(rti, par, zp, shift)
    nodes = [Xb.T, Uext, Ulin, ca.repmat(par[1], 1, N + 1), ca.repmat(par[3], 1, N + 1)]  # lin's (x, u, ulin, W, dp)
    # the looped form: a twenty-first of the code; the unrolled one shares table look-ups (the nodes'
    # first RK4 stage, p) through its common-subexpression elimination: 14 % less work
    return mapped_function("rti_c_qp_data", [par, zp, shift, wts], ["par", "z_prev", "shift", "weights"],
                           ["Px", "Ax", "q", "l", "u", "z0", "ok"], rti.stage.lin, nodes,
                           lambda L: _assemble(rti, par, wts, Xb, Ub, *L), looped)


def _plan(rti: _RtiOsqp, par, zp, shift) -> tuple:
    """The step's linearisation points from the previous solution ``zp`` (SX, :func:`shifted_plan`)."""
    N = rti.N
    X = zp[rti.ix.tolist()]
    Uc = ca.fmin(ca.fmax(ca.reshape(zp[rti.iu.ravel().tolist()], 3, N), 0.0), 1.0)  # 3 x N, as solve() keeps
    return shifted_plan(shift * par[0] + (1 - shift) * X[0], X, Uc, shift, rti.s.rti_lin_floor)


def shifted_plan(x_first, X, U, shift, floor: float) -> tuple:
    """The RTI step's linearisation points (SX) from the previous plan, states ``X`` (N+1) and inputs
    ``U`` (3 x N, in [0, 1]): moved one stage on (the last repeated) where ``shift`` is 1, kept where it
    is 0, the first state ``x_first``. Returns Xb (N+1), Ub (3 x N), Uext (3 x (N+1), the last input
    repeated) and Ulin (Uext with speed and inlet floored at ``floor``: where the Jacobians are taken)."""
    N = U.shape[1]
    Xb = ca.vertcat(x_first, shift * ca.vertcat(X[2:], X[N]) + (1 - shift) * X[1:])
    Ub = shift * ca.horzcat(U[:, 1:], U[:, N - 1]) + (1 - shift) * U
    Uext = ca.horzcat(Ub, Ub[:, N - 1])
    Ulin = ca.vertcat(ca.fmax(Uext[0, :], floor), ca.fmax(Uext[1, :], floor), Uext[2, :])
    return Xb, Ub, Uext, Ulin


def linearised_terms(s: MPCSettings, wk, dh, dp, p_lim, r, Xb, Ub, f, a, b, h, ch, p, cp, lam, cl) -> tuple:
    """The RTI QP's terms along the plan, whatever its variable layout (SX; QP units: mm, kPa, 1/100).

    ``wk``: the height weights of the N+1 nodes; ``dh`` (m), ``dp`` (Pa): the output biases; ``p_lim``
    (Pa); ``r`` (N targets, m); ``Xb``, ``Ub``: the plan (:func:`shifted_plan`); the rest
    ``_Stage.lin``'s outputs at the nodes as columns (``b``: (N+1) x 3). Returns the height cost's x
    diagonal and gradient at the nodes, the dynamics' offsets c (x_{k+1} = a_k x_k + b_k u_k + c_k,
    k < N) and the soft limits at nodes 1..N as (slope, bound) pairs: slope x_k - slack <= bound
    (pressure, stretch, the upper height and, with ``h_min`` > 0, the lower one).
    """
    N = Ub.shape[1]
    dh_mm = dh * 1e3
    e = h - ch * Xb + dh_mm - ca.vertcat(r[0], r) * 1e3  # h_k(x) + dh - r = ch x + e
    cost = (2 * wk * ch ** 2 + 1e-8, 2 * wk * ch * e)
    c = f[:N] - a[:N] * Xb[:N] - ca.sum2(b[:N, :] * Ub.T)
    h, ch, p, cp, lam, cl, X = (v[1:] for v in (h, ch, p, cp, lam, cl, Xb))
    limits = [(cp, p_lim * 1e-3 - dp * 1e-3 - (p - cp * X)), (cl, s.lam_max * 1e2 - (lam - cl * X)),
              (ch, s.h_max * 1e3 - dh_mm - (h - ch * X))]
    if s.h_min > 0:  # (below lift-off H is a virtual negative height: no bound at h_min = 0)
        limits.append((-ch, -(s.h_min * 1e3 - dh_mm - (h - ch * X))))
    return (*cost, c, limits)


def _assemble(rti: _RtiOsqp, par, wts, Xb, Ub, f, a, b, h, ch, p, cp, lam, cl) -> list:
    """OSQP's data from the nodes' linearisation (each output of ``_Stage.lin`` at the N+1 nodes as a
    column) and the cost's weights ``wts`` (:data:`WEIGHTS`): [P (its upper triangle), A (both sparse:
    their nonzeros in OSQP's CSC order), q, l, u, z0, ok]."""
    s, N, nz = rti.s, rti.N, rti.nz
    ix, iu, isl = rti.ix.tolist(), rti.iu.tolist(), rti.isl.tolist()
    w_height, w_terminal, wr, wu, cu, w_slack, c_slack = (wts[0], wts[1], wts[2:5], wts[5:8], wts[8:11], wts[11],
                                                          wts[12])
    f, a, h, ch, p, cp, lam, cl = (ca.vec(v) for v in (f, a, h, ch, p, cp, lam, cl))
    b = ca.reshape(b, 3, N + 1).T  # (N+1) x 3
    x0, dh, dp = par[0], par[2], par[3]
    u_prev, p_lim, r = par[4:7], par[7], par[8:]
    # only what the QP uses: the last node's dynamics and the first node's outputs are never built
    ok = ca.logic_and(ca.logic_and(ca.sumsqr(f[:N]) < ca.inf, ca.sumsqr(b[:N, :]) < ca.inf),
                      ca.sumsqr(ch[1:]) < ca.inf)
    wk = ca.vertcat(0.0, ca.repmat(w_height, N - 1, 1), w_height + w_terminal)
    Hx, gx, c, limits = linearised_terms(s, wk, dh, dp, p_lim, r, Xb, Ub, f, a, b, h, ch, p, cp, lam, cl)
    # --- cost: the x diagonal from the Gauss-Newton height cost; each input's diagonal and its rate
    # coupling to the previous stage; the slacks' diagonal
    P = [(ix[k], ix[k], Hx[k]) for k in range(N + 1)]
    q = ca.SX.zeros(nz)
    q[ix] = gx
    for k in range(N):
        for i in range(3):
            nd = 2 if k < N - 1 else 1  # u_k appears in (u_k - u_{k-1}) and (u_{k+1} - u_k)
            P.append((iu[k][i], iu[k][i], 2 * wr[i] * nd + 2 * wu[i] + 1e-8))
            if k > 0:
                P.append((iu[k - 1][i], iu[k][i], -2 * wr[i]))
            q[iu[k][i]] = cu[i] - 2 * wr[i] * u_prev[i] if k == 0 else cu[i]
        P.append((isl[k], isl[k], 2 * w_slack))
    q[isl] = c_slack
    # --- constraints: x_0, the dynamics, the input box (the first input also within the rate limit
    # from the applied command), the rates, inlet - speed >= 0, per stage k + 1 the soft limits
    # (pressure, stretch, height; at h_min = 0 no lower bound: H below lift-off is a virtual negative
    # height, and an unbounded row only costs OSQP), the slacks >= 0
    inf, umax = ca.inf, np.array(s.u_max, float)
    A = Rows()
    A.add([(ix[0], 1.0)], x0, x0)
    for k in range(N):  # x_{k+1} - a x_k - b u_k = f - a xb - b ub
        A.add([(ix[k + 1], 1.0), (ix[k], -a[k])] + [(iu[k][i], -b[k, i]) for i in range(3)], c[k], c[k])
    for k in range(N):
        for i in range(3):
            if k == 0:
                lo, up = ca.fmax(0.0, u_prev[i] - rti.du[i]), ca.fmin(umax[i], u_prev[i] + rti.du[i])
            else:
                lo, up = 0.0, umax[i]
            A.add([(iu[k][i], 1.0)], lo, up)
    for k in range(1, N):
        for i in range(3):
            A.add([(iu[k][i], 1.0), (iu[k - 1][i], -1.0)], -rti.du[i], rti.du[i])
    for k in range(N):
        A.add([(iu[k][1], 1.0), (iu[k][0], -1.0)], 0.0, inf)
    for k in range(N):
        for slope, bound in limits:
            A.add([(ix[k + 1], slope[k]), (isl[k], -1.0)], -inf, bound[k])
    for k in range(N):
        A.add([(isl[k], 1.0)], 0.0, inf)
    A, lo, up = A.matrix(nz)
    z0 = ca.SX.zeros(nz)
    z0[ix] = Xb
    z0[rti.iu.ravel().tolist()] = ca.vec(Ub)
    return [sparse(P, (nz, nz)), A, q, ca.fmax(lo, -_OSQP_INF), ca.fmin(up, _OSQP_INF), z0, ok]


def _csc(sparsity: ca.Sparsity, values=None) -> sp.csc_matrix:
    """A casadi sparsity as a scipy CSC matrix with these values in its nonzero order (a copy; default
    1e-12 each: OSQP's set-up, whose values the steps update)."""
    v = np.full(sparsity.nnz(), 1e-12) if values is None else np.array(values, dtype=float)
    return sp.csc_matrix((v, sparsity.row(), sparsity.colind()), shape=sparsity.shape)


class _RtiOsqp:
    """Real-time iteration: one sparse QP per step, fixed pattern, its data from :func:`qp_data_function`,
    OSQP updated in place (see the module docstring).

    ``compile``: the data as generated C when ``settings.codegen`` is set and a C compiler is found
    (``mode`` "c"), else on casadi's virtual machine (``mode`` "vm"; with ``codegen`` set, a warning
    says why).
    """

    def __init__(self, model: PredictionModel, s: MPCSettings, compile: bool = True):
        self.s, self.model = s, model
        N = self.N = s.horizon
        self.stage = _Stage(model, s, "poly")
        # variable layout
        self.ix = np.arange(N + 1)
        self.iu = (N + 1) + np.arange(3 * N).reshape(N, 3)
        self.isl = (N + 1) + 3 * N + np.arange(N)  # slack of stage k+1
        self.nz = (N + 1) + 4 * N
        self.du = np.array(s.du_max, float) * s.sample_period
        fun = qp_data_function(self)
        compile_c = compile and bool(s.codegen) and has_compiler()
        if compile and s.codegen and not compile_c:
            warnings.warn("rti_c_osqp: no C compiler (cc, gcc, clang) found; the QP data runs on casadi's "
                          "virtual machine (slower, same results)", RuntimeWarning, stacklevel=2)
        self.data = FastFunction(fun, compile=compile_c, opt=HOT_OPT, flags=HOT_FLAGS)
        self.mode = "c" if self.data.fun is not fun else "vm"
        if compile_c and self.mode == "vm":
            warnings.warn("rti_c_osqp: the generated C did not compile; the QP data runs on casadi's "
                          "virtual machine (slower, same results)", RuntimeWarning, stacklevel=2)
        # OSQP on the data's patterns (the values and bounds are the first step's update)
        P, A = (_csc(fun.sparsity_out(i)) for i in (0, 1))
        self.nc = A.shape[0]
        self.solver = osqp.OSQP()
        self.solver.setup(P, np.zeros(self.nz), A, np.zeros(self.nc), np.zeros(self.nc), verbose=False,
                          eps_abs=s.qp_eps, eps_rel=s.qp_eps, max_iter=s.qp_max_iter, polishing=False,
                          warm_starting=True, adaptive_rho=False, rho=QP_RHO, time_limit=qp_time_limit(s),
                          check_termination=QP_CHECK_EVERY, scaling=QP_SCALING)
        self.X = None
        self.U = None
        self.iterations = 0
        self._par = self.data.inp[0]  # written in place: passed as None (kept) to the call
        self._z, self._shift = self.data.inp[1], self.data.inp[2]
        self.data.inp[3][:] = weights_of(s)  # the settings' weights, for every call
        self._osqp = self.solver._solver  # the bound solver: update/solve without the wrapper's copies

    def reset(self) -> None:
        self.X = None
        self.U = None

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
