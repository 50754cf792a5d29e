"""A robot scenario's closed loop (robot rig -> EKF bank -> NMPC -> supervisor -> valves -> rig) as a
:class:`~hbma_ctrl.core.loopgen.LoopSpec`: the robot's generated C loop.

The loop is built from the very objects the scene builds (:func:`hbma_ctrl.app.scenes.robot_loop.build_closed_loop`),
and every part of :meth:`hbma_ctrl.runtime.robot.RobotLoop.tick` is the casadi Function that mirrors it,
called in the tick's order:

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
(``mpc_enforce_budget``; ``mpc_budget`` alone acts only in the daemon), the quasi-static rig's
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
    return (s, *scene_parts(scn, s))


def _build(scn, nmpc_class=None):
    """The scene's rig and loop (and its settings), refused where the generated loop cannot follow."""
    from hbma_ctrl.controllers.robot_rti_step import RobotNMPCFunction
    from hbma_ctrl.app.scenes.robot_loop import build_closed_loop

    s, rig, model, mpc = robot_scene_parts(scn)
    if s.controller != "mpc":
        raise ValueError(f"codegen: [robot] controller = '{s.controller}': only 'mpc' generates C")
    if mpc.enforce_budget and mpc.budget > 0:
        raise ValueError("codegen: [robot] mpc_enforce_budget = true: an enforced wall-time budget depends on "
                         "the machine's clock; set it to false to generate the loop")
    sim, system = build_closed_loop(s, s.targets, "mpc", scn.pneumatics, rig, mpc, model=model, tip_load=s.tip_load,
                                    nmpc_class=nmpc_class or RobotNMPCFunction)
    return s, rig, sim.rig, system.loop


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


def _ekf_function(loop) -> ca.Function:
    """robot_ekf(z[n], w_prev[2 x n], act_hist, act_fill[n], X[4 x n], P[16 x n], W[n], gated_run[n])
    -> the acting history, the bank's state and its outputs (the bank's step with the command acting)."""
    from hbma_ctrl.estimators.robot_ekf import bank_step_function
    from hbma_ctrl.models.actuation import acting_function

    bank, n = loop.bank, loop.n
    timing = bank._timing
    act = acting_function(timing, "robot_acting").map(n)
    step = bank_step_function(bank, "robot_bank")
    MX = ca.MX
    z, w_prev = MX.sym("z", 1, n), MX.sym("w_prev", 2, n)
    hist, fill = MX.sym("act_hist", act.sparsity_in(1)), MX.sym("act_fill", 1, n)
    X, P, W, run = MX.sym("X", 4, n), MX.sym("P", 16, n), MX.sym("W", 1, n), MX.sym("gated_run", 1, n)
    # the supply as a full-speed inlet duty: the pump's row is 1 (ChamberEKFBank.step on [a, o])
    w = ca.vertcat(MX.ones(1, n), w_prev)
    u, hist_n, fill_n = act(w, hist, fill)
    out = dict(zip(step.name_out(), step(X, P, u, W, z, run)))
    keys = ["X_next", "P_next", "gated_run_next", "h", "p", "lam", "lost", "r", "outlier", "k_std", "reset"]
    return ca.Function("robot_ekf", [z, w_prev, hist, fill, X, P, W, run], [hist_n, fill_n] + [out[k] for k in keys],
                       ["z", "w_prev", "act_hist", "act_fill", "X", "P", "W", "gated_run"],
                       ["act_hist_next", "act_fill_next"] + keys)


