"""The chamber NMPC's real-time-iteration step as ONE casadi Function (shift, linearisation, QP, solve).

:func:`rti_step_function` builds a Function that does everything one RTI step of
:class:`hbma_ctrl.controllers.mpc.NMPC` does: it shifts the previous plan by one stage, linearises the
gas-mass dynamics and the outputs along it and assembles the QP of the RTI + OSQP variants (the same
plan, ``_Stage.lin`` and terms: :func:`hbma_ctrl.controllers.rti_c.shifted_plan`,
:func:`hbma_ctrl.controllers.rti_c.linearised_terms`; cost, dynamics, input box and rates,
"speed <= inlet", soft pressure / stretch / height limits; see :mod:`hbma_ctrl.controllers.mpc`) in a
stage-wise layout (below), solves it
inside casadi through its conic interface (``qrqp``, ``hpipm``, ``osqp``, ``daqp``: the
``qp_solver`` argument) and returns the first input and the new plan. Everything is numeric, so the
Function can be code-generated to C (``qrqp`` generates self-contained C; ``hpipm`` needs the
hpipm/blasfeo headers and libraries shipped inside the casadi package; ``osqp`` those of OSQP)
and the Python controller calls exactly this Function (see :class:`_RtiFunction`).

Solver choice (measured on a 2-core machine, N = 20, one QP of a step, casadi 3.8)
-----------------------------------------------------------------------------------
OSQP (default: its generated C works and equals the plugin to the last bit, see below).
HPIPM: ~10-13 interior-point iterations in "balance" mode, 0.5-0.8 ms per QP through the
plugin (its "speed" mode stops at the iteration limit on this QP); first input within 1e-3 of the
reference OSQP path. OSQP through casadi: 0.5 ms (casadi sets OSQP up at every call, so the
factorisation is never reused). qrqp: 10-30 ms and "Failed to calculate search direction" on cold
starts. daqp, proxqp: 2-18 ms. None reaches the 0.2 ms per step the RTI variants aim at; the persistent
OSQP of ``rti_osqp`` (set up once, updated in place) stays the fastest path from Python.

Generated C (``compiled_step`` or the ``codegen`` command): qrqp's C is self-contained; OSQP's and
HPIPM's need the headers and libraries shipped in the casadi package (``_solver_flags``). The
OSQP step compiles and runs (about 0.65 ms per call); the generated HPIPM solver compiles but
reports failure inside this Function (it solves the QP alone once infinite bounds are made finite,
which the data part already does), so the C closed loop should use ``qp_solver="osqp"``.

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
``lam_x_guess``  nz      previous multipliers of the QP's variable bounds (dual guess; zeros at a cold start)
``lam_a_guess``  nc      previous multipliers of the QP's linear constraints (dual guess)
``shift``     1          1: a new step (the guess is shifted by one stage); 0: another iteration at
                         the same time, the guess used unshifted (the extra iterations of a cold start)
============  =========  ===========================================================================

nz = 8 N + 4 QP variables (stage-wise: [x_k, u_{k-1}, u_k, slack_{k+1}] for k < N, [x_N, u_{N-1}]) and
nc = 11 N (h_min > 0: 12 N) QP rows; ``function.size1_in("lam_x_guess")`` etc. give them.

Outputs:

============  =========  ===========================================================================
``u0``        3          first input (speed, inlet, outlet) clipped to [0, 1]
``X_plan``    N + 1      new state plan (the next call's ``X_guess``)
``U_plan``    3 x N      new input plan, clipped to [0, 1] (the next call's ``U_guess``)
``lam_x``     nz         the QP's bound multipliers (the next call's ``lam_x_guess``)
``lam_a``     nc         the QP's constraint multipliers (the next call's ``lam_a_guess``)
``status``    1          0: ok; 1: non-finite linearisation or solution; 2: the QP solution violates
                         its constraints by more than :func:`usable_tolerance` (solver failure)
``residual``  1          largest constraint violation of the QP solution (QP units: kPa, mm, ...)
``cost``      1          the QP's optimal cost (diagnostic)
============  =========  ===========================================================================
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from hbma_ctrl.controllers.mpc_settings import MPCSettings
from hbma_ctrl.controllers.mpc_solvers import Rows, _SolverFailure, _Stage
from hbma_ctrl.controllers.rti_c import linearised_terms, shifted_plan
from hbma_ctrl.core.codegen import FastFunction, casadi_lib_flags, compiled
from hbma_ctrl.models.tables import PredictionModel

__all__ = ["QP_SOLVERS", "RES_CAP", "compiled_step", "rti_step_function", "usable_tolerance"]

#: conic plugins the step can be built with (the first is the default)
QP_SOLVERS = ("osqp", "hpipm", "qrqp", "daqp")

_IN = ["x0", "W", "dh", "dp", "u_prev", "p_lim", "r", "X_guess", "U_guess", "lam_x_guess", "lam_a_guess", "shift"]
_OUT = ["u0", "X_plan", "U_plan", "lam_x", "lam_a", "status", "residual", "cost"]
#: stands for an infinite bound where the solver needs finite ones (QP units: kPa, mm, 1/100, -)
_BIG = 1e6
#: largest constraint violation of a usable QP solution (QP units; as the OSQP path's acceptance)
_RES_TOL = 1e-3
#: the largest violation a usable OSQP solution may have, however large its rows (QP units): OSQP's own
#: relative test reaches it only for a row beyond 99 units at the NMPC's tolerance (1e-4; the soft
#: limits' rows reach 20 to 41 on track_height), so it rejects a runaway iterate
RES_CAP = 1e-2


def usable_tolerance(qp_solver: str, eps: float, z, Az):
    """The largest constraint violation (QP units) of a usable solution ``z`` with rows ``Az`` (casadi
    expressions). OSQP ends a solve on its relative primal test, ``eps (1 + max(|z|, |Az|))`` in the
    max-norm, which allows more than :data:`_RES_TOL` once a row reaches 9 units: a solution OSQP calls
    solved is usable up to that test (at most :data:`RES_CAP`). The other solvers' solutions are exact
    to rounding: :data:`_RES_TOL`."""
    if qp_solver != "osqp":
        return _RES_TOL
    scale = ca.fmax(ca.mmax(ca.fabs(z)), ca.mmax(ca.fabs(Az)))
    return ca.fmin(RES_CAP, ca.fmax(_RES_TOL, eps * (1.0 + scale)))


def _solver_opts(qp_solver: str, s: MPCSettings) -> dict:
    if qp_solver == "qrqp":
        return {"print_iter": False, "print_header": False, "print_info": False, "error_on_fail": False,
                "max_iter": 1000}
    if qp_solver == "osqp":
        return {"osqp": {"verbose": False, "eps_abs": s.qp_eps, "eps_rel": s.qp_eps, "max_iter": s.qp_max_iter,
                         "polish": False}, "error_on_fail": False, "warm_start_primal": True}
    if qp_solver == "hpipm":
        # "balance" converges on this OCP (the default "speed" mode stops at its iteration limit)
        return {"hpipm": {"mode": "balance", "iter_max": 50, "res_g_max": 1e-5,
                          "res_b_max": 1e-8, "res_d_max": 1e-8, "res_m_max": 1e-6}, "error_on_fail": False}
    return {"error_on_fail": False}


def rti_step_function(model: PredictionModel, settings: MPCSettings, qp_solver: str = "osqp",
                      compile_parts: bool = False) -> ca.Function:
    """The RTI step of the chamber NMPC as one casadi Function (signature in the module docstring).

    ``model``: the controller's :class:`PredictionModel`; ``settings``: its :class:`MPCSettings`
    (validated here); ``qp_solver``: one of :data:`QP_SOLVERS`. ``compile_parts``: the two SX parts
    (QP data from the inputs; checks and outputs from the solution) run as C compiled with the
    system compiler (cached on disk by source hash; casadi's virtual machine without a compiler);
    the QP solver runs in casadi's plugin either way. The Function's inputs, outputs and results
    are the same (to rounding). ValueError on an unknown solver or one this casadi build lacks.
    """
    s = settings.validate()
    if qp_solver not in QP_SOLVERS:
        raise ValueError(f"rti_step.qp_solver = '{qp_solver}'; allowed: {', '.join(QP_SOLVERS)}")
    if not ca.has_conic(qp_solver):
        raise ValueError(f"rti_step.qp_solver = '{qp_solver}': this casadi build has no such conic plugin")
    N = s.horizon
    # the tables as bspline calls: this step is compiled into every generated C program
    stage = _Stage(model, s, "bspline")
    SX = ca.SX
    x0, W, dh, dp, p_lim, shift = (SX.sym(n) for n in ("x0", "W", "dh", "dp", "p_lim", "shift"))
    u_prev, r = SX.sym("u_prev", 3), SX.sym("r", N)
    Xg, Ug = SX.sym("X", N + 1), SX.sym("U", 3, N)
    # --- shift (shift = 1) or keep (shift = 0) the guess; the first state is always the estimate;
    # the linearisation at the N + 1 nodes
    Xb, Ub, Uext, Ulin = shifted_plan(x0, Xg, Ug, shift, s.rti_lin_floor)
    lin = [stage.lin(Xb[k], Uext[:, k], Ulin[:, k], W, dp) for k in range(N + 1)]
    f, a, b, h, ch, p, cp, lam, cl = (ca.vertcat(*[ln[i] for ln in lin]) for i in range(9))  # b: (N+1) x 3
    # --- variables, stage-wise (the OCP structure HPIPM detects): stage k < N holds
    # [x_k, v_k (the previous input, 3), u_k (3), s_k], stage N [x_N, v_N]. v_{k+1} = u_k turns the
    # input-rate terms into stage-local ones; s_k is the slack of the limits at stage k + 1, written
    # through x_{k+1} = a x_k + b u_k + c on stage k's variables. The optimum is that of the reference
    # path's QP (the same cost and feasible set once the dynamics hold).
    ns = 8
    nz = ns * N + 4
    ix = [ns * k for k in range(N + 1)]
    iv = [[ns * k + 1 + i for i in range(3)] for k in range(N + 1)]
    iu = [[ns * k + 4 + i for i in range(3)] for k in range(N)]
    isl = [ns * k + 7 for k in range(N)]
    # --- cost 1/2 z'Hz + g'z
    wk = ca.DM([0.0] + [s.w_height] * (N - 1) + [s.w_height + s.w_terminal])
    Hx, gx, c, limits = linearised_terms(s, wk, dh, dp, p_lim, r, Xb, Ub, f, a, b, h, ch, p, cp, lam, cl)
    H = SX(nz, nz)
    g = SX.zeros(nz)
    for k in range(N + 1):
        H[ix[k], ix[k]] = Hx[k]
        g[ix[k]] = gx[k]
    wr, wu, cu = (np.array(v, float) for v in (s.w_rate, s.w_input, s.c_input))
    for k in range(N):
        for i in range(3):  # w_rate |u_k - v_k|^2 + w_input |u_k|^2 + c_input . u_k
            H[iu[k][i], iu[k][i]] = 2 * wr[i] + 2 * wu[i] + 1e-8
            H[iv[k][i], iv[k][i]] = 2 * wr[i] + 1e-8
            H[iu[k][i], iv[k][i]] = -2 * wr[i]
            H[iv[k][i], iu[k][i]] = -2 * wr[i]
            g[iu[k][i]] = cu[i]
        H[isl[k], isl[k]] = 2 * s.w_slack
        g[isl[k]] = s.c_slack
    for i in range(3):
        H[iv[N][i], iv[N][i]] = 1e-8
    # --- simple bounds: x_0 and v_0 fixed, u box (u_0 also within the rate limit of u_prev), s >= 0
    inf = ca.inf
    umax = np.array(s.u_max, float)
    du = np.array(s.du_max, float) * s.sample_period
    lbx = [-inf] * nz
    ubx = [inf] * nz
    lbx[ix[0]] = ubx[ix[0]] = x0
    for i in range(3):
        lbx[iv[0][i]] = ubx[iv[0][i]] = u_prev[i]
        lbx[iu[0][i]] = ca.fmax(0.0, u_prev[i] - du[i])
        ubx[iu[0][i]] = ca.fmin(umax[i], u_prev[i] + du[i])
        for k in range(1, N):
            lbx[iu[k][i]], ubx[iu[k][i]] = 0.0, umax[i]
    for k in range(N):
        lbx[isl[k]] = 0.0
    # --- linear constraints lba <= A z <= uba, stage by stage: dynamics, then the stage's rows
    A = Rows()
    for k in range(N):  # x_{k+1} = a x_k + b u_k + c
        A.add([(ix[k], a[k])] + [(iu[k][i], b[k, i]) for i in range(3)] + [(ix[k + 1], -1.0)], -c[k], -c[k])
        for i in range(3):
            A.add([(iu[k][i], 1.0), (iv[k + 1][i], -1.0)], 0.0, 0.0)
        for i in range(3):  # (at k = 0 a bound of u_0 does it: a free row keeps rows per stage equal)
            A.add([(iu[k][i], 1.0), (iv[k][i], -1.0)], -du[i] if k > 0 else -inf, du[i] if k > 0 else inf)
        A.add([(iu[k][1], 1.0), (iu[k][0], -1.0)], 0.0, inf)  # inlet - speed >= 0
        # soft limits at stage k + 1 through the dynamics: y(x_{k+1}) ~ slope (a x_k + b u_k + c) + ...
        for slope, bound in limits:
            A.add([(ix[k], slope[k] * a[k])] + [(iu[k][i], slope[k] * b[k, i]) for i in range(3)] + [(isl[k], -1.0)],
                  -inf, bound[k] - slope[k] * c[k])
    A, lba, uba = A.matrix(nz)
    nc = A.shape[0]
    Hsp, Asp = H.sparsity(), A.sparsity()
    z0 = SX.zeros(nz)
    Vb = ca.horzcat(u_prev, Ub)
    for k in range(N + 1):
        z0[ix[k]] = Xb[k]
        for i in range(3):
            z0[iv[k][i]] = Vb[i, k]
            if k < N:
                z0[iu[k][i]] = Ub[i, k]
    lbx, ubx = ca.vertcat(*lbx), ca.vertcat(*ubx)
    if qp_solver == "hpipm":  # casadi's generated HPIPM C mishandles infinite bounds: far finite ones
        lbx, ubx, lba, uba = (ca.fmin(ca.fmax(v, -_BIG), _BIG) for v in (lbx, ubx, lba, uba))
    # dual guess, shifted as the primal one (N stages of ms rows / ns variables, stage N: 4 variables)
    ms = nc // N
    lxg, lag = SX.sym("lam_x_guess", nz), SX.sym("lam_a_guess", nc)
    lx0 = shift * ca.vertcat(lxg[ns:ns * N], lxg[ns * (N - 1):ns * N], lxg[ns * N:]) + (1 - shift) * lxg
    la0 = shift * ca.vertcat(lag[ms:], lag[nc - ms:]) + (1 - shift) * lag
    ins = [x0, W, dh, dp, u_prev, p_lim, r, Xg, Ug, lxg, lag, shift]
    data = ca.Function("rti_qp_data", ins, [H, g, A, lba, uba, lbx, ubx, z0, lx0, la0, ca.vertcat(f, ch, a, cp)])
    post_z = SX.sym("z", nz)
    Xn = ca.vertcat(*[post_z[i] for i in ix])
    Un = ca.fmin(ca.fmax(ca.horzcat(*[ca.vertcat(*[post_z[i] for i in iu[k]]) for k in range(N)]), 0.0), 1.0)
    Az = ca.mtimes(A, post_z)
    viol = ca.vertcat(ca.fmax(lbx - post_z, 0), ca.fmax(post_z - ubx, 0), ca.fmax(lba - Az, 0), ca.fmax(Az - uba, 0))
    # an infinite bound gives fmax(-inf, 0) = 0: only finite violations count
    res = ca.mmax(viol)
    chk = SX.sym("chk", 4 * (N + 1))
    finite = ca.logic_and(ca.sumsqr(post_z) < inf, ca.sumsqr(chk) < inf)
    status = ca.if_else(finite, ca.if_else(res <= usable_tolerance(qp_solver, s.qp_eps, post_z, Az), 0.0, 2.0), 1.0)
    # the solver's cost and multipliers are inputs of the post-processing so that every solver output
    # has a buffer (casadi 3.8's HPIPM interface writes all of them, and crashes on a missing one)
    cost, lam_a, lam_x = SX.sym("cost"), SX.sym("lam_a", nc), SX.sym("lam_x", nz)
    post = ca.Function("rti_post", [post_z, cost, lam_a, lam_x, chk] + ins,
                       [Un[:, 0], Xn, Un, lam_x, lam_a, status, res, cost])
    if compile_parts:
        data, post = compiled(data, "-O1"), compiled(post, "-O1")
    # --- the MX wrapper: data -> conic -> post
    qp = ca.conic("rti_qp", qp_solver, {"h": Hsp, "a": Asp}, _solver_opts(qp_solver, s))
    mx = [ca.MX.sym(n, *v.shape) for n, v in zip(_IN, ins)]
    Hm, gm, Am, lbam, ubam, lbxm, ubxm, z0m, lx0m, la0m, chkm = data(*mx)
    sol = qp(h=Hm, g=gm, a=Am, lba=lbam, uba=ubam, lbx=lbxm, ubx=ubxm, x0=z0m, lam_x0=lx0m, lam_a0=la0m)
    outs = post(sol["x"], sol["cost"], sol["lam_a"], sol["lam_x"], chkm, *mx)
    return ca.Function("rti_step", mx, list(outs), _IN, _OUT)



def _solver_flags(qp_solver: str) -> list[str]:
    """Compiler flags for the generated C of a Function containing ``qp_solver`` (headers and libraries
    shipped inside the casadi package; qrqp needs none)."""
    return casadi_lib_flags({"hpipm": ["-lhpipm", "-lblasfeo"], "osqp": ["-losqp"]}.get(qp_solver, []))


def compiled_step(fun: ca.Function, qp_solver: str, opt: str = "-O1") -> ca.Function | None:
    """``fun`` (from :func:`rti_step_function`) as generated C compiled with the system compiler and
    loaded by ``casadi.external``; the library is cached under :func:`hbma_ctrl.core.codegen.cache_dir`
    keyed by the SHA-1 of the source and flags (compiled once per machine, about 20 s). None when
    there is no compiler or the build fails (the caller falls back to casadi's virtual machine)."""
    return compiled(fun, opt, flags=_solver_flags(qp_solver), on_failure="none")


class _RtiFunction:
    """NMPC backend calling :func:`rti_step_function`'s Function once per step (through buffers).

    ``qp_solver`` as in :func:`rti_step_function`. With ``settings.codegen`` the whole Function runs
    as generated C (:func:`compiled_step`; ``mode`` "c") when it builds and solves a probe step (the
    results equal the plugin's: OSQP's C gave the same first inputs to the last bit over 30 steps,
    at half the time); else its SX parts run as C around the solver plugin (``mode`` "parts": the
    generated HPIPM C fails inside this Function, see the module docstring). Without ``codegen``
    casadi's virtual machine runs it all (``mode`` "vm").
    """

    def __init__(self, model: PredictionModel, s: MPCSettings, qp_solver: str = "osqp"):
        self.s, self.model, self.N = s, model, s.horizon
        self.function = rti_step_function(model, s, qp_solver)
        self.nz, self.nc = self.function.nnz_in("lam_x_guess"), self.function.nnz_in("lam_a_guess")
        self.mode = "vm"
        fun = self.function
        if s.codegen:
            c = compiled_step(self.function, qp_solver)
            if c is not None and self._probe(c):
                fun, self.mode = c, "c"
            else:
                fun, self.mode = rti_step_function(model, s, qp_solver, compile_parts=True), "parts"
        self.call = FastFunction(fun, compile=False)
        self.reset()
        self.iterations = 0

    def _probe(self, fun: ca.Function) -> bool:
        """Does ``fun`` solve a nominal cold step (to mid-range height under a tenth of the largest load)?"""
        N, s = self.N, self.s
        W = 0.1 * self.model.load_max
        try:
            x0 = float(self.model.x_at_height(0.5 * s.h_max, W))
            out = fun(x0, W, 0.0, 0.0, np.zeros(3), s.p_max - s.p_margin, np.full(N, 0.5 * s.h_max),
                      np.full(N + 1, x0), np.zeros((3, N)), np.zeros(self.nz), np.zeros(self.nc), 0.0)
        except RuntimeError:
            return False
        return float(out[5]) == 0.0

    def reset(self) -> None:
        """Forget the plan (the next step is a cold start)."""
        self.X = self.U = self.lam_x = self.lam_a = None

    def solve(self, pr):
        """One RTI step (rti_init_iterations unshifted ones at a cold start): (X (N+1,), U (N, 3))."""
        N = self.N
        if self.X is None:
            Xg, Ug = np.full(N + 1, pr.x0), np.tile(pr.u_prev, N)
            lx, la = np.zeros(self.nz), np.zeros(self.nc)
            iters, shift = self.s.rti_init_iterations, 0.0
        else:
            Xg, Ug, lx, la, iters, shift = self.X, self.U, self.lam_x, self.lam_a, 1, 1.0
        for _ in range(iters):
            self.call.out[5][:] = np.nan  # a failed evaluation leaves it: counted as a failure
            try:
                out = self.call(float(pr.x0), float(pr.W), float(pr.dh), float(pr.dp), pr.u_prev,
                                float(pr.p_lim), pr.r, Xg, Ug, lx, la, shift)
            except RuntimeError as exc:  # a generated solver that reports failure by its return code
                self.reset()
                raise _SolverFailure(f"rti_step: {str(exc).splitlines()[-1]}") from None
            status = out[5][0]
            if status != 0.0:
                self.reset()
                if np.isnan(status):
                    why = "evaluation failed"
                elif status == 1.0:
                    why = "non-finite linearisation or solution"
                else:
                    why = f"QP solution violates its constraints by {out[6][0]:.3g}"
                raise _SolverFailure(f"rti_step: {why}")
            Xg, Ug, lx, la, shift = out[1].copy(), out[2].copy(), out[3].copy(), out[4].copy(), 0.0
        self.X, self.U, self.lam_x, self.lam_a = Xg, Ug, lx, la
        self.iterations = iters
        return Xg, Ug.reshape(N, 3)
