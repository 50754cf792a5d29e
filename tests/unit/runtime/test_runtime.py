"""The runtime layer: one supervisor (guard, vent, fallback), bounded step statistics, the loops."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from hbma_ctrl.controllers.baselines import PIDController, PIDSettings
from hbma_ctrl.controllers.mpc_settings import timing_stats
from hbma_ctrl.controllers.robot_mpc import RobotMPCSettings, RobotNMPC
from hbma_ctrl.estimators.robot_ekf import ChamberEKFBank, ChamberEKFSettings
from hbma_ctrl.system.sections import RobotSettings
from hbma_ctrl.core import units as U
from hbma_ctrl.core.interfaces import (
    SAFE_COMMAND,
    STEP_OK,
    Command,
    ControllerBase,
    Estimate,
    EstimatorBase,
    Reference,
    RobotControllerBase,
    SolveStatus,
    StepStatus,
)
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.robot.design import RobotDesign, RobotPneumatics
from hbma_ctrl.robot.rig import RobotRig, RobotRigSettings
from hbma_ctrl.runtime.chamber import ChamberLoop, chamber_supervisor
from hbma_ctrl.runtime.robot import RobotLoop, robot_supervisor
from hbma_ctrl.runtime.safety import Supervisor, SupervisorSettings
from hbma_ctrl.runtime.stats import StepStats
from hbma_ctrl.sim.rig import Rig, RigSettings

PUMP = np.array([1.0, 1.0, 0.0])


def est(h=5e-3, p=15e3, F=0.0, t=0.0):
    return Estimate(t=t, h1=h, h2=0.0, h=h, F=F, p=p, flags=frozenset())


class FakeController(ControllerBase):
    """Pumps with a known 5-row plan; fails (reports or raises) inside a time window."""

    reports_failures = True

    def __init__(self, fail=(1.0, 2.0), mode="report"):
        self.fail, self.mode = fail, mode
        self.settings = PIDSettings(p_max=35e3, guard_margin=1e3)
        self.plan = None
        self.applied_cmds: list = []

    def step(self, t, estimate, reference):
        if self.fail[0] <= t <= self.fail[1]:
            if self.mode == "raise":
                raise RuntimeError("solver exploded")
            self.step_status = StepStatus(SolveStatus.FAILED, "fake")
            self.plan = None
            return SAFE_COMMAND
        self.step_status = STEP_OK
        self.plan = np.array([[1.0, 1.0, 0.0], [0.9, 0.9, 0.0], [0.8, 0.8, 0.0], [0.7, 0.7, 0.0], [0.6, 0.6, 0.0]])
        return Command(*self.plan[0])

    def applied(self, cmd):
        self.applied_cmds.append(cmd)

    def stats(self):
        return {"variant": "fake", "horizon": 5, "target_clipped_steps": 0}


# --- supervisor ----------------------------------------------------------------------------------
def test_guard_cuts_the_pump_then_vents_near_the_limit():
    sup = Supervisor(SupervisorSettings(p_max=35e3, guard_margin=1e3, vent_margin=0.5e3))
    assert list(sup.apply(0.0, PUMP, 30e3)) == [1.0, 1.0, 0.0]
    assert list(sup.apply(0.1, PUMP, 34.2e3)) == [0.0, 0.0, 0.0]  # in the guard band: pump cut
    assert list(sup.apply(0.2, PUMP, 34.8e3)) == [0.0, 0.0, 1.0]  # within the vent margin: vent
    assert list(sup.apply(0.3, PUMP, float("nan"))) == [0.0, 0.0, 1.0]  # lost estimate: at the limit
    assert sup.counts["guard"] == 3
    ev = list(sup.events)
    assert [(e.t, e.chamber, e.cause) for e in ev] == [(0.1, 0, "guard"), (0.2, 0, "guard"), (0.3, 0, "guard")]


def test_robot_interlock_cuts_supply_only_and_ignores_dropouts():
    sup = robot_supervisor(45e3, 3, interlock_margin=1e3)
    cmd = np.array([[1.0, 0.0], [1.0, 0.0], [0.5, 0.2]])
    out = sup.apply(1.0, cmd, np.array([44.5e3, np.nan, 10e3]))
    assert out.tolist() == [[0.0, 0.0], [1.0, 0.0], [0.5, 0.2]]
    assert sup.counts["guard"] == 1 and sup.events[0].chamber == 0 and sup.events[0].t == 1.0


def test_zero_target_vents_and_logs_once():
    sup = robot_supervisor(45e3, 3)
    for k in range(3):
        out = sup.apply(0.01 * k, np.full((3, 2), 0.5), np.zeros(3), target=np.array([0.0, 5e-3, 2e-5]))
        assert out.tolist() == [[0.0, 1.0], [0.5, 0.5], [0.0, 1.0]]
    assert sup.counts["vent"] == 6
    assert [(e.chamber, e.cause) for e in sup.events] == [(0, "vent"), (2, "vent")]


@pytest.mark.parametrize("mode", ["report", "raise"])
def test_fallback_replays_the_plan_then_the_safe_command(mode):
    ctrl = FakeController(fail=(0.1, 1.0), mode=mode)
    loop = ChamberLoop(None, ctrl, chamber_supervisor(ctrl.settings, fallback_plan_steps=3))
    e = est(p=10e3)
    assert loop.control(0.0, e, Reference(6e-3)).as_array().tolist() == [1.0, 1.0, 0.0]
    cmds = [loop.control(0.02 * (k + 5), e, Reference(6e-3)).as_array() for k in range(5)]
    assert np.allclose(cmds[:3], [[0.9, 0.9, 0.0], [0.8, 0.8, 0.0], [0.7, 0.7, 0.0]])  # plan rows 1..3
    assert cmds[3].tolist() == [0.0, 0.0, 1.0] and cmds[4].tolist() == [0.0, 0.0, 1.0]
    st = loop.stats()
    assert st["fallbacks"] == 5
    assert st["fallback_detail"]["shifted_plan"] == 3 and st["fallback_detail"]["safe_command"] == 2
    ev = loop.events()
    assert [e.cause for e in ev] == ["shifted_plan"] * 3 + ["safe_command"] * 2
    assert [e.t for e in ev] == pytest.approx([0.1, 0.12, 0.14, 0.16, 0.18])
    assert ("solver_failed" if mode == "report" else "exception") in ev[0].detail
    assert ctrl.applied_cmds[-1] == SAFE_COMMAND  # the controller is told what was sent
    # recovery: the next good step resets the chain
    assert loop.control(1.5, e, Reference(6e-3)).as_array().tolist() == [1.0, 1.0, 0.0]


def test_fallback_per_chamber_on_arrays():
    sup = Supervisor(SupervisorSettings(vent_margin=None, fallback_plan_steps=10, plan_period=0.02), n=2)
    plan = np.stack([np.column_stack([np.linspace(1, 0.6, 5), np.zeros(5)])] * 2, axis=1)  # (5, 2, 2)
    sup.apply(0.0, plan[0], np.zeros(2), ok=True, plan=plan)
    out = sup.apply(0.01, np.zeros((2, 2)), np.zeros(2), ok=np.array([True, False]))
    assert out[0].tolist() == [0.0, 0.0] and out[1].tolist() == pytest.approx([1.0, 0.0])  # row 0 still due
    out = sup.apply(0.02, np.zeros((2, 2)), np.zeros(2), ok=np.array([True, False]))
    assert out[1].tolist() == pytest.approx([0.9, 0.0])
    out = sup.apply(0.2, np.zeros((2, 2)), np.zeros(2), ok=np.array([True, False]))
    assert out[1].tolist() == [0.0, 1.0]  # the plan ran out: safe command
    assert sup.failed_steps == 3 and {e.chamber for e in sup.events} == {1}


def test_settings_are_validated():
    with pytest.raises(ValueError, match="guard_margin"):
        SupervisorSettings(guard_margin=-1.0).validate()
    with pytest.raises(ValueError, match="fallback_plan_steps"):
        SupervisorSettings(fallback_plan_steps=-1).validate()


# --- stats ---------------------------------------------------------------------------------------
def test_stats_equal_numpy_when_the_buffer_holds_everything():
    x = np.random.default_rng(0).lognormal(size=1000)
    st = StepStats(1000)
    for v in x:
        st.add(v)
    assert st.summary() == timing_stats(list(x))
    assert st.summary()["median"] == float(np.median(x)) and st.summary()["p99"] == float(np.percentile(x, 99))
    assert StepStats(5).summary()["n"] == 0


def test_stats_stay_bounded_over_1e5_ticks():
    st = StepStats(256)
    for v in range(1000):
        st.add(float(v))
    tracemalloc.start()
    base = tracemalloc.take_snapshot()
    for v in range(100_000):
        st.add(float(v % 977))
    grown = sum(s.size_diff for s in tracemalloc.take_snapshot().compare_to(base, "filename"))
    tracemalloc.stop()
    assert grown < 64 * 1024
    s = st.summary()
    assert s["n"] == 101_000 and s["max"] == 999.0 and st.values().size == 256
    assert s["median"] == float(np.median(st.values()))


# --- loops ---------------------------------------------------------------------------------------
class _Oracle(EstimatorBase):
    """Estimator stub: the rig's true state (keeps the short run independent of filter tuning)."""

    def __init__(self, rig):
        self.rig = rig

    def step(self, t, z, cmd):
        tr = self.rig.truth()
        return Estimate(t=t, h1=tr["h1"], h2=tr["h2"], h=tr["h"], F=tr["F"], p=tr["p"])


