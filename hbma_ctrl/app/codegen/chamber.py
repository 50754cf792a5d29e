"""A scenario's closed loop (rig -> EKF -> RTI NMPC -> rig) as a :class:`~hbma_ctrl.core.loopgen.LoopSpec`.

The three step Functions are the ones the Python roles call: the plant over one rig period
(:func:`hbma_ctrl.sim.plant_step.plant_step_function`), the EKF step
(:func:`hbma_ctrl.estimators.ekf_step.ekf_step_function`) and the RTI step
(:func:`hbma_ctrl.controllers.rti_step.rti_step_function`). What the Python classes do around them is written
here as small casadi Functions too, so that the C loop needs no Python:

- ``sensor``: the rig's reading, the true (or lagged) pressure plus the tick's noise, saturated at the
  range (noise and dropouts drawn at generation time from the rig's seeded stream, as :class:`Rig` draws
  them); the rig's structure around its plant: ``valve_line`` (the valves' delay and minimum opening)
  and ``sensor_lag`` (:mod:`hbma_ctrl.sim.plant_step`);
- ``ekf_kind``: the reading's kind (:func:`hbma_ctrl.estimators.common.classify_measurement`); ``ekf_acting``: the
  command acting for the EKF's valve and sensor delays (:func:`hbma_ctrl.models.actuation.acting_function`);
- ``mpc_prep``: the NMPC's problem data from the estimate (its load filter, initial state, output
  biases, reachable height, clipped targets and integral action): the Function the NMPC itself calls
  (:mod:`hbma_ctrl.controllers.mpc_prep`);
- ``mpc_cold``: the cold-start guess (after the first step or a failure);
- ``mpc_post``: the command after the NMPC and the runtime's supervisor (plan replay on a failure,
  safe command, pressure guard; :class:`hbma_ctrl.runtime.safety.Supervisor`);
- ``pwm``: the command sent every tick, shaped for the valves' minimum on-time
  (:meth:`hbma_ctrl.runtime.pwm.MinOnTime.function`).

The glue rounds as the Python classes do (``np.interp``'s formula, the load filter's gain from the
scene's clock), so the generated loop follows the scene's own closed loop (``closed_loop(...,
calibrate=False)`` with the NMPC variant ``rti_fn_osqp`` and no enforced budget;
:func:`scene_reference`) to rounding: measured over the whole scenarios, on ``track_height.toml`` (the
default rig and models) 1e-15 m in the heights, 1e-11 in the commands and 2.4e-9 Pa in the pressures;
on ``mpc_ramp_sine.toml``, through its solver failures, 9e-14 m, 5e-10 and 3e-7 Pa. A solve that fails
inside the generated step (its QP solver returns non-zero) reads as failed (``Stage.fails_to``), as in the
NMPC. casadi's virtual machine and the generated C of the same step can disagree where a QP is marginal
(on ``mpc_ramp_sine.toml`` at t = 5.2 s OSQP gives up in the generated C and not on the VM), which is
why the Python path runs the generated library.

Not reproduced (the generated loop and its Python path leave them out, both alike): the start-up
calibration, the EKF's rare reference-path events (``exact`` = 0; counted in the trajectory's
``ekf_reference_events``), the budget/overrun logic (wall-clock dependent), load steps during the
run. Refused with the key named: the quasi-static rig's snap-through search, an enforced budget
(``enforce_budget``). The loop starts at t = 0
with the rig at rest.
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

from hbma_ctrl.controllers.mpc_prep import problem_function
from hbma_ctrl.core.loopgen import LOG, LogColumn, LoopSpec, Stage
from hbma_ctrl.estimators.common import classify_expr
from hbma_ctrl.core import units as U
from hbma_ctrl.models.fidelity import OUTPUTS
from hbma_ctrl.runtime.chamber import chamber_supervisor
from hbma_ctrl.runtime.safety_step import state_parts, supervisor_function
from hbma_ctrl.sim.plant_step import (
    initial_plant_state,
    plant_step_function,
    plant_step_support,
    sensor_lag_function,
    valve_line_function,
)
from hbma_ctrl.sim.rig import Rig, RigSettings
from hbma_ctrl.sim.trial import DEFAULT_DT

__all__ = ["scenario_loop", "mpc_glue", "rig_noise", "plant_stage_parts", "rig_stages", "qp_solver_for",
           "scene_reference", "loop_run_metrics", "ESTIMATORS"]


# --------------------------------------------------------------------------------------------- rig
def plant_stage_parts(actuator, pneumatics, platform, rs: RigSettings):
    """(plant_step Function, theta, x0, mode0, y0, fidelity name) of the rig a scene would build; the
    Function takes the inputs of each internal step (``per_substep``) when the rig has valve timing.

    ValueError naming the scenario key when the rig's period step is not one casadi Function."""
    rig = Rig(actuator, pneumatics, platform, rs)
    fid = rig._plant.fid
    why = plant_step_support(fid.name, rs)
    if why:
        raise ValueError(f"codegen: {why}")
    nsub = _substeps(rs, fid.name)
    fun = plant_step_function(fid, rs.integrator, rs.sample_period / nsub, nsub, per_substep=_valve_timing(rs))
    theta = rig._plant.thetas[:, 0].copy()
    x0, m0, y0 = initial_plant_state(fid, theta)
    return fun, theta, x0, m0, y0, fid.name


