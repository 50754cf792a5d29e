"""A robot scenario's closed loop (robot rig -> EKF bank -> NMPC -> supervisor -> valves -> rig) as a
:class:`~hbma_ctrl.core.loopgen.LoopSpec`: the robot's generated C loop.

The loop is built from the very objects the scene builds (:func:`hbma_ctrl.app.scenes.robot_loop.build_closed_loop`):
its control side is the system's own (:meth:`hbma_ctrl.system.robot.RobotSystem.to_function`: every part
of :meth:`hbma_ctrl.runtime.robot.RobotLoop.tick` as the casadi Function that mirrors it), and this module
adds the rig around it. The stages, in the tick's order:

- ``robot_sensor``: the 3N readings, each chamber's (lagged) pressure plus the tick's noise,
  saturated at the sensor range (the noise drawn at generation time from the rig's seeded stream, as
  :meth:`~hbma_ctrl.robot.rig.RobotRig.measure` draws it);
- ``robot_ekf``: the command acting through the valves' and sensors' delays
  (:func:`hbma_ctrl.models.actuation.acting_function` mapped) and the bank's period
  (:func:`hbma_ctrl.estimators.robot_ekf.bank_step_function`); the bank starts from the first readings (its
  state at generation time, as :meth:`~hbma_ctrl.estimators.robot_ekf.ChamberEKFBank.step` starts it);
- ``robot_pre``: the readings the bank trusted, the burst test (:func:`hbma_ctrl.runtime.burst.burst_function`),
  the loads from the estimated heights (:func:`hbma_ctrl.robot.plant_step.load_sharing_function`),
  the targets' slew and the NMPC's supply caps (:mod:`hbma_ctrl.runtime.robot_step`);
- ``robot_rti_step``: the robot NMPC (:func:`hbma_ctrl.controllers.robot_rti_step.robot_rti_step_function`, OSQP
  inside);
- ``robot_post``: the plan with a shared pump's budget, the supervisor
  (:func:`hbma_ctrl.runtime.safety_step.supervisor_function`), a released chamber's filter restarted
  from its reading, the short vents netted (:func:`hbma_ctrl.runtime.robot_step.net_vents_function`),
  the throttled valve inputs (:func:`hbma_ctrl.models.bank.throttled_inputs_function`), the valves'
  minimum opening (:meth:`hbma_ctrl.runtime.pwm.MinOnTime.function` mapped) and what the bank
  predicts with next;
- ``robot_rig_step``: the rig's period (:func:`hbma_ctrl.robot.plant_step.robot_rig_step_function`).

Time and targets are data: the rig's clock (its internal steps summed as
:class:`~hbma_ctrl.sim.simulate.Plant` sums them), the chamber targets at each tick, the tip load at
each period's end. The loop runs in lockstep, one tick per period, as the scene does: a late tick's
predict over several periods and a rig's report of the command it held (``RobotLoop.tick``'s
``held``) are not generated.

Its scene counterpart is :func:`hbma_ctrl.app.scenes.robot_loop.run_closed_loop` with the NMPC
:class:`hbma_ctrl.controllers.robot_rti_step.RobotNMPCFunction` (the same step Function, compiled), no
wall-time budget: :func:`scene_reference` runs it and compares. The scene's supervisor, targets' slew,
supply caps and short vents run the same Functions; its other parts are numpy classes, which the
Functions equal to rounding (``tests/unit/robot/test_robot_loop_blocks.py``), not to the bit.

Refused with one error naming the key: the pressure-PID controller, an enforced wall-time budget
(``enforce_budget``; ``mpc_budget`` alone acts only in the daemon), the quasi-static rig's
snap-through search.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from hbma_ctrl.core.loopgen import LogColumn, LoopSpec, Stage

__all__ = ["robot_loop", "robot_scene_parts", "scene_reference", "loop_run_metrics"]


def robot_scene_parts(scn):
    """(RobotSettings, RobotRigSettings, ChamberBank model, RobotMPCSettings) of a closed-loop
    ``[robot]`` scenario, as its scene builds them."""
    from hbma_ctrl.app.scenes.robot_closed import scene_parts

    s = scn.role("robot")
    if s is None or s.mode != "closed_loop":
        raise ValueError("codegen: the scenario has no [robot] section with mode = 'closed_loop'")
    est = scn.settings.get("estimator")
    if est is not None and est.filter != "ekf":
        raise ValueError(f"codegen: [estimator] kind = '{est.filter}': the robot's generated loop runs the EKF bank "
                         "only (kind = \"ekf\")")
    return (s, *scene_parts(scn, s))


def _build(scn, nmpc_class=None):
    """The scene's rig and system (and its settings), refused where the generated loop cannot follow."""
    from hbma_ctrl.controllers.robot_rti_step import RobotNMPCFunction
    from hbma_ctrl.app.scenes.robot_loop import build_closed_loop

    s, rig, model, mpc = robot_scene_parts(scn)
    if s.controller != "mpc":
        raise ValueError(f"codegen: [robot] controller = '{s.controller}': only 'mpc' generates C")
    sim, system = build_closed_loop(s, s.targets, "mpc", scn.pneumatics, rig, mpc, model=model, tip_load=s.tip_load,
                                    nmpc_class=nmpc_class or RobotNMPCFunction)
    return s, rig, sim.rig, system


