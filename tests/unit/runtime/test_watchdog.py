"""The safety monitor: each fault kind is found within the delay its module doc states, each is
reported once and latches the safe state, and a normal closed loop (EKF + RTI MPC on the mismatched
sim rig, as the controller scene builds it) raises no fault over several seeds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hbma_ctrl.controllers.mpc import NMPC
from hbma_ctrl.estimators.ekf import EKF, EKFSettings
from hbma_ctrl.app.daemon.faults import FaultSpec, FaultyRig
from hbma_ctrl.system.sim_rig import SimRig
from hbma_ctrl.system.rigio import Readings, RigLinkError, safe_u
from hbma_ctrl.app.schema import parse_role
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.runtime.chamber import ChamberLoop, chamber_supervisor
from hbma_ctrl.runtime.watchdog import FAULT_KINDS, MonitorSettings, SafetyMonitor
from hbma_ctrl.sim.rig import RigSettings

ACT, PN = Actuator(), Pneumatics()
S = MonitorSettings()
TS = S.sample_period


def open_loop(spec, load=0.0, speed=1.0, T=3.0, seed=1, settings=None):
    """Pump at ``speed`` (inlet open, outlet closed) on the faulty sim rig; the first faults found and
    their delay in periods from the fault's start (None when nothing is found in T s)."""
    rig = FaultyRig(SimRig.chamber(ACT, PN, Platform(load=load), RigSettings(seed=seed)), [spec])
    mon = SafetyMonitor(settings or MonitorSettings(), 1)
    u, sent = np.array([[speed], [1.0], [0.0]]), safe_u(1)
    for _ in range(int(round(T / TS))):
        r = rig.read()
        found = mon.check(r.t, r, sent)
        if found:
            return found, round((r.t - spec.start) / TS)
        rig.write(u)
        sent = u
    return [], None


def pump_bound(speed, inlet=1.0):
    return math.ceil(S.pump_effort / (speed * inlet) / TS - 1e-6)


CASES = [  # (fault, load kg, pump speed, kind found, documented delay bound in periods)
    (FaultSpec("dropout", None, 1.0), 0.0, 1.0, "sensor_missing", S.nan_periods - 1),
    (FaultSpec("frozen", None, 1.0), 0.0, 1.0, "sensor_frozen", S.stale_periods - 1),
    (FaultSpec("out_of_range", None, 1.0, value=-50e3), 0.0, 1.0, "out_of_range", S.range_periods - 1),
    (FaultSpec("offset", None, 0.1, value=-8e3), 0.0, 0.3, "out_of_range", S.range_periods - 1),
    (FaultSpec("offset", None, 1.0, value=15e3), 0.4, 1.0, "over_pressure", 0),
    (FaultSpec("leak", None, 1.5, value=1.0), 0.0, 1.0, "leak", 10),  # a burst
    (FaultSpec("leak", None, 1.5, value=0.3), 0.4, 1.0, "leak", S.periods(S.leak_window)),
    (FaultSpec("leak", None, 1.5, value=0.3), 0.0, 1.0, "leak", S.periods(S.leak_window)),
    (FaultSpec("stuck_outlet", None, 1.5, value=1.0), 0.4, 0.3, "leak", 10),
    (FaultSpec("pump_failure", None, 0.0), 0.0, 1.0, "pump_failure", pump_bound(1.0)),
    (FaultSpec("pump_failure", None, 0.0), 0.4, 0.3, "pump_failure", pump_bound(0.3)),
    (FaultSpec("stuck_inlet", None, 0.0, value=0.0), 0.0, 1.0, "pump_failure", pump_bound(1.0)),
]


@pytest.mark.parametrize("spec,load,speed,kind,bound", CASES,
                         ids=[f"{c[0].kind}-{c[0].value:g}-{c[1]:g}kg-{c[2]:g}" for c in CASES])
def test_each_fault_is_found_within_its_documented_delay(spec, load, speed, kind, bound):
    found, delay = open_loop(spec, load, speed)
    assert [f.kind for f in found] == [kind], found
    assert found[0].chamber == 0
    assert delay is not None and 0 <= delay <= bound, (delay, bound)


