"""The system layer: one chamber system for the scenes and the daemon, one lockstep driver, one rig interface."""

from __future__ import annotations

import re

import numpy as np
import pytest

from hbma_ctrl.app.daemon.build import build_runner
from hbma_ctrl.app.daemon.config import load_config
from hbma_ctrl.app.scenes.controller import closed_loop
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.sim.rig import RigSettings
from hbma_ctrl.system.chamber import ChamberSystem, chamber_system
from hbma_ctrl.system.robot import RobotSystem
from hbma_ctrl.system.run import run_lockstep
from hbma_ctrl.system.sections import ControllerSection, ReferenceProfile
from hbma_ctrl.system.sim_rig import SimRig
from checkout import ROOT

# whole closed loops and systems built from the scenario files: seconds each
pytestmark = pytest.mark.slow

PERIOD = 0.01


def _pid_section(calibrate: bool) -> ControllerSection:
    # a step at 0.05 s: a whole number of periods after the loop closes, whenever that is
    return ControllerSection(kind="pid", reference=ReferenceProfile(points=((0.0, 2e-3), (0.05, 5e-3))),
                             calibrate=calibrate)


def _system(calibrate: bool) -> tuple[ChamberSystem, SimRig]:
    act, pn, pl = Actuator(), Pneumatics(), Platform()
    rs = RigSettings(sample_period=PERIOD)
    return chamber_system(act, pn, pl, _pid_section(calibrate), rs), SimRig.chamber(act, pn, pl, rs)


@pytest.mark.parametrize("calibrate", [False, True])
def test_the_target_schedule_starts_when_the_loop_closes_on_whole_periods(calibrate):
    """With or without the start-up calibration first, the step at 0.05 s reaches the controller at the
    sixth closed-loop period exactly, and the loop's time is a whole number of periods."""
    system, rig = _system(calibrate)
    seen: list[tuple[float, float]] = []

    def ticked(k, r, u):
        seen.append((system.loop_time(r.t), system.loop.target))

    n = run_lockstep(system, rig, 0.1, ticked=ticked)
    assert n == 10 and len(seen) == 10
    assert [t for t, _ in seen] == [k * PERIOD for k in range(10)]
    assert [h for _, h in seen] == [2e-3] * 5 + [5e-3] * 5
    if calibrate:
        assert system.calibration_summary["status"] == system.calibration.status
        assert system.t_closed == pytest.approx(system.calibration_summary["duration_s"], abs=1e-12)
        assert system.t_closed > 0.5  # the calibration's periods came first and were not counted
    else:
        assert system.t_closed == 0.0 and system.calibration_summary is None


class _Spy:
    """Records the time every step is called with, and passes the call on."""

    def __init__(self, role):
        self.role, self.times = role, []

    def step(self, t, *args, **kwargs):
        self.times.append(t)
        return self.role.step(t, *args, **kwargs)

    def __getattr__(self, name):
        return getattr(self.role, name)


def test_the_estimator_runs_on_the_rigs_time_stamps_and_the_controller_on_the_loops():
    from hbma_ctrl.system.roles import default_estimator, make_controller

    act, pn, pl = Actuator(), Pneumatics(), Platform()
    rs = RigSettings(sample_period=PERIOD)
    sec = _pid_section(True)
    est = _Spy(default_estimator(act, pn, rs))
    ctrl = _Spy(make_controller(sec, act, pn))
    system, rig = chamber_system(act, pn, pl, sec, rs, estimator=est, controller=ctrl), SimRig.chamber(act, pn, pl, rs)
    stamps = []
    run_lockstep(system, rig, 0.05, ticked=lambda k, r, u: stamps.append(r.t))
    # the estimator saw every closed-loop reading at its rig time stamp (after the calibration's own)
    assert est.times[-5:] == stamps and stamps[0] == system.t_closed > 0.5
    # the controller ran on the loop's time, every controller period: whole rig periods from 0
    every = round(sec.sample_period / PERIOD)
    assert every > 1 and ctrl.times == [m * PERIOD for m in range(0, 5, every)]


def test_run_lockstep_stops_when_advanced_says_so_and_runs_no_hook_while_warming():
    system, rig = _system(True)
    calls = []
    n = run_lockstep(system, rig, 0.1, before=lambda k, t: calls.append(("before", k, t)),
                     advanced=lambda k, r, u: k == 3)
    assert n == 4
    assert calls == [("before", k, k * PERIOD) for k in range(4)]


def test_run_lockstep_refuses_a_duration_out_of_range():
    system, rig = _system(False)
    with pytest.raises(ValueError, match="duration"):
        run_lockstep(system, rig, 0.0)


