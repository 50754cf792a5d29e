"""The blocks of a generated robot loop against the Python classes they replace: the rig's period
(hbma_ctrl.robot.plant_step) against RobotRig, its load sharing against hbma_ctrl.robot.statics, the EKF
bank's step against ChamberEKFBank, the acting command mapped over the chambers against the bank's
CommandTiming, and the NMPC's RTI step against RobotNMPC."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from hbma_ctrl.core.params import Pneumatics
from hbma_ctrl.robot.design import RobotDesign
from hbma_ctrl.robot.plant_step import load_sharing_function, robot_rig_step_function
from hbma_ctrl.robot.rig import RobotRig, RobotRigSettings
from hbma_ctrl.robot.statics import load_sharing
from hbma_ctrl.sim.rig import IDEAL_STRUCTURE

DESIGN = RobotDesign(n_layers=2).validate()


def test_load_sharing_function_equals_the_numpy_statics_over_poses_and_tip_loads():
    """Level layers (the bend's direction undefined), one chamber up, random poses up to 17 mm, with
    and without a tip force and moment: the same forces (and tip) to rounding."""
    f = load_sharing_function(DESIGN)
    rng = np.random.default_rng(0)
    poses = [np.zeros(6), np.full(6, 4e-3), np.array([17e-3, 0, 0, 0, 0, 0]), np.array([0, 0, 0, 0, 17e-3, 17e-3])]
    poses += [rng.uniform(0.0, 17e-3, 6) for _ in range(30)]
    for i, h in enumerate(poses):
        ft = np.zeros(3) if i % 2 == 0 else rng.normal(0.0, 0.1, 3)
        mt = np.zeros(3) if i % 3 == 0 else rng.normal(0.0, 2e-3, 3)
        ref = load_sharing(DESIGN, h.reshape(2, 3), ft, mt)
        F, tip = (np.asarray(v).ravel() for v in f(h, ft, mt))
        np.testing.assert_allclose(F, ref.forces.ravel(), rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(tip, ref.pose.tip_position, rtol=1e-12, atol=1e-15)


def _run(rig: RobotRig, periods: int, seed: int):
    """The Function and the rig side by side on the same commands: the largest relative differences
    of the states, modes, lagged readings, parameters (loads, moving masses) and shared forces, and the
    modes seen and the largest height, m."""
    fn = robot_rig_step_function(rig)
    n = rig.n
    X, mode, th = rig.plant.X.copy(), rig.plant.mode[None, :].copy(), rig.plant.thetas.copy()
    hist = np.zeros((fn.size1_in(3), n))
    ps, pp = rig._p_sensed[None, :].copy(), rig._p_prev[None, :].copy()
    rng = np.random.default_rng(seed)
    worst, modes, h_max = {}, set(), 0.0
    for k in range(periods):
        # pump hard (the chambers lift, the layers tilt), then vent (back to rest), with noise in both
        pump = k < 2 * periods // 3
        U = np.vstack([rng.uniform(0.6, 1.0, n), rng.uniform(0.6, 1.0, n) * pump,
                       rng.uniform(0.5, 1.0, n) * (not pump)])
        X, mode, y, hist, th, ps, pp, F = (np.asarray(o) for o in fn(X, mode, U, hist, th, ps, pp, np.zeros(3)))
        rig.apply(U)
        modes |= set(rig.plant.mode.tolist())
        h_max = max(h_max, float(rig.plant.output("h").max()))
        for key, a, b in (("X", X, rig.plant.X), ("mode", mode.ravel(), rig.plant.mode),
                          ("p_sensed", ps.ravel(), rig._p_sensed), ("theta", th, rig.plant.thetas),
                          ("F", F.ravel(), rig.loads)):
            scale = np.abs(b).max(axis=-1, keepdims=True) + 1e-300
            worst[key] = max(worst.get(key, 0.0), float(np.max(np.abs(a - b) / scale)))
    return worst, modes, h_max


@pytest.mark.slow
@pytest.mark.parametrize("topology", ["per_chamber", "shared"])
def test_robot_rig_step_follows_the_rig_through_lift_off_and_touch_down(topology):
    """The default robot rig (platform chambers, valve delay and minimum opening, tilted pump, sensor
    lag): 120 periods of the Function and of RobotRig.apply on the same commands agree to 1e-9 of each
    quantity's scale, through lift-offs and touch-downs; a shared pump's manifold included."""
    rig = RobotRig(DESIGN, Pneumatics(), 50e3, topology, RobotRigSettings(noise_std=0.0))
    worst, modes, h_max = _run(rig, 120, 1)
    assert modes == {0.0, 1.0} and h_max > 1.5e-3  # the run lifted and came back to rest
    assert all(v < 1e-9 for v in worst.values()), worst


def test_robot_rig_step_without_valve_timing_and_refused_for_the_quasi_static_rig():
    rig = RobotRig(DESIGN, Pneumatics(), 50e3, "per_chamber", RobotRigSettings(noise_std=0.0, **IDEAL_STRUCTURE))
    worst, _, _ = _run(rig, 30, 2)
    assert all(v < 1e-9 for v in worst.values()), worst
    fn = robot_rig_step_function(rig)
    cg = ca.CodeGenerator("robot_rig_step_check.c")
    cg.add(fn)  # one generable Function (no Python callbacks)
    assert "robot_rig_step" in cg.dump()
    qs = RobotRig(DESIGN, Pneumatics(), 50e3, "per_chamber", RobotRigSettings(fidelity="quasi_static"))
    with pytest.raises(ValueError, match=r"\[rig\] fidelity = 'quasi_static'"):
        robot_rig_step_function(qs)


@pytest.mark.parametrize("valve_delay, sensor_delay", [(5e-3, 3e-3), (12e-3, 0.0), (0.0, 0.0)])
def test_the_acting_command_mapped_over_the_chambers_follows_the_banks_timing(valve_delay, sensor_delay):
    """acting_function mapped over n chambers, fed acting_state(timing, n) at the start and its own
    history after, gives the command CommandTiming.acting gives for 3 x n commands (the bank's call),
    period after period from an empty history: the short histories and the full one."""
    from hbma_ctrl.models.actuation import CommandTiming, acting_function, acting_state

    n, period = 9, 0.01
    timing = CommandTiming(period, valve_delay, sensor_delay)
    f = acting_function(timing).map(n)
    hist, fill = acting_state(timing, n)  # flat, as a generated loop's buffers hold them
    hist = hist.reshape(3, -1, order="F")
    rng = np.random.default_rng(4)
    for k in range(12):
        u = rng.uniform(0.0, 1.0, (3, n))
        u[:, rng.uniform(size=n) < 0.3] = 0.0  # closed valves and stopped pumps too
        if k == 5:  # the state read back mid-run is the Function's own
            h2, f2 = acting_state(timing, n)
            np.testing.assert_array_equal(h2, np.asarray(hist).ravel(order="F"))
            np.testing.assert_array_equal(f2, np.asarray(fill).ravel())
        want = timing.acting(u, 1)
        got, hist, fill = f(u, hist, fill)
        np.testing.assert_allclose(np.asarray(got), want, rtol=0, atol=1e-15)


@pytest.mark.slow
def test_the_ekf_banks_step_as_one_function_follows_the_bank():
    """bank_step_function against ChamberEKFBank.step over a run with every kind of reading (dropouts,
    +-inf, out of the physical bounds, saturated, a jump the gate holds off until it re-opens) and a
    diverged filter restarted from its reading: the same states, covariances, outputs and flags."""
    from hbma_ctrl.estimators.robot_ekf import NS, ChamberEKFBank, ChamberEKFSettings, bank_step_function
    from hbma_ctrl.system.roles import make_model

    d = RobotDesign(n_layers=1).validate()
    model = make_model(d, Pneumatics(), "per_chamber")
    s = ChamberEKFSettings(valve_delay=0.0, sensor_delay=0.0)  # the command passed is the one acting
    n = 3
    bank = ChamberEKFBank(model, n, s)
    fn = bank_step_function(bank)
    rng = np.random.default_rng(4)
    bank.reset(np.zeros(n))
    X, P, run = bank.X.copy(), bank.P.copy(), np.zeros((1, n))
    p_true = np.zeros(n)
    seen = set()
    for k in range(160):
        pump = k < 100
        w = np.vstack([np.ones(n), np.full(n, 0.8 if pump else 0.0), np.full(n, 0.0 if pump else 0.6)])
        p_true = np.maximum(p_true + (350.0 if pump else -500.0) * np.array([1.0, 0.8, 1.2]), 0.0)
        z = p_true + 200.0 * rng.standard_normal(n)
        if k % 17 == 3:
            z[0] = np.nan
        if k % 23 == 5:
            z[1] = np.inf
        if k % 29 == 7:
            z[2] = 1e6  # above the physical bound
        if k == 40:
            z[2] = 60e3  # at the sensor range: not used
        if 60 <= k < 66:
            z[1] += 15e3  # a jump: gated, then the gate re-opens
        if k == 120:
            bank.X[0, 1] = X[0, 1] = np.nan  # a diverged filter: both restart it
        W = np.array([0.17, 0.2, 0.23])
        got = dict(zip(fn.name_out(), (np.asarray(v) for v in fn(X, P, w, W, z, run))))
        want = bank.step(z, w, W)
        X, P, run = got["X_next"], got["P_next"], got["gated_run_next"]
        np.testing.assert_allclose(X, bank.X, rtol=1e-10, atol=1e-14, err_msg=f"X at {k}")
        np.testing.assert_allclose(P, bank.P, rtol=1e-9, atol=1e-18, err_msg=f"P at {k}")
        np.testing.assert_array_equal(run.ravel(), bank._gated_run)
        for key in ("h", "p", "h_std", "lam", "nis", "r", "k_std"):
            np.testing.assert_allclose(got[key].ravel(), want[key], rtol=1e-9, atol=1e-12, err_msg=f"{key} at {k}")
        for key in ("beyond", "lost", "used", "outlier"):
            np.testing.assert_array_equal(got[key].ravel() > 0.5, want[key], err_msg=f"{key} at {k}")
        seen |= {key for key in ("used", "outlier", "reset") if np.any(got[key] > 0.5)}
        seen |= {"gated"} if np.any(want["outlier"] & ~np.isinf(z) & (np.abs(z) < 1e5) & ~np.isnan(z)) else set()
    assert seen == {"used", "outlier", "reset", "gated"} and bank.resets == 1 and NS == 4


@pytest.mark.slow
@pytest.mark.parametrize("topology", ["per_chamber", "shared"])
def test_the_robot_rti_step_as_one_function_follows_the_nmpc(topology):
    """robot_rti_step_function against RobotNMPC.step over a closed run on the model itself (both at
    OSQP eps 1e-7: their OSQPs differ in version and set-up, so they agree to the tolerance, not to the
    bit): the same decisions within 5e-3 of a duty (the later stages of a plan are weakly determined:
    two solutions within the tolerance differ there by up to 1e-2, and a step that takes OSQP 800
    iterations moves the first decision by up to 3e-3), the same planned states within 1e-4; with a
    shared pump within 1e-2 and 5e-4 (how the one budget is split among the chambers is weakly
    determined too: from the Function's rho of 0.5, FN_RHO, one step's first decisions differ by
    8.2e-3 and its first planned states by 2.5e-4, both solves converged to a residual of 1e-7); a
    non-finite state is status 1 with zero decisions."""
    from hbma_ctrl.controllers.robot_mpc import RobotMPCSettings, RobotNMPC
    from hbma_ctrl.controllers.robot_rti_step import robot_rti_step_function
    from hbma_ctrl.system.roles import make_model

    d = RobotDesign(n_layers=1).validate()
    model = make_model(d, Pneumatics(), topology)
    s = RobotMPCSettings(eps=1e-7, max_iter=20000)
    nmpc = RobotNMPC(model, 3, s)
    fn = robot_rti_step_function(nmpc)
    n, N = 3, s.horizon
    x = np.array([0.05, 0.08, 0.02])
    b, W = np.ones(n), np.array([0.17, 0.2, 0.23])
    href = np.array([6e-3, 3e-3, 9e-3])
    st = dict(xbar=np.zeros((n, N + 1)), abar=np.zeros((n, N)), obar=np.zeros((n, N)), first=1.0,
              z_prev=np.zeros(nmpc.nv), y_prev=np.zeros(nmpc.m_rows), warm=0.0)
    prev = np.zeros((2, n))
    worst = 0.0
    u_tol, x_tol = (5e-3, 1e-4) if topology == "per_chamber" else (1e-2, 5e-4)
    for step in range(25):
        a_ref, o_ref = nmpc.step(x, b, W, href)
        out = dict(zip(fn.name_out(), fn(x, b, W, np.ones(n), np.ones(n), np.ones(n),
                                          np.repeat(href[:, None], N, 1), prev, st["xbar"], st["abar"],
                                          st["obar"], st["first"], st["z_prev"], st["y_prev"], st["warm"])))
        a, o = np.asarray(out["a"]).ravel(), np.asarray(out["o"]).ravel()
        assert float(out["status"]) == 0.0 and not nmpc.failed
        worst = max(worst, np.abs(a - a_ref).max(), np.abs(o - o_ref).max())
        np.testing.assert_allclose(np.asarray(out["xbar_next"]), nmpc.xbar, atol=x_tol)
        st = dict(xbar=np.asarray(out["xbar_next"]), abar=np.asarray(out["abar_next"]),
                  obar=np.asarray(out["obar_next"]), first=0.0, z_prev=np.asarray(out["z"]).ravel(),
                  y_prev=np.asarray(out["y"]).ravel(), warm=1.0)
        prev = np.vstack([a_ref, o_ref])
        nmpc.applied(a_ref, o_ref)
        # the chambers move as the model says (the plan's next state)
        x = nmpc.xbar[:, 1].copy()
    assert worst < u_tol
    cg = ca.CodeGenerator("robot_rti_step_check.c")
    cg.add(fn)  # one generable Function, the QP solver's C included
    assert "robot_rti_step" in cg.dump()
    bad = fn(np.array([np.nan, 0.0, 0.0]), b, W, np.ones(n), np.ones(n), np.ones(n), np.repeat(href[:, None], N, 1),
             prev, st["xbar"], st["abar"], st["obar"], 0.0, st["z_prev"], st["y_prev"], 1.0)
    assert float(bad[7]) == 1.0 and np.all(np.asarray(bad[0]) == 0.0) and np.all(np.asarray(bad[1]) == 0.0)


@pytest.mark.slow
def test_the_loops_targets_and_supply_caps_follow_their_numpy_oracles():
    """A one-layer RobotLoop on the rig (NMPC, EKF bank, cautious cap, a 10 mm/s target rate): a
    rise to 5 mm, a bend, then a zero target on one chamber. At every tick the targets the loop
    worked to (slew_function) equal the numpy slew's, and the supply bounds it handed its NMPC
    (caps_function) the numpy caps' with the limit-point pressures the oracle keeps (refreshed every
    tenth tick); the cap and the vent both act."""
    from oracles import robot_loop as oracle

    from hbma_ctrl.controllers.robot_mpc import RobotMPCSettings, RobotNMPC
    from hbma_ctrl.estimators.robot_ekf import ChamberEKFBank, ChamberEKFSettings
    from hbma_ctrl.system.roles import make_model
    from hbma_ctrl.system.sections import RobotSettings
    from hbma_ctrl.robot.design import RobotPneumatics
    from hbma_ctrl.runtime.robot import RobotLoop, robot_supervisor

    d = RobotDesign(n_layers=1).validate()
    s = RobotSettings(design=d, pneumatics=RobotPneumatics()).validate()
    model = make_model(d, Pneumatics(), s.pneumatics.topology)
    rs = RobotRigSettings().validate()
    n, rate = 3, 10e-3
    rig = RobotRig(d, Pneumatics(), s.pneumatics.sensor_range, s.pneumatics.topology, rs, ())
    bank = ChamberEKFBank(model, n, ChamberEKFSettings(sample_period=rs.sample_period, noise_std=max(rs.noise_std, 1.0),
                                                       sensor_range=s.pneumatics.sensor_range))
    ms = RobotMPCSettings(sample_period=rs.sample_period, p_max=s.pneumatics.pressure_limit)
    ctrl = RobotNMPC(model, n, ms)
    targets = {0: ((0.0, 5e-3, 0.0, 0.0), (0.6, 5e-3, 0.15, 0.0), (1.0, 0.0, 0.0, 0.0))}
    loop = RobotLoop(d, model, bank, ctrl, robot_supervisor(s.pneumatics.pressure_limit, n, plan_period=ms.dt),
                     targets, target_rate=rate)
    seen = {"near": 0, "vent": 0, "moving": 0}
    peak = oracle.peaks(model, loop.loads, np.ones(n))
    np.testing.assert_allclose(loop._peak_p, peak, rtol=1e-12)
    slew_calls, step_calls = [], []
    _slew, _step = loop._slew, ctrl.step

    def spy_slew(goal, h_est, dt):
        prev = None if loop.href is None else loop.href.copy()
        out = _slew(goal, h_est, dt)
        slew_calls.append((np.array(goal, dtype=float), np.array(h_est, dtype=float), dt, prev, out.copy()))
        return out

    def spy_step(x0, b, W, h_ref, k, c, a_max):
        est, sup = loop.estimate, loop.supervisor
        step_calls.append(({key: est[key].copy() for key in ("p", "k", "k_std", "lam", "lost")}, np.array(W),
                           np.array(h_ref), sup.lost.copy(), sup.burst.copy(), loop._k % 10 == 0, np.array(a_max),
                           loop._peak_p.copy()))
        return _step(x0, b, W, h_ref, k, c, a_max)

    loop._slew, ctrl.step = spy_slew, spy_step
    for _ in range(130):
        loop.tick(rig.t, rig.measure())
        rig.apply(loop.valve_commands)
    assert len(slew_calls) == len(step_calls) == 130
    for goal, h_est, dt, prev, got in slew_calls:
        want = oracle.slew(goal, h_est, dt, prev, rate)
        np.testing.assert_array_equal(got, want)
        seen["moving"] += int(np.any((want != goal) & (goal > 0)))
    sset = loop.supervisor.settings
    for est, W, href, sup_lost, sup_burst, refresh, a_max, peak_kept in step_calls:
        if refresh:
            peak = oracle.peaks(model, W, est["k"])
        np.testing.assert_allclose(peak_kept, peak, rtol=1e-12)
        want, near = oracle.caps(sset, loop.cautious, est, href, sup_lost, sup_burst, peak)
        np.testing.assert_array_equal(a_max, want)
        seen["near"] += int(near.sum())
        seen["vent"] += int(oracle.vent_mask(sset, href).sum())
    assert all(v > 0 for v in seen.values()), seen


@pytest.mark.slow
@pytest.mark.parametrize("topology, n, margin", [("per_chamber", 3, None), ("shared", 3, None), ("shared", 9, None),
                                                 ("per_chamber", 9, 0.0), ("shared", 4, 0.0)])
def test_the_throttled_valve_inputs_as_one_function_follow_numpy(topology, n, margin):
    """throttled_inputs_function against throttled_inputs over 300 random decisions: duties in and out
    of [0, 1] and under the 1e-4 floor, a shared pump's budget exceeded, pressures across the map,
    above its stall and NaN, all chambers idle: the same plant inputs (a shared pump's bisection and
    budget to a few ulps), the throttle and the stall floor both acting."""
    from hbma_ctrl.system.roles import make_model
    from hbma_ctrl.models.bank import STALL_MARGIN, throttled_inputs_function
    from oracles.throttle import NumpyPump, throttled_inputs

    model = make_model(RobotDesign(n_layers=1).validate(), Pneumatics(), topology)
    pump = model.pump
    numpy_pump = NumpyPump(model.pneumatics.csv_path)
    m = STALL_MARGIN if margin is None else margin
    f = throttled_inputs_function(pump, n, topology, m)
    rng = np.random.default_rng(n)
    throttled = 0
    for k in range(300):
        a = rng.uniform(-0.1, 1.1, n) * (rng.uniform(size=n) < 0.7)
        a[rng.uniform(size=n) < 0.1] = 5e-5
        if k % 50 == 0:
            a[:] = 0.0
        o = rng.uniform(-0.1, 1.1, n) * (rng.uniform(size=n) < 0.5)
        p = rng.uniform(-2e3, 80e3, n)
        p[rng.uniform(size=n) < 0.1] = np.nan
        want = throttled_inputs(a, o, p, topology, numpy_pump, m)
        got = np.asarray(f(a, o, p))
        np.testing.assert_allclose(got, want, rtol=0, atol=4e-16, err_msg=f"draw {k}")
        throttled += int(np.sum((want[0] > 0) & (want[0] < 1)))
    assert throttled > 0


@pytest.mark.slow
def test_the_loops_vent_netting_follows_its_numpy_oracle():
    """A one-layer RobotLoop on the rig with the valves' 2 ms minimum opening, holding heights and
    stepping down (short vents): at every tick the supply and outlet duties the loop sent
    (net_vents_function) and the minimum on-time's carry it left equal the numpy netting's, short
    vents netted, dropped and sent all seen."""
    from oracles import robot_loop as oracle

    from hbma_ctrl.controllers.robot_mpc import RobotMPCSettings, RobotNMPC
    from hbma_ctrl.estimators.robot_ekf import ChamberEKFBank, ChamberEKFSettings
    from hbma_ctrl.system.roles import make_model
    from hbma_ctrl.system.sections import RobotSettings
    from hbma_ctrl.robot.design import RobotPneumatics
    from hbma_ctrl.runtime.robot import RobotLoop, robot_supervisor

    d = RobotDesign(n_layers=1).validate()
    s = RobotSettings(design=d, pneumatics=RobotPneumatics()).validate()
    model = make_model(d, Pneumatics(), s.pneumatics.topology)
    rs = RobotRigSettings().validate()
    n = 3
    rig = RobotRig(d, Pneumatics(), s.pneumatics.sensor_range, s.pneumatics.topology, rs, ())
    bank = ChamberEKFBank(model, n, ChamberEKFSettings(sample_period=rs.sample_period, noise_std=max(rs.noise_std, 1.0),
                                                       sensor_range=s.pneumatics.sensor_range))
    ms = RobotMPCSettings(sample_period=rs.sample_period, p_max=s.pneumatics.pressure_limit)
    targets = {0: ((0.0, 6e-3, 0.0, 0.0), (0.8, 5.5e-3, 0.1, 0.0), (1.4, 4e-3, 0.0, 0.0))}
    loop = RobotLoop(d, model, bank, RobotNMPC(model, n, ms),
                     robot_supervisor(s.pneumatics.pressure_limit, n, plan_period=ms.dt), targets, valve_min_on=0.002)
    calls, _net = [], loop.net_vents

    def spy(a, o, est, W, excess):
        args = (a.copy(), o.copy(), {k: v.copy() for k, v in est.items() if isinstance(v, np.ndarray)}, W.copy(),
                excess.copy(), loop.pwm.carry.copy())
        out = _net(a, o, est, W, excess)
        calls.append((args, out[0].copy(), out[1].copy(), loop.pwm.carry.copy()))
        return out

    loop.net_vents = spy
    for _ in range(200):
        loop.tick(rig.t, rig.measure())
        rig.apply(loop.valve_commands)
    seen = {"netted": 0, "dropped": 0, "sent": 0}
    md = loop.pwm.min_duty
    for (a, o, est, W, excess, carry), a_got, o_got, carry_got in calls:
        a_want, o_want, carry_want = oracle.net_vents(model, md, loop._period, a, o, est, W, excess, carry)
        np.testing.assert_allclose(a_got, a_want, rtol=1e-13, atol=0)
        np.testing.assert_allclose(o_got, o_want, rtol=1e-13, atol=0)
        np.testing.assert_allclose(carry_got, carry_want, rtol=1e-13, atol=0)
        short = (o > 0) & (o < md)
        seen["netted"] += int(np.sum(short & (a > 0) & (a_want != a)))
        seen["dropped"] += int(np.sum(short & (o_want == 0)))
        seen["sent"] += int(np.sum(short & (o_want > 0)))
    assert all(v > 0 for v in seen.values()), seen


def test_the_minimum_on_time_over_the_chambers_follows_the_numpy_oracle():
    """MinOnTime.shape_inputs (its Function mapped over 6 chambers) gives the plant inputs and carries
    the numpy oracle does for 3 x n inputs (the robot's call) over 300 periods, with duties at 0, at
    the minimum and at half of it among them and the forgetting RobotLoop.net_vents applies to
    dropped vents in between: the same bits, duties raised to the minimum and dropped both seen."""
    from oracles.pwm import MinOnTimeOracle

    from hbma_ctrl.runtime.pwm import MinOnTime

    n, period = 6, 0.01
    pwm, oracle = MinOnTime(period, 0.002), MinOnTimeOracle(period, 0.002)
    m = pwm.min_duty
    pwm.carry = np.zeros((2, n))
    rng = np.random.default_rng(6)
    raised = dropped = 0
    for k in range(300):
        U = rng.uniform(0.0, 1.0, (3, n))
        U[1:3] *= np.where(rng.uniform(size=(2, n)) < 0.6, rng.uniform(0.0, 0.3, (2, n)), 1.0)
        U[1:3] *= rng.uniform(size=(2, n)) < 0.8
        edge = rng.uniform(size=(2, n)) < 0.1
        U[1:3][edge] = rng.choice([0.0, m, 0.5 * m, np.nextafter(m, 0.0)], int(edge.sum()))
        want = oracle.shape_inputs(U)
        got = pwm.shape_inputs(U)
        np.testing.assert_array_equal(got, want, err_msg=f"period {k}")
        np.testing.assert_array_equal(pwm.carry, oracle.carry, err_msg=f"period {k}")
        small = (U[1:3] > 0) & (U[1:3] < m)
        raised += int(np.sum(small & (want[1:3] == m)))
        dropped += int(np.sum(small & (want[1:3] == 0)))
        if k % 7 == 0:  # the loop's netting forgets a dropped vent's carry
            which = rng.uniform(size=n) < 0.5
            for sh in (pwm, oracle):
                sh.carry[1] = np.where(which, 0.0, sh.carry[1])
    assert raised > 0 and dropped > 0
