"""The robot's membranes are bounded when their estimates are not: the stretch interlock, the vent of
a chamber whose filter has left its model (gas mass past the tables' top, a factor at the edge of its
range) with its filter restarted once the chamber is down, and the bank's clips: the gas mass at the
tables' top for the chamber's own dead volume (a clip at the nominal top pinned a growing membrane's
estimate at a mid height), the floor a pressure, not a gas mass."""

from __future__ import annotations


import casadi as ca
import numpy as np
import pytest

from checkout import ROOT
from hbma_ctrl.controllers.robot_mpc import RobotMPCSettings, RobotNMPC
from hbma_ctrl.estimators.robot_ekf import B_RANGE, ChamberEKFBank, ChamberEKFSettings
from hbma_ctrl.app.scenes.robot_loop import run_closed_loop
from hbma_ctrl.system.sections import RobotSettings
from hbma_ctrl.core import units as U
from hbma_ctrl.robot.design import RobotDesign, RobotPneumatics
from hbma_ctrl.robot.rig import RobotRigSettings
from hbma_ctrl.runtime.robot import RobotLoop, robot_supervisor
from hbma_ctrl.runtime.safety import Supervisor, SupervisorSettings


@pytest.fixture(scope="module")
def robot(robot_bank):
    d = RobotDesign(n_layers=1).validate()
    return d, robot_bank  # make_model(d, Pneumatics(), "per_chamber")


# --- the supervisor ------------------------------------------------------------------------------
def test_stretch_guard_cuts_the_supply_of_a_pumping_chamber_at_the_limit_only():
    sup = Supervisor(SupervisorSettings(p_max=45e3, vent_margin=None, stretch_max=4.0), n=4)
    cmd = np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 0.5], [1.0, 0.0]])
    out = sup.apply(0.5, cmd, np.full(4, 10e3), stretch=np.array([4.0, 3.99, 5.0, np.nan]))
    # at the limit and pumping: supply cut; below it: as proposed; not pumping: nothing to cut;
    # unknown (NaN) stretch: not guarded
    assert out.tolist() == [[0.0, 0.0], [1.0, 0.0], [0.0, 0.5], [1.0, 0.0]]
    assert sup.counts["stretch_guard"] == 1
    assert [(e.chamber, e.cause, e.detail) for e in sup.events] == [(0, "stretch_guard", "stretch=4.00")]


def test_stretch_guard_is_off_without_a_limit():
    sup = Supervisor(SupervisorSettings(p_max=45e3, vent_margin=None), n=1)
    assert sup.apply(0.0, np.array([[1.0, 0.0]]), [10e3], stretch=[50.0]).tolist() == [[1.0, 0.0]]


def test_lost_estimate_vents_until_the_reading_is_down_and_a_dropout_keeps_it_venting():
    sup = Supervisor(SupervisorSettings(p_max=45e3, vent_margin=None, missing_is_limit=False, lost_release=1e3), n=2)
    pump = np.array([[1.0, 0.0], [1.0, 0.0]])
    out = sup.apply(0.0, pump, [30e3, 30e3], lost=[True, False])
    assert out.tolist() == [[0.0, 1.0], [1.0, 0.0]] and sup.lost.tolist() == [True, False]
    # the flag need not persist: the vent holds until the reading is down, a dropout included
    for t, p in ((0.01, 20e3), (0.02, np.nan), (0.03, 1.2e3)):
        out = sup.apply(t, pump, [p, 30e3], lost=[False, False])
        assert out[0].tolist() == [0.0, 1.0] and not sup.released.any()
    out = sup.apply(0.04, pump, [0.9e3, 30e3], lost=[False, False])
    # the release step still sends the safe command (its command came from the lost estimate)
    assert out[0].tolist() == [0.0, 1.0] and sup.released.tolist() == [True, False]
    assert not sup.lost.any()
    assert sup.apply(0.05, pump, [0.9e3, 30e3]).tolist() == pump.tolist()
    assert sup.counts["lost_estimate"] == 5
    assert [(e.t, e.cause) for e in sup.events] == [(0.0, "lost_estimate"), (0.04, "lost_estimate_released")]