def test_the_scene_is_the_system_driven_by_run_lockstep():
    """closed_loop's commands are those of chamber_system on a SimRig driven by hand with run_lockstep."""
    act, pn, pl = Actuator(), Pneumatics(), Platform()
    rs = RigSettings(sample_period=PERIOD)
    sec = _pid_section(True)
    log = closed_loop(act, pn, pl, sec, 0.2, rs)
    system, rig = chamber_system(act, pn, pl, sec, rs), SimRig.chamber(act, pn, pl, rs)
    u = []
    run_lockstep(system, rig, 0.2, ticked=lambda k, r, cmd: u.append(cmd[:, 0].copy()))
    np.testing.assert_array_equal(log.u, np.array(u))


def test_the_daemon_runs_the_scenes_system_classes(tmp_path):
    chamber = build_runner(load_config(ROOT / "scenarios" / "daemon_chamber.toml", {"--rig": "sim"}))
    assert type(chamber) is ChamberSystem


def test_run_lockstep_ticks_on_the_clock_it_is_given():
    system, rig = _system(False)
    seen = []
    tick = system.tick
    system.tick = lambda t, p, held=None: (seen.append(t), tick(t, p, held))[1]
    run_lockstep(system, rig, 0.03, clock=lambda r: 100.0 + r.t)
    assert seen == [100.0 + k * PERIOD for k in range(3)]
    assert RobotSystem.warming is False


def test_both_systems_keep_the_system_contract():
    """The daemon's runner for either file is a System (the members its loop uses, no probing)."""
    from hbma_ctrl.system.base import System

    chamber = build_runner(load_config(ROOT / "scenarios" / "daemon_chamber.toml", {"--rig": "sim"}))
    assert isinstance(chamber, System)
    assert chamber.take_faults() == [] and chamber.burst_peak() is None and chamber.controller_report() is None
    robot = build_runner(load_config(ROOT / "scenarios" / "daemon_robot.toml", {"--rig": "sim"}))
    assert isinstance(robot, System) and robot.warming is False
    robot.tick(0.0, np.zeros(robot.n))
    timing = robot.tick_timing()
    assert len(timing) == 3 and all(np.isfinite(timing))
    report = robot.controller_report()
    assert report is robot.loop.controller.last_parts and "status" in report
    assert {"nmpc status", "controller"} <= set(robot.tick_parts())


def test_to_function_refuses_what_has_no_generated_form_naming_the_setting():
    """A system generates its control side only from roles that have a generated form; each refusal
    is one error naming the setting: the start-up calibration, a controller with no step Function
    (the PID, the NMPC's rti_c_osqp variant, the robot's numpy NMPC)."""
    t = np.arange(3) * PERIOD
    for calibrate, why in ((True, "[controller] calibrate = true"), (False, "[controller] kind: PIDController")):
        with pytest.raises(ValueError, match=re.escape(why)):
            _system(calibrate)[0].to_function(t, 0.0)
    chamber = build_runner(load_config(ROOT / "scenarios" / "daemon_chamber.toml", {"--rig": "sim"}))
    chamber.calibration = None
    with pytest.raises(ValueError, match=re.escape("[controller] variant = 'rti_c_osqp'")):
        chamber.to_function(t, 0.0)
    robot = build_runner(load_config(ROOT / "scenarios" / "daemon_robot.toml", {"--rig": "sim"}))
    with pytest.raises(ValueError, match=re.escape("[robot] controller: RobotNMPC has no step Function")):
        robot.to_function(t, np.zeros(robot.n))


def test_a_chamber_system_of_role_objects_ticks_arrays_at_the_controllers_period():
    """Built from Python objects (no scenario): tick(t, p[1]) -> u[3, 1], the rig's own layout, and the
    20 ms controller runs every second 10 ms sample; a period it does not divide is an error naming both."""
    from hbma_ctrl.controllers.baselines import PIDController, PIDSettings
    from hbma_ctrl.core.interfaces import Estimate, EstimatorBase

    class Reading(EstimatorBase):
        def step(self, t, measurement, applied_command):
            return Estimate(t=t, h1=0.0, h2=0.0, h=0.0, F=0.0, p=float(measurement))

    act, pn, pl = Actuator(), Pneumatics(), Platform()
    rig = SimRig.chamber(act, pn, pl, RigSettings(sample_period=PERIOD))
    system = ChamberSystem.of(Reading(), PIDController(settings=PIDSettings()), rig.sample_period, reference=3e-3)
    assert system.loop.every == 2
    for _ in range(5):
        r = rig.read()
        u = system.tick(r.t, r.p)
        assert u.shape == (3, 1)
        rig.write(u)
    assert system.loop.stats()["steps"] == 3
    with pytest.raises(ValueError, match=r"PIDController sample_period = 20 ms must be a whole multiple of the "
                                         r"rig's sample_period = 15 ms"):
        ChamberSystem.of(Reading(), PIDController(settings=PIDSettings()), 0.015)
