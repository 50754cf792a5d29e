"""A scenario's closed loop (rig -> EKF -> RTI NMPC -> rig) as a :class:`~hbma_ctrl.core.loopgen.LoopSpec`.

The control side is the scenario's own system (:func:`scenario_system`, built as the scene builds it)
generating itself (:meth:`hbma_ctrl.system.chamber.ChamberSystem.to_function`): the EKF's stages
(:meth:`hbma_ctrl.estimators.ekf.EKF.stages`), the NMPC's (:meth:`hbma_ctrl.controllers.mpc.NMPC.stages`:
its problem data, cold start and RTI step Functions), the supervisor's
(:meth:`hbma_ctrl.runtime.safety.Supervisor.stages`) and the valves' minimum on-time shaping
(:meth:`hbma_ctrl.runtime.pwm.MinOnTime.function`). This module adds the rig around it, as casadi
Functions too, so that the C loop needs no Python:

- ``sensor``: the rig's reading, the true (or lagged) pressure plus the tick's noise, saturated at the
  range (noise and dropouts drawn at generation time from the rig's seeded stream, as :class:`Rig` draws
  them);
- the plant over one rig period (:func:`hbma_ctrl.sim.plant_step.plant_step_function`) and its structure:
  ``valve_line`` (the valves' delay and minimum opening) and ``sensor_lag`` (:mod:`hbma_ctrl.sim.plant_step`).

The roles' Functions round as their Python classes do (``np.interp``'s formula, the load filter's gain from the
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

from hbma_ctrl.core.loopgen import LOG, LogColumn, LoopSpec, Stage
from hbma_ctrl.core import units as U
from hbma_ctrl.models.fidelity import OUTPUTS
from hbma_ctrl.sim.plant_step import (
    initial_plant_state,
    plant_step_function,
    plant_step_support,
    sensor_lag_function,
    valve_line_function,
)
from hbma_ctrl.sim.rig import Rig, RigSettings
from hbma_ctrl.sim.trial import DEFAULT_DT

__all__ = ["scenario_loop", "scenario_system", "rig_noise", "plant_stage_parts", "rig_stages", "qp_solver_for",
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
    signals = {"x": x0, "mode": [m0], "y": y0, "u": np.zeros(3), "theta": theta, "noise": [0.0], "p": [0.0]}
    sensor = _sensor(rs.sensor_range, lagged)
    read = [Stage(sensor, ["p_sensed" if lagged else "y", "noise"], ["p"])]
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
    signals["p"] = [z0]
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


# --------------------------------------------------------------------------------------------- loop
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


def _truth_stages() -> tuple[list, dict]:
    """A stand-in estimator that reads the rig's true height, pressure, force and mode (isolates the
    controller and the plant from the filter): its stage and meta."""
    y, mode = ca.SX.sym("y", len(OUTPUTS)), ca.SX.sym("mode")
    fun = ca.Function("truth_estimate", [y, mode],
                      [y[OUTPUTS.index("h")], y[OUTPUTS.index("p")], y[OUTPUTS.index("F")], mode == 0],
                      ["y", "mode"], ["h", "p", "F", "resting"])
    return [Stage(fun, ["y", "mode"], ["est_h", "est_p", "est_F", "resting"])], {
        "estimator": "the rig's true state (no filter)"}


def _unsupported(scn, rs: RigSettings) -> list[str]:
    """What the generated loop cannot run that the scenario sets, each naming its key: the rig's
    quasi-static snap-through (a search). Every membrane law, valve timing, pump map, sensor lag and
    the EKF's and controller's timing models generate."""
    why = plant_step_support("free" if scn.platform.mass <= 0 else rs.fidelity, rs)
    return [why] if why else []


#: estimators a generated loop can run: the scenario's EKF, or the rig's truth (tests, controller alone)
ESTIMATORS = ("ekf", "truth")


def scenario_system(scn, rs: RigSettings, qp_solver: str | None = None):
    """The scenario's chamber system as its scene builds it (:func:`hbma_ctrl.system.chamber.chamber_system`)
    for a generated loop: no start-up calibration, an RTI variant as the one calling the RTI step
    Function (``rti_fn_<solver>``, :func:`qp_solver_for`), left uncompiled (the sources are generated
    from its Functions, nothing is built here)."""
    from dataclasses import replace

    from hbma_ctrl.system.chamber import chamber_system
    from hbma_ctrl.system.roles import estimator_from_scenario

    section = scn.role("controller")
    if section.mpc.variant.startswith("rti"):
        mpc = replace(section.mpc, variant=f"rti_fn_{qp_solver_for(section.mpc.variant, qp_solver)}", codegen=False)
        section = replace(section, mpc=mpc)
    return chamber_system(scn.actuator, scn.pneumatics, scn.platform, section, rs,
                          estimator=estimator_from_scenario(scn, rs), calibrate=False)


#: the trajectory's columns, in order (those of the roles the loop runs)
_COLUMNS = ("target_mm", "h_true_mm", "h_est_mm", "p_true_kpa", "p_meas_kpa", "p_est_kpa", "F_true_n", "F_est_n",
            "speed", "inlet", "outlet", "mode", "mpc_status", "ekf_reference_events")


def scenario_loop(scn, duration: float | None = None, estimator: str = "ekf",
                  qp_solver: str | None = None) -> LoopSpec:
    """The scenario's closed loop (see the module docstring) over ``duration`` s (None: the
    scenario's): the rig's stages around its system's own (:meth:`hbma_ctrl.system.chamber.ChamberSystem.to_function`);
    ``estimator`` one of :data:`ESTIMATORS`; ``qp_solver`` the RTI step's conic plugin
    (:func:`qp_solver_for`). ValueError naming the setting that cannot be generated."""
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
    rs = scn.role("rig") or RigSettings(sensor_range=scn.sim.sensor_range)
    why = _unsupported(scn, rs)
    if why:
        raise ValueError("codegen: the generated loop cannot run this scenario as written: " + "; ".join(why))
    system = scenario_system(scn, rs, qp_solver)
    T = scn.duration if duration is None else float(duration)
    n = int(round(T / rs.sample_period))
    read, rig_after, rig_signals, noise, rig_desc = rig_stages(scn, rs, n)
    try:
        ctrl = system.to_function(np.arange(n) * rs.sample_period, float(rig_signals["p"][0]), estimator == "ekf")
    except ValueError as exc:
        raise ValueError(f"codegen: {exc}") from None
    truth, truth_meta = _truth_stages() if estimator == "truth" else ([], {})
    cols = {c.name: c for c in ctrl.log}
    cols.update({"h_true_mm": LogColumn("h_true_mm", "y", OUTPUTS.index("h"), 1e3),
                 "p_true_kpa": LogColumn("p_true_kpa", "y", OUTPUTS.index("p"), 1e-3),
                 "p_meas_kpa": LogColumn("p_meas_kpa", "p", 0, 1e-3),
                 "F_true_n": LogColumn("F_true_n", "y", OUTPUTS.index("F"), 1.0), "mode": LogColumn("mode", "mode", 0)})
    meta = {"scenario": scn.name, "rig": rig_desc, **ctrl.meta, **truth_meta}
    if section.calibrate and estimator == "ekf":
        # the scene calibrates before it closes the loop; the C loop starts from the EKF's prior
        meta["left out"] = ("the start-up calibration ([controller] calibrate = true): the EKF starts from "
                            "its prior ([estimator] flow_factor_init, modulus_init, dead_volume_init)")
    return LoopSpec(scn.name, rs.sample_period, n, dict(ctrl.signals, **rig_signals), dict(ctrl.streams, noise=noise),
                    read + truth + ctrl.stages + [LOG] + rig_after, [cols[c] for c in _COLUMNS if c in cols],
                    meta).validate()


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

    from hbma_ctrl.core.loopgen_c import time_summary
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