def _substeps(rs: RigSettings, fidelity: str) -> int:
    """Internal steps per rig period, as :class:`Rig` takes them."""
    dt = rs.dt if rs.dt is not None else DEFAULT_DT[(rs.integrator, fidelity)]
    return max(1, int(np.ceil(rs.sample_period / dt - 1e-9)))


def _valve_timing(rs: RigSettings) -> bool:
    """Whether the rig's valves are delayed or have a minimum on-time (the plant then takes the inputs
    of each internal step from ``valve_line``)."""
    return rs.valve_delay > 0 or rs.valve_min_on > 0


def rig_stages(scn, rs: RigSettings, n: int) -> tuple[list, list, dict, np.ndarray, str]:
    """The rig's stages around the controllers over ``n`` ticks: (stages before the estimator: the
    reading; stages after the command: valve line, plant and sensor lag; their signals; the noise
    stream; a description). The reading at tick k is taken before the command of tick k is applied, as
    :meth:`Rig.measure` then :meth:`Rig.apply`."""
    plant, theta, x0, m0, y0, fid_name = plant_stage_parts(scn.actuator, scn.pneumatics, scn.platform, rs)
    noise = rig_noise(rs, n)
    lagged = rs.sensor_tau > 0
    p0 = float(y0[OUTPUTS.index("p")])
    signals = {"x": x0, "mode": [m0], "y": y0, "u": np.zeros(3), "theta": theta, "noise": [0.0], "z": [0.0]}
    sensor = _sensor(rs.sensor_range, lagged)
    read = [Stage(sensor, ["p_sensed" if lagged else "y", "noise"], ["z"])]
    after = []
    if _valve_timing(rs):
        nsub = _substeps(rs, fid_name)
        line = valve_line_function(rs, nsub)
        signals.update(u_sub=np.zeros(3 * nsub), valve_hist=np.zeros(line.nnz_in(1)))
        after.append(Stage(line, ["u", "valve_hist"], ["u_sub", "valve_hist"]))
        after.append(Stage(plant, ["x", "mode", "u_sub", "theta"], ["x", "mode", "y"]))
    else:
        after.append(Stage(plant, ["x", "mode", "u", "theta"], ["x", "mode", "y"]))
    if lagged:
        signals.update(p_sensed=[p0], p_prev=[p0])
        after.append(Stage(sensor_lag_function(rs), ["p_sensed", "p_prev", "y"], ["p_sensed", "p_prev"]))
    z0 = float(np.asarray(sensor(p0 if lagged else y0, noise[0])).ravel()[0])
    signals["z"] = [z0]
    membrane = getattr(rs, "membrane", "cap")
    desc = (f"{fid_name}, {membrane} membrane, {rs.integrator}, {rs.sample_period * 1e3:g} ms, seed {rs.seed}; "
            f"valve delay {rs.valve_delay * 1e3:g} ms, minimum opening {rs.valve_min_on * 1e3:g} ms, "
            f"pump tilt {rs.compressor_tilt:g}, sensor lag {rs.sensor_tau * 1e3:g} ms")
    return read, after, signals, noise, desc


def rig_noise(rs: RigSettings, n: int) -> np.ndarray:
    """The rig's first n sensor perturbations (Pa; NaN = dropout), drawn as :meth:`Rig.measure` does."""
    rng = np.random.default_rng(rs.seed)
    out = np.zeros(n)
    for k in range(n):
        noise = rng.standard_normal() * rs.noise_std
        drop = rng.random() < rs.dropout_prob if rs.dropout_prob > 0 else False
        out[k] = math.nan if drop else noise
    return out


def _sensor(sensor_range: float, lagged: bool = False) -> ca.Function:
    """The reading: the pressure (the plant's outputs ``y``, or the lagged ``p_sensed``) plus the tick's
    noise, saturated at the range."""
    noise = ca.SX.sym("noise")
    if lagged:
        src = ca.SX.sym("p_sensed")
        p = src
    else:
        src = ca.SX.sym("y", len(OUTPUTS))
        p = src[OUTPUTS.index("p")]
    z = p + noise
    # NaN noise (a dropout) stays NaN: the comparison is false for it
    return ca.Function("sensor", [src, noise], [ca.if_else(z > sensor_range, sensor_range, z)],
                       ["p_sensed" if lagged else "y", "noise"], ["z"])


