"""The robot NMPC's RTI step as ONE casadi Function, its QP solved inside casadi (OSQP's conic plugin).

:class:`hbma_ctrl.controllers.robot_mpc.RobotNMPC` computes its QP's values in one generated call, then updates
and solves a persistent OSQP from Python. For a loop without Python the whole step is one Function
(the third block of a generated robot loop, after :mod:`hbma_ctrl.robot.plant_step` and
:func:`hbma_ctrl.estimators.robot_ekf.bank_step_function`):

    robot_rti_step(x0[n], b[n], W[n], k[n], c[n], a_max[n], h_ref[n x N] (m), prev[2 x n],
                   xbar[n x (N + 1)], abar[n x N], obar[n x N], first, z_prev[nv], y_prev[m], warm)
        -> (a[n], o[n], xbar_next, abar_next, obar_next, z[nv], y[m], status, residual)

The inputs are :meth:`RobotNMPC.step`'s (loads clipped to the tables and ``a_max`` to [0, 1] here),
its plan as it holds it (``first`` = 1: no plan yet, the states start at x0), and the last usable QP
solution (``warm`` = 1: warm-started from it shifted by one stage, primal and dual, as the class does).
``status`` is 0 for a usable solution, 1 for a non-finite one, 2 when a finite one violates its
constraints by more than :data:`RES_TOL` (QP units: mm, kPa, duty); on 1 and 2 the decisions and the
plan's inputs are zero, as the class's on an unusable solve.

Differences from the class, both of the solver: casadi's OSQP keeps its workspace between calls but
cold-starts it at every call (then the warm start given), resets its step size rho to the option's
value (:data:`FN_RHO`; a second factorisation after the matrices' update) and carries the
variables' (here infinite) bounds as rows of its own; its iterates differ from the Python package's
within the tolerance (``eps``); the class accepts a solve OSQP stopped at its
iteration limit whatever its residual, this Function judges every solve by its residual. The wall-time
budget (overruns) is not here: a generated loop times its own steps.
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

from hbma_ctrl.controllers.robot_mpc import RobotMPCSettings, RobotNMPC
from hbma_ctrl.core.codegen import FastFunction, casadi_lib_flags

__all__ = ["robot_rti_step_function", "robot_rti_qp_functions", "RES_TOL", "FN_MAX_ITER", "FN_RHO", "RobotNMPCFunction"]

#: the largest constraint violation (QP units: mm, kPa, duty) a usable solution may have. OSQP stops at
#: eps_abs + eps_rel x the size of the rows' values, so a good solve's residual scales with the
#: pressures' kPa: over ``robot_bending`` (2800 steps, eps 3e-4) it peaked at 0.014 (median 0.004),
#: which 1e-3 refused at every step
RES_TOL = 0.05

#: the fewest OSQP iterations the Function allows a solve. casadi's OSQP resets its step size rho at
#: every call instead of keeping the one the class's persistent solver adapted to. Measured with rho
#: at OSQP's default (0.1, before :data:`FN_RHO`): capped at the class's 125 iterations
#: (``RobotMPCSettings.max_iter``) the steps never converge and the chambers barely move
#: (``robot_bending``, 28 s: final heights 3.9-6.6 mm for 7.0 mm targets, a median step of 2.0 ms); at
#: 2000 the solves converge, the loop tracks as the class's does (6.8-7.1 mm) and the median step is
#: 0.56 ms
FN_MAX_ITER = 2000

#: the step size rho casadi's OSQP starts every call from (it resets it at every call; the class's
#: persistent solver keeps the one it adapted to). Against OSQP's default 0.1, over seeds 1-5 of
#: robot_bending, robot_sequential_closed and robot_tip_load (RobotNMPCFunction in the scene): a lower
#: chamber height RMSE in all 15 runs (the shared pump's 0.134-0.215 -> 0.111-0.160 mm) and the
#: controller's p99 7.9-9.7 -> 2.7-9.2 ms with the shared pump, 3.9-4.4 -> 2.5-3.5 ms with a pump per
#: chamber; all segments settled either way. 1.0 is faster still but lets a 6-layer stress run's rig
#: diverge
FN_RHO = 0.5

_IN = ["x0", "b", "W", "k", "c", "a_max", "h_ref", "prev", "xbar", "abar", "obar", "first", "z_prev", "y_prev",
       "warm"]
_OUT = ["a", "o", "xbar_next", "abar_next", "obar_next", "z", "y", "status", "residual"]


def _step_inputs(nmpc: RobotNMPC) -> list:
    """The step's inputs as MX symbols, in :data:`_IN`'s order."""
    n, N, MX = nmpc.n, nmpc.s.horizon, ca.MX
    x0, b, W, k, c, amax = (MX.sym(nm, n) for nm in ("x0", "b", "W", "k", "c", "a_max"))
    return [x0, b, W, k, c, amax, MX.sym("h_ref", n, N), MX.sym("prev", 2, n), MX.sym("xbar", n, N + 1),
            MX.sym("abar", n, N), MX.sym("obar", n, N), MX.sym("first"), MX.sym("z_prev", nmpc.nv),
            MX.sym("y_prev", nmpc.m_rows), MX.sym("warm")]


def _step_qp(nmpc: RobotNMPC, ins: list) -> tuple:
    """The step's QP from its inputs: (Pu (OSQP's upper triangle), A, q, lo, up, the shifted primal and
    dual guesses, the shifted states, whether the data are finite). Non-finite data become a zero QP."""
    s, n, N = nmpc.s, nmpc.n, nmpc.s.horizon
    nv, m = nmpc.nv, nmpc.m_rows
    data = nmpc._qp_data_function(nmpc.model.linearisation(s.dt, 1, s.integrator))
    MX = ca.MX
    x0, b, W, k, c, amax, href, prev, xbar, abar, obar, first, z_prev, y_prev, warm = ins
    Wc = nmpc.model.clip_load(W)
    amc = ca.fmin(ca.fmax(amax, 0.0), 1.0)
    # the plan shifted one stage on (the last repeated), the first state the estimate
    xs = ca.if_else(first, ca.repmat(x0, 1, N + 1), ca.horzcat(xbar[:, 1:], xbar[:, N]))
    xs = ca.horzcat(x0, xs[:, 1:])
    as_ = ca.if_else(first, abar, ca.horzcat(abar[:, 1:], abar[:, N - 1]))
    os_ = ca.if_else(first, obar, ca.horzcat(obar[:, 1:], obar[:, N - 1]))
    Pu, A, q, lo, up = data(x0, b, Wc, k, c, amc, href * 1e3, prev, xs, as_, os_)
    # a non-finite input makes non-finite data, which casadi's conic refuses with an exception: solve a
    # zero QP instead and report status 1 (bounds at OSQP's infinity, 1e30, square to 1e60: finite)
    d_ok = ca.sumsqr(Pu) + ca.sumsqr(A) + ca.sumsqr(q) + ca.sumsqr(lo) + ca.sumsqr(up) < ca.inf
    Pu, A, q, lo, up = (ca.if_else(d_ok, v, MX.zeros(v.sparsity())) for v in (Pu, A, q, lo, up))
    sx, sy = nmpc._shift_x, nmpc._shift_y
    zw = ca.if_else(warm, z_prev[sx.tolist()], MX.zeros(nv))
    yw = ca.if_else(warm, y_prev[sy.tolist()], MX.zeros(m))
    return Pu, A, q, lo, up, zw, yw, xs, d_ok


def _step_outputs(nmpc: RobotNMPC, x0, xs, d_ok, A, lo, up, z, y) -> list:
    """The step's outputs (:data:`_OUT`) from the QP's solution (z, y), its rows (A, lo, up) and the
    step's shifted states and data check."""
    n, N = nmpc.n, nmpc.s.horizon
    nb = 3 * N + 1
    MX = ca.MX
    Az = ca.mtimes(A, z)
    # bounds at OSQP's infinity (1e30) never bind: only finite violations count
    res = ca.mmax(ca.vertcat(ca.fmax(lo - Az, 0), ca.fmax(Az - up, 0)))
    finite = ca.sumsqr(z) < ca.inf  # a NaN or an inf anywhere makes the sum so
    status = ca.if_else(ca.logic_and(d_ok, finite), ca.if_else(res <= RES_TOL, 0.0, 2.0), 1.0)
    ok = status == 0
    Z = ca.reshape(z, nb, n).T  # chamber i's block is row i: x_1..x_N | a_0..a_{N-1} | o_0.. | slack
    a_plan = ca.if_else(ok, ca.fmin(ca.fmax(Z[:, N:2 * N], 0.0), 1.0), MX.zeros(n, N))
    o_plan = ca.if_else(ok, ca.fmin(ca.fmax(Z[:, 2 * N:3 * N], 0.0), 1.0), MX.zeros(n, N))
    x_next = ca.if_else(ok, ca.horzcat(x0, Z[:, :N]), xs)
    a0, o0 = a_plan[:, 0], o_plan[:, 0]
    if nmpc.topology == "shared":
        tot = ca.sum1(a0)
        a0 = ca.if_else(tot > 1.0, a0 / tot, a0)
    return [a0, o0, x_next, a_plan, o_plan, z, y, status, res]