def test_chamber_loop_ticks_on_a_short_run():
    act, pn = Actuator(), Pneumatics()
    rig = Rig(act, pn, Platform(load=0.0), RigSettings(seed=1))
    ctrl = PIDController(settings=PIDSettings())
    loop = ChamberLoop(_Oracle(rig), ctrl, reference=lambda t: 3e-3, every=1)
    for k in range(100):
        cmd = loop.tick(k * 0.02, rig.measure())
        assert isinstance(cmd, Command) and 0.0 <= cmd.speed <= 1.0
        rig.apply(cmd)
    st = loop.stats()
    assert st["steps"] == 100 and st["fallbacks"] == 0 and np.isfinite(st["solve_ms_median"])
    assert loop.estimate.h > 1e-3


@pytest.fixture(scope="module")
def robot(robot_bank):
    d = RobotDesign(n_layers=1).validate()
    s = RobotSettings(design=d, pneumatics=RobotPneumatics()).validate()
    assert s.pneumatics.topology == robot_bank.topology
    return d, s, robot_bank  # make_model(d, Pneumatics(), s.pneumatics.topology)


def test_robot_loop_ticks_on_a_short_run(robot):
    d, s, model = robot
    rs = RobotRigSettings().validate()
    n = 3
    rig = RobotRig(d, Pneumatics(), s.pneumatics.sensor_range, s.pneumatics.topology, rs, ())
    bank = ChamberEKFBank(model, n, ChamberEKFSettings(sample_period=rs.sample_period,
                                                       noise_std=max(rs.noise_std, 1.0),
                                                       sensor_range=s.pneumatics.sensor_range))
    ms = RobotMPCSettings(sample_period=rs.sample_period, p_max=s.pneumatics.pressure_limit)
    ctrl = RobotNMPC(model, n, ms)
    targets = {k: ((0.0, U.mm(5.0), 0.0, 0.0),) for k in range(d.n_layers)}
    loop = RobotLoop(d, model, bank, ctrl, robot_supervisor(s.pneumatics.pressure_limit, n, plan_period=ms.dt),
                     targets)
    for _ in range(40):
        a, o = loop.tick(rig.t, rig.measure())
        assert a.shape == (n,) and o.shape == (n,) and np.all((a >= 0) & (a <= 1))
        rig.apply(loop.valve_commands)
    st = loop.stats()
    assert st["step_ms"]["n"] == 40 and st["fallbacks"] == 0
    assert loop.estimate["h"].shape == (n,) and np.all(loop.estimate["h"] > 0.5e-3)
    # the last tick's controller part, split up (what a slow tick's report names), within its total
    parts = loop.last_parts
    assert set(parts) == {"targets", "controller", "supervisor", "valves"} and min(parts.values()) >= 0.0
    assert sum(parts.values()) <= loop.last_timing[2] + 1e-9
    nm = ctrl.last_parts
    assert nm["iterations"] >= 1 and nm["data"] > 0.0 and nm["solve"] > 0.0 and nm["status"] == ctrl.status
    assert nm["data"] + nm["update"] + nm["solve"] <= parts["controller"] + 1e-9