def test_supervisor_refuses_a_stretch_limit_or_release_out_of_range():
    with pytest.raises(ValueError, match=r"supervisor.stretch_max = 1.0 is out of range \(1.0, 20.0\]"):
        SupervisorSettings(stretch_max=1.0).validate()
    with pytest.raises(ValueError, match=r"supervisor.lost_release = -1.0 is out of range"):
        SupervisorSettings(lost_release=-1.0).validate()


# --- the bank ------------------------------------------------------------------------------------
def test_x_top_is_the_nominal_tables_top_for_nominal_factors_and_moves_with_the_dead_volume(robot):
    _, model = robot
    W, k, c = ca.SX.sym("W"), ca.SX.sym("k"), ca.SX.sym("c")
    top = ca.Function("top", [W, k, c], [model.x_top_expr(W, k, c)])
    # just inside the top (the tables are zero outside their grid)
    eps = 1e-6
    out = ca.Function("out", [W, k, c], list(model.outputs_expr(model.x_top_expr(W, k, c) - eps, W, k, c, iters=30)))
    for w in (0.05, 0.2, 0.5):
        assert float(top(w, 1.0, 1.0)) == pytest.approx(model.x_max, abs=1e-12)
        h_top = float(model.tables.H_table(ca.vertcat(model.x_max - eps, w)))
        assert h_top > 0
        # at x_top a chamber of factors (k, c) has the shape of the tables' top at W / k
        for kk, cc in ((1.0, 1.5), (1.2, 0.8), (0.8, 1.3)):
            h = float(out(w * kk, kk, cc)[0])
            assert h == pytest.approx(h_top, rel=1e-4)
        # a larger dead volume holds more gas at the same shape
        assert float(top(w, 1.0, 1.5)) > float(top(w, 1.0, 1.0)) > float(top(w, 1.0, 0.8))


def test_bank_reports_a_factor_at_its_bound_as_lost_and_does_not_pin_a_large_dead_volume(robot):
    _, model = robot
    bank = ChamberEKFBank(model, 3, ChamberEKFSettings(sample_period=0.01, sensor_range=50e3))
    w = np.zeros((2, 3))
    W = np.full(3, 0.2)
    est = bank.step(np.zeros(3), w, W)
    assert not est["lost"].any() and not est["beyond"].any()
    bank.X[1, 0] = B_RANGE[0]  # the flow factor at its floor
    # chamber 2: a large dead volume holding more gas than the nominal tables' top (the state is
    # y = (x + 1) / c)
    bank.X[3, 2] = 1.5
    x_big = model.x_max + 0.1
    bank.X[0, 2] = (x_big + 1) / 1.5
    est = bank.step(np.full(3, np.nan), w, W)  # predict only: nothing moves the states
    assert est["lost"].tolist() == [True, False, False]
    assert est["x"][2] == pytest.approx(x_big, rel=1e-9)  # not clipped at the nominal top
    assert bank.stats()["factor_at_bound"] == 1 and bank.stats()["beyond_tables"] == 0
    assert est["lam"].shape == (3,) and np.all(est["lam"] >= 1.0 - 1e-9)


def test_bank_floor_is_a_pressure_floor_so_a_small_dead_volume_vents_with_its_readings(robot):
    _, model = robot
    pe = model.actuator.p_env
    bank = ChamberEKFBank(model, 3, ChamberEKFSettings(sample_period=0.01, sensor_range=50e3))
    w = np.vstack([np.zeros(3), np.ones(3)])  # venting
    W = np.full(3, 0.2)
    bank.step(np.zeros(3), w, W)
    # dead volumes below, at and above nominal, each chamber at ambient (y = 1: gas x + 1 = c)
    bank.X[3] = [0.85, 1.0, 1.2]
    bank.X[0] = 1.0
    for _ in range(20):
        est = bank.step(np.zeros(3), w, W)
    # a floor on the gas mass x >= -0.04 held the first at p_env (0.96 / 0.85 - 1) = 13 kPa
    assert np.abs(est["p"]).max() < 300.0
    assert est["x"][0] == pytest.approx(bank.X[3, 0] - 1.0, abs=5e-3) and est["x"][0] < -0.1
    assert not est["lost"].any()
    # the floor itself: 4 % of an atmosphere below ambient, whatever the dead volume (predict only)
    bank.X[0] = 0.9
    bank.step(np.full(3, np.nan), np.zeros((2, 3)), W)
    assert bank.X[0] == pytest.approx(np.full(3, 0.96), abs=1e-12)
    for i in range(3):
        p = float(model.out(ChamberEKFBank.gas_mass(bank.X[:, i]), W[i], bank.X[2, i], bank.X[3, i])[1])
        assert p == pytest.approx(-0.04 * pe, rel=1e-6)


