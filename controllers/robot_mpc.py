"""Structured NMPC for the whole robot: per-chamber RTI QPs in one block-sparse OSQP problem (SI).

Model: every chamber is the gas-mass model of :class:`hbma_ctrl.models.bank.ChamberBank` with
its own load ``W`` (the robot's load sharing of the estimated heights, one control period old) and
flow factor ``b`` (from the chamber's EKF). The targets are chamber heights: the layer targets
(centre height, bend angle, bend direction) map onto them exactly by
:func:`hbma_ctrl.robot.kinematics.inverse_kinematics` (linear in the heights for a given bend), so tracking the
nine heights tracks every layer's height and bend.

Why the NMPC controls gas mass, and why it can hold the far branch: the state is the gas mass and
the height follows from it single-valued (``H(x, W)`` grows monotonically, also past the balloon
limit point). Holding a far-branch height means holding a gas mass, which is open-loop stable (the
gas is compressible); the pressure there is *below* the peak, and the QP only needs to keep the
predicted pressure under the limit while passing the peak.

Structure (real-time iteration, one QP per control period):

- linearisation and QP values: ONE call of a Function generated as C (cached on disk, called
  through preallocated buffers) that linearises the single-chamber stage (integrator step, its
  Jacobians, height and pressure with their slopes) at ``n_chambers x`` every ``lin_every``-th stage
  of the shifted previous solution and returns the QP's values in OSQP's CSC order (see
  ``_qp_data_function``); the previous solution, shifted by one stage, primal and dual, warm-starts
  OSQP;
- QP: variables per chamber block ``[x_1..x_N, a_0..a_{N-1}, o_0..o_{N-1}]`` (gas mass, supply,
  outlet duty); per block: dynamics rows, pressure-limit rows (linearised ``Pp(x_k) <= p_max``),
  input bounds. The cost is per chamber (height error in mm, small input and input-rate costs), so
  the Hessian and the constraint matrix are block diagonal — except for the shared-compressor
  topology's one coupling row per stage, ``sum_i a_i,k <= 1`` (the pump's flow budget, see
  :mod:`hbma_ctrl.models.bank`). The sparsity pattern is fixed; every period only the values are
  updated (``osqp.update``) and the solver is warm started.

If OSQP does not return a usable solution (status not solved), ``failed`` is set and
the step returns zeros (no decision); what is sent then (the last plan, then the safe command) is
the runtime supervisor's policy (:mod:`hbma_ctrl.runtime`), as are the step timing and the counts.
``plan`` (horizon, n, 2) holds the solved supply and outlet sequence of the last usable solve.

Time budget: with ``enforce_budget`` set (a real-time loop: the rig daemon), ``budget`` is a fraction
of the control period for the whole step (linearisation and QP); unset (scenes, benches, tests), the
wall clock decides nothing and a simulation's results do not depend on the machine's load. OSQP gets
what is left of the budget when its update begins as its ``time_limit`` at every solve (OSQP counts
the update in its own run time, so a QP it stops took the step past its budget; one stopped unusable
is ``failed``, ``overran``). A step that solved but took longer than the budget (the
linearisation was slow, a QP stopped that still passed OSQP's approximate test, say) is an overrun
too: ``failed`` and ``overran`` are set, the step returns zeros, and its solution is offered as
``late_plan``. Why not send a late solution: in the daemon the
command of a period is due at its deadline, and a step that ate its budget leaves the rest of the
period (I/O, logging) to chance; the supervisor's replay of the previous plan (one row on) is the
same trajectory the late solve refines. The late plan becomes the supervisor's plan for the NEXT
failure (its first row is already missed), and it warm-starts the next solve; the single chamber's
NMPC (:mod:`hbma_ctrl.controllers.mpc`) does the same. The first step (OSQP's setup) is exempt: a daemon
steps the controller once before its loop starts.

Inputs are checked: a non-finite state, factor, load, target or bound is a ValueError naming the
argument and chamber (a bad input is not a solver failure).
"""

from __future__ import annotations

from dataclasses import dataclass

import copy
import time

import casadi as ca
import numpy as np
import osqp

