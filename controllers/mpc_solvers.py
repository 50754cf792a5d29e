"""What the variants of :class:`hbma_ctrl.controllers.mpc.NMPC` share (the stage, the step's problem, the
failures, sparsity patterns) and its NLP variants, IPOPT and fatrop (accurate); the RTI variants are in
:mod:`hbma_ctrl.controllers.rti_c` and :mod:`hbma_ctrl.controllers.rti_step`.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import casadi as ca
import numpy as np
import scipy.sparse as sp

from hbma_ctrl.controllers.mpc_settings import WEIGHTS, MPCSettings, weights_of
from hbma_ctrl.core.codegen import (HOT_FLAGS, HOT_OPT, NATIVE_FLAGS, cache_dir, casadi_lib_flags, compiled,
                                    has_compiler)
from hbma_ctrl.models.tables import PredictionModel


class _SolverFailure(RuntimeError):
    pass


class _BudgetExceeded(_SolverFailure):
    """The solver stopped at its time limit (the step's budget): counted as an overrun."""


#: OSQP's own default ``time_limit``, s: no limit in practice (it refuses 0)
OSQP_NO_TIME_LIMIT = 1e10


def qp_time_limit(s: MPCSettings) -> float:
    """OSQP's ``time_limit`` for a warm step, s: the step's budget when it is enforced, else none
    (:data:`OSQP_NO_TIME_LIMIT`), so that a simulation's QPs never stop on the wall clock."""
    return float(s.budget) if s.enforce_budget else OSQP_NO_TIME_LIMIT


@dataclass
class _Problem:
    """Per-step parameters of the OCP (scaled units: h in mm, p in kPa)."""

    x0: float
    W: float
    dh: float  # m
    dp: float  # Pa
    r: np.ndarray  # m, target at stages 1..N (clipped)
    u_prev: np.ndarray
    p_lim: float  # Pa, on the model pressure + dp


def sparse(entries: list, shape: tuple) -> ca.SX:
    """A sparse SX of ``shape`` with these (row, column, value) entries, each one structural (a zero
    value too); its nonzeros are the values in CSC order (OSQP's)."""
    rows, cols, vals = zip(*entries)
    # each entry's number at its place: the CSC data order is then the permutation of the entries
    M = sp.csc_matrix((np.arange(1, len(rows) + 1, dtype=float), (rows, cols)), shape=shape)
    M.sort_indices()
    if M.nnz != len(rows):
        raise RuntimeError("duplicate entries in a sparsity pattern")
    sparsity = ca.Sparsity(shape[0], shape[1], M.indptr.tolist(), M.indices.tolist())
    return ca.SX(sparsity, ca.vertcat(*vals)[(M.data.astype(np.int64) - 1).tolist()])


class Rows:
    """Linear constraints lo <= A z <= up written row by row: (column, value) entries and the bounds."""

    def __init__(self):
        self.entries, self.lo, self.up = [], [], []

    def add(self, entries: list, lo, up) -> None:
        self.entries.append(entries)
        self.lo.append(lo)
        self.up.append(up)

    def matrix(self, n: int) -> tuple:
        """(A (sparse SX, a row per :meth:`add`, ``n`` columns), lo, up)."""
        A = sparse([(r, c, v) for r, ents in enumerate(self.entries) for c, v in ents], (len(self.entries), n))
        return A, ca.vertcat(*self.lo), ca.vertcat(*self.up)


def mapped_function(name: str, ins: list, names: list[str], out_names: list[str], lin: ca.Function, args: list,
                    assemble, looped: bool = True) -> ca.Function:
    """ONE Function of the SX inputs ``ins`` (named ``names``) to ``assemble(L)``: L holds ``lin``'s
    outputs at n points (output i as an SX of ``lin.nnz_out(i)`` x n, a column a point), whose inputs
    are ``args`` (SX expressions of ``ins``: lin's input i at the points, a column a point).

    ``looped``: lin runs as one mapped call (C runs one point's code in a loop), built with casadi's
    common-subexpression elimination (the table look-ups its outputs share are made once), between two
    SX Functions (the points, the assembly); otherwise lin is inlined at every point (the code grows
    with the points).
    """
    n = args[0].shape[1]
    if not looped:
        outs = [lin(*[a[:, j] for a in args]) for j in range(n)]
        L = [ca.horzcat(*[ca.vec(o[i]) for o in outs]) for i in range(lin.n_out())]
        return ca.Function(name, ins, assemble(L), names, out_names, {"cse": True})
    sx_in = [ca.SX.sym(lin.name_in(i), lin.sparsity_in(i)) for i in range(lin.n_in())]
    node = ca.Function(f"{name}_node", sx_in, lin(*sx_in), lin.name_in(), lin.name_out(), {"cse": True})
    points = ca.Function(f"{name}_points", ins, args)
    L = [ca.SX.sym(node.name_out(i), node.nnz_out(i), n) for i in range(node.n_out())]
    post = ca.Function(f"{name}_assemble", ins + L, assemble(L), {"cse": True})
    mx = [ca.MX.sym(nm, v.sparsity()) for nm, v in zip(names, ins)]
    outs = node.map(n)(*points(*mx))
    return ca.Function(name, mx, post(*mx, *[ca.reshape(o, node.nnz_out(i), n) for i, o in enumerate(outs)]),
                       names, out_names)


class _Stage:
    """Discrete dynamics and outputs shared by every variant (casadi), the tables evaluated as ``form``
    (:meth:`PredictionModel.functions`: 'poly' where the stage runs on casadi's virtual machine or in C
    compiled once per machine; 'bspline' where it is compiled at every construction or into every
    generated program, whose build time the polynomials double)."""

    def __init__(self, model: PredictionModel, s: MPCSettings, form: str = "bspline"):
        self.F = model.discrete(s.sample_period, s.integrator, s.substeps, form)
        fns = model.functions(form)
        x, W, dp = ca.SX.sym("x"), ca.SX.sym("W"), ca.SX.sym("dp")
        u = ca.SX.sym("u", 3)
        ulin = ca.SX.sym("ulin", 3)
        xn = self.F(x, u, W, dp)
        h = fns.H(x, W) * 1e3  # mm
        p = fns.Pp(x, W) * 1e-3  # kPa (model, without bias)
        lam = fns.L(x, W) * 1e2  # 1/100
        # dynamics value at the plan, Jacobians at the (floored) linearisation point: one Jacobian in
        # (x, ulin), one reverse sweep for the scalar dynamics; two separate ones cost a forward and a
        # reverse sweep through every table call (the generated QP data: 83 -> 67 us, equal to 2e-16)
        xl = self.F(x, ulin, W, dp)
        J = ca.jacobian(xl, ca.vertcat(x, ulin))
        self.lin = ca.Function(
            "lin", [x, u, ulin, W, dp],
            [xn, J[:, 0], J[:, 1:], h, ca.jacobian(h, x), p, ca.jacobian(p, x),
             lam, ca.jacobian(lam, x)],
            ["x", "u", "ulin", "W", "dp"], ["f", "a", "b", "h", "ch", "p", "cp", "lam", "cl"])
        self.out = ca.Function("out", [x, W], [h, p, lam])


def _input_terms(u, u_before, du: np.ndarray, wr, wu, cu) -> tuple:
    """An input's cost (rate from ``u_before``, quadratic, linear) and rows (the rate within ``du``,
    speed <= inlet) of the NLP variants: (cost, rows, lower bounds, upper bounds)."""
    d = u - u_before
    return (ca.dot(wr, d ** 2) + ca.dot(wu, u ** 2) + ca.dot(cu, u), [d, u[1] - u[0]], [*(-du), 0.0],
            [*du, ca.inf])


def _soft_limits(stage: _Stage, s: MPCSettings, x, W, dh, dp, p_lim, slack) -> tuple:
    """The NLP variants' soft limits at state ``x`` (QP units; ``dh`` in mm, ``dp`` in Pa, ``p_lim`` in
    kPa): the biased height (mm) and the rows (pressure, stretch, height above and below, each minus
    ``slack``) with their upper bounds."""
    h, p, lam = stage.out(x, W)
    rows = [(p + dp * 1e-3 - p_lim, 0.0), (lam - s.lam_max * 1e2, 0.0), (h + dh - s.h_max * 1e3, 0.0),
            (s.h_min * 1e3 - h - dh, 0.0 if s.h_min > 0 else ca.inf)]
    return h + dh, [e - slack for e, _ in rows], [ub for _, ub in rows]


def _shifted(a: np.ndarray) -> np.ndarray:
    """A plan moved one stage on (along the first axis), the last stage repeated."""
    return np.concatenate([a[1:], a[-1:]])


class _Ipopt:
    """Multiple-shooting NLP, IPOPT to convergence, warm-started with the shifted solution.

    Its functions run on casadi's virtual machine (``mode`` "vm"). ``generate``: the whole solver generated
    as C instead, IPOPT's calls into the ``libipopt`` shipped in the casadi wheel, built as the fatrop
    variant's is (:data:`HOT_OPT`, the processor's :data:`NATIVE_FLAGS`, cached on disk: about 80 s the
    first time at N = 20; ``mode`` "c"), for ``bench mpc --ipopt-c``: fatrop against IPOPT on the same
    footing. The generated solver keeps no statistics: a failed solve is the error it raises, and
    ``iterations`` is None.
    """

    def __init__(self, model: PredictionModel, s: MPCSettings, generate: bool = False):
        self.s, self.model = s, model
        N = self.N = s.horizon
        self.stage = _Stage(model, s, "poly")  # no JIT: the polynomials are evaluated faster
        F = self.stage.F
        X = ca.SX.sym("X", N + 1)
        U = ca.SX.sym("U", 3, N)
        S = ca.SX.sym("S", N)
        par = ca.SX.sym("par", 8 + N)  # x0, W, dh(mm), dp(Pa), u_prev(3), p_lim(kPa), r(mm, N stages)
        x0, W, dh, dp = par[0], par[1], par[2], par[3]
        u_prev, p_lim, rr = par[4:7], par[7], par[8:]
        J = 0
        g, lbg, ubg = [X[0] - x0], [0.0], [0.0]
        wr, wu, cu = (ca.DM(list(v)) for v in (s.w_rate, s.w_input, s.c_input))
        du = np.array(s.du_max, float) * s.sample_period
        for k in range(N):
            g.append(X[k + 1] - F(X[k], U[:, k], W, dp))
            lbg.append(0.0); ubg.append(0.0)  # noqa: E702
            cost, rows, lo, up = _input_terms(U[:, k], u_prev if k == 0 else U[:, k - 1], du, wr, wu, cu)
            hd, soft, ubs = _soft_limits(self.stage, s, X[k + 1], W, dh, dp, p_lim, S[k])
            w = s.w_height + (s.w_terminal if k == N - 1 else 0.0)
            J += cost
            J += w * (hd - rr[k]) ** 2 + s.w_slack * S[k] ** 2 + s.c_slack * S[k]
            g += rows + soft
            lbg += lo + [-ca.inf] * len(soft)
            ubg += up + ubs
        z = ca.vertcat(X, ca.vec(U), S)
        self.nz = z.shape[0]
        nlp = {"x": z, "p": par, "f": J, "g": ca.vertcat(*g)}
        opts = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
                "ipopt.max_iter": s.ipopt_max_iter, "ipopt.tol": 1e-6,
                "ipopt.warm_start_init_point": "yes", "ipopt.mu_init": 1e-3,
                "error_on_fail": False}
        if s.enforce_budget:  # a real-time loop bounds the solve; a simulation never stops on the wall clock
            opts["ipopt.max_wall_time"] = max(10 * s.budget, 0.5)
        self.solver = ca.nlpsol("mpc_ipopt", "ipopt", nlp, dict(opts, error_on_fail=generate))
        self.mode = "vm"
        if generate:
            if not has_compiler():
                raise ValueError("ipopt generated as C needs a C compiler (cc, gcc or clang); none was found")
            ext = compiled(self.solver, HOT_OPT, [*casadi_lib_flags(["-lipopt"]), *HOT_FLAGS, *NATIVE_FLAGS],
                           on_failure="none", notice=_build_notice("ipopt", N))
            if ext is None:
                raise ValueError("ipopt generated as C: the build failed")
            self.solver, self.mode = ext, "c"
        self.lbg, self.ubg = np.array(lbg, float), np.array(ubg, float)
        umax = np.array(s.u_max, float)
        self.lbz = np.r_[np.full(N + 1, -0.5), np.zeros(3 * N), np.zeros(N)]
        self.ubz = np.r_[np.full(N + 1, 50.0), np.tile(umax, N), np.full(N, np.inf)]
        self.X = self.U = self.S = None
        self.lam_g = None
        self.iterations = 0

    def reset(self) -> None:
        self.X = self.U = self.S = None
        self.lam_g = None

    def solve(self, pr: _Problem):
        N = self.N
        if self.X is None:
            Xb, Ub, Sb = np.full(N + 1, pr.x0), np.tile(pr.u_prev, (N, 1)), np.zeros(N)
        else:
            Xb, Ub, Sb = np.r_[pr.x0, _shifted(self.X)[1:]], _shifted(self.U), _shifted(self.S)
        z0 = np.r_[Xb, Ub.ravel(), Sb]
        par = np.r_[pr.x0, pr.W, pr.dh * 1e3, pr.dp, pr.u_prev, pr.p_lim * 1e-3, pr.r * 1e3]
        kw = {}
        if self.lam_g is not None:
            kw["lam_g0"] = self.lam_g
        sol = _nlp_solve(self, "ipopt", x0=z0, p=par, lbx=self.lbz, ubx=self.ubz, lbg=self.lbg, ubg=self.ubg, **kw)
        z = np.asarray(sol["x"]).ravel()
        self.lam_g = np.asarray(sol["lam_g"]).ravel()
        self.X = z[:N + 1]
        self.U = np.clip(z[N + 1:N + 1 + 3 * N].reshape(N, 3), 0.0, 1.0)
        self.S = z[N + 1 + 3 * N:]
        return self.X, self.U