@pytest.mark.slow
def test_robot_loop_with_a_minimum_opening_sends_realisable_duties_and_predicts_with_them(robot):
    """valve_min_on: every inlet and outlet duty sent is 0 or at least the minimum; the bank is told
    the supply the sent inlet gives (the decided one scaled by sent / decided inlet)."""
    d, s, model = robot
    rs = RobotRigSettings(valve_min_on=0.002).validate()
    n = 3
    rig = RobotRig(d, Pneumatics(), s.pneumatics.sensor_range, s.pneumatics.topology, rs, ())
    bank = ChamberEKFBank(model, n, ChamberEKFSettings(sample_period=rs.sample_period,
                                                       sensor_range=s.pneumatics.sensor_range))
    ms = RobotMPCSettings(sample_period=rs.sample_period, p_max=s.pneumatics.pressure_limit)
    loop = RobotLoop(d, model, bank, RobotNMPC(model, n, ms),
                     robot_supervisor(s.pneumatics.pressure_limit, n, plan_period=ms.dt),
                     {k: ((0.0, U.mm(5.0), 0.0, 0.0),) for k in range(d.n_layers)}, valve_min_on=0.002)
    small = 0
    for _ in range(120):
        a, o = loop.tick(rig.t, rig.measure())
        U_sent = loop.valve_commands
        duties = U_sent[1:3]
        assert np.all((duties == 0.0) | (duties >= 0.2 - 1e-12))
        decided = model.valve_inputs(a, o, loop.estimate["p"])
        small += int(np.sum((decided[1:3] > 0) & (decided[1:3] < 0.2)))
        supply = loop._w_prev[0]
        expect = np.where(decided[1] > 0, a * U_sent[1] / np.where(decided[1] > 0, decided[1], 1.0), 0.0)
        assert np.allclose(supply, np.where(a > 1e-6, expect, supply), atol=1e-9)
        assert np.array_equal(loop._w_prev[1], U_sent[2])
        rig.apply(U_sent)
    assert small > 0  # the loop did ask for duties the valves cannot open for (the test exercised them)
    assert np.all(loop.estimate["h"] > 0.5e-3)