# --- the loop ------------------------------------------------------------------------------------
def test_robot_loop_vents_a_lost_chamber_then_restarts_its_filter_from_the_flat_reading(robot):
    d, model = robot
    n = 3
    # instant valves: the pumped chambers' filters take the pump as acting in the period it is sent
    bank = ChamberEKFBank(model, n, ChamberEKFSettings(sample_period=0.01, sensor_range=50e3, valve_delay=0.0))
    ms = RobotMPCSettings(sample_period=0.01, p_max=45e3)
    loop = RobotLoop(d, model, bank, RobotNMPC(model, n, ms), robot_supervisor(45e3, n, plan_period=ms.dt),
                     {0: ((0.0, U.mm(5.0), 0.0, 0.0),)}, valve_min_on=0.0)
    assert loop.supervisor.settings.stretch_max == d.max_stretch  # the design's limit by default
    loop.tick(0.0, np.zeros(n))
    bank.X[1, 1] = B_RANGE[0] - 0.1  # chamber 1's filter leaves its range
    # chambers 0 and 2 are pumped but read nothing (a dead pump): their flow factors fall to the floor
    # in a step, they are lost, and released at once (flat: nothing to vent), their filters restarted
    a, o = loop.tick(0.01, np.array([0.0, 20e3, 0.0]))
    assert a[1] == 0.0 and o[1] == 1.0 and loop.estimate["lost"][1]
    a, o = loop.tick(0.02, np.array([0.0, 5e3, 0.0]))
    assert a[1] == 0.0 and o[1] == 1.0  # still venting: the reading is not down yet
    a, o = loop.tick(0.03, np.array([0.0, 0.5e3, 0.0]))
    assert a[1] == 0.0 and o[1] == 1.0
    # restarted at rest from the reading, factors at their priors
    assert bank.X[:, 1] == pytest.approx(bank.rest_state(np.full(n, 0.5e3))[:, 1])
    ev = [(e.t, e.chamber, e.cause) for e in loop.supervisor.events]
    assert [e for e in ev if e[1] == 1] == [(0.01, 1, "lost_estimate"), (0.03, 1, "lost_estimate_released")]
    assert [e for e in ev if e[1] != 1] == [(0.02, 0, "lost_estimate"), (0.02, 2, "lost_estimate"),
                                            (0.02, 0, "lost_estimate_released"), (0.02, 2, "lost_estimate_released")]
    assert loop.stats()["lost_estimate_steps"] == 3 + 2


@pytest.mark.slow
def test_structured_robot_with_the_sensor_delay_modelled_does_not_run_a_membrane_away():
    """Seed 0 of robot_bending on the structured rig with the filters' 3 ms sensor delay: one chamber's filter
    read its membrane on the near branch while it grew past 20 mm at a falling pressure, pump on (max
    stretch 13 over the run). The lost-estimate vent then caught it; with the gas-mass floor a pressure
    floor (a floor in the gas mass held a chamber of a small estimated dead volume kilopascals above its
    readings and threw its factors to their bounds) no filter is lost at all."""
    d = RobotDesign(n_layers=3).validate()
    tg = {k: ((0.0, U.mm(6.0), 0.0, 0.0),) for k in range(3)}
    s = RobotSettings(design=d, pneumatics=RobotPneumatics(sensor_range=50e3, pressure_limit=45e3),
                      mode="closed_loop", targets=tg, valve_min_on=0.002, valve_delay=0.005, sensor_delay=0.003).validate()
    rig = RobotRigSettings(modulus_spread=0.15, flow_scale=0.9, V0_scale=1.2, noise_std=200.0, seed=0,
                           valve_delay=0.005, valve_min_on=0.002, compressor_tilt=0.2, sensor_tau=0.003)
    run = run_closed_loop(s, tg, 2.5, "mpc", rig=rig, mpc=RobotMPCSettings(horizon=15, dt=0.02))
    assert run.status == "ok"
    assert run.lost_estimate_steps == 0
    assert run.lam.max() < d.max_stretch
    late = run.t >= 2.0
    assert np.abs(run.h[late] - run.h_ref[late]).max() < U.mm(1.5)