# --------------------------------------------------------------------------------------------- MPC
def mpc_glue(model, s, sup, nz: int = 0, nc: int = 0) -> tuple:
    """(mpc_prep, mpc_cold, mpc_post) casadi Functions of the NMPC with settings ``s`` (MPCSettings)
    on its PredictionModel and the supervisor settings ``sup`` (see the module docstring); ``nz``, ``nc``
    the RTI step's numbers of QP variables and rows (the cold start's zero duals). mpc_prep is the
    NMPC's own (:func:`hbma_ctrl.controllers.mpc_prep.problem_function`, which ``NMPC._problem`` calls); it takes
    the load filter's gain ``load_a`` = min(1, dt / load_tau) as an input: dt is the time since the last
    step, which the scene computes from its clock (a data stream of the loop)."""
    N = s.horizon
    prep = problem_function(model, s)
    # --- cold start (the backend without a plan): the estimate held, the last command repeated
    x0s, up = ca.SX.sym("x0"), ca.SX.sym("u_prev", 3)
    cold = ca.Function("mpc_cold", [x0s, up], [ca.repmat(x0s, N + 1, 1), ca.repmat(up, 1, N), ca.SX.zeros(nz),
                                                ca.SX.zeros(nc)],
                       ["x0", "u_prev"], ["X_guess", "U_guess", "lam_x_guess", "lam_a_guess"])
    # --- NMPC result -> the runtime's supervisor (its Function: fallback, clip, guard) -> the command sent
    SX = ca.SX
    u0, Up, status, p_g_in = SX.sym("u0", 3), SX.sym("U_plan", 3, N), SX.sym("status"), SX.sym("p")
    fail_s = SX.sym("fail")
    plan, has_plan, age, streak = SX.sym("plan", 3, N), SX.sym("has_plan"), SX.sym("age"), SX.sym("streak")
    okc = ca.logic_and(status == 0, fail_s == 0)
    supervise = supervisor_function(sup, 1, 3, N, "mpc_supervisor")
    # one chamber, plans by row (no plan times), no vent rule, stretch guard, lost or burst input: the
    # state in state_parts' order, its plan time and latches 0
    parts = state_parts(1, 3, N)
    state = ca.vertcat(ca.vec(plan), has_plan, 0.0, streak, age, 0.0, 0.0)
    nan = ca.DM.nan()
    out, nxt = supervise(0.0, u0, p_g_in, okc, ca.vec(Up), okc, nan, nan, 0.0, 0.0, state)[:2]
    plan_n = ca.reshape(nxt[parts["plan"]], 3, N)
    has_n, streak_n, age_n = (nxt[parts[key].start] for key in ("has_plan", "streak", "age"))
    post = ca.Function("mpc_post", [u0, Up, status, fail_s, p_g_in, plan, has_plan, age, streak],
                       [out, 1 - okc, plan_n, has_n, age_n, streak_n],
                       ["u0", "U_plan", "status", "fail", "p", "plan", "has_plan", "age", "streak"],
                       ["u", "cold", "plan_next", "has_plan_next", "age_next", "streak_next"])
    return prep, cold, post


def qp_solver_for(variant: str, qp_solver: str | None = None) -> str:
    """The conic plugin the generated RTI step uses: ``qp_solver`` if given, the variant's own for the
    'rti_fn_*' variants, else OSQP (as 'rti_osqp'; linked from the casadi package). qrqp generates
    self-contained C but fails on the cold starts of this QP (hbma_ctrl.controllers.rti_step)."""
    from hbma_ctrl.controllers.rti_step import QP_SOLVERS

    if qp_solver is None:
        qp_solver = variant[len("rti_fn_"):] if variant.startswith("rti_fn_") else "osqp"
    if qp_solver not in QP_SOLVERS:
        raise ValueError(f"--qp-solver = '{qp_solver}'; allowed: {', '.join(QP_SOLVERS)}")
    return qp_solver