def test_robot_loop_falls_back_when_the_qp_fails(robot):
    d, s, model = robot
    n = 3
    bank = ChamberEKFBank(model, n, ChamberEKFSettings(sample_period=0.01, sensor_range=s.pneumatics.sensor_range))
    ctrl = RobotNMPC(model, n, RobotMPCSettings())
    sup = robot_supervisor(s.pneumatics.pressure_limit, n, plan_period=0.02, fallback_plan_steps=2)
    loop = RobotLoop(d, model, bank, ctrl, sup, {k: ((0.0, U.mm(5.0), 0.0, 0.0),) for k in range(d.n_layers)})
    loop.tick(0.0, np.zeros(n))
    ctrl.step = lambda *a, **k: (_ for _ in ()).throw(RuntimeError("qp"))  # every later solve raises
    outs = [loop.tick(0.01 * (k + 1), np.zeros(n)) for k in range(4)]
    assert loop.stats()["fallbacks"] == 4
    assert np.all(outs[-1][0] == 0.0) and np.all(outs[-1][1] == 1.0)  # safe: supply off, outlets open
    # (pumped while reading nothing, the filters also leave their range: lost-estimate events, not these)
    causes = [e.cause for e in sup.events if e.chamber == 0 and not e.cause.startswith("lost_estimate")]
    assert causes == ["shifted_plan", "shifted_plan", "safe_command", "safe_command"]