from hbma_ctrl.controllers.mpc_solvers import mapped_function, sparse
from hbma_ctrl.controllers.rti_c import _csc
from hbma_ctrl.core.codegen import FastFunction
from hbma_ctrl.core.interfaces import RobotControllerBase
from hbma_ctrl.core.settings import Settings, setting

__all__ = ["RobotMPCSettings", "RobotNMPC"]


@dataclass(frozen=True)
class RobotMPCSettings(Settings):
    """Robot NMPC settings (SI; each field's unit, range and one-line doc are in its declaration).

    w_slack : the limit rows are soft so that the QP stays feasible when noise or model error puts a
    chamber at the bound (the hard guard is the loop's interlock). Default 1e-3: the limit gives way
    by a few kPa for a millimetre of height, which lets a stiff chamber pass its limit point near the
    limit (``robot_bending`` settles 20/20 with it, 0/20 with 100); the rig daemon uses
    :data:`hbma_ctrl.app.daemon.build.DAEMON_W_SLACK` (100: the limit first, such poses not reached).
    max_iter, eps : measured on ``bench robot``'s 6-layer run against 400 and 1e-4, with lin_every = 2
    and the shifted warm start: 13860 OSQP iterations against 38625 with those, the worst step capped
    at 125 of them, the height RMSE 2.286 against 2.295 mm; a cap of 110 gave 2.286 mm too, 100 gave
    2.364 mm.
    budget : an overrun is a failure (see the module doc); it acts only with enforce_budget.
    enforce_budget : default False: offline runs -- scenes, tests, benchmarks -- stay reproducible
    whatever the machine's load; the rig daemon sets it, with a budget of e.g. 0.8.
    integrator : 'euler' is one gas-mass step per stage; the flow is smooth over 20 ms and it costs a
    quarter of rk4, which decides the 20 ms budget.
    lin_every : the linearisation is most of a step's work after the QP.
    """

    WHERE = "robot_mpc"

    sample_period: float = setting(0.01, lo=1e-3, hi=1.0, unit="s", doc="control period")
    dt: float = setting(0.02, lo=1e-3, hi=1.0, unit="s", doc="prediction step (inputs held over it)")
    horizon: int = setting(15, integer=True, lo=1, hi=200, unit="stages", doc="prediction stages")
    w_h: float = setting(1.0, lo=0.0, hi=1e6, unit="1/mm^2", doc="weight of the height error")
    w_terminal: float = setting(3.0, lo=0.0, hi=1e6, doc="factor on the last stage's weight")
    w_in: float = setting(1e-3, lo=0.0, hi=1e6, doc="quadratic input cost (supply and outlet)")
    r_in: float = setting(1e-3, lo=0.0, hi=1e6, doc="linear input cost (discourages pumping and venting at once)")
    w_du: float = setting(2e-3, lo=0.0, hi=1e6, doc="input-rate cost")
    p_max: float = setting(45e3, lo=1e3, hi=1e6, unit="Pa", doc="pressure limit")
    p_margin: float = setting(3e3, lo=0.0, hi=1e6, unit="Pa",
                              doc="the QP keeps the model pressure this far under p_max (noise, model error)")
    w_slack: float = setting(1e-3, lo=0.0, hi=1e6, unit="1/kPa",
                             doc="linear cost per kPa of each chamber's pressure slack")
    max_iter: int = setting(125, integer=True, lo=1, doc="OSQP iteration limit")
    eps: float = setting(3e-4, lo=1e-8, hi=1e-1, doc="OSQP tolerance")
    budget: float = setting(0.0, lo=0.0, hi=10.0,
                            doc="wall time of a step (linearisation and QP) as a fraction of sample_period; 0 = none")
    integrator: str = setting("euler", choices=("euler", "rk4"), doc="the prediction's scheme per stage")
    lin_every: int = setting(2, integer=True, lo=1, hi=10,
                             doc="the plan is linearised at every lin_every-th stage, standing for the stages "
                                 "up to the next one (1: at every stage)")
    enforce_budget: bool = setting(False, doc="act on budget (the rig daemon sets it)")

    def check_rules(self) -> None:
        self.within("p_margin", hi=self.p_max)


#: compiled QP data Functions of this process, by stage function, size and cost (see RobotNMPC._data_call)
_DATA_CACHE: dict = {}