def _mpc_stages(scn, section, every: int, qp_solver: str | None, pwm=None) -> tuple[list, dict, dict]:
    """The NMPC's stages (RTI variants), its signals and meta data. ``pwm``: the valves' minimum on-time
    shaping (:class:`hbma_ctrl.runtime.pwm.MinOnTime`, None = none); with it the NMPC and its supervisor
    keep the command they asked for (``wanted``) and every tick sends it shaped (``u``), as
    :class:`hbma_ctrl.runtime.chamber.ChamberLoop` does."""
    from hbma_ctrl.controllers.mpc import NMPC
    from hbma_ctrl.controllers.rti_step import rti_step_function

    s = section.mpc
    if not s.variant.startswith("rti"):
        raise ValueError(f"codegen: [controller] variant = '{s.variant}': only the RTI variants generate C "
                         "(rti_osqp, rti_fn_*)")
    solver = qp_solver_for(s.variant, qp_solver)
    nmpc = NMPC(scn.actuator, scn.pneumatics, s)
    model = nmpc.model
    sup = chamber_supervisor(s).settings
    rti = rti_step_function(model, s, solver)
    N = s.horizon
    nz, nc = rti.nnz_in("lam_x_guess"), rti.nnz_in("lam_a_guess")
    prep, cold, post = mpc_glue(model, s, sup, nz, nc)
    signals = {"Wf": [0.0], "has_W": [0.0], "x0": [0.0], "W": [0.0], "dh": [0.0], "dp": [0.0], "p_lim": [0.0],
               "r_c": np.zeros(N), "X_guess": np.zeros(N + 1), "U_guess": np.zeros(3 * N), "lam_x": np.zeros(nz),
               "lam_a": np.zeros(nc), "u0": np.zeros(3), "status": [0.0], "qp_residual": [0.0], "qp_cost": [0.0],
               "shift0": [0.0], "shift1": [1.0], "cold": [1.0], "run_cold": [0.0], "run_warm": [0.0], "fail": [0.0],
               "load_a": [0.0], "I": [0.0], "I_target": [0.0], "has_I": [0.0],
               "ctrl_dt": [section.sample_period],
               "plan": np.zeros(3 * N), "has_plan": [0.0],
               "age": [0.0], "streak": [0.0]}
    cmd = "u" if pwm is None else "wanted"  # the command the NMPC and its supervisor hold
    rti_in = ["x0", "W", "dh", "dp", cmd, "p_lim", "r_c", "X_guess", "U_guess", "lam_x", "lam_a"]
    rti_out = ["u0", "X_guess", "U_guess", "lam_x", "lam_a", "status", "qp_residual", "qp_cost"]
    stages = [
        Stage(prep, ["est_h", "est_p", "est_F", "resting", "ref", "target", "Wf", "has_W", "fail", "cold", "load_a",
                     "I", "I_target", "has_I", "ctrl_dt"],
              ["x0", "W", "dh", "dp", "p_lim", "r_c", "Wf", "has_W", "run_cold", "run_warm",
               "I", "I_target", "has_I", None, None, None], every=every),
        # cold start (first step, or after a failure): the guess from the estimate, zero duals, then
        # rti_init_iterations unshifted iterations, stopping at a failure (as _RtiFunction.solve)
        Stage(cold, ["x0", cmd], ["X_guess", "U_guess", "lam_x", "lam_a"], every=every, gate="run_cold"),
        Stage(rti, rti_in + ["shift0"], rti_out, every=every, gate="run_cold", repeat=s.rti_init_iterations,
              stop_on="status", fails_to="status"),
        Stage(rti, rti_in + ["shift1"], rti_out, every=every, gate="run_warm", fails_to="status"),
        Stage(post, ["u0", "U_guess", "status", "fail", "est_p", "plan", "has_plan", "age", "streak"],
              [cmd, "cold", "plan", "has_plan", "age", "streak"], every=every),
    ]
    if pwm is not None:
        # every tick, the held command shaped for the valves' minimum opening (its carry per valve)
        signals.update(wanted=np.zeros(3), pwm_carry=np.zeros(2))
        stages.append(Stage(pwm.function(), ["wanted", "pwm_carry"], ["u", "pwm_carry"]))
    shaping = "" if pwm is None else f", duties shaped for a {pwm.min_duty:g} minimum duty"
    return stages, signals, {"controller": f"RTI NMPC (hbma_ctrl.controllers.rti_step), N = {N}, QP {solver}, "
                                           f"every {every} rig periods{shaping}"}