def _build_notice(name: str, N: int) -> str:
    """The line a generated NLP solver's first build on a machine writes to stderr."""
    return (f"{name}: building the generated solver for N = {N} on this machine, once (about 80 s at N = 20, "
            f"6 s at N = 6); cached in {cache_dir()}")


def _nlp_solve(backend, name: str, **args) -> dict:
    """One solve of ``backend.solver`` (an nlpsol, or its generated C when ``backend.mode`` is "c"); sets
    ``backend.iterations`` (None from generated C, which keeps no statistics) and returns the solution.
    A failed solve is a _SolverFailure naming the solver: generated C raises it (``error_on_fail``, its
    only report), the virtual machine reports it in its statistics (and raises too where the solver was
    built to be generated and its build failed)."""
    backend.iterations = None
    try:
        sol = backend.solver(**args)
    except RuntimeError:
        why = "the solve failed (not converged)" if backend.mode == "c" else \
            str(backend.solver.stats().get("return_status", "the solve failed"))
        raise _SolverFailure(f"{name}: {why}") from None
    if backend.mode != "c":
        st = backend.solver.stats()
        backend.iterations = int(st.get("iter_count", 0) or 0)
        if not st.get("success", False):
            raise _SolverFailure(f"{name}: {st.get('return_status')}")
    return sol