def robot_rti_step_function(nmpc: RobotNMPC, name: str = "robot_rti_step") -> ca.Function:
    """One RTI step of ``nmpc`` (its model, size, topology and settings) as a Function (module docstring)."""
    s = nmpc.s
    ins = _step_inputs(nmpc)
    Pu, A, q, lo, up, zw, yw, xs, d_ok = _step_qp(nmpc, ins)
    # OSQP's P is the upper triangle; casadi's conic takes the whole symmetric Hessian
    H = Pu + Pu.T - ca.diag(ca.diag(Pu))
    opts = {"osqp": {"verbose": False, "eps_abs": s.eps, "eps_rel": s.eps, "max_iter": max(s.max_iter, FN_MAX_ITER),
                     "polish": False, "check_termination": 5, "scaling": 1, "rho": FN_RHO},
            "error_on_fail": False, "warm_start_primal": True, "warm_start_dual": True}
    qp = ca.conic(f"{name}_qp", "osqp", {"h": H.sparsity(), "a": A.sparsity()}, opts)
    sol = qp(h=H, g=q, a=A, lba=lo, uba=up, x0=zw, lam_a0=yw)
    return ca.Function(name, ins, _step_outputs(nmpc, ins[0], xs, d_ok, A, lo, up, sol["x"], sol["lam_a"]), _IN, _OUT)