# --------------------------------------------------------------------------------------------- EKF
def _ekf_glue(settings, bounds: tuple) -> tuple:
    """(ekf_kind, ekf_out): the reading's kind code and the z the step takes (as EKF.step classifies it),
    and the estimate's h, p, F, its 'resting' flag and the count of steps the Python EKF would have
    finished on its reference path (``exact`` = 0, or a no-load lift-off it replays)."""
    from hbma_ctrl.estimators import ekf_step as es

    z = ca.SX.sym("z")
    lo, hi = bounds
    _, _, sat, ok = classify_expr(z, settings.sensor_range, lo, hi)
    # NaN (a dropout) and outliers are "none"
    code = ca.if_else(ok, es.KIND_OK, ca.if_else(sat, es.KIND_SATURATED, es.KIND_NONE))
    z_in = ca.if_else(code == es.KIND_OK, z, 0)
    kind = ca.Function("ekf_kind", [z], [z_in, code], ["z"], ["z_in", "kind"])
    est, flags, exact, x, n_ref = (ca.SX.sym("est", 5), ca.SX.sym("flags"), ca.SX.sym("exact"), ca.SX.sym("x", 5),
                                   ca.SX.sym("n_ref"))
    bit = es.FLAG_BITS.index

    def has(name):
        return ca.fmod(ca.floor(flags / 2 ** bit(name)), 2) == 1

    replay = ca.logic_and(has("lift_off"), x[1] == 0)
    ref = ca.logic_or(exact < 0.5, replay)
    out = ca.Function("ekf_out", [est, flags, exact, x, n_ref],
                      [est[2], est[4], est[3], has("resting"), n_ref + ref],
                      ["est", "flags", "exact", "x", "n_ref"], ["h", "p", "F", "resting", "n_ref_next"])
    return kind, out


def _ekf_stages(scn, rs: RigSettings, z0: float) -> tuple[list, dict, dict]:
    """The EKF's stages and signals, initialised from the first reading z0 (Pa) by the Python EKF
    (its first step is the reference path's initialisation)."""
    try:
        from hbma_ctrl.estimators import ekf_step as es
    except ImportError:  # pragma: no cover - a build without the EKF step Function
        raise ValueError("codegen: this build has no hbma_ctrl.estimators.ekf_step (the EKF step Function)") from None
    from hbma_ctrl.estimators.common import physical_reading_bounds
    from hbma_ctrl.system.roles import default_estimator, estimator_from_scenario
    from hbma_ctrl.core.interfaces import Command
    from hbma_ctrl.models.actuation import acting_function, acting_state

    est = estimator_from_scenario(scn, rs)
    if est is None:
        est = default_estimator(scn.actuator, scn.pneumatics, None, rs)
    if type(est).__name__ != "EKF":
        raise ValueError(f"codegen: [estimator] filter = '{type(est).__name__.lower()}': only the EKF generates C")
    s = est.settings
    fun = es.ekf_step_function(scn.actuator, scn.pneumatics, s)
    kind, out = _ekf_glue(s, physical_reading_bounds(s.sensor_range, s.reading_min, s.reading_max_rel))
    e0 = est.step(0.0, z0, Command(0.0, 0.0, 0.0))
    flags = sum(2 ** i for i, n in enumerate(es.FLAG_BITS) if n in e0.flags)
    signals = {"ekf_x": est.x, "ekf_P": np.asarray(est.P).ravel(order="F"), "ekf_s": est.s,
               "ekf_theta": est.theta, "ekf_resting": [float(est.resting)], "z_in": [0.0], "kind": [0.0],
               "ekf_det": est.detector_state(),
               "ekf_y": np.zeros(fun.nnz_out(3)), "ekf_est": [e0.h1, e0.h2, e0.h, e0.F, e0.p], "ekf_std": np.zeros(5),
               "ekf_C": np.zeros(25), "ekf_H": np.zeros(5), "ekf_A": np.zeros(25), "ekf_nis": [0.0],
               "ekf_innov": [0.0], "ekf_flags": [float(flags)], "ekf_exact": [1.0], "est_h": [e0.h], "est_p": [e0.p],
               "est_F": [e0.F], "resting": [float("resting" in e0.flags)], "ekf_n_ref": [0.0], "not_first": [0.0],
               "one": [1.0]}
    timing = est._timing  # the command acting, for the valve and sensor delays the EKF models
    step_in = ["ekf_x", "ekf_P", "ekf_s", "u_act" if timing.active else "u", "ekf_theta", "ekf_resting", "z_in",
               "kind", "ekf_det"]
    step_out = ["ekf_x", "ekf_P", "ekf_s", "ekf_y", "ekf_est", "ekf_std", "ekf_C", "ekf_H", "ekf_A", "ekf_resting",
                "ekf_det", "ekf_nis", "ekf_innov", "ekf_flags", "ekf_exact"]
    # tick 0 is the Python EKF's initialisation (its signals above); the Function runs from tick 1
    first = ca.Function("mark_started", [ca.SX.sym("one")], [ca.SX(1.0)], ["one"], ["started"])
    stages = [Stage(kind, ["z"], ["z_in", "kind"], gate="not_first")]
    if timing.active:
        # the commands sent so far as the initialisation left them
        hist, fill = acting_state(timing)
        signals.update(u_act=np.zeros(3), ekf_uhist=hist, ekf_ufill=[fill])
        stages.append(Stage(acting_function(timing, "ekf_acting"), ["u", "ekf_uhist", "ekf_ufill"],
                            ["u_act", "ekf_uhist", "ekf_ufill"], gate="not_first"))
    stages += [Stage(fun, step_in, step_out, gate="not_first"),
               Stage(out, ["ekf_est", "ekf_flags", "ekf_exact", "ekf_x", "ekf_n_ref"],
                     ["est_h", "est_p", "est_F", "resting", "ekf_n_ref"], gate="not_first"),
               Stage(first, ["one"], ["not_first"])]
    delays = f", commands acting {s.valve_delay * 1e3:g} + {s.sensor_delay * 1e3:g} ms late" if timing.active else ""
    return stages, signals, {"estimator": f"EKF (hbma_ctrl.estimators.ekf_step), {s.sample_period * 1e3:g} ms{delays}"}