class _Fatrop:
    """The IPOPT variant's OCP in stage form for fatrop (casadi ``nlpsol``, structure detected).

    Stage k < N holds the states [x_k, v_k (the previous input), sigma_k (the previous slack)] and
    the controls [u_k, s_k], stage N the states [x_N, v_N, sigma_N]. v_{k+1} = u_k makes the
    input-rate terms stage-local; sigma_{k+1} = s_k carries the slack of the limits at stage k + 1
    to that stage, so the height cost and the limits are written on the stage's own state x_k, as
    IPOPT's are on X[k] (sigma_0 = 0). The optimum is the IPOPT variant's (same cost, same feasible
    set). Written on the prediction F(x_k, u_k) instead, every stage's Hessian would hold the outputs'
    second derivatives through the integrator: the same iterations, dearer ones (docs/concepts/control.md).

    With ``settings.codegen`` and a C compiler the whole solver (fatrop and the NLP's functions, the
    tables as inline polynomials) is generated as C, built at :data:`HOT_OPT` for this machine's processor
    (:data:`~hbma_ctrl.core.codegen.NATIVE_FLAGS`) against the fatrop
    library shipped in the casadi package and cached on disk (:func:`compiled`: about 80 s the first
    time on a machine at N = 20, then a load); ``mode`` is then "c". Otherwise (or if that build
    fails, with a warning) the solver runs on casadi's virtual machine (``mode`` "vm"). With one
    state per stage the NLP is bound by function evaluations, not by the linear algebra fatrop's
    structure speeds up, so how they are compiled sets the step's time.
    The generated solver reports no statistics: a solve that does not converge raises inside it
    (``error_on_fail``), and ``iterations`` is None.
    """

    def __init__(self, model: PredictionModel, s: MPCSettings):
        self.s, self.model = s, model
        N = self.N = s.horizon
        generate = bool(s.codegen) and has_compiler()
        # the polynomials: a cold solve (N = 20, 41 iterations) 96 -> 86 ms on the virtual machine, and
        # as C at -O3 36 -> 31 ms, for twice the build (once per machine)
        self.stage = _Stage(model, s, "poly")
        F = self.stage.F
        # as _Ipopt: x0, W, dh(mm), dp(Pa), u_prev(3), p_lim(kPa), r(mm), then the cost's weights (WEIGHTS):
        # parameters, so that the generated solver serves every weighting (a tuning study's trials)
        par = ca.SX.sym("par", 8 + N + len(WEIGHTS))
        x0, W, dh, dp = par[0], par[1], par[2], par[3]
        u_prev, p_lim, rr = par[4:7], par[7], par[8:8 + N]
        wts = par[8 + N:]
        w_height, w_terminal, wr, wu, cu, w_slack, c_slack = (wts[0], wts[1], wts[2:5], wts[5:8], wts[8:11], wts[11],
                                                              wts[12])
        self._weights = weights_of(s)
        du = np.array(s.du_max, float) * s.sample_period
        umax = np.array(s.u_max, float)
        inf = ca.inf
        xs = [ca.SX.sym(f"x{k}") for k in range(N + 1)]
        vs = [ca.SX.sym(f"v{k}", 3) for k in range(N + 1)]
        sg = [ca.SX.sym(f"sigma{k}") for k in range(N + 1)]
        us = [ca.SX.sym(f"u{k}", 3) for k in range(N)]
        ss = [ca.SX.sym(f"s{k}") for k in range(N)]
        z, lbz, ubz, g, lbg, ubg = [], [], [], [], [], []
        J = 0
        for k in range(N + 1):
            z += [xs[k], vs[k], sg[k]]
            lbz += [-0.5, -inf, -inf, -inf, -inf]
            ubz += [50.0, inf, inf, inf, inf]
            if k < N:
                z += [us[k], ss[k]]
                lbz += [0.0, 0.0, 0.0, 0.0]
                ubz += list(umax) + [inf]
                # the dynamics first (what fatrop's detection reads); v and sigma carry the input
                # and the slack into the next stage
                g += [xs[k + 1] - F(xs[k], us[k], W, dp), vs[k + 1] - us[k], sg[k + 1] - ss[k]]
                lbg += [0.0] * 5
                ubg += [0.0] * 5
            if k == 0:
                g += [xs[0] - x0, vs[0] - u_prev, sg[0]]
                lbg += [0.0] * 5
                ubg += [0.0] * 5
            if k < N:
                cost, rows, lo, up = _input_terms(us[k], vs[k], du, wr, wu, cu)
                g += rows
                lbg += lo
                ubg += up
                J += cost
                J += w_slack * ss[k] ** 2 + c_slack * ss[k]
            if k == 0:
                continue
            # stage k's outputs on its own state: the limits with the slack sigma_k = s_{k-1}
            hd, soft, ubs = _soft_limits(self.stage, s, xs[k], W, dh, dp, p_lim, sg[k])
            w = w_height + w_terminal if k == N else w_height
            J += w * (hd - rr[k - 1]) ** 2
            g += soft
            lbg += [-inf] * len(soft)
            ubg += ubs
        zz = ca.vertcat(*z)
        nlp = {"x": zz, "p": par, "f": J, "g": ca.vertcat(*g)}
        eq = [bool(lo == up) for lo, up in zip(lbg, ubg)]
        opts = {"structure_detection": "auto", "equality": eq, "print_time": False, "error_on_fail": generate,
                "fatrop": {"print_level": 0, "max_iter": s.ipopt_max_iter, "tol": 1e-6,
                           "mu_init": 1e-3}}
        self.solver = ca.nlpsol("mpc_fatrop", "fatrop", nlp, opts)
        self.mode = "vm"
        if generate:
            ext = compiled(self.solver, HOT_OPT, [*casadi_lib_flags(["-lfatrop", "-lblasfeo"]), *HOT_FLAGS, *NATIVE_FLAGS],
                           on_failure="none", notice=_build_notice("fatrop", N))
            if ext is None:
                warnings.warn("fatrop: its generated C did not build; the solver runs on casadi's virtual "
                              "machine (slower, same results)", RuntimeWarning, stacklevel=3)
            else:
                self.solver, self.mode = ext, "c"
        self.lbz, self.ubz = np.array(lbz, float), np.array(ubz, float)
        self.lbg, self.ubg = np.array(lbg, float), np.array(ubg, float)
        self.nz = zz.shape[0]
        ns = 9  # per stage [x, v (3), sigma, u (3), s]; the last stage [x, v, sigma]
        self.ix = ns * np.arange(N + 1)
        self.iv = (ns * np.arange(N + 1))[:, None] + 1 + np.arange(3)[None, :]
        self.isg = ns * np.arange(N + 1) + 4
        self.iu = (ns * np.arange(N))[:, None] + 5 + np.arange(3)[None, :]
        self.isl = ns * np.arange(N) + 8
        self.z = None
        self.lam_g = None
        self.iterations = 0

    @property
    def X(self):
        return None if self.z is None else self.z[self.ix]

    def reset(self) -> None:
        self.z = None
        self.lam_g = None

    def solve(self, pr: _Problem):
        z0 = np.zeros(self.nz)
        if self.z is None:
            z0[self.ix] = pr.x0
            z0[self.iu] = pr.u_prev
            z0[self.iv] = pr.u_prev
        else:  # the previous solution shifted by one stage (the last stage repeated)
            z0[self.ix] = np.r_[pr.x0, _shifted(self.z[self.ix])[1:]]
            Ub = _shifted(self.z[self.iu])
            z0[self.iu] = Ub
            z0[self.iv] = np.vstack([pr.u_prev, Ub])
            z0[self.isl] = _shifted(self.z[self.isl])
            z0[self.isg[1:]] = z0[self.isl]
        par = np.r_[pr.x0, pr.W, pr.dh * 1e3, pr.dp, pr.u_prev, pr.p_lim * 1e-3, pr.r * 1e3, self._weights]
        sol = _nlp_solve(self, "fatrop", x0=z0, p=par, lbx=self.lbz, ubx=self.ubz, lbg=self.lbg, ubg=self.ubg)
        z = np.asarray(sol["x"]).ravel()
        if not np.all(np.isfinite(z)):
            raise _SolverFailure("fatrop: non-finite solution")
        self.z = z
        return z[self.ix], np.clip(z[self.iu], 0.0, 1.0)