def _pre_function(loop) -> ca.Function:
    """robot_pre: the tick's part between the bank and the NMPC (module docstring)."""
    from hbma_ctrl.robot.plant import W_FLOOR
    from hbma_ctrl.robot.plant_step import load_sharing_function
    from hbma_ctrl.runtime.burst import burst_function
    from hbma_ctrl.runtime.robot_step import caps_function, slew_function
    from hbma_ctrl.runtime.safety_step import state_parts, state_size

    n, N, sup, model = loop.n, loop.controller.s.horizon, loop.supervisor, loop.model
    MX = ca.MX
    t, first, refresh = MX.sym("t"), MX.sym("first"), MX.sym("refresh")
    z, outlier, r, lost, lam, h, p, k_std = (MX.sym(s, n) for s in ("z", "outlier", "r", "lost", "lam", "h", "p",
                                                                     "k_std"))
    X = MX.sym("X", 4, n)
    goal, href_prev, peak, released = (MX.sym(s, n) for s in ("goal", "href_prev", "peak", "released"))
    sst = MX.sym("sup_state", state_size(n, 2, N))
    bst = MX.sym("burst_state", 1 if loop.burst is None else _burst_state(loop).size)
    # the interlock sees the readings the bank trusted (an outlier is no pressure)
    zs = ca.if_else(outlier != 0, ca.DM.nan(n, 1), z)
    parts = state_parts(n, 2, N)
    sup_lost, sup_burst = sst[parts["lost"]], sst[parts["burst"]]
    if loop.burst is not None:
        bf = burst_function(loop.burst.settings, n, "robot_burst")
        lost_new = ca.logic_and(lost != 0, ca.logic_not(sup_lost != 0))
        _, flagged, bst_next = bf(t, r, lost_new, released, bst)
    else:
        flagged, bst_next = MX.zeros(n), bst
    share = load_sharing_function(loop.design, "robot_loads")
    W = ca.fmax(share(h, MX.zeros(3), MX.zeros(3))[0], W_FLOOR)
    href = slew_function(n, loop.target_rate, "robot_slew")(goal, href_prev, h, first, loop._period)
    caps = caps_function(model, n, loop.cautious, sup.settings.vent_height, sup.settings.stretch_max, "robot_caps")
    k = X[2, :].T
    a_max, near, peak_next = caps(W, k, p, k_std, href, lam, lost, sup_lost, sup_burst, peak, refresh)
    x, b, c = (X[3, :] * X[0, :] - 1).T, X[1, :].T, X[3, :].T
    return ca.Function(
        "robot_pre", [t, first, refresh, z, outlier, r, lost, lam, h, p, k_std, X, goal, href_prev, peak, released, sst,
                      bst],
        [zs, flagged, bst_next, W, href, ca.repmat(href, 1, N), a_max, ca.sum1(near), peak_next, x, b, k, c],
        ["t", "first", "refresh", "z", "outlier", "r", "lost", "lam", "h", "p", "k_std", "X", "goal", "href_prev",
         "peak", "released", "sup_state", "burst_state"],
        ["zs", "burst_flagged", "burst_state_next", "W", "href", "href_N", "a_max", "near_count", "peak_next", "x", "b", "k",
         "c"])