def _truth_stages() -> tuple[list, dict, dict]:
    """A stand-in estimator that reads the rig's true height, pressure, force and mode (isolates the
    controller and the plant from the filter)."""
    y, mode = ca.SX.sym("y", len(OUTPUTS)), ca.SX.sym("mode")
    fun = ca.Function("truth_estimate", [y, mode],
                      [y[OUTPUTS.index("h")], y[OUTPUTS.index("p")], y[OUTPUTS.index("F")], mode == 0],
                      ["y", "mode"], ["h", "p", "F", "resting"])
    signals = {"est_h": [0.0], "est_p": [0.0], "est_F": [0.0], "resting": [1.0]}
    return [Stage(fun, ["y", "mode"], ["est_h", "est_p", "est_F", "resting"])], signals, {
        "estimator": "the rig's true state (no filter)"}


# --------------------------------------------------------------------------------------------- loop
def _unsupported(scn, rs: RigSettings) -> list[str]:
    """What the generated loop cannot run that the scenario sets, each naming its key: the rig's
    quasi-static snap-through (a search). Every membrane law, valve timing, pump map, sensor lag and
    the EKF's and controller's timing models generate."""
    why = plant_step_support("free" if scn.platform.mass <= 0 else rs.fidelity, rs)
    return [why] if why else []


#: estimators a generated loop can run: the scenario's EKF, or the rig's truth (tests, controller alone)
ESTIMATORS = ("ekf", "truth")


