"""The chamber's (or the robot's) estimator + controller + supervisor tick as a self-contained C library
(``codegen --library``).

The control side of a scenario's chamber system (:meth:`hbma_ctrl.system.chamber.ChamberSystem.to_function`:
the EKF's stages, the NMPC's problem data, cold start and RTI step, the supervisor and the valves'
minimum on-time shaping) becomes a C library with a fixed-memory API:

- ``hbma_init(&ws, &params)``, ``hbma_set_target(&ws, h, preview)``, ``hbma_tick(&ws, t, p, held, u)``
  and ``hbma_outputs(&ws, &out)`` (``hbma.h``), status codes ``HBMA_OK``, ``HBMA_SOLVE_FAILED``, ...;
- all memory in the caller's ``hbma_workspace_t``, whose size is a compile-time constant: the signals,
  one set of casadi work arrays sized by the largest ``*_work`` of the generated Functions, and the QP
  solver's memory; no malloc, no file I/O, no global state, nothing outside the generated tree;
- a named parameter struct (``hbma_model_params_t``: the EKF model's parameters by their names, SI).

The QP inside the RTI step is solved by OSQP's own embedded code (osqp >= 1.0, ``codegen`` with
matrix updates: its sources copied into ``osqp/``), the problem data and the post-processing by the
same casadi Functions the RTI step Function calls (``rti_qp_data``, ``rti_post``,
:func:`hbma_ctrl.controllers.rti_step.rti_step_function`); a solution is usable when it violates the
QP's constraints by no more than OSQP's own primal test allows (:func:`_qp_post`). Why OSQP's embedded
code and not casadi's own code-generated solvers: qrqp fails on this QP's cold starts and needs 10-200
ms per solve on a PC (``hbma_ctrl.controllers.rti_step``), ``ipqp`` does not code-generate, and the
other conic plugins (OSQP, HPIPM, DAQP) generate calls into shared libraries. OSQP's generated workspace is a
set of globals; :func:`hbma_ctrl.core.osqp_embed.own_workspace` moves them into a struct the
workspace holds. The solver is warm-started from the RTI step's shifted primal and dual guesses.

The EKF starts from the scenario's first reading at generation time (its prior, as the generated
loop's does); the library's first tick marks it started. Left out as in the generated loop: the
start-up calibration, the NMPC's fallback drill (``fail_window``), load steps.

A closed-loop ``[robot]`` scenario with the NMPC gives the robot's library through the same path
(:func:`library_spec` dispatches): the stages of its system's control side
(:meth:`hbma_ctrl.system.robot.RobotSystem.to_function`: the EKF bank, the loads, the targets' slew and
supply caps, the robot NMPC's step, the supervisor and the valves), its n chambers' signals
(``hbma_tick(&ws, t, p[n], held[3][n], u[3][n])``), the layers' poses as targets
(``hbma_set_target(&ws, pose[L][3])``: centre height, bend, direction, through the inverse kinematics),
the bank started at rest from the first tick's readings, and the NMPC's QP taken out of its step
(:func:`hbma_ctrl.controllers.robot_rti_step.robot_rti_qp_functions`) for OSQP's embedded code with the
step's settings. Its bank predicts with what the rig reports it held, matched against the commands sent
lately as :meth:`hbma_ctrl.runtime.robot.RobotLoop.tick` matches it (in lockstep: the command it
returned, as in the robot's generated loop).

:func:`record_inputs` runs the scenario's own closed loop on the sim rig to record the pressures a run
replays; :func:`run_library` builds and runs the library's driver ``hbma_run.c`` (host, or bare-metal
on QEMU through semihosting) on them and reads its commands and instruction counts.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import struct
import subprocess
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import casadi as ca
import numpy as np

from hbma_ctrl.core.codegen import OPT_ENV
from hbma_ctrl.core.loopgen import LOG, LoopSpec, dense_function
from hbma_ctrl.core.loopgen_c import c_array, stage_guard
from hbma_ctrl.core.osqp_embed import own_workspace

__all__ = ["TARGETS", "PRECISIONS", "QP_SOLVERS", "LibrarySpec", "library_spec", "write_library", "record_inputs",
           "write_inputs", "build_library", "run_library", "check_precision", "LibraryRun", "embedded_report",
           "qemu_command"]

#: build targets: the host's C compiler, or arm-none-eabi-gcc for a Cortex-M run on QEMU
TARGETS = ("host", "cortex-m7", "cortex-m4f")
#: the library's QP solvers: OSQP's embedded code on the sparse QP, or DAQP on the QP condensed onto the
#: inputs and slacks (a chamber's library, double precision)
QP_SOLVERS = ("osqp", "daqp")
#: floating-point precision of the library (casadi_real, OSQPFloat and the API's hbma_real)
PRECISIONS = ("double", "single")
#: the arm-none-eabi-gcc flags and the QEMU machine of each Cortex-M target
_ARM = {
    "cortex-m7": (["-mcpu=cortex-m7", "-mthumb", "-mfpu=fpv5-d16", "-mfloat-abi=hard"], "mps2-an500"),
    "cortex-m4f": (["-mcpu=cortex-m4", "-mthumb", "-mfpu=fpv4-sp-d16", "-mfloat-abi=hard"], "mps2-an386"),
}
#: optimisation of every build (no fast-math: host and target round alike). -O3 computes what -O2 does bit
#: for bit (C99 mode contracts no multiply-adds) with 27 % fewer instructions in the QP data Function and
#: 14 % fewer in the EKF's step on the Cortex-M7 (track_height), for 0.4 % more flash
OPT = "-O3"
#: OSQP's prefix of its generated workspace
QP_PREFIX = "hbma_qp_"
#: OSQP settings beyond the NMPC's tolerances and iteration limit: the termination test every 5 iterations
#: (OSQP's default, 25, runs up to 24 iterations past convergence of a warm-started RTI QP: 30 % fewer
#: instructions over track_height's first 200 ticks).
#: OSQP's 10 Ruiz passes stay, although the embedded solver redoes them at every matrix update (about
#: 0.89 M instructions per controller tick on the Cortex-M7): fewer passes lower the median tick on one
#: scenario and raise it, or the tail, on another. Controller ticks over 2,000 ticks (`--duration-s 20`),
#: median / mean / 99th percentile in M instructions, QP iterations median, no failed step in any run:
#: track_height 10 passes 3.84 / 4.31 / 9.83, 15; 5 passes 4.70 / 4.43 / 9.40, 30; 3 passes 3.25 / 3.57 /
#: 7.92, 15; 2 passes 4.02 / 3.83 / 8.05, 25; 1 pass 3.07 / 3.50 / 11.28, 15. mpc_ramp_sine 10 passes
#: 4.31 / 4.39 / 7.09, 20; 3 passes 4.62 / 5.06 / 10.90, 30; 1 pass 3.50 / 3.63 / 11.29, 20 (and QPs at the
#: 300-iteration limit). A tick's budget is set by its tail, which 1 pass raises on both. OSQP's
#: duality-gap test off: 4.34 M median and 268 steps above an absolute violation of 1e-3 over
#: track_height's first 1,000 ticks; no
#: scaling, or the setup's scaling kept: 25 and 55 iterations per QP against 15 over its first 200.
#: The step size rho OSQP adapts carries over from one QP to the next; restarting it at 0.1 at every step
#: (as casadi's OSQP does) takes a median of 35 iterations per QP instead of 15 over track_height's 2,000
#: ticks, 50 with the termination test every 25 iterations as well.
QP_SETTINGS: dict = {"check_termination": 5}
#: the parts of the RTI step's QP path a profiled build counts apart (hbma.h's HBMA_PART_NAMES), by QP solver
_QP_PARTS = {"osqp": ("qp_data", "osqp_update_mat", "osqp_update_vec", "osqp_solve", "qp_post"),
             "daqp": ("qp_data", "daqp_update_ldp", "daqp_solve", "qp_post")}
#: the casadi-generated source's base name
STEPS = "hbma_steps"


@dataclass
class LibrarySpec:
    """What the library is made of: the control side's loop spec (its stages without the log mark), the
    names of the EKF model's parameters (``ekf_theta``; none for a robot), the controller's period in
    ticks and in s, the load filter's time constant (s), the horizon, the QP's Functions and OSQP problem
    at a nominal point, a description, and the NMPC's RTI backend (its model and settings).

    With ``qp_solver`` 'daqp' (a chamber's), ``dense`` holds the condensed QP's parts
    (:func:`_dense_qp`). A robot's library (``kind`` 'robot') has ``n`` chambers in ``n_layers`` layers, the Function of its
    targets (``targets``: the layers' poses -> the chambers' heights, which ``hbma_set_target`` calls)
    and the period in ticks of its supply caps' peak window (``refresh_every``)."""

    loop: LoopSpec
    theta_names: list
    every: int
    ctrl_dt: float
    load_tau: float
    horizon: int
    qp_data: ca.Function
    qp_post: ca.Function
    qp_setup: dict
    meta: dict
    backend: object = None
    kind: str = "chamber"
    n: int = 1
    n_layers: int = 0
    targets: ca.Function | None = None
    refresh_every: int = 0
    qp_solver: str = "osqp"
    dense: dict | None = None

    @property
    def rti_name(self) -> str:
        """The RTI step's stage name (the stage the library replaces by its OSQP path)."""
        return "robot_rti_step" if self.kind == "robot" else "rti_step"


#: what the base entries of a model's parameter list are (hbma_ctrl.core.physics.ParamSpace), for the header
_PARAM_DOC = {"r1": "clamp radius, m", "t0": "membrane thickness, m", "V0": "dead volume, m^3",
              "R": "specific gas constant, J/(kg K)", "T": "gas temperature, K", "p_env": "ambient pressure, Pa",
              "W": "platform weight, N", "M": "moving mass, kg", "c": "platform damping, N s/m",
              "flow_scale": "pump flow scale, -", "C_out": "outlet sonic conductance, m^3/(s Pa)",
              "b_out": "outlet critical pressure ratio, -", "lam_out": "outlet laminar ratio, -"}


def _c_ident(name: str) -> str:
    out = re.sub(r"\W", "_", name)
    return out if not out[0].isdigit() else "p_" + out


def _cse(fun: ca.Function) -> ca.Function:
    """An SX Function with each of its common subexpressions evaluated once (casadi's ``cse`` option):
    the same operations on the same operands, so the same values, with fewer operations and calls (the
    QP data Function evaluates some of the model's tables at the same point more than once); any other
    Function as it is."""
    if not fun.is_a("SXFunction"):
        return fun
    ins = fun.sx_in()
    return ca.Function(fun.name(), ins, fun.call(ins), fun.name_in(), fun.name_out(), {"cse": True})


def _qp_functions(rti: ca.Function) -> tuple[ca.Function, ca.Function, int, int]:
    """(OSQP's problem data from the RTI step's inputs, the RTI step's post-processing, nz, nc).

    The data Function returns P's upper triangle and ``[I; A]`` as OSQP's CSC values (the patterns fixed),
    q, l = [lbx; lba], u = [ubx; uba] (infinite bounds as OSQP's infinity), the primal guess, the dual
    guess [lam_x; lam_a] and the linearisation check the post-processing reads."""
    data = _cse(rti.find_function("rti_qp_data"))
    post = rti.find_function("rti_post")
    ins = [ca.MX.sym(data.name_in(i), data.sparsity_in(i)) for i in range(data.n_in())]
    H, g, A, lba, uba, lbx, ubx, z0, lx0, la0, chk = data(*ins)
    Hsp, Asp = data.sparsity_out(0), data.sparsity_out(2)
    nz, nc = Asp.size2(), Asp.size1()
    rows = np.array(Hsp.row())
    cols = np.repeat(np.arange(nz), np.diff(np.array(Hsp.colind())))
    upper = np.nonzero(rows <= cols)[0]
    Px = ca.vertcat(*[H.nz[int(i)] for i in upper]) if upper.size else ca.MX(0, 1)
    Acol, Arow = np.array(Asp.colind()), np.array(Asp.row())
    parts = []
    for j in range(nz):
        parts.append(ca.MX(1.0))
        for i in range(Acol[j], Acol[j + 1]):
            parts.append(A.nz[int(i)])
    Ax = ca.vertcat(*parts)
    big = 1e30  # OSQP_INFTY: a bound beyond it is no bound
    clip = lambda v: ca.fmin(ca.fmax(v, -big), big)  # noqa: E731
    qp = ca.Function("hbma_qp_data", ins, [Px, g, Ax, clip(ca.vertcat(lbx, lba)), clip(ca.vertcat(ubx, uba)), z0,
                                          ca.vertcat(lx0, la0), chk],
                     [data.name_in(i) for i in range(data.n_in())],
                     ["Px", "q", "Ax", "l", "u", "x_guess", "y_guess", "chk"])
    # the patterns OSQP is set up with
    p_rows, p_cols = rows[upper], cols[upper]
    a_rows, a_cols = [], []
    for j in range(nz):
        a_rows.append(j)
        a_cols.append(j)
        for i in range(Acol[j], Acol[j + 1]):
            a_rows.append(nz + int(Arow[i]))
            a_cols.append(j)
    qp.patterns = (p_rows, p_cols, np.array(a_rows), np.array(a_cols), nz, nc)
    return qp, post, nz, nc


def _qp_post(post: ca.Function, patterns: tuple, horizon: int, eps: float | None = None) -> ca.Function:
    """The RTI step's post-processing on OSQP's form: (z, cost, y = [lam_x; lam_a], chk, [I; A]'s values,
    l, u) -> the outputs of ``rti_post`` (first input, plans clipped to [0, 1], multipliers, status,
    largest constraint violation, cost). ``rti_post`` itself recomputes the linearisation from the step's
    inputs to evaluate the constraints; the library has them from the data Function already. The plan's
    places in z are read from ``rti_post`` (evaluated on z = its own indices).

    A solution is usable (status 0) as in ``rti_post``: without ``eps`` (DAQP's solutions) when it violates
    its constraints by at most ``_RES_TOL``; with ``eps`` (OSQP's absolute and relative tolerance) up to
    OSQP's own primal test (:func:`hbma_ctrl.controllers.rti_step.usable_tolerance`)."""
    from hbma_ctrl.controllers.rti_step import _RES_TOL, usable_tolerance

    _, _, a_rows, a_cols, nz, nc = patterns
    N = horizon
    args = [np.zeros(post.sparsity_in(i).shape) for i in range(post.n_in())]
    args[0] = 1.0 + np.arange(nz)
    X = np.asarray(post(*args)[1]).ravel()
    args[0] = (1.0 + np.arange(nz)) / (2.0 * nz)  # inside [0, 1]: the plan's clipping keeps them
    U = np.asarray(post(*args)[2])
    ix = np.rint(X - 1.0).astype(int)
    iu = np.rint(U * 2.0 * nz - 1.0).astype(int)  # 3 x N
    # MX: the sparse product and the element-wise bounds become loops in C (as SX every one of the
    # ~2000 operations is a line of its own: 0.1 MB of code on a Cortex-M7), the same operations in
    # the same order
    MX = ca.MX
    z, cost, y, chk = MX.sym("z", nz), MX.sym("cost"), MX.sym("y", nz + nc), MX.sym("chk", post.nnz_in(4))
    sp = ca.Sparsity.triplet(nz + nc, nz, [int(r) for r in a_rows], [int(c) for c in a_cols])
    ax = MX.sym("Ax", sp.nnz())
    lo, hi = MX.sym("l", nz + nc), MX.sym("u", nz + nc)
    Az = ca.mtimes(MX(sp, ax), z)
    res = ca.mmax(ca.vertcat(ca.fmax(lo - Az, 0), ca.fmax(Az - hi, 0)))
    Xn = z[[int(i) for i in ix]]
    Un = ca.fmin(ca.fmax(ca.reshape(z[[int(i) for i in iu.ravel(order="F")]], 3, N), 0.0), 1.0)
    finite = ca.logic_and(ca.sumsqr(z) < ca.inf, ca.sumsqr(chk) < ca.inf)
    # [I; A] z: OSQP's form holds the bounds as rows, so its max-norm covers |z| too
    tol = _RES_TOL if eps is None else usable_tolerance("osqp", eps, Az, Az)
    status = ca.if_else(finite, ca.if_else(res <= tol, 0.0, 2.0), 1.0)
    return ca.Function("hbma_qp_post", [z, cost, y, chk, ax, lo, hi],
                       [Un[:, 0], Xn, Un, y[:nz], y[nz:], status, res, cost],
                       ["z", "cost", "y", "chk", "Ax", "l", "u"], post.name_out())


def _dense_qp(rti: ca.Function, qp: ca.Function, post: ca.Function) -> dict:
    """The condensed QP's parts for DAQP (:mod:`hbma_ctrl.controllers.rti_condense`): ``data`` (one SX
    Function of the RTI step's inputs: the dense Hc, gc, Ac row by row, [lby; lbc], [uby; ubc], T's nonzeros,
    t, the linearisation check and OSQP's form of the constraints Ax, l, u, which the post-processing
    checks the solution against), ``post`` ((y, cost, T's nonzeros, t, chk, Ax, l, u) -> ``rti_post``'s
    outputs for z = T y + t, the multipliers 0: DAQP is warm-started from its own working set), ``shift``
    (for each constraint of the condensed QP the one of the next stage, whose state it takes when the RTI
    step shifts its plan; itself at the last stage), ``ny`` and ``mc``."""
    from hbma_ctrl.controllers.rti_condense import condensing

    data = rti.find_function("rti_qp_data")
    cond = condensing(data)
    ins = [ca.SX.sym(data.name_in(i), data.sparsity_in(i)) for i in range(data.n_in())]
    H, g, A, lba, uba, lbx, ubx = data(*ins)[:7]
    dense = cond.function(H.nz[:], g, A.nz[:], lba, uba, lbx, ubx)
    _, _, Ax, lo, hi, _, _, chk = qp(*ins)
    fun = ca.Function("hbma_qp_dense", ins, list(dense) + [chk, Ax, lo, hi], data.name_in(),
                      list(cond.function.name_out()) + ["chk", "Ax", "l", "u"], {"cse": True})
    ny, nz, nc = cond.ny, A.size2(), A.size1()
    MX = ca.MX
    y, cost, Tnz, t = MX.sym("y", ny), MX.sym("cost"), MX.sym("T", cond.T.nnz()), MX.sym("t", nz)
    chk_in, ax, l_in, u_in = (MX.sym(post.name_in(i), post.sparsity_in(i)) for i in (3, 4, 5, 6))
    z = ca.mtimes(MX(cond.T, Tnz), y) + t
    outs = post(z, cost, MX(nz + nc, 1), chk_in, ax, l_in, u_in)
    dpost = ca.Function("hbma_qp_dense_post", [y, cost, Tnz, t, chk_in, ax, l_in, u_in], list(outs),
                        ["y", "cost", "T", "t", "chk", "Ax", "l", "u"], post.name_out())
    # stage and place of every constraint: a variable bound by its sparse variable, a row by its row (the
    # sparse QP's layout: the same number of variables, and of rows, at every stage but the last)
    N = (nz - 4) // 8
    ns, ms = (nz - 4) // N, nc // N
    where = [(int(i) // ns, int(i) % ns, "x") for i in cond.free] + [(int(r) // ms, int(r) % ms, "a") for r in cond.rows]
    index = {w: j for j, w in enumerate(where)}
    shift = np.array([index.get((k + 1, p, kind), j) for j, (k, p, kind) in enumerate(where)], int)
    return {"data": fun, "post": dpost, "shift": shift, "ny": ny, "mc": cond.mc}


def _nominal_inputs(backend, rti: ca.Function) -> list:
    """The RTI step's inputs at a nominal cold start (to mid-range height under a tenth of the largest
    load), as the NMPC's probe: the point OSQP's generated setup is made at."""
    s, model, N = backend.s, backend.model, backend.N
    W = 0.1 * model.load_max
    x0 = float(model.x_at_height(0.5 * s.h_max, W))
    return [x0, W, 0.0, 0.0, np.zeros(3), s.p_max - s.p_margin, np.full(N, 0.5 * s.h_max), np.full(N + 1, x0),
            np.zeros((3, N)), np.zeros(rti.nnz_in(9)), np.zeros(rti.nnz_in(10)), 0.0]


def library_spec(scn, qp_solver: str = "osqp") -> LibrarySpec:
    """The library of the scenario's chamber or, for a ``[robot]`` scenario, of its robot (see the module
    docstring), its QP solved by ``qp_solver`` (:data:`QP_SOLVERS`; a robot's: osqp). ValueError naming
    the setting that cannot be generated (no NMPC, load steps, a fallback drill, a UKF, an enforced budget)."""
    from hbma_ctrl.app.codegen.chamber import _unsupported, rig_stages, scenario_system
    from hbma_ctrl.sim.rig import RigSettings

    if qp_solver not in QP_SOLVERS:
        raise ValueError(f"--qp-solver = '{qp_solver}'; allowed with --library: {', '.join(QP_SOLVERS)}")
    if scn.role("robot") is not None:
        if qp_solver != "osqp":
            raise ValueError(f"--qp-solver = '{qp_solver}': a robot's library solves its QP with OSQP (allowed: osqp)")
        return _robot_library_spec(scn)
    section = scn.role("controller")
    if section is None or section.kind != "mpc":
        raise ValueError("codegen --library: needs [controller] kind = 'mpc' (the library is EKF -> NMPC -> "
                         "supervisor)")
    if section.load_steps:
        raise ValueError("codegen --library: [controller] load_steps_g changes the rig's load during a run; "
                         "remove it")
    if section.mpc.fail_window is not None:
        raise ValueError("codegen --library: [controller] fail_window (the fallback drill) does not generate; "
                         "remove it")
    rs = scn.role("rig") or RigSettings(sensor_range=scn.sim.sensor_range)
    why = _unsupported(scn, rs)
    if why:
        raise ValueError("codegen --library: " + "; ".join(why))
    system = scenario_system(scn, rs, "osqp")
    _, _, rig_signals, _, _ = rig_stages(scn, rs, 1)
    p0 = float(rig_signals["p"][0])
    try:
        spec = system.to_function(np.zeros(1), p0, True)
    except ValueError as exc:
        raise ValueError(f"codegen --library: {exc}") from None
    ctrl = system.loop.controller
    est = system.loop.estimator.inner
    rti = next(st.fun for st in spec.stages if st != LOG and st.name == "rti_step")
    qp, post, nz, nc = _qp_functions(rti)
    nominal = _nominal_inputs(ctrl.backend, rti)
    vals = [np.asarray(v, float).ravel() for v in qp(*nominal)]
    s = ctrl.settings
    names = list(getattr(getattr(est.model, "chamber", None), "space", None).names) if hasattr(
        getattr(est.model, "chamber", None), "space") else [f"theta_{i}" for i in range(spec.signals["ekf_theta"].size)]
    if len(names) != spec.signals["ekf_theta"].size:
        raise ValueError("codegen --library: the EKF model's parameter names do not match its theta")
    # DAQP's solutions are exact to rounding: its post-processing keeps rti_post's acceptance
    post = _qp_post(post, qp.patterns, int(s.horizon), float(s.qp_eps) if qp_solver == "osqp" else None)
    setup = {"Px": vals[0], "q": vals[1], "Ax": vals[2], "l": vals[3], "u": vals[4], "eps": float(s.qp_eps),
             "max_iter": int(s.qp_max_iter), "patterns": qp.patterns}
    meta = dict(spec.meta)
    dense = _dense_qp(rti, qp, post) if qp_solver == "daqp" else None
    meta["controller"] = meta["controller"].replace(
        "QP osqp", "QP OSQP (embedded, generated C)" if dense is None else
        f"QP condensed onto its {dense['ny']} inputs and slacks, DAQP (dense active set, C sources)")
    meta["first reading"] = f"{p0:.6g} Pa (the EKF's initial estimate is made from it at generation)"
    return LibrarySpec(spec, names, system.loop.every, float(s.sample_period), float(s.load_tau), int(s.horizon), qp, post,
                       setup, meta, ctrl.backend, qp_solver=qp_solver, dense=dense)


def _robot_start_function(bank, n: int) -> ca.Function:
    """robot_start(p[n]) -> (X 4 x n, P 16 x n): the bank at rest from the first readings (Pa; one out
    of the physical range read as 0), as :meth:`hbma_ctrl.estimators.robot_ekf.ChamberEKFBank.step`'s
    first call starts it."""
    p = ca.SX.sym("p", 1, n)
    lo, hi = bank._bounds
    p0 = ca.if_else(ca.logic_and(p >= lo, p <= hi), p, 0.0)
    X, P = bank.rest_expr(p0)
    return ca.Function("robot_start", [p], [X, P], ["p"], ["X", "P"])


def _robot_targets_function(design) -> ca.Function:
    """robot_targets(pose[3 x L]: each layer's centre height m, bend rad, direction rad) -> the chambers'
    target heights (3 L, m): :func:`hbma_ctrl.robot.targets.chamber_targets`' inverse kinematics and its
    floor at 0."""
    from hbma_ctrl.robot.kinematics import _plane_matrix

    L = design.n_layers
    A = _plane_matrix(design)
    pose = ca.SX.sym("pose", 3, L)
    out = []
    for k in range(L):
        c, th, ps = pose[0, k], pose[1, k], pose[2, k]
        t = ca.tan(th)
        v = [c, -t * ca.cos(ps), -t * ca.sin(ps)]
        out += [ca.fmax(A[i, 0] * v[0] + A[i, 1] * v[1] + A[i, 2] * v[2], 0.0) for i in range(3)]
    return ca.Function("robot_targets", [pose], [ca.vertcat(*out)], ["pose"], ["h"])


def _robot_library_spec(scn) -> LibrarySpec:
    """The library of a closed-loop ``[robot]`` scenario with the NMPC: its system's control side
    (:meth:`hbma_ctrl.system.robot.RobotSystem.to_function`) with the bank started from the first tick's
    readings (``robot_start``), the NMPC's QP taken out of its step for OSQP's embedded code
    (:func:`hbma_ctrl.controllers.robot_rti_step.robot_rti_qp_functions`) and the layers' poses as targets."""
    from dataclasses import replace
    from functools import partial

    from hbma_ctrl.app.codegen.robot import _build
    from hbma_ctrl.controllers.robot_rti_step import FN_MAX_ITER, FN_RHO, RobotNMPCFunction, robot_rti_qp_functions
    from hbma_ctrl.core.loopgen import Stage

    try:
        s, rs, _, system = _build(scn, partial(RobotNMPCFunction, compile=False))
        n = system.n
        ticks = 2 * 10 + 1  # enough for the supply caps' window to show in the streams
        spec = system.to_function(np.arange(ticks) * rs.sample_period, np.zeros(n))
    except ValueError as exc:
        raise ValueError(f"codegen --library: {str(exc).removeprefix('codegen: ')}") from None
    loop, nmpc = system.loop, system.loop.controller
    refresh = np.asarray(spec.streams["refresh"]).ravel()
    refresh_every = int(np.nonzero(refresh[1:])[0][0]) + 1
    stages = [Stage(_robot_start_function(loop.bank, n), ["p"], ["ekf_X", "ekf_P"], gate="first")]
    for st in spec.stages:
        # a failure inside the library's QP path reads as a failed step (the NMPC's status not 0)
        stages.append(replace(st, fails_to="rti_status") if st.name == "robot_rti_step" else st)
    # the targets until hbma_set_target: the scenario's first poses
    signals = dict(spec.signals, goal=loop.chamber_targets(0.0))
    spec = LoopSpec(spec.name, spec.dt, spec.n_ticks, signals, spec.streams, stages, spec.log, spec.meta)
    qp, post, patterns = robot_rti_qp_functions(nmpc)
    ms = nmpc.s
    N = ms.horizon
    # OSQP's setup point: every chamber at rest under its share of the robot's weight, at its first target
    goal = loop.chamber_targets(0.0)
    nominal = [np.zeros(n), np.full(n, loop.bank.settings.b0), np.asarray(spec.signals["W"], float), np.ones(n),
               np.ones(n), np.ones(n), np.repeat(goal[:, None], N, 1), np.zeros((2, n)), np.zeros((n, N + 1)),
               np.zeros((n, N)), np.zeros((n, N)), 1.0, np.zeros(nmpc.nv), np.zeros(nmpc.m_rows), 0.0]
    vals = [np.asarray(v, float).ravel() for v in qp(*nominal)]
    setup = {"Px": vals[0], "q": vals[1], "Ax": vals[2], "l": vals[3], "u": vals[4], "eps": float(ms.eps),
             "max_iter": max(int(ms.max_iter), FN_MAX_ITER), "patterns": patterns,
             # the generated step's OSQP settings (robot_rti_step_function's)
             "settings": {"rho": FN_RHO, "scaling": 1}}
    meta = dict(spec.meta)
    meta["controller"] = meta["controller"].replace("OSQP (casadi's) inside", "QP OSQP (embedded, generated C)")
    meta["estimator"] += "; started at rest from the first tick's readings"
    return LibrarySpec(spec, [], 1, float(ms.dt), 0.0, int(N), qp, post, setup, meta, nmpc, kind="robot", n=n,
                       n_layers=s.design.n_layers, targets=_robot_targets_function(s.design),
                       refresh_every=refresh_every)


# --------------------------------------------------------------------------------------------- write
#: libm's functions the generated code calls, each with a float variant (name + "f")
_LIBM = ("sqrt", "exp", "log", "pow", "fabs", "fmin", "fmax", "floor", "ceil", "sin", "cos", "tan", "atan2", "atan",
         "tanh", "asin", "acos", "sinh", "cosh", "fmod", "erf", "round", "copysign", "log1p", "expm1", "cbrt",
         "hypot", "trunc")
_FLOAT_LITERAL = re.compile(r"(?<![\w.])(\d+\.\d*(?:[eE][-+]?\d+)?|\d+[eE][-+]?\d+)(?![\w.])")
_FLT_MIN, _FLT_MAX = 1.17549435e-38, 3.40282347e38


def _single(source: str) -> str:
    """The generated C in single precision: libm's float functions (``sqrtf`` for ``sqrt``; the
    arguments are floats, and a double routine would cost a soft-float call on a single-precision FPU),
    and the literals outside float's range mapped to its limits (a 1e-300 guard against a division by
    zero stays the smallest normal float instead of 0, the largest double the largest float)."""
    source = re.sub(r"\b(" + "|".join(_LIBM) + r")\(", r"\1f(", source)

    def lit(m):
        v = float(m.group(1))
        if 0.0 < v < _FLT_MIN:
            return repr(_FLT_MIN)
        if _FLT_MAX < v < float("inf"):
            return repr(_FLT_MAX)
        return m.group(1)

    return _FLOAT_LITERAL.sub(lit, source)


def _osqp(lib: LibrarySpec, out: Path, precision: str, settings: dict | None = None) -> None:
    """OSQP's embedded sources and its caller-owned workspace (:mod:`hbma_ctrl.core.osqp_embed`) in ``out/osqp``."""
    import osqp
    import scipy.sparse as sp

    if int(osqp.__version__.split(".")[0]) < 1:
        raise ValueError(f"codegen --library: needs osqp >= 1.0 (its embedded code generation); this is "
                         f"{osqp.__version__}: pip install 'osqp>=1.0'")
    st = lib.qp_setup
    p_rows, p_cols, a_rows, a_cols, nz, nc = st["patterns"]
    # the patterns must survive the setup: a value that is 0 at the nominal point is stored as a tiny one
    nonzero = lambda v: np.where(v == 0.0, 1e-9, v)  # noqa: E731
    P = sp.csc_matrix((nonzero(st["Px"]), (p_rows, p_cols)), shape=(nz, nz))
    A = sp.csc_matrix((nonzero(st["Ax"]), (a_rows, a_cols)), shape=(st["l"].size, nz))  # its rows: the bounds'
    if P.nnz != len(p_rows) or A.nnz != len(a_rows):
        raise RuntimeError("codegen --library: the QP's sparsity changed in OSQP's setup")
    solver = osqp.OSQP()
    solver.setup(P, st["q"], A, st["l"], st["u"], verbose=False, polishing=False, eps_abs=st["eps"],
                 eps_rel=st["eps"], max_iter=st["max_iter"], warm_starting=True,
                 **{**QP_SETTINGS, **st.get("settings", {}), **(settings or {})})
    d = out / "osqp"
    if d.exists():
        shutil.rmtree(d)
    solver.codegen(str(d), parameters="matrices", extension_name=None, force_rewrite=True, prefix=QP_PREFIX,
                   use_float=precision == "single", printing_enable=False, profiling_enable=False,
                   interrupt_enable=False)
    for extra in ("emosqp.c", "Makefile"):
        (d / extra).unlink(missing_ok=True)
    own_workspace(d, QP_PREFIX)


def _functions(lib: LibrarySpec) -> list:
    """The Functions the library calls: the stages' (the RTI step's replaced by its QP parts) and a
    robot's targets."""
    seen, out = set(), []
    for st in lib.loop.stages:
        if st == LOG or st.name in seen or st.name == lib.rti_name:
            continue
        seen.add(st.name)
        out.append(dense_function(st.fun))
    extra = [lib.targets] if lib.targets is not None else []
    qp = [lib.dense["data"], lib.dense["post"]] if lib.dense else [lib.qp_data, lib.qp_post]
    return out + [dense_function(f) for f in qp + extra]


def _daqp(out: Path) -> None:
    """DAQP's C sources and its licence (:mod:`hbma_ctrl.core`'s ``c/daqp``) in ``out/daqp``."""
    d = out / "daqp"
    if d.exists():
        shutil.rmtree(d)
    src = resources.files("hbma_ctrl.core").joinpath("c/daqp")
    for sub in ("src", "include"):
        (d / sub).mkdir(parents=True)
        for f in src.joinpath(sub).iterdir():
            if f.name.endswith((".c", ".h")):
                (d / sub / f.name).write_text(f.read_text())
    for name in ("LICENSE", "README.txt"):
        (d / name).write_text(src.joinpath(name).read_text())


def check_qp_solver(qp_solver: str, precision: str) -> None:
    """ValueError naming ``--qp-solver`` for a solver the library has not, or one it builds in double
    precision only (DAQP's)."""
    if qp_solver not in QP_SOLVERS:
        raise ValueError(f"--qp-solver = '{qp_solver}'; allowed with --library: {', '.join(QP_SOLVERS)}")
    if qp_solver == "daqp" and precision != "double":
        raise ValueError("--qp-solver daqp: the library's DAQP path is built in double precision "
                         "(allowed with daqp: --precision double)")


def check_precision(kind: str, precision: str) -> None:
    """ValueError naming ``--precision`` when a library of this kind ('chamber' or 'robot') cannot be
    built in it: a robot's in single precision. Measured on robot_bending: the robot step's finiteness
    check squares the bounds at OSQP's infinity (1e30), which overflows a float; with that check scaled,
    OSQP's float LDL factor of the KKT matrix loses its quasi-definiteness at the first warm-started
    step, and every step after it fails."""
    if precision == "single" and kind == "robot":
        raise ValueError("--precision single: the robot NMPC's QP does not factorise in single precision "
                         "(OSQP: the KKT matrix is not quasi-definite); allowed for a robot: double")


def write_library(lib: LibrarySpec, out_dir: Path | str, precision: str = "double") -> list:
    """Write the library's sources into ``out_dir``: ``hbma.h``, ``hbma.c``, ``hbma_steps.c/.h``, ``osqp/``,
    the driver ``hbma_run.c``, ``board/`` (start-up file and linker scripts for the MPS2 boards QEMU
    emulates), ``CMakeLists.txt``, ``Makefile`` and ``README.txt``; returns the written paths."""
    if precision not in PRECISIONS:
        raise ValueError(f"--precision = '{precision}'; allowed: {', '.join(PRECISIONS)}")
    check_precision(lib.kind, precision)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    funs = _functions(lib)
    opts = {"with_header": True, "main": False, "casadi_real": "float" if precision == "single" else "double"}
    cg = ca.CodeGenerator(f"{STEPS}.c", opts)
    for f in funs:
        cg.add(f)
    cg.generate(str(out) + os.sep)
    if precision == "single":
        src = out / f"{STEPS}.c"
        src.write_text(_single(src.read_text()))
    if lib.dense:
        _daqp(out)
    else:
        _osqp(lib, out, precision)
    sz = {k: max(getattr(f, f"sz_{k}")() for f in funs) for k in ("arg", "res", "iw", "w")}
    spec = lib.loop
    stages = [st for st in spec.stages if st != LOG]
    sig = dict(spec.signals)
    # ---------------------------------------------------------------- header
    api = _robot_api(lib) if lib.kind == "robot" else _chamber_api(lib)
    hdr = f"""/* {spec.name}: the {api['what']}'s estimator + controller + supervisor tick (generated by hbma-ctrl codegen --library).
 *
{api['doc']}
 * All memory is in the caller's hbma_workspace_t (sizeof is a compile-time constant); no allocation, no I/O.
 */
#ifndef HBMA_H
#define HBMA_H

#include "{STEPS}.h"
@QP_INCLUDE@

#ifdef __cplusplus
extern "C" {{
#endif

typedef casadi_real hbma_real;

#define HBMA_TICK_S {spec.dt!r}
/* the controller runs every HBMA_CONTROL_EVERY ticks; its horizon has HBMA_HORIZON steps of
   {'HBMA_CONTROL_EVERY * HBMA_TICK_S' if lib.kind == 'chamber' else repr(lib.ctrl_dt) + ' s'} */
#define HBMA_CONTROL_EVERY {lib.every}
#define HBMA_HORIZON {lib.horizon}
#define HBMA_SINGLE_PRECISION {1 if precision == "single" else 0}
{api['defines']}
/* status codes */
#define HBMA_OK 0
#define HBMA_SOLVE_FAILED 1      /* the controller's step failed: the supervisor's fallback command is out */
#define HBMA_ERR_ARGUMENT (-1)   /* {api['err_argument']} */
#define HBMA_ERR_NOT_INIT (-2)   /* hbma_init has not succeeded on this workspace */
#define HBMA_ERR_WORKSPACE (-3)  /* the generated Functions need more work memory than the workspace holds */

{api['params']}

/* What the last tick estimated and decided (SI). */
typedef struct {{
{api['outputs']}
}} hbma_outputs_t;

/* the workspace: every signal of the tick, the generated Functions' work arrays, the QP solver */
typedef struct {{
  int initialised;
  long k;                 /* ticks since hbma_init */
  hbma_real t_last;       /* time of the last tick, s */
  hbma_real t_ctrl;       /* time of the controller's last step, s */
  int qp_iterations, qp_status;
{api['state']}@SIGNALS@
  const casadi_real* arg[{sz['arg']}];
  casadi_real* res[{sz['res']}];
  const casadi_real* arg2[{sz['arg']}];
  casadi_real* res2[{sz['res']}];
  casadi_int iw[{max(sz['iw'], 1)}];
  casadi_real w[{max(sz['w'], 1)}];
@OUTBUFS@
@QP_MEMBERS@
}} hbma_workspace_t;

/* The tick's parts, for an instruction count per part: "other" (between stages), the stages in order,
   then the RTI step's QP path (its data Function, OSQP's matrix update with its scaling and KKT
   factorisation, its vector update and warm start, its iterations, the post-processing). Built with
   -DHBMA_PROFILE, the library calls hbma_profile_mark(i) (the caller's) where the tick enters part i. */
#define HBMA_N_PARTS @N_PARTS@
#define HBMA_PART_NAMES {{@PART_NAMES@}}
#ifdef HBMA_PROFILE
void hbma_profile_mark(int part);
#endif

/* The generation scenario's parameters. */
void hbma_default_params(hbma_params_t* params);
/* Start (or restart) the workspace: {api['init_doc']}. */
int hbma_init(hbma_workspace_t* ws, const hbma_params_t* params);
{api['prototypes']}
/* What the last tick estimated and decided. */
void hbma_outputs(const hbma_workspace_t* ws, hbma_outputs_t* out);

#ifdef __cplusplus
}}
#endif

#endif
"""
    sig_lines = [f"  hbma_real s_{_c_ident(k)}[{max(v.size, 1)}];" for k, v in sig.items()]
    # one scratch area holds a stage's outputs until they are copied to their signals (a Function
    # never writes the buffers it reads)
    rti = next(st.fun for st in stages if st.name == lib.rti_name)
    lib_rti_numel = [rti.numel_out(i) for i in range(rti.n_out())]
    per_stage = [lib_rti_numel if st.name == lib.rti_name else [st.fun.numel_out(i) for i in range(st.fun.n_out())]
                 for st in stages]
    n_scratch = max(sum(v) for v in per_stage)
    qd = lib.dense["data"] if lib.dense else lib.qp_data
    qp_sizes = [qd.nnz_out(i) for i in range(qd.n_out())]
    outbufs = [f"  hbma_real o[{n_scratch}];  /* a stage's outputs */"]
    outbufs += [f"  hbma_real o_qp_{i}[{max(n_, 1)}];  /* the QP's data: {qd.name_out(i)} */" for i, n_ in enumerate(qp_sizes)]
    part_names = ["other"] + _unique([st.name for st in stages]) + list(_QP_PARTS[lib.qp_solver])
    qp_c = _qp_c(lib)
    hdr = (hdr.replace("@SIGNALS@", "\n".join(sig_lines)).replace("@OUTBUFS@", "\n".join(outbufs))
           .replace("@QP_INCLUDE@", qp_c["include"]).replace("@QP_MEMBERS@", qp_c["members"])
           .replace("@N_PARTS@", str(len(part_names)))
           .replace("@PART_NAMES@", ", ".join(f'"{n}"' for n in part_names)))
    (out / "hbma.h").write_text(hdr)
    # ---------------------------------------------------------------- source
    init = []
    for k, v in sig.items():
        if k in api["from_params"]:
            continue
        init.append(f"  {{ static const hbma_real v[] = {c_array(v)}; "
                    f"memcpy(ws->s_{_c_ident(k)}, v, sizeof v); }}")
    init += api["init_params"]
    defaults = api["defaults"]
    checks = []
    for f in funs:
        checks.append(f"  {{ casadi_int a, r, i, w; {f.name()}_work(&a, &r, &i, &w);\n"
                      f"    if (a > {sz['arg']} || r > {sz['res']} || i > {max(sz['iw'], 1)} || w > {max(sz['w'], 1)}) "
                      f"return HBMA_ERR_WORKSPACE; }}")
    tick = []
    for st in stages:
        f = st.fun if st.name != lib.rti_name else None
        if f is None:
            nout = rti.n_out()
            body = [f"ws->arg[{i}] = ws->s_{_c_ident(s)};" for i, s in enumerate(st.inputs)]
            offs = np.concatenate([[0], np.cumsum(lib_rti_numel)]).astype(int)
            body += [f"ws->res[{i}] = ws->o + {offs[i]};" for i in range(nout)]
            call = "rti_step_qp(ws)"
        else:
            nout = f.n_out()
            body = [f"ws->arg[{i}] = ws->s_{_c_ident(s)};" for i, s in enumerate(st.inputs)]
            offs = np.concatenate([[0], np.cumsum([f.numel_out(i) for i in range(nout)])]).astype(int)
            body += [f"ws->res[{i}] = ws->o + {offs[i]};" for i in range(nout)]
            call = f"{st.name}(ws->arg, ws->res, ws->iw, ws->w, 0)"
        obuf = lambda i, offs=offs: f"(ws->o + {offs[i]})"  # noqa: E731
        numel = (lambda i: lib_rti_numel[i]) if f is None else (lambda i: f.numel_out(i))
        copies = [f"memcpy(ws->s_{_c_ident(s)}, {obuf(i)}, sizeof(hbma_real) * {numel(i)});"
                  for i, s in enumerate(st.outputs) if s is not None]
        if st.fails_to is not None:
            # a failed call writes nothing but its failure flag (NaN): the signals keep their values
            body.append(f"if ({call}) {{\n      ws->s_{_c_ident(st.fails_to)}[0] = NAN;\n    }} else {{\n      "
                        + "\n      ".join(copies) + "\n    }")
        else:
            body.append(f"(void){call};")
            body += copies
        prefix, stop = stage_guard(st, "ws->k", lambda name: f"ws->s_{_c_ident(name)}[0]")
        body += [stop] if stop else []
        body = [f"HBMA_PART({1 + len(tick)});"] + body + ["HBMA_PART(0);"]
        tick.append(f"  {prefix}{{  /* {st.name} */\n    " + "\n    ".join(body) + "\n  }")
    _, _, _, _, nz, nc = lib.qp_setup["patterns"]
    qpost = lib.dense["post"] if lib.dense else lib.qp_post
    res2 = "\n".join(f"  ws->res2[{i}] = ws->o_qp_{i};" for i in range(qd.n_out()))
    src = (_template("hbma.c.in").replace("@RTI_STEP_QP@", _template(f"qp_{lib.qp_solver}.c.in"))
           .replace("@QP_INIT@", qp_c["init"]).replace("@QP_SOLVER_DOC@", qp_c["doc"]).replace("@RES2@", res2)
           .replace("@SHIFT_IN@", str(rti.index_in("shift")) if lib.dense else "")
           .replace("@DAQP_N@", str(lib.dense["ny"]) if lib.dense else "")
           .replace("@DAQP_M@", str(lib.dense["ny"] + lib.dense["mc"]) if lib.dense else "")
           .replace("@DAQP_SHIFT@", c_int_array(lib.dense["shift"]) if lib.dense else "")
           .replace("@API@", _template(f"hbma_api_{lib.kind}.c.in"))
           .replace("@NAME@", spec.name).replace("@WHAT@", api["what"]).replace("@INIT_SIGNALS@", "\n".join(init))
           .replace("@INIT_END@", api["init_end"]).replace("@QP_STATUS_CHECK@", api["qp_status_check"])
           .replace("@QP_FAIL_DOC@", api["qp_fail_doc"]).replace("@RTI_NAME@", lib.rti_name)
           .replace("@RTI_N_IN@", str(rti.n_in())).replace("@RTI_N_OUT@", str(rti.n_out()))
           .replace("@TARGETS_FUN@", lib.targets.name() if lib.targets is not None else "")
           .replace("@REFRESH_EVERY@", str(lib.refresh_every)).replace("@INIT_STATE@", api["init_state"])
           .replace("@DEFAULTS@", "\n".join(defaults)).replace("@WORK_CHECKS@", "\n".join(checks))
           .replace("@TICK@", "\n".join(tick)).replace("@EVERY@", str(lib.every))
           .replace("@LOAD_TAU@", repr(lib.load_tau)).replace("@CTRL_DT@", repr(lib.ctrl_dt)).replace("@N@", str(lib.horizon))
           .replace("@NZ@", str(nz)).replace("@NC@", str(nc)).replace("@QP_PREFIX@", QP_PREFIX)
           .replace("@NPX@", str(qd.nnz_out(0))).replace("@NAX@", str(qd.nnz_out(2)))
           .replace("@NCHK@", str(qd.nnz_out(7))).replace("@RTI_OUTBUFS@", "")
           .replace("@QP_DATA@", qd.name()).replace("@QP_POST@", qpost.name())
           .replace("@PART_QP_DATA@", str(1 + len(stages))))
    for key, value in api.get("replace", {}).items():
        src = src.replace(key, value)
    (out / "hbma.c").write_text(src)
    (out / "hbma_run.c").write_text(_template("hbma_run.c.in").replace("@INPUT_FORMAT@", api["input_format"])
                                    .replace("@MAIN@", _template(f"hbma_run_{lib.kind}.c.in")))
    board = out / "board"
    board.mkdir(exist_ok=True)
    for name in ("startup.c", "mps2.ld"):
        (board / name).write_text(_template(f"board_{name}.in"))
    (out / "Makefile").write_text(_makefile(precision, lib.qp_solver))
    (out / "CMakeLists.txt").write_text(_cmake(precision, lib.qp_solver))
    (out / "README.txt").write_text(_readme(lib, precision, sz))
    return [out / n for n in ("hbma.h", "hbma.c", f"{STEPS}.c", f"{STEPS}.h", "hbma_run.c", "Makefile",
                              "CMakeLists.txt", "README.txt")]


def c_int_array(v) -> str:
    """A C initialiser of the integers ``v``, ten a line."""
    v = [str(int(x)) for x in v]
    return "{" + ",\n    ".join(", ".join(v[i:i + 10]) for i in range(0, len(v), 10)) + "}"


def _qp_c(lib: LibrarySpec) -> dict:
    """The QP solver's parts of hbma.h and hbma.c: its header, its memory in the workspace, its start in
    hbma_init and its name in hbma.c's first comment."""
    if not lib.dense:
        return {"include": f'#include "osqp/{QP_PREFIX}workspace.h"', "members": f"  {QP_PREFIX}mem_t qp;",
                "init": f"  {QP_PREFIX}mem_init(&ws->qp);", "doc": "OSQP's embedded code"}
    n, mc = lib.dense["ny"], lib.dense["mc"]
    m = n + mc
    members = f"""  /* DAQP: its workspace, problem and settings, and the memory they point into ({n} variables,
     {n} bounds and {mc} constraint rows) */
  DAQPWorkspace daqp;
  DAQPProblem daqp_qp;
  DAQPSettings daqp_settings;
  c_float daqp_lam[{n + 1}], daqp_lam_star[{n + 1}], daqp_D[{n + 1}], daqp_xldl[{n + 1}], daqp_zldl[{n + 1}];
  c_float daqp_L[{(n + 1) * (n + 2) // 2}];
  c_float daqp_u[{n}], daqp_xold[{n}], daqp_v[{n}], daqp_x[{n}];
  int daqp_WS[{n + 1}], daqp_prox_mask[{n}];
  c_float daqp_scaling[{m}], daqp_dupper[{m}], daqp_dlower[{m}], daqp_lam_out[{m}], daqp_Mu[{mc}];
  c_float daqp_M[{n * mc}];
  c_float daqp_Rinv[{(n + 1) * n // 2}];
  int daqp_sense[{m}], daqp_sense_in[{m}];  /* the working set after the last QP; the next one's start */"""
    return {"include": '#include "daqp/include/types.h"', "members": members, "init": "  daqp_init(ws);",
            "doc": "DAQP (a dense active-set solver) on the QP condensed onto the inputs and slacks"}


def _chamber_api(lib: LibrarySpec) -> dict:
    """The chamber library's own parts of hbma.h, hbma.c and the driver (the rest is shared)."""
    th0 = lib.loop.signals["ekf_theta"]
    theta = [f"  hbma_real {_c_ident(n)};  /* {_PARAM_DOC.get(n, 'material parameter, SI')} */"
             for n in lib.theta_names]
    return {
        "what": "chamber",
        "state": "",
        "init_state": "",
        "doc": """ * Every tick (period HBMA_TICK_S): hbma_tick(&ws, t, p, held, u) takes the time t (s), the pressure reading p
 * (Pa, gauge; NaN: no reading) and the command held over the last period, and writes the command u to hold
 * over the next one (speed, inlet, outlet; each in [0, 1]). The target height (m) is set by hbma_set_target.""",
        "defines": "",
        "err_argument": "a NULL pointer, or a time that is not finite or goes back",
        "params": f"""/* The EKF model's parameters (SI; the names of the model's parameter list). */
typedef struct {{
{chr(10).join(theta)}
}} hbma_model_params_t;

typedef struct {{
  hbma_model_params_t ekf_model;  /* the estimator's model */
}} hbma_params_t;""",
        "outputs": """  hbma_real height_m;     /* estimated height */
  hbma_real pressure_pa;  /* estimated pressure (gauge) */
  hbma_real force_n;      /* estimated load force */
  int resting;            /* the estimator holds the platform at rest */
  hbma_real mpc_status;   /* the controller's last step: 0 solved, else failed (NaN: the QP solver gave up) */
  int qp_iterations;      /* the QP solver's iterations in the controller's last QP */
  int qp_status;          /* its status of that QP (OSQP: 1 solved; DAQP: its exit flag, above 0 solved) */""",
        "init_doc": "the estimator at its prior, the controller cold, the target 0",
        "prototypes": """/* The target height (m) from now on; preview: the targets at the controller's next HBMA_HORIZON steps
   (NULL: height_m at all of them). */
int hbma_set_target(hbma_workspace_t* ws, hbma_real height_m, const hbma_real* preview);
/* One tick; returns HBMA_OK, HBMA_SOLVE_FAILED or an error (u then unchanged). */
int hbma_tick(hbma_workspace_t* ws, hbma_real t, hbma_real p, const hbma_real held[3], hbma_real u[3]);""",
        "from_params": ("ekf_theta",),
        "init_params": [f"  ws->s_ekf_theta[{i}] = params->ekf_model.{_c_ident(n)};" for i, n in enumerate(lib.theta_names)],
        "defaults": [f"  params->ekf_model.{_c_ident(n)} = {float(v)!r};" for n, v in zip(lib.theta_names, th0)],
        "init_end": "  return hbma_set_target(ws, 0, 0);",
        "qp_status_check": """  if (ws->qp_status != OSQP_SOLVED && ws->qp_status != OSQP_SOLVED_INACCURATE &&
      ws->qp_status != OSQP_MAX_ITER_REACHED) return 1;
""",
        "qp_fail_doc": " or OSQP returns no solution",
        "input_format": """ * INPUTS.bin: little-endian doubles: ticks, preview length P (0 or HBMA_HORIZON), then per tick t (s),
 * p (Pa; NaN: no reading), target (m) and P preview targets (m).""",
    }


def _robot_api(lib: LibrarySpec) -> dict:
    """The robot library's own parts of hbma.h, hbma.c and the driver (the rest is shared)."""
    from hbma_ctrl.runtime.robot import HELD_ATOL, HELD_HISTORY

    n, L = lib.n, lib.n_layers
    loads = np.asarray(lib.loop.signals["W"], float)
    return {
        "what": "robot",
        # the commands sent lately, to match a rig's report of the one it held (RobotLoop._held_input)
        "state": (f"  hbma_real sent_u[{HELD_HISTORY}][{3 * n}], sent_w[{HELD_HISTORY}][{2 * n}];  "
                  "/* the commands sent lately */\n  int sent_next, sent_count;\n"
                  "  long held_unmatched;    /* held reports that matched no command sent lately */\n"),
        "init_state": "  ws->sent_next = ws->sent_count = 0;\n  ws->held_unmatched = 0;",
        "replace": {"@HELD_HISTORY@": str(HELD_HISTORY), "@HELD_ATOL@": repr(HELD_ATOL)},
        "doc": f""" * The robot: {L} layers of 3 chambers, HBMA_N_CHAMBERS = {n} (chamber 3 k + i is layer k's i-th).
 * Every tick (period HBMA_TICK_S): hbma_tick(&ws, t, p, held, u) takes the time t (s), the chambers' pressure
 * readings p (Pa, gauge; NaN: no reading) and the valve inputs held over the last period, and writes the
 * valve inputs u to hold over the next one (u[0]: pump speed, u[1]: inlet, u[2]: outlet, each chamber's in
 * [0, 1]). The estimators predict with what the rig held, as the robot's runtime reads it: the newest command
 * sent lately whose valve inputs held equals (to HELD_ATOL), else the safe command's. The targets are the
 * layers' poses (hbma_set_target: centre height m, bend rad, direction rad), as the robot's runtime takes
 * them.""",
        "defines": f"#define HBMA_N_CHAMBERS {n}\n#define HBMA_N_LAYERS {L}\n",
        "err_argument": "a NULL pointer, a time that is not finite or goes back, a pose out of range",
        "params": """/* What the robot starts with (SI). */
typedef struct {
  hbma_real load_n[HBMA_N_CHAMBERS];  /* each chamber's load before the first estimate, N */
} hbma_params_t;""",
        "outputs": """  hbma_real height_m[HBMA_N_CHAMBERS];     /* estimated heights */
  hbma_real pressure_pa[HBMA_N_CHAMBERS];  /* estimated pressures (gauge) */
  hbma_real target_m[HBMA_N_CHAMBERS];     /* the heights the controller worked to (the targets slewed) */
  hbma_real rti_status;   /* the NMPC's last step: 0 usable, 1 non-finite, 2 residual too large (NaN: failed) */
  int failed;             /* the supervisor replaced the NMPC's command in the last tick */
  int qp_iterations;      /* OSQP's iterations in the last QP */
  int qp_status;          /* OSQP's status of that QP (1 solved) */
  long held_unmatched;    /* held reports that matched no command sent lately (the last one used) */""",
        "init_doc": ("the estimators start at rest from the first tick's readings, the controller cold, every "
                     "layer's target the generation scenario's first pose"),
        "prototypes": """/* The layers' poses from now on: pose[k] = (centre height m, bend rad in [0, pi/2), direction rad) of
   layer k; the chambers' target heights follow by the inverse kinematics (a negative height read as 0). */
int hbma_set_target(hbma_workspace_t* ws, const hbma_real pose[HBMA_N_LAYERS][3]);
/* One tick; returns HBMA_OK, HBMA_SOLVE_FAILED (the NMPC's step was not usable) or an error (u then
   unchanged). */
int hbma_tick(hbma_workspace_t* ws, hbma_real t, const hbma_real p[HBMA_N_CHAMBERS],
              const hbma_real held[3][HBMA_N_CHAMBERS], hbma_real u[3][HBMA_N_CHAMBERS]);""",
        "from_params": ("W",),
        "init_params": ["  memcpy(ws->s_W, params->load_n, sizeof(hbma_real) * HBMA_N_CHAMBERS);"],
        "defaults": [f"  params->load_n[{i}] = {float(v)!r};" for i, v in enumerate(loads)],
        "init_end": "  return HBMA_OK;",
        # casadi's OSQP gives its iterate whatever OSQP's status; the step's post-processing judges it
        "qp_status_check": "",
        "qp_fail_doc": "",
        "input_format": f""" * INPUTS.bin: little-endian doubles: ticks, chambers ({n}), layers ({L}), then per tick t (s), the
 * chambers' readings p (Pa; NaN: no reading) and each layer's pose (centre m, bend rad, direction rad).""",
    }


def _unique(names: list) -> list:
    """The names, a repeated one numbered from its second place on (``rti_step``, ``rti_step_2``)."""
    out, seen = [], {}
    for n in names:
        seen[n] = seen.get(n, 0) + 1
        out.append(n if seen[n] == 1 else f"{n}_{seen[n]}")
    return out


def _template(name: str) -> str:
    return resources.files("hbma_ctrl.core").joinpath(f"c/embedded/{name}").read_text()


#: DAQP's sources the library builds
_DAQP_SRC = ["api", "auxiliary", "avi", "bnb", "daqp", "daqp_prox", "eq_elim", "factorization", "hierarchical",
             "presolve", "utils"]
#: DAQP's allocator calls, mapped onto the library's stubs (hbma.c: DAQP's allocating paths are never taken)
_DAQP_DEFS = ["-Dmalloc=hbma_daqp_malloc", "-Dcalloc=hbma_daqp_calloc", "-Dfree=hbma_daqp_free"]


def _qp_sources(qp_solver: str = "osqp") -> list[str]:
    """The QP solver's C sources (relative to the library's folder)."""
    if qp_solver == "daqp":
        return [f"daqp/src/{s}.c" for s in _DAQP_SRC]
    osqp_src = ["auxil", "error", "scaling", "util", "osqp_api", "kkt", "algebra_libs", "csc_math", "csc_utils",
                "matrix", "vector", "qdldl", "qdldl_interface"]
    return [f"osqp/{QP_PREFIX}workspace.c"] + [f"osqp/src/{s}.c" for s in osqp_src]


#: the library's C sources (relative to its folder), for the Makefile and CMake
def _sources(qp_solver: str = "osqp") -> list[str]:
    return ["hbma.c", f"{STEPS}.c"] + _qp_sources(qp_solver)


def _includes(qp_solver: str = "osqp") -> list[str]:
    return ["-I.", "-Idaqp/include"] if qp_solver == "daqp" else ["-I.", "-Iosqp", "-Iosqp/inc/public",
                                                                    "-Iosqp/inc/private"]


def _defs(precision: str) -> list[str]:
    return ["-fsingle-precision-constant"] if precision == "single" else []


def _makefile(precision: str, qp_solver: str = "osqp") -> str:
    arm7, m7 = _ARM["cortex-m7"]
    arm4, m4 = _ARM["cortex-m4f"]
    return f"""# The library and its driver (hbma_run.c) for the host and for two Cortex-M boards run on QEMU.
#   make host          build/host/libhbma.a and hbma_run_host      (./hbma_run_host INPUTS.bin)
#   make cortex-m7     build/cortex-m7/libhbma.a and hbma_run_cortex-m7.elf   (MPS2 AN500)
#   make cortex-m4f    build/cortex-m4f/libhbma.a and hbma_run_cortex-m4f.elf (MPS2 AN386)
#   make run-cortex-m7 INPUTS=inputs.bin      (QEMU, semihosting; the same for run-host, run-cortex-m4f)
#   make clean cortex-m7 PROFILE=1   the board driver also prints each tick's instructions per part
# make -j builds the sources in parallel.
SRC = {' '.join(_sources(qp_solver))}
INC = {' '.join(_includes(qp_solver))}
OPT ?= {OPT}
CFLAGS_COMMON = $(OPT) -std=c99 -Wall -Wno-unused-variable -Wno-unused-but-set-variable -Wno-unused-function \\
  -Wno-parentheses {' '.join(_defs(precision))}
CC ?= cc
ARMCC ?= arm-none-eabi-gcc
AR_ARM ?= arm-none-eabi-ar
FLAGS_host =
FLAGS_cortex-m7 = {' '.join(arm7)} -ffunction-sections -fdata-sections
FLAGS_cortex-m4f = {' '.join(arm4)} -ffunction-sections -fdata-sections
ARM_LD = -T board/mps2.ld --specs=rdimon.specs -nostartfiles -Wl,--gc-sections
INPUTS ?= inputs.bin
PROFILE ?=
BOARD_DEFS = -DHBMA_BOARD $(if $(PROFILE),-DHBMA_PROFILE)
QEMU_FLAGS = -nographic -monitor none -serial none -icount shift=0

host: hbma_run_host
cortex-m7: hbma_run_cortex-m7.elf
cortex-m4f: hbma_run_cortex-m4f.elf

build/host/%.o: %.c hbma.h
\t@mkdir -p $(dir $@)
\t$(CC) $(CFLAGS_COMMON) $(INC) -c $< -o $@
build/cortex-m7/%.o: %.c hbma.h
\t@mkdir -p $(dir $@)
\t$(ARMCC) $(FLAGS_cortex-m7) $(CFLAGS_COMMON) $(BOARD_DEFS) $(INC) -c $< -o $@
build/cortex-m4f/%.o: %.c hbma.h
\t@mkdir -p $(dir $@)
\t$(ARMCC) $(FLAGS_cortex-m4f) $(CFLAGS_COMMON) $(BOARD_DEFS) $(INC) -c $< -o $@

build/host/libhbma.a: $(SRC:%.c=build/host/%.o)
\tar rcs $@ $^
build/cortex-m7/libhbma.a: $(SRC:%.c=build/cortex-m7/%.o)
\t$(AR_ARM) rcs $@ $^
build/cortex-m4f/libhbma.a: $(SRC:%.c=build/cortex-m4f/%.o)
\t$(AR_ARM) rcs $@ $^

hbma_run_host: build/host/hbma_run.o build/host/libhbma.a
\t$(CC) -o $@ $^ -lm
hbma_run_cortex-m7.elf: build/cortex-m7/board/startup.o build/cortex-m7/hbma_run.o build/cortex-m7/libhbma.a board/mps2.ld
\t$(ARMCC) $(FLAGS_cortex-m7) $(ARM_LD) -o $@ $(filter %.o %.a,$^) -lm
hbma_run_cortex-m4f.elf: build/cortex-m4f/board/startup.o build/cortex-m4f/hbma_run.o build/cortex-m4f/libhbma.a board/mps2.ld
\t$(ARMCC) $(FLAGS_cortex-m4f) $(ARM_LD) -o $@ $(filter %.o %.a,$^) -lm

run-host: hbma_run_host
\t./hbma_run_host $(INPUTS)
run-cortex-m7: hbma_run_cortex-m7.elf
\tqemu-system-arm -M {m7} $(QEMU_FLAGS) -semihosting-config enable=on,target=native,arg=hbma_run,arg=$(INPUTS) -kernel $<
run-cortex-m4f: hbma_run_cortex-m4f.elf
\tqemu-system-arm -M {m4} $(QEMU_FLAGS) -semihosting-config enable=on,target=native,arg=hbma_run,arg=$(INPUTS) -kernel $<

clean:
\trm -rf build hbma_run_host hbma_run_cortex-m7.elf hbma_run_cortex-m4f.elf

.PHONY: host cortex-m7 cortex-m4f run-host run-cortex-m7 run-cortex-m4f clean
""" + ("" if qp_solver != "daqp" else f"""
# DAQP allocates only on paths the library never takes: its allocator's names map onto hbma.c's stubs
QP_SRC = {' '.join(_qp_sources(qp_solver))}
$(foreach t,host cortex-m7 cortex-m4f,$(QP_SRC:%.c=build/$(t)/%.o)): CFLAGS_COMMON += {' '.join(_DAQP_DEFS)}
""")


def _cmake(precision: str, qp_solver: str = "osqp") -> str:
    single = ' "-fsingle-precision-constant"' if precision == "single" else ""
    return f"""# The library as a static library target (hbma) for the host or a cross toolchain file.
cmake_minimum_required(VERSION 3.13)
project(hbma C)
add_library(hbma STATIC {' '.join(_sources(qp_solver))})
target_include_directories(hbma PUBLIC {' '.join(i[2:] for i in _includes(qp_solver))})
set_property(TARGET hbma PROPERTY C_STANDARD 99)
target_compile_options(hbma PRIVATE{single})
{'' if qp_solver != 'daqp' else 'set_source_files_properties(' + ' '.join(_qp_sources(qp_solver)) + chr(10) + '  PROPERTIES COMPILE_DEFINITIONS "' + ';'.join(d[2:] for d in _DAQP_DEFS) + '")' + chr(10)}find_library(M_LIB m)
if(M_LIB)
  target_link_libraries(hbma PUBLIC ${{M_LIB}})
endif()
add_executable(hbma_run hbma_run.c)
target_link_libraries(hbma_run hbma)
"""


def _readme(lib: LibrarySpec, precision: str, sz: dict) -> str:
    spec = lib.loop
    stages = "\n".join(f"  {st.name}" + (f" every {st.every} ticks" if st.every > 1 else "")
                       + (f" while {st.gate} {'== 0' if st.gate_off else '!= 0'}" if st.gate else "")
                       + (f", up to {st.repeat} calls" if st.repeat > 1 else "")
                       for st in spec.stages if st != LOG)
    if lib.kind == "robot":
        inputs = (f"inputs.bin: little-endian doubles: ticks, chambers ({lib.n}), layers ({lib.n_layers}), then per tick\n"
                  "t, the chambers' readings and each layer's pose (centre m, bend rad, direction rad). The driver\n"
                  "prints per tick: k, u (3 x chambers: speeds, inlets, outlets), status, OSQP's iterations, the\n"
                  "estimated heights (m)")
    else:
        inputs = ("inputs.bin: little-endian doubles: ticks, preview length P, then per tick\n"
                  "t, p, target and P preview targets. The driver prints per tick: k, u (3), status, the QP solver's iterations,\n"
                  "the estimated height (m)")
    return (f"The {lib.kind}'s tick as a C library (hbma-ctrl codegen --library), scenario \"{spec.name}\", "
            f"{precision} precision, tick {spec.dt * 1e3:g} ms.\n\n"
            "API (hbma.h): hbma_default_params, hbma_init, hbma_set_target, hbma_tick, hbma_outputs. All memory in\n"
            "hbma_workspace_t (sizeof: compile-time); no malloc, no file I/O, only libm.\n\n"
            "Build: make host | make cortex-m7 | make cortex-m4f | make libhbma.a, or CMake (target hbma).\n"
            "make clean cortex-m7 PROFILE=1: the board driver also prints each tick's instructions per part\n"
            "(hbma.h's HBMA_PART_NAMES: the stages, then the QP's: " + ", ".join(_QP_PARTS[lib.qp_solver]) + ").\n"
            "Run on recorded inputs: ./hbma_run_host inputs.bin, or make run-cortex-m7 INPUTS=inputs.bin\n"
            f"(QEMU, semihosting). {inputs}, and on a board the SysTick counts of the tick (with QEMU's -icount\n"
            "shift=0, 40 instructions per count; the driver prints its calibration first).\n\n"
            f"Files: hbma.c (the tick), {STEPS}.c/.h (casadi-generated Functions), "
            + ("daqp/ (DAQP's C sources and licence: the dense QP solver, its workspace in hbma_workspace_t)"
               if lib.dense else "osqp/ (OSQP's embedded solver, its workspace a struct)")
            + ", hbma_run.c (driver), board/ (start-up file, linker script).\n"
            f"Work arrays: arg {sz['arg']}, res {sz['res']}, iw {sz['iw']}, w {sz['w']}.\n\n"
            f"Stages per tick:\n{stages}\n" + "".join(f"\n{k}: {v}" for k, v in lib.meta.items()) + "\n")


# --------------------------------------------------------------------------------------------- inputs
def record_inputs(scn, lib: LibrarySpec, ticks: int) -> dict:
    """The scenario's own closed loop on the sim rig over ``ticks`` ticks (no start-up calibration): its
    readings (Pa, NaN for a dropout), the library's targets at those times (the target, and the
    controller's preview when the scenario previews), its commands and estimated heights. Returns arrays
    t, p, target, preview (ticks x P), u (ticks x 3), h_est; for a robot (:func:`_record_robot`) t, p,
    pose, u, h_est."""
    if lib.kind == "robot":
        return _record_robot(scn, lib, ticks)
    from hbma_ctrl.app.scenes.controller import closed_loop
    from hbma_ctrl.sim.rig import RigSettings
    from hbma_ctrl.system.roles import estimator_from_scenario
    from hbma_ctrl.app.codegen.chamber import scenario_system

    rs = scn.role("rig") or RigSettings(sensor_range=scn.sim.sensor_range)
    section = scn.role("controller")
    log = closed_loop(scn.actuator, scn.pneumatics, scn.platform, section, ticks * rs.sample_period, rs,
                      estimator=estimator_from_scenario(scn, rs), calibrate=False)
    t = np.arange(ticks) * rs.sample_period
    system = scenario_system(scn, rs, "osqp")
    loop = system.loop
    target = np.array([loop.reference(tk) for tk in t])
    P, dp = loop.preview_steps, loop.preview_period
    preview = (np.array([[loop.reference(tk + dp * (min(j, P - 1) + 1)) for j in range(lib.horizon)] for tk in t])
               if P else np.zeros((ticks, 0)))
    return {"t": t, "p": np.asarray(log.p_meas, float)[:ticks], "target": target, "preview": preview,
            "u": np.asarray(log.u, float)[:ticks], "h_est": np.asarray(log.h_est, float)[:ticks]}


def _record_robot(scn, lib: LibrarySpec, ticks: int) -> dict:
    """The robot scenario's own closed loop (its scene's rig and system, the NMPC running the generated
    step's Function, :class:`hbma_ctrl.controllers.robot_rti_step.RobotNMPCFunction`) over ``ticks``
    ticks in lockstep: the rig's clock t (s), the readings p (ticks x n, Pa), each layer's pose at those
    times (ticks x L x 3: centre m, bend rad, direction rad), the valve inputs sent (ticks x 3 n, the
    speeds, inlets, outlets) and the estimated heights (ticks x n, m)."""
    from functools import partial

    from hbma_ctrl.app.codegen.robot import robot_scene_parts
    from hbma_ctrl.app.scenes.robot_loop import build_closed_loop
    from hbma_ctrl.controllers.robot_rti_step import RobotNMPCFunction
    from hbma_ctrl.robot.targets import _layer_pose

    s, rig, model, mpc = robot_scene_parts(scn)
    sim, system = build_closed_loop(s, s.targets, "mpc", scn.pneumatics, rig, mpc, model=model, tip_load=s.tip_load,
                                    nmpc_class=partial(RobotNMPCFunction, compile=False))
    plant, L = sim.rig, s.design.n_layers
    t, p, pose, u = np.zeros(ticks), np.zeros((ticks, lib.n)), np.zeros((ticks, L, 3)), np.zeros((ticks, 3 * lib.n))
    h_est = np.zeros((ticks, lib.n))
    for k in range(ticks):
        r = sim.read()
        t[k] = plant.t  # the plant's clock, which the scene ticks on
        p[k] = r.p
        pose[k] = [_layer_pose(s.targets[j], t[k])[1:4] for j in range(L)]
        cmd = system.tick(t[k], r.p, r.held)
        sim.write(cmd)
        u[k] = np.asarray(cmd).ravel()
        h_est[k] = system.loop.estimate["h"]
    return {"t": t, "p": p, "pose": pose, "u": u, "h_est": h_est}


def write_inputs(rec: dict, path: Path | str) -> Path:
    """The driver's input file (README.txt of the library: little-endian doubles)."""
    if "pose" in rec:
        n, nc, L = rec["t"].size, rec["p"].shape[1], rec["pose"].shape[1]
        rows = np.column_stack([rec["t"], rec["p"], rec["pose"].reshape(n, 3 * L)])
        path = Path(path)
        with path.open("wb") as fh:
            fh.write(struct.pack("<3d", float(n), float(nc), float(L)))
            fh.write(np.ascontiguousarray(rows, dtype="<f8").tobytes())
        return path
    n, P = rec["t"].size, rec["preview"].shape[1]
    rows = np.column_stack([rec["t"], rec["p"], rec["target"], rec["preview"]]) if P else np.column_stack(
        [rec["t"], rec["p"], rec["target"]])
    path = Path(path)
    with path.open("wb") as fh:
        fh.write(struct.pack("<2d", float(n), float(P)))
        fh.write(np.ascontiguousarray(rows, dtype="<f8").tobytes())
    return path


# --------------------------------------------------------------------------------------------- build, run
def build_library(out_dir: Path | str, target: str) -> Path:
    """Build the driver for ``target`` with the library's Makefile; the program's path. RuntimeError with
    the compiler's message. ``$HBMA_CTRL_CC_OPT`` (:data:`hbma_ctrl.core.codegen.OPT_ENV`), when set,
    replaces the Makefile's optimisation level as it does for every Function the package compiles."""
    if target not in TARGETS:
        raise ValueError(f"--target = '{target}'; allowed: {', '.join(TARGETS)}")
    out = Path(out_dir)
    jobs = str(max(1, min(4, os.cpu_count() or 1)))
    opt = os.environ.get(OPT_ENV)
    res = subprocess.run(["make", "-s", f"-j{jobs}", target] + ([f"OPT={opt}"] if opt else []), cwd=out,
                         capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"make {target} failed: {(res.stderr or res.stdout).strip()[-3000:]}")
    return out / ("hbma_run_host" if target == "host" else f"hbma_run_{target}.elf")


def qemu_command(target: str, elf: Path | str, inputs: Path | str) -> list[str]:
    """QEMU's command line of a Cortex-M run: the target's MPS2 board, semihosting on the host's files,
    instruction counting (``-icount shift=0``: the virtual clock advances 1 ns per instruction)."""
    return ["qemu-system-arm", "-M", _ARM[target][1], "-nographic", "-monitor", "none", "-serial", "none",
            "-semihosting-config", f"enable=on,target=native,arg=hbma_run,arg={inputs}", "-icount", "shift=0",
            "-kernel", str(elf)]


@dataclass
class LibraryRun:
    """One run of the driver: the commands (ticks x 3), the tick's status codes, the instructions per tick
    (boards only; None on the host), the driver's calibration of its counter (instructions per count)
    OSQP's iterations in the controller's last QP at each tick, sizeof(hbma_workspace_t) there, the
    estimated height at each tick (m) and, from a profiled board build (``PROFILE=1``), each part's
    instructions per tick by the part's name (None otherwise)."""

    u: np.ndarray
    status: np.ndarray
    instructions: np.ndarray | None
    per_count: float | None
    qp_iterations: np.ndarray | None = None
    workspace_bytes: int | None = None
    height: np.ndarray | None = None
    parts: dict | None = None


def _parse(text: str) -> LibraryRun:
    """The driver's output (hbma_run.c): its calibration, workspace size, parts, the commands' and heights'
    counts per line (``signals NU NH``; 3 and 1 without the line) and the ticks."""
    rows, per_count, wsb, names, nu, nh = [], None, None, [], 3, 1
    for line in text.splitlines():
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "signals":
            nu, nh = int(parts[1]), int(parts[2])
        elif parts[0] == "parts":
            names = parts[1:]
        elif parts[0] == "workspace":
            wsb = int(parts[1])
        elif parts[0] == "calibration":
            per_count = float(parts[2]) / float(parts[1])
        elif parts[0].lstrip("-").isdigit():
            rows.append([float(v) for v in parts])
    if not rows:
        raise RuntimeError(f"the driver printed no ticks: {text[-2000:]}")
    a = np.array(rows)
    c = 3 + nu + nh  # the tick's count's column
    ins = a[:, c] * per_count if a.shape[1] > c and per_count else None
    by_part = ({n: a[:, c + 1 + i] * per_count for i, n in enumerate(names)}
               if names and per_count and a.shape[1] == c + 1 + len(names) else None)
    height = a[:, 3 + nu] if nh == 1 else a[:, 3 + nu:3 + nu + nh]
    return LibraryRun(a[:, 1:1 + nu], a[:, 1 + nu].astype(int), ins, per_count, a[:, 2 + nu], wsb, height, by_part)


def run_library(out_dir: Path | str, target: str, inputs: Path | str, timeout: float = 3600.0) -> LibraryRun:
    """Run the built driver of ``target`` on ``inputs`` (the host's program, or QEMU for a board); its output
    is kept in ``run_<target>.txt``."""
    out = Path(out_dir).resolve()
    inputs = Path(inputs).resolve()
    if target == "host":
        cmd = [str(out / "hbma_run_host"), str(inputs)]
    else:
        cmd = qemu_command(target, out / f"hbma_run_{target}.elf", inputs)
    res = subprocess.run(cmd, cwd=out, capture_output=True, text=True, timeout=timeout)
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} exited {res.returncode}: {(res.stderr or res.stdout)[-2000:]}")
    (out / f"run_{target}.txt").write_text(res.stdout)  # the driver's own lines: every number is in them
    return _parse(res.stdout)


def _size(elf: Path) -> tuple[int, int]:
    """(flash bytes: text + data, RAM bytes: data + bss) of a board program (arm-none-eabi-size)."""
    res = subprocess.run(["arm-none-eabi-size", "-A", str(elf)], capture_output=True, text=True, check=True)
    sec = {}
    for line in res.stdout.splitlines()[2:]:
        parts = line.split()
        if len(parts) >= 2 and parts[1].isdigit():
            sec[parts[0]] = int(parts[1])
    text = sum(v for k, v in sec.items() if k in (".isr_vector", ".text", ".rodata", ".ARM.exidx", ".init_array",
                                                     ".fini_array", ".ARM.extab"))
    data, bss = sec.get(".data", 0), sec.get(".bss", 0)
    return text + data, data + bss


def embedded_report(target: str, host: LibraryRun, board: LibraryRun, elf: Path, every: int = 1,
                    precision: str = "double") -> dict:
    """``embedded.json``: the target, ticks, the largest |board - host| command, instructions per tick
    (median, p99, max over all ticks; the medians of the ticks the controller runs in, every ``every``-th
    from the first, and of the others, the estimator's alone), flash and RAM of the board program
    (arm-none-eabi-size: text + rodata + data, and data + bss, which holds the driver's workspace), and
    from a profiled board build each part's median over the controller's ticks."""
    if board.u.shape != host.u.shape:
        raise RuntimeError(f"the board ran {board.u.shape[0]} ticks, the host {host.u.shape[0]}")
    d = np.abs(board.u - host.u)
    both_nan = np.isnan(board.u) & np.isnan(host.u)
    d = np.where(both_nan, 0.0, d)
    flash, ram = _size(elf)
    ins = board.instructions
    return {"target": target, "precision": precision, "ticks": int(host.u.shape[0]),
            "max_abs_diff": float(np.nanmax(d)) if np.isfinite(d).all() else float("inf"),
            "instructions_per_tick_median": float(np.median(ins)), "instructions_per_tick_max": float(np.max(ins)),
            "instructions_per_tick_p99": float(np.percentile(ins, 99)),
            "instructions_controller_tick_median": float(np.median(ins[::every])),
            "instructions_estimator_tick_median": float(np.median(np.delete(ins, np.s_[::every])))
            if every > 1 else None,
            "instruction_counting": "qemu-system-arm -icount shift=0 (1 ns of virtual time per instruction), the "
                                    "SysTick counter (25 MHz) read around hbma_tick, calibrated against a loop of "
                                    "known length",
            "instructions_per_count": board.per_count,
            "flash_bytes": flash, "ram_bytes": ram, "workspace_bytes": board.workspace_bytes,
            "status_solve_failed": int(np.sum(board.status == 1)),
            **({"instructions_controller_tick_median_by_part": {
                n: float(np.median(v[::every])) for n, v in board.parts.items()}} if board.parts else {})}


def toolchain_missing(target: str) -> list[str]:
    """The programs a target's build and run need that are not on PATH (empty: none missing)."""
    need = ["make"] + (["arm-none-eabi-gcc", "arm-none-eabi-size", "qemu-system-arm"] if target != "host" else [])
    return [p for p in need if shutil.which(p) is None]


def _commands_diff(a: LibraryRun, b: LibraryRun) -> float:
    """Largest |a - b| of two runs' commands (NaN in both: equal)."""
    d = np.abs(a.u - b.u)
    d = np.where(np.isnan(a.u) & np.isnan(b.u), 0.0, d)
    return float(np.max(d)) if np.isfinite(d).all() else float("inf")


def generate(scn, out_dir: Path | str, target: str = "host", precision: str = "double",
             duration_s: float | None = None, log=print, qp_solver: str = "osqp") -> dict:
    """``codegen --library``: write the library into ``out_dir`` and build it for the host; with a Cortex-M
    ``target`` also record ``ticks`` ticks of the scenario's pressures (None: its duration), build the
    board program, run host and board on them and write ``embedded.json`` (returned; {} for the host
    target). A single-precision library is also compared with a double one built in
    ``out_dir/double``. ``qp_solver``: :data:`QP_SOLVERS`. ValueError naming the option when the toolchain
    is missing."""
    if target not in TARGETS:
        raise ValueError(f"--target = '{target}'; allowed: {', '.join(TARGETS)}")
    if precision not in PRECISIONS:
        raise ValueError(f"--precision = '{precision}'; allowed: {', '.join(PRECISIONS)}")
    missing = toolchain_missing(target)
    if missing:
        raise ValueError(f"--target {target}: {', '.join(missing)} not on PATH (Debian: apt-get install "
                         "gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm)")
    check_qp_solver(qp_solver, precision)
    out = Path(out_dir)
    lib = library_spec(scn, qp_solver)
    write_library(lib, out, precision)
    log(f"building the library for the host ({precision})")
    build_library(out, "host")
    if target == "host":
        return {}
    n = int(round((scn.duration if duration_s is None else duration_s) / lib.loop.dt))
    log(f"recording {n} ticks of the scenario's pressures on the sim rig")
    rec = record_inputs(scn, lib, n)
    inputs = write_inputs(rec, out / "inputs.bin")
    log(f"building for {target}")
    elf = build_library(out, target)
    log("running the host build")
    host = run_library(out, "host", inputs)
    log(f"running on QEMU ({_ARM[target][1]})")
    board = run_library(out, target, inputs)
    (out / "commands_host.txt").write_text(_commands_text(host))
    (out / f"commands_{target}.txt").write_text(_commands_text(board))
    report_qp = float(np.median(host.qp_iterations[::lib.every]))
    report = embedded_report(target, host, board, elf, lib.every, precision)
    report["qemu_machine"] = _ARM[target][1]
    report["scenario"] = scn.name
    report["qp_iterations_median"] = report_qp
    if "u" in rec:
        # the scenario's own run the pressures were recorded from (its controller's solver, not the library's)
        d = np.abs(host.u - rec["u"][: host.u.shape[0]])
        report["recorded_commands_max_abs_diff"] = float(np.nanmax(d))
        report["recorded_commands_median_abs_diff"] = float(np.nanmedian(d))
        report["recorded_ticks_diff_above_1e-3"] = int(np.sum(np.nanmax(d.reshape(d.shape[0], -1), axis=1) > 1e-3))
        dh = np.abs(host.height - rec["h_est"][: host.u.shape[0]].reshape(host.height.shape))
        report["recorded_height_estimate_max_abs_diff_m"] = float(np.nanmax(dh))
    if precision == "single":
        ref = out / "double"
        write_library(lib, ref, "double")
        log("building the double-precision library on the host (the single build's reference)")
        build_library(ref, "host")
        dbl = run_library(ref, "host", inputs)
        report["max_abs_diff_vs_double"] = _commands_diff(host, dbl)
        d = np.abs(host.u - dbl.u)
        report["abs_diff_vs_double_median"] = float(np.nanmedian(d))
        report["abs_diff_vs_double_p99"] = float(np.nanpercentile(d, 99))
        report["ticks_diff_vs_double_above_1e-3"] = int(np.sum(np.nanmax(d, axis=1) > 1e-3))
        report["height_estimate_max_abs_diff_vs_double_m"] = float(np.nanmax(np.abs(host.height - dbl.height)))
    (out / "embedded.json").write_text(json.dumps(report, indent=2) + "\n")
    return report


def _commands_text(run: LibraryRun) -> str:
    return "".join(f"{k} " + " ".join(f"{v:.17g}" for v in u) + "\n" for k, u in enumerate(run.u))