def _has_text(v) -> bool:
    if isinstance(v, np.ndarray) and v.dtype.kind in "biuf":  # numbers (the usual case): no per-element look
        return False
    return any(isinstance(e, (str, bytes)) for e in np.ravel(np.asarray(v, dtype=object)))


def _finite(name: str, v, n: int) -> np.ndarray:
    """v as (n,) floats; ValueError naming the argument and the chamber when not a finite number."""
    try:
        if _has_text(v):
            raise ValueError
        a = np.asarray(v, dtype=float).reshape(n)
    except (TypeError, ValueError):
        raise ValueError(f"robot_mpc.{name}: need {n} finite numbers, got {v!r}") from None
    if not np.all(np.isfinite(a)):
        i = int(np.argwhere(~np.isfinite(a))[0][0])
        raise ValueError(f"robot_mpc.{name}: chamber {i}'s value is {a[i]!r}; it must be a finite number")
    return a


class RobotNMPC(RobotControllerBase):
    """NMPC over n chambers (see module doc): a :class:`~hbma_ctrl.core.interfaces.RobotEstimateController`.

    ``step(x0, b, W, h_ref, k=None, c=None) -> (a, o)``: x0 (n,) estimated scaled gas masses, b (n,)
    flow factors, W (n,) loads N, h_ref (n,) or (n, horizon) target heights m, k and c (n,) the
    estimated modulus and dead-volume factors (default 1), a_max (n,) an upper bound on each
    chamber's supply duty (default 1); returns the supply
    and outlet decisions (n,) each for this period. ``failed``: this step had no usable solution.
    """

    #: its step takes the EKF bank's estimate (gas masses and factors)
    feedback = "estimate"

    def __init__(self, model, n: int, settings: RobotMPCSettings | None = None):
        if not isinstance(n, int) or n < 1:
            raise ValueError(f"robot_mpc.n = {n!r} must be an integer >= 1")
        self.s = (settings or RobotMPCSettings()).validate()
        self.model = model
        self.n = n
        self.topology = model.topology
        N = self.s.horizon
        L = self.s.lin_every
        self._anchor = (np.arange(N + 1) // L) * L  # each stage's linearisation point
        self._anchor_pts = np.unique(self._anchor)
        self._expand = np.searchsorted(self._anchor_pts, self._anchor)
        self._build_pattern()
        self._data = self._data_call(model.linearisation(self.s.dt, 1, self.s.integrator))
        self.xbar = None
        self.abar = np.zeros((n, N))
        self.obar = np.zeros((n, N))
        self.prev = np.zeros((2, n))
        self.failed = False
        self.plan = None  # (horizon, n, 2): supply and outlet of the last usable solve
        self.inaccurate = 0
        self.overruns = 0
        self.overran = False
        self.late_plan = None  # (horizon, n, 2): the solution of an overrun step
        self.last_step_s = 0.0
        #: the last step's parts, s: QP data (the generated-C call), OSQP's update (values, warm start,
        #: time limit; refactorises), OSQP's solve (and its own timer's ``osqp_solve``); the solve's
        #: iterations and rho updates; the step's status (``status``, set at its end)
        self.last_parts = {"data": 0.0, "update": 0.0, "solve": 0.0, "iterations": 0, "rho_updates": 0,
                           "osqp_solve": 0.0}
        self.status = ""
        self._solver = None
        self._z = self._y = None  # the last usable QP solution (primal, dual)
        self._shift_x, self._shift_y = self._shift_maps()

    def applied(self, a, o) -> None:
        """The supply and outlet (n,) each actually sent (after the supervisor): the next step's input
        rate terms start from them (not from a decision a fallback or an interlock replaced)."""
        self.prev = np.vstack([np.asarray(a, dtype=float).reshape(self.n), np.asarray(o, dtype=float).reshape(self.n)])

    # --- layout ----------------------------------------------------------------------------------
    def _build_pattern(self) -> None:
        """The QP's size: per chamber a block of variables [x_1..x_N, a_0..a_{N-1}, o_0..o_{N-1}, slack]
        and of rows [dynamics N | pressure N | bounds 2N | slack >= 0], then a shared pump's coupling rows."""
        n, N = self.n, self.s.horizon
        self.nv = n * (3 * N + 1)
        self.m_rows = n * (4 * N + 1) + (N if self.topology == "shared" else 0)

    def _data_call(self, lin: ca.Function) -> FastFunction:
        """The QP data Function (compiled) through this controller's own buffers; built once per process
        for the same stage function, size and cost (building and hashing the graph takes seconds)."""
        s = self.s
        key = (id(lin), self.n, self.topology, s.horizon, s.lin_every, s.w_h, s.w_terminal, s.w_in, s.r_in,
               s.w_du, s.p_max, s.p_margin, s.w_slack)
        hit = _DATA_CACHE.get(key)
        if hit is None or hit[0] is not lin:  # (the identity check: an id can be reused after a model is freed)
            hit = (lin, FastFunction(self._qp_data_function(lin)).fun)
            _DATA_CACHE[key] = hit
        return FastFunction(hit[1], compile=False)

    def _qp_data_function(self, lin: ca.Function, looped: bool = True) -> ca.Function:
        """The QP's values from the step's data, as ONE Function generated as C (cached on disk):
        (x0, b, W, k, c, a_max (n each), targets (n, N) mm, previous inputs (2, n), the shifted plan
        x (n, N + 1), a, o (n, N)) -> P and A values in OSQP's CSC data order, q, l, u.

        The stage linearisation ``lin`` (one chamber, one point) runs at every linearisation point
        (every ``lin_every``-th stage, standing for the stages up to the next one) of every chamber:
        ``looped``, as one mapped call (C runs one node's code in a loop; built with casadi's
        common-subexpression elimination, so the table look-ups the value, the Jacobians and the
        outputs share are made once); otherwise inlined at every point (the code grows with the
        chambers and the stages). Infinite bounds are OSQP's infinity (1e30).
        """
        n, N = self.n, self.s.horizon
        SX = ca.SX
        x0, b, W, k, c, amax = (SX.sym(nm, n) for nm in ("x0", "b", "W", "k", "c", "a_max"))
        href, prev = SX.sym("h_ref_mm", n, N), SX.sym("prev", 2, n)
        xbar, abar, obar = SX.sym("xbar", n, N + 1), SX.sym("abar", n, N), SX.sym("obar", n, N)
        ins = [x0, b, W, k, c, amax, href, prev, xbar, abar, obar]
        names = ["x0", "b", "W", "k", "c", "a_max", "h_ref_mm", "prev", "xbar", "abar", "obar"]
        pts = self._anchor_pts.tolist()
        # the linearisation points, point-major (entry jj * n + i: chamber i at the jj-th point)
        xp = ca.vec(xbar[:, pts])
        ap = ca.vec(ca.horzcat(abar, abar[:, N - 1])[:, pts])
        op = ca.vec(ca.horzcat(obar, obar[:, N - 1])[:, pts])
        args = [xp.T, ca.horzcat(ap, op).T] + [ca.repmat(v, len(pts), 1).T for v in (W, b, k, c)]
        keys = ("xn", "Ax", "B", "h", "Hx", "p", "Px")
        return mapped_function("robot_qp_data", ins, names, ["Px", "Ax", "q", "l", "u"], lin, args,
                               lambda L: self._assemble(ins, dict(zip(keys, L))), looped)

    def _assemble(self, ins: list, L: dict) -> list:
        """[Px, Ax, q, l, u] from the step's data ``ins`` (the data Function's inputs, SX) and the
        linearisation at every point ``L`` (key -> (rows, n x points) SX, point-major columns)."""
        s, n, N = self.s, self.n, self.s.horizon
        SX, inf = ca.SX, 1e30
        x0, b, W, k, c, amax, href, prev, xbar, abar, obar = ins
        anc, ex = self._anchor.tolist(), self._expand.tolist()
        aext = ca.horzcat(abar, abar[:, N - 1])[:, anc]
        oext = ca.horzcat(obar, obar[:, N - 1])[:, anc]
        xb = xbar[:, anc]
        npts = len(self._anchor_pts)
        B = L["B"]
        M = {key: L[key] for key in ("xn", "Ax", "h", "Hx", "p", "Px")}
        M["Ba"], M["Bo"] = B[0, :], B[1, :]
        # (n, points) per quantity, then each stage's point
        L = {key: ca.reshape(v, n, npts)[:, ex] for key, v in M.items()}
        xn, Ax, Ba, Bo, p, Px = L["xn"], L["Ax"], L["Ba"], L["Bo"], L["p"], L["Px"]
        h, Hx = L["h"] * 1e3, L["Hx"] * 1e3
        # --- cost
        wk = np.full(N, s.w_h)
        wk[-1] *= s.w_terminal
        Wk = ca.repmat(ca.DM(wk).T, n, 1)
        Hs = Hx[:, 1:]
        r = h[:, 1:] - Hs * xb[:, 1:] - href  # h_lin = Hs x + r
        # the pressure slack (last) costs w_slack per kPa (see the settings: cheap in scenes, an exact
        # penalty in the daemon, where a chamber short of its target parked at the limit itself with a
        # cheap one)
        q = ca.horzcat(2 * Wk * Hs * r, s.r_in * SX.ones(n, 2 * N), s.w_slack * SX.ones(n, 1))
        q[:, N] = s.r_in - 2 * s.w_du * prev[0, :].T
        q[:, 2 * N] = s.r_in - 2 * s.w_du * prev[1, :].T
        du_diag = np.full(N, 4 * s.w_du)
        du_diag[-1] = 2 * s.w_du  # the last input has only one rate term after it
        diag_in = 2 * s.w_in + du_diag
        Px_diag = 2 * Wk * Hs ** 2 + 1e-6
        pmax = s.p_max - s.p_margin
        Aab = Ax[:, :N]
        cc = xn[:, :N] - Aab * xb[:, :N] - Ba[:, :N] * aext[:, :N] - Bo[:, :N] * oext[:, :N]
        rhs = ca.horzcat(cc[:, 0] + Aab[:, 0] * x0, cc[:, 1:])
        Pz = Px[:, 1:] * 1e-3  # pressure rows in kPa (conditioning), with the slack
        nb, rows_per = 3 * N + 1, 4 * N + 1
        P, A = [], []  # (row, column, value) entries: P's upper triangle, A by rows (_build_pattern)
        for i in range(n):
            x, a, o, sl = (i * nb + blk * N for blk in range(4))  # the block's first x, a, o; its slack
            r0 = i * rows_per
            P += [(x + k, x + k, Px_diag[i, k]) for k in range(N)]
            P += [(v + k, v + k, diag_in[k]) for v in (a, o) for k in range(N)]
            P += [(v + k - 1, v + k, -2 * s.w_du) for v in (a, o) for k in range(1, N)]
            P.append((sl, sl, 2.0))
            for k in range(N):  # x_{k+1} - A_k x_k - Ba a_k - Bo o_k = c_k
                A.append((r0 + k, x + k, 1.0))
                if k > 0:
                    A.append((r0 + k, x + k - 1, -Aab[i, k]))
                A += [(r0 + k, a + k, -Ba[i, k]), (r0 + k, o + k, -Bo[i, k])]
            A += [e for k in range(N) for e in ((r0 + N + k, x + k, Pz[i, k]), (r0 + N + k, sl, -1.0))]
            A += [(r0 + (2 if v == a else 3) * N + k, v + k, 1.0) for v in (a, o) for k in range(N)]
            A.append((r0 + 4 * N, sl, 1.0))
        lo = ca.horzcat(rhs, -inf * SX.ones(n, N), SX.zeros(n, 2 * N + 1))
        up = ca.horzcat(rhs, (pmax - p[:, 1:] + Px[:, 1:] * xb[:, 1:]) * 1e-3, ca.repmat(amax, 1, N),
                        SX.ones(n, N), inf * SX.ones(n, 1))
        lo, up = ca.vec(lo.T), ca.vec(up.T)
        if self.topology == "shared":  # the pump's budget: sum_i a_i,k <= 1
            A += [(n * rows_per + k, i * nb + N + k, 1.0) for k in range(N) for i in range(n)]
            lo = ca.vertcat(lo, -inf * SX.ones(N))
            up = ca.vertcat(up, SX.ones(N))
        return [sparse(P, (self.nv, self.nv)), sparse(A, (self.m_rows, self.nv)), ca.vec(q.T), lo, up]

    def _shift_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """Index maps moving a QP solution one stage on (the last stage repeated): variables, rows."""
        n, N = self.n, self.s.horizon
        st = np.r_[np.arange(1, N), N - 1]  # stage k takes stage k + 1
        nb = 3 * N + 1
        blk = np.r_[st, N + st, 2 * N + st, 3 * N]
        sx = (np.arange(n)[:, None] * nb + blk[None, :]).ravel()
        rows_per = 4 * N + 1
        rb = np.r_[st, N + st, 2 * N + st, 3 * N + st, 4 * N]
        sy = (np.arange(n)[:, None] * rows_per + rb[None, :]).ravel()
        if self.topology == "shared":
            sy = np.r_[sy, n * rows_per + st]
        return sx, sy

    # --- one period --------------------------------------------------------------------------------
    #: what a step changes besides the solver itself (prime restores them)
    _STEP_STATE = ("xbar", "abar", "obar", "prev", "failed", "plan", "inaccurate", "overruns", "overran",
                   "late_plan", "last_step_s", "last_parts", "status", "_z", "_y")

    def prime(self, x0, b, W, h_ref, k=None, c=None, a_max=None) -> None:
        """Start-up work before the first period (the step's arguments, SI): OSQP set up and solved
        once at this state, so the first step neither factorises nor starts from zero (measured on the
        robot daemon here: its first tick took 9-12 ms of a 10 ms period, 2 ms of it OSQP's set-up and
        125 iterations from zero). Everything a step changes is restored but the solver, whose iterate
        is this solution: the first step then warm-starts from it and its budget applies."""
        saved = {name: copy.deepcopy(getattr(self, name)) for name in self._STEP_STATE}
        try:
            self.step(x0, b, W, h_ref, k, c, a_max)
        finally:
            for name, v in saved.items():
                setattr(self, name, v)

    def _inputs(self, x0, b, W, h_ref, k, c, a_max) -> tuple:
        """The step's arguments checked and shaped (SI): (x0, b, W clipped to the tables, h_ref (n, N),
        k, c, a_max clipped to [0, 1]). ValueError naming the argument on a non-finite input."""
        n, N = self.n, self.s.horizon
        x0 = _finite("x0", x0, n)
        b = _finite("b", b, n)
        k = np.ones(n) if k is None else _finite("k", k, n)
        c = np.ones(n) if c is None else _finite("c", c, n)
        amax = np.ones(n) if a_max is None else np.clip(_finite("a_max", a_max, n), 0.0, 1.0)
        W = self.model.clip_load(_finite("W", W, n))
        href = np.asarray(h_ref, dtype=float) if not _has_text(h_ref) else None
        href = np.broadcast_to(href.reshape(n, -1), (n, N)) if href is not None and href.size in (n, n * N) else None
        if href is None:
            raise ValueError(f"robot_mpc.h_ref: need {n} or {n}x{N} target heights (m)")
        if not np.all(np.isfinite(href)):
            i = int(np.argwhere(~np.isfinite(href))[0][0])
            raise ValueError(f"robot_mpc.h_ref: chamber {i}'s target height is {href[i].ravel()[0]!r}; "
                             "it must be a finite number (m)")
        return x0, b, W, href, k, c, amax

    def step(self, x0, b, W, h_ref, k=None, c=None, a_max=None):
        """One RTI step (see the class doc): (supply, outlet) decisions (n,) each, in [0, 1].
        ValueError naming the argument on a non-finite input."""
        t_start = time.perf_counter()
        s, n, N = self.s, self.n, self.s.horizon
        x0, b, W, href, k, c, amax = self._inputs(x0, b, W, h_ref, k, c, a_max)
        href_mm = href * 1e3
        # shifted warm start
        if self.xbar is None:
            self.xbar = np.repeat(x0[:, None], N + 1, 1)
        else:
            self.xbar = np.hstack([self.xbar[:, 1:], self.xbar[:, -1:]])
            self.abar = np.hstack([self.abar[:, 1:], self.abar[:, -1:]])
            self.obar = np.hstack([self.obar[:, 1:], self.obar[:, -1:]])
        self.xbar[:, 0] = x0
        nb = 3 * N + 1  # variables per chamber block
        t_data = time.perf_counter()
        Pv, Av, qv, lo, up = self._data(x0, b, W, k, c, amax, href_mm, self.prev, self.xbar, self.abar, self.obar)
        t_update = time.perf_counter()
        # the wall clock decides only in a real-time loop: a simulation's step has no budget
        budget = s.budget * s.sample_period if s.enforce_budget else 0.0
        cold = self._solver is None
        if cold:
            self._solver = osqp.OSQP()
            # one Ruiz equilibration pass, not OSQP's 10: measured on bench robot's 6-layer run, 8455
            # iterations in all instead of 13860, the slowest steps 27 % shorter (each update of P and A
            # re-scales them too), RMSE 2.289 vs 2.286 mm (0 passes: 36835 iterations, 2.577 mm)
            kw = dict(verbose=False, eps_abs=s.eps, eps_rel=s.eps, max_iter=s.max_iter, polishing=False,
                      warm_starting=True, adaptive_rho=True, check_termination=5, scaling=1)
            P, A = (_csc(self._data.fun.sparsity_out(j), v) for j, v in ((0, Pv), (1, Av)))
            self._solver.setup(P=P, q=qv, A=A, l=lo, u=up, **kw)
        else:
            self._solver.update(Px=Pv, Ax=Av, q=qv, l=lo, u=up)
            if self._z is not None:
                # the previous solution shifted by one stage, primal and dual: OSQP's own warm start
                # (the unshifted one) is a stage off everywhere
                self._solver.warm_start(x=self._z[self._shift_x], y=self._y[self._shift_y])
            if budget > 0:
                # what was left of the step's budget when the update began (at least 0.1 ms: OSQP checks
                # it per iteration): OSQP counts the update's time (its refactorisation) in its run time
                # itself, so a QP it stops has always taken the step past its budget, and the step is an
                # overrun (logged, a replay forces it); what was left after the update would let a cut
                # QP that still ends usable ('solved inaccurate') pass as an ordinary step on a loaded
                # machine
                left = budget - (t_update - t_start)
                self._solver.update_settings(time_limit=max(left, 1e-4))
        t_solve = time.perf_counter()
        res = self._solver.solve(raise_error=False)
        t_end = time.perf_counter()
        self.last_parts = {"data": t_update - t_data, "update": t_solve - t_update, "solve": t_end - t_solve,
                           "iterations": int(res.info.iter), "rho_updates": int(getattr(res.info, "rho_updates", 0)),
                           "osqp_solve": float(getattr(res.info, "solve_time", float("nan")))}
        status = str(res.info.status)
        self.status = status
        usable = res.x is not None and np.all(np.isfinite(res.x)) and \
            status in ("solved", "solved inaccurate", "maximum iterations reached")
        if status != "solved":
            self.inaccurate += 1
        elapsed = time.perf_counter() - t_start
        self.overran = budget > 0 and not cold and (elapsed > budget or "time limit" in status)
        self.overruns += int(self.overran)
        self.late_plan = None
        self.failed = not usable or self.overran
        if self.overran and usable:
            self.status = f"overrun ({elapsed * 1e3:.1f} ms > {budget * 1e3:.1f} ms)"
        elif self.overran:
            self.status = f"overrun ({status})"
        if not usable:
            a = np.zeros(n)
            o = np.zeros(n)
            self.abar[:] = 0.0
            self.obar[:] = 0.0
        else:
            self._z, self._y = np.array(res.x), np.array(res.y)
            z = res.x.reshape(n, nb)
            self.xbar[:, 1:] = z[:, :N]
            self.abar = np.clip(z[:, N:2 * N], 0.0, 1.0)
            self.obar = np.clip(z[:, 2 * N:3 * N], 0.0, 1.0)
            a = self.abar[:, 0].copy()
            o = self.obar[:, 0].copy()
            plan = np.stack([self.abar.T, self.obar.T], axis=-1)
            if self.overran:
                # late: not sent (see the module doc); the warm start keeps the solution
                self.late_plan = plan
                a, o = np.zeros(n), np.zeros(n)
            else:
                self.plan = plan
            if self.topology == "shared" and a.sum() > 1.0:
                a /= a.sum()
        self.prev = np.vstack([a, o])
        self.last_step_s = time.perf_counter() - t_start
        # last in the parts: a slow tick's event ends with it (whether the step overran and how)
        self.last_parts["status"] = self.status
        return a, o