def scenario_loop(scn, duration: float | None = None, estimator: str = "ekf",
                  qp_solver: str | None = None) -> LoopSpec:
    """The scenario's closed loop (see the module docstring) over ``duration`` s (None: the
    scenario's); ``estimator`` one of :data:`ESTIMATORS`; ``qp_solver`` the RTI step's conic plugin
    (:func:`qp_solver_for`). ValueError naming the section that cannot be generated."""
    from hbma_ctrl.system.roles import make_pwm

    if estimator not in ESTIMATORS:
        raise ValueError(f"codegen: estimator = '{estimator}'; allowed: {', '.join(ESTIMATORS)}")
    if scn.role("robot") is not None:
        raise ValueError("codegen: a [robot] scenario's loop is hbma_ctrl.app.codegen.robot.robot_loop's, "
                         "not this single-chamber one")
    section = scn.role("controller")
    if section is None:
        raise ValueError("codegen: the scenario has no [controller] section (the generated loop is "
                         "rig -> EKF -> NMPC -> rig)")
    if section.kind != "mpc":
        raise ValueError(f"codegen: [controller] kind = '{section.kind}': only 'mpc' generates C")
    if section.load_steps:
        raise ValueError("codegen: [controller] load_steps_g: load changes during the run switch the rig's "
                         "plant model in Python; remove them to generate C")
    if section.mpc.enforce_budget:
        raise ValueError("codegen: [controller] enforce_budget = true: an enforced wall-clock budget depends on "
                         "the machine's clock; set it to false to generate the loop")
    rs = scn.role("rig") or RigSettings(sensor_range=scn.sim.sensor_range)
    why = _unsupported(scn, rs)
    if why:
        raise ValueError("codegen: the generated loop cannot run this scenario as written: " + "; ".join(why))
    ratio = section.sample_period / rs.sample_period
    every = int(round(ratio))
    if every < 1 or abs(ratio - every) > 1e-6:
        raise ValueError(f"codegen: [controller] sample_ms = {section.sample_period * 1e3:g} ms must be a whole "
                         f"multiple of [rig] sample_period_ms = {rs.sample_period * 1e3:g} ms")
    T = scn.duration if duration is None else float(duration)
    n = int(round(T / rs.sample_period))
    read, rig_after, rig_signals, noise, rig_desc = rig_stages(scn, rs, n)
    z0 = float(rig_signals["z"][0])
    ekf_stages, ekf_signals, ekf_meta = _ekf_stages(scn, rs, z0) if estimator == "ekf" else _truth_stages()
    mpc_stages, mpc_signals, mpc_meta = _mpc_stages(scn, section, every, qp_solver,
                                                     make_pwm(section, rs.sample_period))
    N = section.mpc.horizon
    use_preview = section.preview if section.preview is not None else (
        section.reference.interpolation == "linear" or section.reference.sine_amplitude > 0)
    t = np.arange(n) * rs.sample_period
    target = np.array([section.reference(tk) for tk in t])
    if use_preview:
        ref = np.array([[section.reference(tk + section.sample_period * (j + 1)) for j in range(N)] for tk in t])
    else:
        ref = np.repeat(target[:, None], N, axis=1)
    fw = section.mpc.fail_window  # the fallback drill: every solve in [t0, t1] is treated as failed
    fail = np.zeros(n) if fw is None else ((t >= fw[0]) & (t <= fw[1])).astype(float)
    # the load filter's gain from the time since the controller's last step, as NMPC._load rounds it
    tau = section.mpc.load_tau
    dts = [section.mpc.sample_period if k < every else max(t[k] - t[k - every], 0.0) for k in range(n)]
    load_a = np.array([1.0 if tau <= 0 else min(1.0, d / tau) for d in dts])
    signals = dict(rig_signals, target=[0.0], ref=np.zeros(N))
    signals.update(ekf_signals)
    signals.update(mpc_signals)
    stages = read + ekf_stages + mpc_stages + [LOG] + rig_after
    hi = OUTPUTS.index("h")
    pi = OUTPUTS.index("p")
    Fi = OUTPUTS.index("F")
    log = [LogColumn("target_mm", "target", 0, 1e3), LogColumn("h_true_mm", "y", hi, 1e3),
           LogColumn("h_est_mm", "est_h", 0, 1e3), LogColumn("p_true_kpa", "y", pi, 1e-3),
           LogColumn("p_meas_kpa", "z", 0, 1e-3), LogColumn("p_est_kpa", "est_p", 0, 1e-3),
           LogColumn("F_true_n", "y", Fi, 1.0), LogColumn("F_est_n", "est_F", 0, 1.0),
           LogColumn("speed", "u", 0), LogColumn("inlet", "u", 1), LogColumn("outlet", "u", 2),
           LogColumn("mode", "mode", 0), LogColumn("mpc_status", "status", 0)]
    if "ekf_n_ref" in signals:
        log.append(LogColumn("ekf_reference_events", "ekf_n_ref", 0))
    meta = {"scenario": scn.name, "rig": rig_desc}
    meta.update(ekf_meta)
    meta.update(mpc_meta)
    if section.calibrate and estimator == "ekf":
        # the scene calibrates before it closes the loop; the C loop starts from the EKF's prior
        meta["left out"] = ("the start-up calibration ([controller] calibrate = true): the EKF starts from "
                            "its prior ([estimator] flow_factor_init, modulus_init, dead_volume_init)")
    return LoopSpec(scn.name, rs.sample_period, n, signals, {"noise": noise, "target": target, "ref": ref, "fail": fail,
                                                             "load_a": load_a},
                    stages, log, meta).validate()


# --------------------------------------------------------------------------------------------- scene
#: trajectory columns compared with the scene's log: (column, log attribute, column index in log.u or None)
_SCENE_COLUMNS = (("h_true_mm", "h_true", None), ("h_est_mm", "h_est", None), ("p_true_kpa", "p_true", None),
                  ("p_est_kpa", "p_est", None), ("F_est_n", "F_est", None), ("speed", "u", 0), ("inlet", "u", 1),
                  ("outlet", "u", 2))


def _trajectory_log(scn, spec: LoopSpec, trajectory: np.ndarray, qp_solver: str | None = None):
    """A generated loop's trajectory as the scene's :class:`~hbma_ctrl.app.scenes.controller.ClosedLoopLog`
    (SI; what the trajectory does not hold, the controller's step times, estimator covariances and
    events, left empty). Its variant is the scene's name for the same step, ``rti_fn_<solver>``."""
    from hbma_ctrl.app.scenes.controller import ClosedLoopLog

    col = {n: i for i, n in enumerate(spec.header())}
    scale = {c.name: c.scale for c in spec.log}

    def si(name):
        return trajectory[:, col[name]] / scale[name]

    section = scn.role("controller")
    every = max(1, int(round(section.sample_period / spec.dt)))
    steps = trajectory[::every, col["mpc_status"]]  # held between controller steps: one row per step
    n = trajectory.shape[0]
    stats = {"variant": f"rti_fn_{qp_solver_for(section.mpc.variant, qp_solver)}", "horizon": section.mpc.horizon,
             "solve_ms_median": None,
             "solve_ms_p99": None, "solve_ms_max": None, "fallbacks": int(np.sum(steps != 0))}
    return ClosedLoopLog(t=trajectory[:, col["t_s"]], target=si("target_mm"), h_true=si("h_true_mm"),
                         h_est=si("h_est_mm"), p_true=si("p_true_kpa"), p_meas=si("p_meas_kpa"),
                         p_est=si("p_est_kpa"), F_true=si("F_true_n"), F_est=si("F_est_n"),
                         load=np.full(n, scn.platform.load), u=np.column_stack([si("speed"), si("inlet"), si("outlet")]),
                         stats=stats, events=[], wall_s=float("nan"))