class _TargetRecorder(RobotControllerBase):
    """A pressure-PID-like controller (the loop's non-NMPC path) that records the targets it is given."""

    feedback = "readings"

    def __init__(self, n):
        self.n, self.hrefs = n, []

    def step(self, z, W, href):
        self.hrefs.append(np.array(href, dtype=float))
        return np.zeros(self.n), np.zeros(self.n)


def test_robot_targets_move_no_faster_than_target_rate_and_zero_targets_vent_at_once(robot):
    d, s, model = robot
    n, Ts, rate = 3, 0.01, 3e-3
    bank = ChamberEKFBank(model, n, ChamberEKFSettings(sample_period=Ts, sensor_range=s.pneumatics.sensor_range))
    ctrl = _TargetRecorder(n)
    pose = lambda c: {0: ((0.0, U.mm(c), 0.0, 0.0),)}  # noqa: E731
    loop = RobotLoop(d, model, bank, ctrl, robot_supervisor(s.pneumatics.pressure_limit, n), pose(5.0),
                     target_rate=rate)
    for k in range(250):
        loop.tick(k * Ts, np.zeros(n))
    loop.set_targets(pose(2.0))
    for k in range(250, 400):
        loop.tick(k * Ts, np.zeros(n))
    loop.set_targets(pose(0.0))
    loop.tick(400 * Ts, np.zeros(n))
    h = np.array(ctrl.hrefs)
    # from the estimate at rest (flat), never more than rate x period a tick in either direction
    assert np.all(np.abs(np.diff(h[:400], axis=0)) <= rate * Ts + 1e-12)
    assert h[0].max() <= rate * Ts + 1e-12
    # 5 mm reached after 5 / 3 s, then 2 mm 1 s after that change
    np.testing.assert_allclose(h[200], U.mm(5.0), atol=1e-12)
    assert h[260].min() > U.mm(4.0)  # 0.1 s after the change: still on the way down
    np.testing.assert_allclose(h[399], U.mm(2.0), atol=1e-12)
    assert np.all(h[400] == 0.0)  # a zero target (vent) applies at once
    np.testing.assert_allclose(loop.href, h[400])


def test_robot_target_rate_must_be_finite_and_non_negative(robot):
    d, s, model = robot
    bank = ChamberEKFBank(model, 3, ChamberEKFSettings(sample_period=0.01, sensor_range=s.pneumatics.sensor_range))
    for bad in (-1e-3, float("nan"), "fast"):
        with pytest.raises(ValueError, match="target_rate"):
            RobotLoop(d, model, bank, _TargetRecorder(3), robot_supervisor(45e3, 3),
                      {0: ((0.0, U.mm(5.0), 0.0, 0.0),)}, target_rate=bad)


class _Counting(PIDController):
    """A PID (20 ms sample period) that counts its steps."""

    def __init__(self):
        super().__init__(settings=PIDSettings())
        self.steps = 0

    def step(self, t, estimate, reference, preview=None):
        self.steps += 1
        return super().step(t, estimate, reference)


class _Reading(EstimatorBase):
    def step(self, t, measurement, applied_command):
        return Estimate(t=t, h1=0.0, h2=0.0, h=0.0, F=0.0, p=float(measurement))


def test_chamber_loop_without_every_runs_the_controller_at_its_own_sample_period():
    ctrl = _Counting()
    loop = ChamberLoop(_Reading(), ctrl, reference=3e-3)
    for k in range(10):
        loop.tick(0.01 * k, 5e3)  # 10 ms ticks under a 20 ms controller: every second tick
    assert loop.every == 2 and ctrl.steps == 5


def test_chamber_loop_without_every_names_both_periods_when_they_do_not_divide():
    loop = ChamberLoop(_Reading(), _Counting(), reference=3e-3)
    loop.tick(0.0, 5e3)
    with pytest.raises(ValueError, match=r"_Counting sample_period = 20 ms must be a whole multiple of the tick "
                                         r"period \(the time between the first two ticks\) = 15 ms"):
        loop.tick(0.015, 5e3)