def _clock(plant, n_ticks: int) -> tuple[np.ndarray, np.ndarray]:
    """The rig's time at the start of each tick and at its end (s), summed per internal step as
    :meth:`hbma_ctrl.sim.simulate.Plant.advance` sums it."""
    dt = plant.plant.dt
    nsub = max(1, int(round(plant.s.sample_period / dt)))
    t, start = 0.0, np.zeros(n_ticks)
    ends = np.zeros(n_ticks)
    for k in range(n_ticks):
        start[k] = t
        for _ in range(nsub):
            t = t + dt
        ends[k] = t
    return start, ends


def _sensor_function(n: int, sensor_range: float) -> ca.Function:
    """robot_sensor(p[n], noise[n]) -> z[n]: the pressure plus the noise, saturated at the range (Pa)."""
    p, noise = ca.SX.sym("p", n), ca.SX.sym("noise", n)
    return ca.Function("robot_sensor", [p, noise], [ca.fmin(p + noise, sensor_range)], ["p", "noise"], ["z"])


#: the trajectory's columns per chamber (prefix, suffix), in order, then the loop's own after them
_CHAMBER_COLUMNS = (("h_", "_mm"), ("h_est_", "_mm"), ("h_ref_", "_mm"), ("p_", "_kpa"), ("p_meas_", "_kpa"), ("a_", ""),
                    ("o_", ""), ("speed_", ""), ("inlet_", ""), ("outlet_", ""), ("load_", "_n"), ("lam_", ""),
                    ("burst_", ""))


def robot_loop(scn, duration: float | None = None) -> LoopSpec:
    """The closed-loop ``[robot]`` scenario's loop (module docstring) over ``duration`` s (None: the
    scenario's): the rig's stages around its system's own (:meth:`hbma_ctrl.system.robot.RobotSystem.to_function`).
    ValueError naming the key the generated loop cannot follow."""
    from functools import partial

    from hbma_ctrl.controllers.robot_rti_step import RobotNMPCFunction
    from hbma_ctrl.robot.plant_step import robot_rig_step_function

    # the NMPC's step uncompiled: the sources are generated from its Function, nothing is built here
    s, rs, plant, system = _build(scn, partial(RobotNMPCFunction, compile=False))
    n = system.n
    T = scn.duration if duration is None else float(duration)
    n_ticks = int(round(T / rs.sample_period))
    try:
        rig_fn = robot_rig_step_function(plant)
    except ValueError as exc:
        raise ValueError(f"codegen: {exc}") from None
    fid = plant.plant.fid
    t0, t1 = _clock(plant, n_ticks)
    # RobotRig.measure's draws: the scene takes one reading before its first tick (its log's row 0)
    rng = np.random.default_rng(rs.seed)
    draws = np.array([rng.standard_normal(n) for _ in range(n_ticks + 1)])
    noise = rs.noise_std * draws[1:]
    lagged = rs.sensor_tau > 0
    p_first = plant._p_sensed if lagged else plant.plant.output("p")
    try:
        ctrl = system.to_function(t0, np.minimum(p_first + noise[0], plant.sensor_range))
    except ValueError as exc:
        raise ValueError(f"codegen: {exc}") from None
    signals = dict(ctrl.signals, **{
        "X": plant.plant.X.ravel(order="F"), "mode": plant.plant.mode.astype(float),
        "hist": np.zeros(rig_fn.nnz_in(3)), "theta": plant.plant.thetas.ravel(order="F"),
        "p_sensed": plant._p_sensed, "p_prev": plant._p_prev, "y": plant.plant.y.ravel(order="F"),
        "F_rig": plant.loads, "f_tip": np.zeros(3), "noise": np.zeros(n),
        "p_true": plant.plant.output("p").copy(), "h_true": np.maximum(plant.plant.output("h"), 0.0),
        "lam_true": plant.plant.output("lam").copy()})
    stages = [Stage(_sensor_function(n, plant.sensor_range), ["p_sensed" if lagged else "p_true", "noise"], ["p"]),
              *ctrl.stages,
              Stage(rig_fn, ["X", "mode", "u", "hist", "theta", "p_sensed", "p_prev", "f_tip"],
                    ["X", "mode", "y", "hist", "theta", "p_sensed", "p_prev", "F_rig"]),
              Stage(_truth_function(n), ["y"], ["p_true", "h_true", "lam_true"])]
    cols = {c.name: c for c in ctrl.log}
    for i, nm in enumerate(system.names):
        cols.update({c.name: c for c in (
            LogColumn(f"h_{nm}_mm", "h_true", i, 1e3), LogColumn(f"p_{nm}_kpa", "p_true", i, 1e-3),
            LogColumn(f"p_meas_{nm}_kpa", "p", i, 1e-3), LogColumn(f"load_{nm}_n", "F_rig", i),
            LogColumn(f"lam_{nm}", "lam_true", i))})
    order = [f"{pre}{nm}{suf}" for nm in system.names for pre, suf in _CHAMBER_COLUMNS]
    log = [cols.pop(c) for c in order] + list(cols.values())
    meta = {"scenario": scn.name,
            "rig": (f"robot rig: {s.design.n_layers} layers, {fid.name}, {plant.s.sample_period * 1e3:g} ms, seed {rs.seed}; "
                    f"valve delay {rs.valve_delay * 1e3:g} ms, minimum opening {rs.valve_min_on * 1e3:g} ms, "
                    f"pump tilt {rs.compressor_tilt:g}, sensor lag {rs.sensor_tau * 1e3:g} ms"),
            **ctrl.meta,
            "timing": "each trajectory row is logged after the rig's period (the scene's log row k + 1)"}
    tip = np.array([plant.tip_force(tk) for tk in t1])  # the tip load at each period's end
    if s.compare_baseline:
        meta["left out"] = "the pressure-PID baseline ([robot] compare_baseline = true): only the NMPC's loop is generated"
    return LoopSpec(scn.name, rs.sample_period, n_ticks, signals, dict(ctrl.streams, noise=noise, f_tip=tip),
                    stages, log, meta).validate()