def _post_function(loop) -> ca.Function:
    """robot_post: the tick's part after the NMPC (module docstring)."""
    from hbma_ctrl.models.bank import throttled_inputs_function
    from hbma_ctrl.runtime.robot_step import net_vents_function
    from hbma_ctrl.runtime.safety_step import state_size, supervisor_function

    nmpc, bank, model, sup = loop.controller, loop.bank, loop.model, loop.supervisor
    n, N, topo = loop.n, nmpc.s.horizon, model.topology
    MX = ca.MX
    t, status = MX.sym("t"), MX.sym("status")
    a_dec, o_dec, zs, href, lam, lost, flagged = (MX.sym(s, n) for s in ("a_dec", "o_dec", "zs", "href", "lam", "lost",
                                                                         "burst_flagged"))
    abar, obar = MX.sym("abar", n, N), MX.sym("obar", n, N)
    sst = MX.sym("sup_state", state_size(n, 2, N))
    X, P = MX.sym("X", 4, n), MX.sym("P", 16, n)
    zq_new, yq_new, zq, yq = (MX.sym(s, m) for s, m in (("qp_z_new", nmpc.nv), ("qp_y_new", nmpc.m_rows),
                                                         ("qp_z", nmpc.nv), ("qp_y", nmpc.m_rows)))
    warm = MX.sym("warm")
    p, b, h, x, W, k, c = (MX.sym(s, n) for s in ("p", "b", "h", "x", "W", "k", "c"))
    carry = MX.sym("carry", 2, n)
    ok = status == 0
    # the plan, rows [row][chamber][supply, outlet], a shared pump's budget on every row (RobotLoop._plan)
    rows = []
    for j in range(N):
        aj, oj = abar[:, j], obar[:, j]
        if topo == "shared":
            s_ = ca.sum1(aj)
            aj = ca.if_else(s_ > 1.0, aj / ca.fmax(s_, 1e-12), aj)
        rows.append(ca.vec(ca.horzcat(aj, oj).T))
    plan = ca.vertcat(*rows)
    command = ca.vec(ca.horzcat(a_dec, o_dec).T)
    supervise = supervisor_function(sup.settings, n, 2, N, "robot_supervisor")
    okv = ca.repmat(ok, n, 1)
    out, sst_next, released, events, failed = supervise(t, command, zs, okv, plan, ok, href, lam, lost, flagged, sst)
    cmd = ca.reshape(out, 2, n)
    a, o = cmd[0, :].T, cmd[1, :].T
    # a released chamber's filter restarts at rest from its reading (ChamberEKFBank.reset)
    lo, hi = bank._bounds
    # a reading out of the physical range (NaN, +-inf too: every comparison is false for NaN) reads as 0
    p0 = ca.if_else(ca.logic_and(zs >= lo, zs <= hi), zs, 0.0)
    X_rest, P_rest = bank.rest_expr(p0.T)
    X_next = ca.if_else(ca.repmat((released != 0).T, 4, 1), X_rest, X)
    P_next = ca.if_else(ca.repmat((released != 0).T, 16, 1), P_rest, P)
    prev = ca.horzcat(a, o).T  # what the NMPC's input-rate terms start from (RobotNMPC.applied)
    if loop.pwm.active:
        nv = net_vents_function(model, n, loop.pwm.min_duty, loop._period, "robot_net_vents")
        a, o, carry_v = nv(a, o, p, b, h - href, x, W, k, c, carry)
    else:
        carry_v = carry
    Uc = throttled_inputs_function(model.pump, n, topo, name="robot_valve_inputs")(a, o, p)
    # the supply as the full-speed inlet duty its flow equals (RobotLoop's _flow_duty)
    supply = ca.fmin(ca.fmax(a, 0.0), 1.0)
    supply = ca.if_else(supply < 1e-4, 0.0, supply)
    if topo == "shared":
        tot = ca.sum1(supply)
        supply = ca.if_else(tot > 1.0, supply / tot, supply)
    if loop.pwm.active:
        Us, carry_n = loop.pwm.function("robot_pwm").map(n)(Uc, carry_v)
        inlet = Uc[1, :].T
        supply = supply * ca.if_else(inlet > 0.0, Us[1, :].T / ca.if_else(inlet > 0.0, inlet, 1.0), 0.0)
        Uc = Us
    else:
        carry_n = carry_v
    w_prev = ca.horzcat(supply, Uc[2, :].T).T
    # this tick's interventions per kind (the Supervisor's counts' increments), EVENTS order
    ev_sums = _event_sums(events, n)
    return ca.Function(
        "robot_post", [t, status, a_dec, o_dec, abar, obar, zs, href, lam, lost, flagged, sst, X, P, zq_new, yq_new, zq,
                       yq, warm, p, b, h, x, W, k, c, carry],
        [Uc, w_prev, sst_next, released, X_next, P_next, prev, ca.if_else(ok, zq_new, zq), ca.if_else(ok, yq_new, yq),
         ca.logic_or(warm != 0, ok), MX(0.0), carry_n, ev_sums, failed, a, o],
        ["t", "status", "a_dec", "o_dec", "abar", "obar", "zs", "href", "lam", "lost", "burst_flagged", "sup_state",
         "X", "P", "qp_z_new", "qp_y_new", "qp_z", "qp_y", "warm", "p", "b", "h", "x", "W", "k", "c", "carry"],
        ["U", "w_prev", "sup_state_next", "released", "X_next", "P_next", "prev", "qp_z_next", "qp_y_next",
         "warm_next", "first_next", "carry_next", "event_sums", "failed", "a_sent", "o_sent"])


def _event_sums(events, n: int):
    """The supervisor's per-chamber event flags (7 rows of n, in
    :data:`~hbma_ctrl.runtime.safety_step.EVENTS` order) summed per row."""
    from hbma_ctrl.runtime.safety_step import EVENTS

    return ca.vertcat(*[ca.sum1(events[j * n:(j + 1) * n]) for j in range(len(EVENTS))])


def _sensor_function(n: int, sensor_range: float) -> ca.Function:
    """robot_sensor(p[n], noise[n]) -> z[n]: the pressure plus the noise, saturated at the range (Pa)."""
    p, noise = ca.SX.sym("p", n), ca.SX.sym("noise", n)
    return ca.Function("robot_sensor", [p, noise], [ca.fmin(p + noise, sensor_range)], ["p", "noise"], ["z"])