def robot_rti_qp_functions(nmpc: RobotNMPC) -> tuple[ca.Function, ca.Function, tuple]:
    """The step of :func:`robot_rti_step_function` with its QP taken out, for a solver outside casadi
    (OSQP's embedded code: :mod:`hbma_ctrl.app.codegen.library`): (data, post, patterns).

    ``robot_qp_data`` (the step's inputs) -> (P's upper triangle and A as OSQP's CSC values, q, l, u,
    the primal and dual guesses, chk = [data finite; x0; the shifted states]); ``robot_qp_post`` (the
    solution z, its cost, the multipliers y, chk, A's values, l, u) -> the step's outputs, the same
    expressions as the step's on its solver's solution. ``patterns``: (P's rows, P's columns, A's rows, A's columns, nv, m)."""
    n, N = nmpc.n, nmpc.s.horizon
    nv, m = nmpc.nv, nmpc.m_rows
    ins = _step_inputs(nmpc)
    Pu, A, q, lo, up, zw, yw, xs, d_ok = _step_qp(nmpc, ins)
    chk = ca.vertcat(d_ok, ins[0], ca.vec(xs))
    data = ca.Function("robot_qp_data", ins, [Pu.nz[:], q, A.nz[:], lo, up, zw, yw, chk], _IN,
                       ["Px", "q", "Ax", "l", "u", "x_guess", "y_guess", "chk"])
    Psp, Asp = Pu.sparsity(), A.sparsity()
    MX = ca.MX
    z, cost, y, chk_s = MX.sym("z", nv), MX.sym("cost"), MX.sym("y", m), MX.sym("chk", chk.numel())
    ax, lo_s, up_s = MX.sym("Ax", Asp.nnz()), MX.sym("l", m), MX.sym("u", m)
    xs_s = ca.reshape(chk_s[1 + n:], n, N + 1)
    outs = _step_outputs(nmpc, chk_s[1:1 + n], xs_s, chk_s[0], MX(Asp, ax), lo_s, up_s, z, y)
    post = ca.Function("robot_qp_post", [z, cost, y, chk_s, ax, lo_s, up_s], outs,
                       ["z_qp", "cost", "y_qp", "chk", "Ax", "l", "u"], _OUT)
    cols = lambda sp: np.repeat(np.arange(sp.size2()), np.diff(np.array(sp.colind())))  # noqa: E731
    patterns = (np.array(Psp.row()), cols(Psp), np.array(Asp.row()), cols(Asp), nv, m)
    return data, post, patterns