@pytest.mark.slow
def test_without_a_fault_the_open_loop_inflation_raises_nothing():
    for load in (0.0, 0.4):
        assert open_loop(FaultSpec("dropout", None, 99.0), load, 1.0, T=3.0) == ([], None)


def test_no_leak_test_above_leak_p_max():
    """The burst the default monitor finds in under 10 periods (at about 20 kPa) is left alone while the
    pressures compared are above leak_p_max, and found once they are all below it."""
    burst = FaultSpec("leak", None, 1.5, value=1.0)
    found, delay = open_loop(burst, settings=MonitorSettings(leak_p_max=15e3))
    assert [f.kind for f in found] == ["leak"] and delay > 10
    assert float(found[0].cause.split("to ")[1].split(" kPa")[0]) < 15.0


def readings(p, fresh=True):
    p = np.atleast_1d(np.asarray(p, dtype=float))
    return Readings(t=0.0, p=p, fresh=np.full(p.shape, fresh))


def test_over_pressure_at_once_and_reported_once_while_it_lasts():
    mon = SafetyMonitor(MonitorSettings(p_max=30e3, sensor_range=35e3), 2)
    u = safe_u(2)
    assert mon.check(0.0, readings([29.9e3, 1e3]), u) == [] and not mon.latched
    got = mon.check(0.01, readings([30e3, 1e3]), u)
    assert [(f.kind, f.chamber) for f in got] == [("over_pressure", 0)] and mon.latched
    assert mon.check(0.02, readings([31e3, 1e3]), u) == []
    assert mon.counts["over_pressure"] == 1
    mon.check(0.03, readings([20e3, 1e3]), u)
    assert len(mon.check(0.04, readings([30e3, 1e3]), u)) == 1  # a new episode is a new report
    assert mon.counts["over_pressure"] == 2