def robot_loop(scn, duration: float | None = None) -> LoopSpec:
    """The closed-loop ``[robot]`` scenario's loop (module docstring) over ``duration`` s (None: the
    scenario's). ValueError naming the key the generated loop cannot follow."""
    from functools import partial

    from hbma_ctrl.controllers.robot_rti_step import RobotNMPCFunction
    from hbma_ctrl.models.actuation import acting_state
    from hbma_ctrl.robot.plant_step import robot_rig_step_function
    from hbma_ctrl.runtime.safety_step import EVENTS

    # the NMPC's step uncompiled: the sources are generated from its Function, nothing is built here
    s, rs, plant, loop = _build(scn, partial(RobotNMPCFunction, compile=False))
    nmpc, bank = loop.controller, loop.bank
    n, N = loop.n, nmpc.s.horizon
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
    z0 = np.minimum(p_first + noise[0], plant.sensor_range)
    act_hist, act_fill = acting_state(bank._timing, n)
    goal = np.array([loop.chamber_targets(t) for t in t0])
    tip = np.array([plant.tip_force(t) for t in t1])
    signals = {
        # the rig
        "X": plant.plant.X.ravel(order="F"), "mode": plant.plant.mode.astype(float),
        "U": np.zeros(3 * n), "hist": np.zeros(rig_fn.nnz_in(3)), "theta": plant.plant.thetas.ravel(order="F"),
        "p_sensed": plant._p_sensed, "p_prev": plant._p_prev, "y": plant.plant.y.ravel(order="F"),
        "F_rig": plant.loads, "f_tip": np.zeros(3), "noise": np.zeros(n), "z": np.zeros(n),
        # the clock and the targets
        "t": [0.0], "goal": np.zeros(n), "first": [1.0], "refresh": [1.0],
        # the bank: it starts at rest from the first readings (ChamberEKFBank.step's first call)
        "w_prev": np.zeros(2 * n), "act_hist": act_hist, "act_fill": act_fill,
        "ekf_X": bank.rest_state(z0).ravel(order="F"),
        "ekf_P": np.repeat(bank._prior_cov().reshape(16, 1, order="F"), n, 1).ravel(order="F"),
        "W": loop.loads, "gated_run": np.zeros(n),
        "h_est": np.zeros(n), "p_est": np.zeros(n), "lam": np.zeros(n), "lost": np.zeros(n), "r": np.zeros(n),
        "outlier": np.zeros(n), "k_std": np.zeros(n), "ekf_reset": np.zeros(n),
        # the tick's middle
        "zs": np.zeros(n), "burst_flagged": np.zeros(n),
        "burst_state": (np.zeros(1) if loop.burst is None else _burst_state(loop)), "href": np.zeros(n),
        "href_N": np.zeros(n * N), "a_max": np.zeros(n), "near_count": [0.0], "peak": loop._peak_p.copy(),
        "x_est": np.zeros(n), "b_est": np.zeros(n), "k_est": np.zeros(n), "c_est": np.zeros(n),
        "sup_state": loop.supervisor.state(2, N), "released": np.zeros(n),
        # the NMPC
        "prev": np.zeros(2 * n), "xbar": np.zeros(n * (N + 1)), "abar": np.zeros(n * N), "obar": np.zeros(n * N),
        "nmpc_first": [1.0], "qp_z": np.zeros(nmpc.nv), "qp_y": np.zeros(nmpc.m_rows),
        "qp_z_new": np.zeros(nmpc.nv), "qp_y_new": np.zeros(nmpc.m_rows), "warm": [0.0],
        "a_dec": np.zeros(n), "o_dec": np.zeros(n), "rti_status": [0.0], "rti_residual": [0.0],
        # after it
        "carry": np.zeros(2 * n), "event_sums": np.zeros(7), "failed": [0.0], "a_sent": np.zeros(n),
        "o_sent": np.zeros(n),
    }
    stages = [
        Stage(_sensor_function(n, plant.sensor_range), ["p_sensed" if lagged else "p_true", "noise"], ["z"]),
        Stage(_ekf_function(loop), ["z", "w_prev", "act_hist", "act_fill", "ekf_X", "ekf_P", "W", "gated_run"],
              ["act_hist", "act_fill", "ekf_X", "ekf_P", "gated_run", "h_est", "p_est", "lam", "lost", "r", "outlier",
               "k_std", "ekf_reset"]),
        Stage(_pre_function(loop), ["t", "first", "refresh", "z", "outlier", "r", "lost", "lam", "h_est", "p_est",
                                    "k_std", "ekf_X", "goal", "href", "peak", "released", "sup_state", "burst_state"],
              ["zs", "burst_flagged", "burst_state", "W", "href", "href_N", "a_max", "near_count", "peak", "x_est", "b_est",
               "k_est", "c_est"]),
        Stage(nmpc._fn.fun, ["x_est", "b_est", "W", "k_est", "c_est", "a_max", "href_N", "prev",
                                              "xbar", "abar", "obar", "nmpc_first", "qp_z", "qp_y", "warm"],
              ["a_dec", "o_dec", "xbar", "abar", "obar", "qp_z_new", "qp_y_new", "rti_status", "rti_residual"]),
        Stage(_post_function(loop), ["t", "rti_status", "a_dec", "o_dec", "abar", "obar", "zs", "href", "lam", "lost",
                                     "burst_flagged", "sup_state", "ekf_X", "ekf_P", "qp_z_new", "qp_y_new", "qp_z",
                                     "qp_y", "warm", "p_est", "b_est", "h_est", "x_est", "W", "k_est", "c_est",
                                     "carry"],
              ["U", "w_prev", "sup_state", "released", "ekf_X", "ekf_P", "prev", "qp_z", "qp_y", "warm", "nmpc_first",
               "carry", "event_sums", "failed", "a_sent", "o_sent"]),
        Stage(rig_fn, ["X", "mode", "U", "hist", "theta", "p_sensed", "p_prev", "f_tip"],
              ["X", "mode", "y", "hist", "theta", "p_sensed", "p_prev", "F_rig"]),
        Stage(_truth_function(n), ["y"], ["p_true", "h_true", "lam_true"]),
    ]
    signals["p_true"] = plant.plant.output("p").copy()
    signals["h_true"] = np.maximum(plant.plant.output("h"), 0.0)
    signals["lam_true"] = plant.plant.output("lam").copy()
    names = loop.design.names
    log = []
    for i, nm in enumerate(names):
        log += [LogColumn(f"h_{nm}_mm", "h_true", i, 1e3), LogColumn(f"h_est_{nm}_mm", "h_est", i, 1e3),
                LogColumn(f"h_ref_{nm}_mm", "href", i, 1e3), LogColumn(f"p_{nm}_kpa", "p_true", i, 1e-3),
                LogColumn(f"p_meas_{nm}_kpa", "z", i, 1e-3), LogColumn(f"a_{nm}", "a_sent", i),
                LogColumn(f"o_{nm}", "o_sent", i), LogColumn(f"speed_{nm}", "U", 3 * i),
                LogColumn(f"inlet_{nm}", "U", 3 * i + 1), LogColumn(f"outlet_{nm}", "U", 3 * i + 2),
                LogColumn(f"load_{nm}_n", "F_rig", i), LogColumn(f"lam_{nm}", "lam_true", i),
                LogColumn(f"burst_{nm}", "burst_flagged", i)]
    log += [LogColumn("rti_status", "rti_status"), LogColumn("failed", "failed"), LogColumn("cautious", "near_count")]
    log += [LogColumn(f"ev_{e}", "event_sums", j) for j, e in enumerate(EVENTS)]
    streams = {"noise": noise, "t": t0[:, None], "goal": goal, "first": (np.arange(n_ticks) == 0).astype(float)[:, None],
               "refresh": (np.arange(n_ticks) % 10 == 0).astype(float)[:, None], "f_tip": tip}
    meta = {"scenario": scn.name,
            "rig": (f"robot rig: {s.design.n_layers} layers, {fid.name}, {plant.s.sample_period * 1e3:g} ms, seed {rs.seed}; "
                    f"valve delay {rs.valve_delay * 1e3:g} ms, minimum opening {rs.valve_min_on * 1e3:g} ms, "
                    f"pump tilt {rs.compressor_tilt:g}, sensor lag {rs.sensor_tau * 1e3:g} ms"),
            "estimator": f"EKF bank over {n} chambers (valve delay {bank.settings.valve_delay * 1e3:g} ms, sensor delay "
                         f"{bank.settings.sensor_delay * 1e3:g} ms)",
            "controller": f"robot RTI NMPC, N = {N}, dt {nmpc.s.dt * 1e3:g} ms, OSQP (casadi's) inside; "
                          f"{s.pneumatics.topology} pump; minimum valve opening {loop.pwm.min_duty * loop._period * 1e3:g} ms",
            "timing": "each trajectory row is logged after the rig's period (the scene's log row k + 1)"}
    if s.compare_baseline:
        meta["left out"] = "the pressure-PID baseline ([robot] compare_baseline = true): only the NMPC's loop is generated"
    return LoopSpec(scn.name, rs.sample_period, n_ticks, signals, streams, stages, log, meta).validate()


def _burst_state(loop) -> np.ndarray:
    from hbma_ctrl.runtime.burst import burst_state

    return burst_state(loop.burst)


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
    from hbma_ctrl.core.loopgen import time_summary
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