class RobotNMPCFunction(RobotNMPC):
    """:class:`RobotNMPC` whose step is :func:`robot_rti_step_function`'s Function, compiled (OSQP linked
    from the casadi package), called through buffers: the controller of a generated robot loop, run
    from Python, so that a scene and its generated loop take the same decisions from the same inputs.

    The state it keeps is the Function's: the plan (``xbar``, ``abar``, ``obar``), the command sent
    (``prev``, from :meth:`applied`) and the last usable QP solution with whether there is one.
    ``failed`` on a status other than 0 (``status`` then says which), counted in ``inaccurate``;
    ``plan`` is the last usable solve's (H, n, 2). No wall-time budget (``overran`` stays False).
    """

    def __init__(self, model, n: int, settings: RobotMPCSettings | None = None, compile: bool = True):
        super().__init__(model, n, settings)
        #: the step (compiled unless ``compile`` is False: then casadi's Function itself, which a generated
        #: loop takes as its stage)
        self._fn = FastFunction(robot_rti_step_function(self), compile=compile, flags=casadi_lib_flags(["-losqp"]))
        self._zk, self._yk = np.zeros(self.nv), np.zeros(self.m_rows)
        self._warm = 0.0

    @property
    def step_function(self) -> ca.Function:
        """The step as casadi's Function (what a generated loop takes as its stage)."""
        return self._fn.fun

    def _data_call(self, lin):
        """None: the class's own QP-data call is never made here (the Function holds the data's graph),
        so its library is not built (12.6 s the first time on a machine for 9 chambers)."""
        return None

    def step(self, x0, b, W, h_ref, k=None, c=None, a_max=None):
        """One RTI step through the Function: (supply, outlet) decisions (n,) each, in [0, 1].
        ValueError naming the argument on a non-finite input."""
        t_start = time.perf_counter()
        n, N = self.n, self.s.horizon
        x0, b, W, href, k, c, amax = self._inputs(x0, b, W, h_ref, k, c, a_max)
        first = self.xbar is None
        xbar = np.zeros((n, N + 1)) if first else self.xbar
        out = self._fn(x0, b, W, k, c, amax, href, self.prev, xbar, self.abar, self.obar, float(first),
                       self._zk, self._yk, self._warm)
        a, o = out[0].copy(), out[1].copy()
        self.xbar = out[2].reshape(N + 1, n).T.copy()
        self.abar = out[3].reshape(N, n).T.copy()
        self.obar = out[4].reshape(N, n).T.copy()
        code = int(out[7][0])
        self.failed = code != 0
        self.overran = False
        self.late_plan = None
        if self.failed:
            self.inaccurate += 1
            self.status = {1: "non-finite solution", 2: f"residual {out[8][0]:.3g} > {RES_TOL:g}"}.get(code, str(code))
        else:
            self.status = "solved"
            self._zk, self._yk = out[5].copy(), out[6].copy()
            self._warm = 1.0
            self.plan = np.stack([self.abar.T, self.obar.T], axis=-1)
        self.prev = np.vstack([a, o])
        self.last_step_s = time.perf_counter() - t_start
        self.last_parts = {"status": self.status}
        return a, o