def test_gaps_in_the_readings_while_pumping_are_skipped_without_warnings():
    """Every other reading missing from the first check on: the trend tests run on what is there (a
    steady rise is no leak) and nothing warns."""
    import warnings

    mon = SafetyMonitor(MonitorSettings(nan_periods=3), 1)
    pump = np.array([[1.0], [1.0], [0.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        found = [f for k in range(100) for f in mon.check(k * TS, readings(np.nan if k % 2 else 100.0 * k), pump)]
        found += [f for k in range(100, 110) for f in mon.check(k * TS, readings(np.nan), pump)]
    assert [f.kind for f in found] == ["sensor_missing"]


def test_identical_values_on_fresh_packets_make_a_frozen_sensor():
    mon = SafetyMonitor(MonitorSettings(same_value_periods=5), 1)
    out = [mon.check(k * TS, readings(1234.5), safe_u(1)) for k in range(5)]
    assert [len(o) for o in out] == [0, 0, 0, 0, 1] and out[-1][0].kind == "sensor_frozen"
    off = SafetyMonitor(MonitorSettings(same_value_periods=None), 1)
    assert all(off.check(k * TS, readings(1234.5), safe_u(1)) == [] for k in range(50))


def test_overrun_after_the_set_number_of_missed_deadlines_in_a_row():
    mon = SafetyMonitor(MonitorSettings(missed_deadlines=3), 1)
    pattern = [True, True, False, True, True, True]
    found = [mon.check(k * TS, readings(1e3 + k), safe_u(1), deadline_missed=m) for k, m in enumerate(pattern)]
    assert [len(f) for f in found] == [0, 0, 0, 0, 0, 1]
    assert found[-1][0].kind == "overrun" and found[-1][0].chamber is None


def test_link_loss_and_other_external_causes_latch_the_safe_state():
    rig = FaultyRig(SimRig.chamber(ACT, PN, Platform(), RigSettings(seed=1)), [FaultSpec("link_loss", None, 0.02)])
    mon = SafetyMonitor(MonitorSettings(), 1)
    with pytest.raises(RigLinkError):
        for _ in range(5):
            mon.check(rig.t, rig.read(), safe_u(1))
            rig.write(safe_u(1))
    f = mon.raise_fault(rig.t, "link_loss", "no packet")
    assert mon.latched and f.kind == "link_loss" and f.t == pytest.approx(0.02) and mon.counts["link_loss"] == 1
    mon.reset()
    assert not mon.latched and mon.counts["link_loss"] == 0
    with pytest.raises(ValueError, match="allowed over_pressure"):
        mon.raise_fault(0.0, "gremlins", "?")
    assert set(mon.counts) == set(FAULT_KINDS)


def test_faults_are_per_chamber_on_a_robot_rig():
    from hbma_ctrl.system.sections import RobotSettings
    from hbma_ctrl.robot.design import RobotDesign, RobotPneumatics
    s = RobotSettings(design=RobotDesign(n_layers=1), pneumatics=RobotPneumatics()).validate()
    rig = FaultyRig(SimRig.robot(s), [FaultSpec("dropout", 2, 0.05)])
    mon = SafetyMonitor(MonitorSettings(p_max=45e3, sensor_range=50e3), 3)
    found = []
    for _ in range(20):
        r = rig.read()
        found += mon.check(r.t, r, safe_u(3))
        rig.write(safe_u(3))
    assert [(f.kind, f.chamber, round(f.t / TS)) for f in found] == [("sensor_missing", 2, 5 + S.nan_periods - 1)]


@pytest.mark.parametrize("field,value", [("p_max", 0.0), ("nan_periods", 0), ("same_value_periods", 1),
                                         ("pump_min", 0.0), ("leak_window", 0.01), ("vacuum_floor", 1e3)])
def test_bad_settings_name_the_field(field, value):
    with pytest.raises(ValueError, match=f"monitor.{field}"):
        MonitorSettings(**{field: value}).validate()


# --- closed loop ----------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def model(prediction_model):
    return prediction_model  # PredictionModel(ACT, PN)


STEPS = [[0.0, 2.0], [1.5, 8.0], [3.0, 5.0]]


def closed_loop(model, load, seed, T, faults=(), targets=STEPS):
    """EKF + RTI MPC + supervisor (as the controller scene builds them) on the (faulty) sim rig, with the
    monitor beside; stops at the first fault. Returns (faults, monitor)."""
    sec = parse_role("controller", {"targets_mm": targets})
    rs = RigSettings(seed=seed)
    rig = FaultyRig(SimRig.chamber(ACT, PN, Platform(load=load), rs), list(faults))
    est = EKF(ACT, PN, EKFSettings(sample_period=rs.sample_period, noise_std=rs.noise_std,
                                   sensor_range=rs.sensor_range))
    ctrl = NMPC(ACT, PN, sec.mpc, model=model)
    loop = ChamberLoop(est, ctrl, chamber_supervisor(ctrl.settings), reference=sec.reference,
                       every=int(round(sec.sample_period / rs.sample_period)))
    mon = SafetyMonitor(MonitorSettings(p_max=sec.p_max, sensor_range=rs.sensor_range,
                                        sample_period=rs.sample_period), 1)
    sent = safe_u(1)
    for _ in range(int(round(T / rs.sample_period))):
        r = rig.read()
        found = mon.check(r.t, r, sent)
        if found:
            return found, mon
        sent = loop.tick(r.t, float(r.p[0])).as_array()[:, None]
        rig.write(sent)
    return [], mon


@pytest.mark.slow
@pytest.mark.parametrize("load,seed", [(0.4, 1), (0.4, 2), (0.4, 3), (0.0, 1)])
def test_no_fault_over_a_normal_closed_loop(model, load, seed):
    """Steps 2 -> 8 -> 5 mm: nothing is reported, and the trend tests stay under half their thresholds."""
    found, mon = closed_loop(model, load, seed, 4.5)
    assert found == [] and not mon.latched
    assert mon.closest["leak_drop"] < 0.5 * S.leak_drop
    assert mon.closest["pump_rise"] > 2 * S.pump_rise


@pytest.mark.slow
def test_a_burst_during_a_closed_loop_step_is_found_as_a_leak(model):
    found, _ = closed_loop(model, 0.4, 1, 2.5, [FaultSpec("leak", None, 1.6, value=1.0)])
    assert [f.kind for f in found] == ["leak"]
    assert 0 <= round((found[0].t - 1.6) / TS) <= 10


@pytest.mark.slow
def test_no_fault_over_a_robot_closed_loop_past_the_limit_point():
    """The robot's NMPC drives every chamber of a layer to 7 mm, past the limit point (where pumping
    lowers the pressure): with leak_p_max at 0.8 x the model's limit-point pressure nothing is reported."""
    from dataclasses import replace

    from hbma_ctrl.controllers.robot_mpc import RobotMPCSettings, RobotNMPC
    from hbma_ctrl.estimators.robot_ekf import ChamberEKFBank, ChamberEKFSettings
    from hbma_ctrl.system.roles import make_model
    from hbma_ctrl.system.sections import RobotSettings
    from hbma_ctrl.core import units as U
    from hbma_ctrl.robot.design import RobotDesign, RobotPneumatics
    from hbma_ctrl.robot.rig import RobotRigSettings
    from hbma_ctrl.runtime.robot import RobotLoop, robot_supervisor

    d = RobotDesign(n_layers=1)
    s = RobotSettings(design=d, pneumatics=RobotPneumatics(pressure_limit=45e3)).validate()
    bank_model = make_model(d, PN, "per_chamber")
    rig = SimRig.robot(s, RobotRigSettings(seed=0))
    n, ts = rig.n, rig.sample_period
    bank = ChamberEKFBank(bank_model, n, ChamberEKFSettings(sample_period=ts, noise_std=200.0, sensor_range=50e3))
    ctrl = RobotNMPC(bank_model, n, replace(RobotMPCSettings(), sample_period=ts, p_max=45e3))
    loop = RobotLoop(d, bank_model, bank, ctrl, robot_supervisor(45e3, n, 1e3, plan_period=ctrl.s.dt),
                     {0: ((0.0, U.mm(7.0), 0.0, 0.0),)}, cautious=(0.75, 0.03, 0.3))
    cap = 0.8 * bank_model.peak(1e-3)[1]
    mon = SafetyMonitor(MonitorSettings(p_max=45e3, sensor_range=rig.sensor_range, sample_period=ts,
                                        leak_p_max=cap), n)
    sent, found = safe_u(n), []
    for _ in range(250):
        r = rig.read()
        found += mon.check(r.t, r, sent)
        loop.tick(r.t, r.p)
        sent = np.asarray(loop.valve_commands).reshape(3, n)
        rig.write(sent)
    assert found == []
    assert np.all(rig.truth()["h"] > bank_model.peak(1e-3)[0])  # the chambers did pass the limit point


@pytest.mark.parametrize("fall_to, found", [(20e3 * 0.65, False), (20e3 * 0.35, True)])
def test_leak_fraction_passes_a_fall_by_a_share_and_finds_one_that_empties_the_chamber(fall_to, found):
    """With leak_fraction 0.6 a 7 kPa fall from 20 kPa while pumping (35 %, what the robot's chambers
    show past their limit point) is no leak; a 13 kPa fall (65 %) is; the margins record the share."""
    s = MonitorSettings(leak_drop=5e3, leak_fraction=0.6, same_value_periods=None)
    mon = SafetyMonitor(s, 1)
    pump = np.array([[1.0], [1.0], [0.0]])
    p = np.concatenate([np.linspace(15e3, 20e3, 20), np.linspace(20e3, fall_to, 20), np.full(10, fall_to)])
    kinds = [f.kind for k, pk in enumerate(p) for f in mon.check(k * TS, readings(pk), pump)]
    assert kinds == (["leak"] if found else [])
    drop = 20e3 - fall_to
    assert mon.closest["leak_drop"] == pytest.approx(drop, rel=0.05)
    assert mon.closest["leak_fraction"] == pytest.approx(drop / 20e3, rel=0.05)