def _truth_function(n: int) -> ca.Function:
    """robot_truth(y[13 x n]) -> (p[n], max(h, 0)[n], lam[n]): the rig's true pressures, heights and
    stretches (the readings' source without a sensor lag, and the log's truth)."""
    from hbma_ctrl.models.fidelity import OUTPUTS

    y = ca.SX.sym("y", len(OUTPUTS), n)
    row = lambda k: y[OUTPUTS.index(k), :].T  # noqa: E731
    return ca.Function("robot_truth", [y], [row("p"), ca.fmax(row("h"), 0.0), row("lam")], ["y"], ["p", "h", "lam"])


# --------------------------------------------------------------------------------------------- runs
def _columns(spec: LoopSpec, trajectory: np.ndarray, names, prefix: str, suffix: str = "") -> np.ndarray:
    """(ticks, n) SI values of the per-chamber columns ``prefix<name>suffix``."""
    col = {c: i for i, c in enumerate(spec.header())}
    scale = {c.name: c.scale for c in spec.log}
    keys = [f"{prefix}{nm}{suffix}" for nm in names]
    return np.column_stack([trajectory[:, col[k]] / scale[k] for k in keys])


def _trajectory_run(scn, spec: LoopSpec, trajectory: np.ndarray):
    """A generated robot loop's trajectory as the scene's
    :class:`~hbma_ctrl.app.scenes.robot_loop.ClosedLoopRun` (SI; row k is the state after tick k, at
    the rig's time (k + 1) dt; the step times, which are per Function in times.json, left empty)."""
    from hbma_ctrl.app.scenes.robot_loop import ClosedLoopRun
    from hbma_ctrl.robot.targets import chamber_targets, change_times
    from hbma_ctrl.runtime.safety_step import EVENTS

    s = scn.role("robot")
    d = s.design
    names = d.names
    cols = lambda p, suf="": _columns(spec, trajectory, names, p, suf)  # noqa: E731
    col = {c: i for i, c in enumerate(spec.header())}
    t = np.round(trajectory[:, 0] + spec.dt, 9)
    cache: dict = {}
    href = np.array([chamber_targets(d, s.targets, tk, cache) for tk in t])
    ev = {e: int(trajectory[:, col[f"ev_{e}"]].sum()) for e in EVENTS}
    burst = cols("burst_")
    finite = np.all(np.isfinite(cols("h_", "_mm")))
    empty = np.zeros(0)
    return ClosedLoopRun(
        "mpc", t, cols("h_", "_mm"), href, cols("h_est_", "_mm"), cols("p_", "_kpa"), cols("p_meas_", "_kpa"),
        cols("lam_"), cols("a_"), cols("o_"), cols("load_", "_n"), empty, empty, empty, ev["guard"],
        int(trajectory[:, col["failed"]].sum()), int(np.sum(trajectory[:, col["rti_status"]] != 0)),
        "ok" if finite else "diverged", float("nan"),
        np.unique(np.concatenate([change_times(s.targets), [r[0] for r in s.tip_load]])),
        cautious_steps=int(trajectory[:, col["cautious"]].sum()), stretch_interlocks=ev["stretch_guard"],
        lost_estimate_steps=ev["lost_estimate"], bursts=[int(i) for i in np.nonzero(burst[-1] > 0.5)[0]])