@pytest.mark.slow
def test_default_robot_rig_start_up_vents_no_chamber_for_a_lost_estimate():
    """scenarios/daemon_robot.toml (3 layers on the cap rig with scalar mismatches, 6 mm straight,
    3 mm/s target ramps) vented chambers at the onset of pumping, C2 and C3 at 0.31 s on the daemon:
    their filters' dead-volume factors fell below 0.96, where the bank's gas-mass floor was a pressure
    floor kilopascals above the readings. Its first second, without the NMPC's wall-time budget (so
    the run does not depend on the machine): no filter lost, no vent."""
    from dataclasses import replace

    from hbma_ctrl.app.scenario import load_scenario
    from hbma_ctrl.app.schema import RigTable

    scn = load_scenario(ROOT / "scenarios" / "daemon_robot.toml")
    s = scn.role("robot")
    rig = RigTable.model_validate(scn.sections["rig"]).to_robot_rig()
    mpc = replace(RobotMPCSettings(horizon=s.mpc_horizon, dt=s.mpc_dt, budget=0.0), w_slack=s.mpc_w_slack)
    run = run_closed_loop(s, s.targets, 1.0, "mpc", scn.pneumatics, rig, mpc)
    assert run.status == "ok"
    assert run.lost_estimate_steps == 0, run.events


# --- the daemon's view ---------------------------------------------------------------------------
def test_daemon_logs_each_supervisor_episode_once_with_the_chambers_name():
    from hbma_ctrl.system.base import SupervisorEpisodes

    sup = Supervisor(SupervisorSettings(p_max=45e3, guard_margin=1e3, vent_margin=None, missing_is_limit=False,
                                        stretch_max=4.0), n=2)
    ep = SupervisorEpisodes(sup, ("A1", "A2"))
    pump = np.array([[1.0, 0.0], [1.0, 0.0]])
    taken = []
    for t, p0 in ((0.0, 30e3), (0.01, 44.5e3), (0.02, 44.6e3), (0.03, 44.7e3), (0.04, 30e3), (0.05, 44.5e3)):
        sup.apply(t, pump, [p0, 10e3], stretch=[1.5, 4.2], lost=[False, t == 0.03])
        taken.append(ep.take())
    # A1's guard acts in three ticks in a row, then again after a tick without: two episodes;
    # A2's stretch guard acts every tick until its lost estimate vents it: one episode, then the vent
    assert taken[0] == [("supervisor", "A2: stretch_guard (stretch=4.20)")]
    assert taken[1] == [("supervisor", "A1: guard (p=44500 Pa)")]
    assert taken[2] == []
    assert taken[3] == [("supervisor", "A2: lost_estimate (the estimate left its model: venting)")]
    assert taken[4] == []
    assert taken[5] == [("supervisor", "A1: guard (p=44500 Pa)")]


def test_loop_primes_the_nmpc_at_the_rest_gas_mass_not_the_filters_state(robot):
    """The bank's state is y = (x + 1) / c; the NMPC works in the gas mass x: priming hands it x."""
    d, model = robot
    n = 3
    bank = ChamberEKFBank(model, n, ChamberEKFSettings(sample_period=0.01, sensor_range=50e3))
    ctrl = RobotNMPC(model, n, RobotMPCSettings(sample_period=0.01, p_max=45e3))
    seen = {}
    ctrl.prime = lambda x0, *a, **k: seen.setdefault("x0", np.array(x0, dtype=float))
    loop = RobotLoop(d, model, bank, ctrl, robot_supervisor(45e3, n), {0: ((0.0, U.mm(5.0), 0.0, 0.0),)})
    p = np.array([0.0, 1e3, 5e3])
    loop.prime(p)
    assert seen["x0"] == pytest.approx(p / model.actuator.p_env, abs=1e-12)