def loop_run_metrics(scn, spec: LoopSpec, trajectory: np.ndarray, qp_solver: str | None = None) -> dict:
    """metrics.json of a generated loop's run: the scene's ``controller`` object
    (:func:`hbma_ctrl.app.scenes.controller.loop_metrics`: tracking, pressure limit, settled steps; its
    step times are in times.json, per Function, not here) and an ``estimator`` object (height and force
    RMSE of the estimate, the EKF steps the C loop left to a reference path). Edge units."""
    from hbma_ctrl.app.scenes.controller import loop_metrics

    log = _trajectory_log(scn, spec, trajectory, qp_solver)
    col = {n: i for i, n in enumerate(spec.header())}
    est = {"height_rmse_mm": float(U.to_mm(np.sqrt(np.mean((log.h_est - log.h_true) ** 2)))),
           "force_rmse_n": float(np.sqrt(np.mean((log.F_est - log.F_true) ** 2)))}
    if "ekf_reference_events" in col:
        est["reference_path_events"] = int(trajectory[-1, col["ekf_reference_events"]])
    ctrl = loop_metrics(log, scn.role("controller"))
    # the scene's keys, each one the trajectory cannot tell None (not measured here): the step times
    # are per Function in times.json; the supervisor's counts and the calibration are not in the C loop
    for key in ("solve_ms_median", "solve_ms_p99", "solve_ms_max", "solve_cpu_ms_median", "solve_cpu_ms_p99",
                "fallback_detail", "guard_activations", "target_clipped_steps", "calibration", "wall_s"):
        ctrl[key] = None
    return {"controller": ctrl, "estimator": est}


def scene_reference(scn, spec: LoopSpec, trajectory: np.ndarray, qp_solver: str | None = None) -> dict:
    """Run the scene's own closed loop (Rig, EKF, NMPC, ChamberLoop with its supervisor) as the generated
    loop models it, and compare: no start-up calibration, the NMPC variant calling the same RTI Function
    (``rti_fn_<solver>``) without an enforced budget (an overrun depends on the wall clock).

    Returns the scene's step times (EKF step, controller step incl. the supervisor; calls, median,
    p99, max in us) and the largest absolute difference of each compared column from ``trajectory``
    (rows of ``spec``'s header; SI).
    """
    from dataclasses import replace

    from hbma_ctrl.core.loopgen import time_summary
    from hbma_ctrl.app.scenes.controller import closed_loop, loop_metrics
    from hbma_ctrl.system.roles import estimator_from_scenario

    section = scn.role("controller")
    solver = qp_solver_for(section.mpc.variant, qp_solver)
    section = replace(section, mpc=replace(section.mpc, variant=f"rti_fn_{solver}", enforce_budget=False))
    rs = scn.role("rig") or RigSettings(sensor_range=scn.sim.sensor_range)
    log = closed_loop(scn.actuator, scn.pneumatics, scn.platform, section, spec.n_ticks * spec.dt, rs,
                      estimator=estimator_from_scenario(scn, rs), calibrate=False)
    col = {n: i for i, n in enumerate(spec.header())}
    scale = {c.name: c.scale for c in spec.log}
    diff = {}
    for name, attr, j in _SCENE_COLUMNS:
        ref = getattr(log, attr) if j is None else log.u[:, j]
        got = trajectory[: len(ref), col[name]] / scale[name]
        diff[name] = float(np.max(np.abs(got - ref)))
    m = loop_metrics(log, section)
    return {"variant": f"rti_fn_{solver}", "ekf_step": time_summary(log.est_step_s),
            "controller_step": time_summary(np.asarray(log.solve_ms) * 1e-3),
            "max_abs_diff_si": diff, "max_abs_diff_si_all": max(diff.values()),
            "supervisor_events": len(log.supervisor_events),
            # the scene's tracking beside the generated loop's (loop_run_metrics): the same metrics
            "height_rmse_mm": m["height_rmse_mm"], "steps_settled": m["steps_settled"]}