#: the scene's robot metrics a generated run cannot know: the step times (per Function in times.json),
#: the burst test's margin and the wall time
UNKNOWN_KEYS = ("step_ms_median", "step_ms_p99", "step_ms_max", "ekf_ms_median", "controller_ms_median",
                "burst_peak_sigma", "wall_s")


def loop_run_metrics(scn, spec: LoopSpec, trajectory: np.ndarray) -> dict:
    """metrics.json of a generated robot loop's run: {"robot": the scene's closed-loop metrics on its
    trajectory (:func:`hbma_ctrl.app.scenes.robot_closed.closed_loop_metrics`)}, the keys it cannot
    know (:data:`UNKNOWN_KEYS`) None. Edge units."""
    import warnings

    from hbma_ctrl.app.scenes.robot_closed import closed_loop_metrics

    s, _, model, _ = robot_scene_parts(scn)
    run = _trajectory_run(scn, spec, trajectory)
    run.step_s = run.ekf_s = run.ctrl_s = np.full(1, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        m = closed_loop_metrics(s.design, run, s.pneumatics.pressure_limit, s.settle_time, model=model)
    for key in UNKNOWN_KEYS:
        m[key] = None
    m["topology"] = s.pneumatics.topology
    m["n_layers"] = s.design.n_layers
    return {"robot": m}


#: the per-chamber quantities compared with the scene: (trajectory prefix, suffix, ClosedLoopRun field)
_SCENE_COLUMNS = (("h_", "_mm", "h"), ("h_est_", "_mm", "h_est"), ("p_", "_kpa", "p"), ("p_meas_", "_kpa", "p_meas"),
                  ("a_", "", "a"), ("o_", "", "o"))


def scene_reference(scn, spec: LoopSpec, trajectory: np.ndarray) -> dict:
    """Run the scene's own closed loop (:func:`hbma_ctrl.app.scenes.robot_loop.run_closed_loop`: its rig, EKF
    bank, loop and supervisor classes, the NMPC :class:`hbma_ctrl.controllers.robot_rti_step.RobotNMPCFunction`)
    over the generated loop's ticks and compare: the largest absolute difference of each compared
    quantity over all chambers (SI), the scene's step times (us: calls, median, p99, max) and its
    tracking beside the generated run's."""
    from hbma_ctrl.controllers.robot_rti_step import RobotNMPCFunction
    from hbma_ctrl.core.loopgen_c import time_summary
    from hbma_ctrl.app.scenes.robot_loop import run_closed_loop
    from hbma_ctrl.app.scenes.robot_closed import closed_loop_metrics

    s, rig, model, mpc = robot_scene_parts(scn)
    run = run_closed_loop(s, s.targets, spec.n_ticks * spec.dt, "mpc", scn.pneumatics, rig, mpc, model=model,
                          tip_load=s.tip_load, nmpc_class=RobotNMPCFunction)
    names = s.design.names
    diff = {}
    for pre, suf, field in _SCENE_COLUMNS:
        ref = getattr(run, field)[1:]  # the scene's row k + 1 is the generated loop's row k
        got = _columns(spec, trajectory[: len(ref)], names, pre, suf)
        diff[field] = float(np.max(np.abs(got - ref)))
    m = closed_loop_metrics(s.design, run, s.pneumatics.pressure_limit, s.settle_time, model=model)
    c = loop_run_metrics(scn, spec, trajectory)["robot"]
    return {"nmpc": "RobotNMPCFunction", "ekf_step": time_summary(run.ekf_s), "controller_step": time_summary(run.ctrl_s),
            "tick": time_summary(run.step_s), "max_abs_diff_si": diff, "max_abs_diff_si_all": max(diff.values()),
            "fallbacks": run.fallbacks, "chamber_height_rmse_mm": m["chamber_height_rmse_mm"],
            "all_segments_settled": m["all_segments_settled"], "c_chamber_height_rmse_mm": c["chamber_height_rmse_mm"],
            "c_all_segments_settled": c["all_segments_settled"]}
