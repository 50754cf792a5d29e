"""What the daemon runs, built from its configuration (SI).

:func:`build_runner` builds the scenario's system with the builders the scenes use
(:func:`hbma_ctrl.system.chamber.chamber_system`, :func:`hbma_ctrl.system.robot.robot_system`; a recording's
:class:`hbma_ctrl.app.daemon.schedule.ScheduleSystem`), with
what a real-time loop needs on top: the NMPC's solve-time budget enforced, and for the robot the
daemon's defaults where the file gives none (the ``DAEMON_*`` and ``ROBOT_*`` constants below).
:func:`make_rig` gives the rig link, :func:`make_monitor` the safety monitor.
"""

from __future__ import annotations

import math
from dataclasses import replace


from hbma_ctrl.controllers.robot_mpc import RobotMPCSettings
from hbma_ctrl.app.daemon.board import BoardSystem, board_system
from hbma_ctrl.app.daemon.config import DaemonConfig
from hbma_ctrl.app.daemon.faults import FaultyRig, parse_faults
from hbma_ctrl.app.daemon.schedule import ScheduleSystem
from hbma_ctrl.system.roles import estimator_from_scenario
from hbma_ctrl.app.schema.rig import RigTable
from hbma_ctrl.core import units as U
from hbma_ctrl.robot.rig import RobotRigSettings
from hbma_ctrl.runtime.watchdog import MonitorSettings, SafetyMonitor
from hbma_ctrl.sim.rig import RigSettings
from hbma_ctrl.system.chamber import ChamberSystem, chamber_system
from hbma_ctrl.system.robot import RobotSystem, robot_system
from hbma_ctrl.system.board_link import BoardControlledRig
from hbma_ctrl.system.serial_link import SerialRig
from hbma_ctrl.system.sim_rig import SimRig

__all__ = ["build_runner", "chamber_rig_settings", "make_monitor", "make_rig",
           "robot_rig_settings", "DAEMON_MPC_BUDGET", "DAEMON_TARGET_RATE", "DAEMON_W_SLACK", "ROBOT_LEAK_DROP", "ROBOT_LEAK_FRACTION",
           "ROBOT_NOISE_MARGIN"]

#: sensor noise sigmas ([rig] noise_std_kpa) between the robot NMPC's pressure bound and the limit
ROBOT_NOISE_MARGIN = 5.0

#: the robot's leak test: a fall while pumping of more than this, Pa, and of more than
#: ROBOT_LEAK_FRACTION of the pressure it fell from (normal work, four soaks: at most 11 kPa and 35 %)
ROBOT_LEAK_DROP = 5e3
ROBOT_LEAK_FRACTION = 0.5

#: the robot NMPC's wall-time budget in the daemon when the file gives none ([robot] mpc_budget = 0),
#: a fraction of the period: the rest of the period is the estimator, the supervisor and the rig I/O
DAEMON_MPC_BUDGET = 0.8
#: the fastest a robot chamber's target height moves in the daemon when [robot] target_rate_mm_s is not
#: given, m/s: a new pose sent as a step moves the layers as fast as the pumps and vents can, and the
#: layers' mass overshoots the membranes' equilibrium (a soak read 48.96 kPa 70 ms after a pose; `bench poses`,
#: 2 seeds x 59 changes: the worst change 43.2-44.0 kPa with steps, 42.0-42.2 kPa at 3 mm/s)
DAEMON_TARGET_RATE = 3e-3
#: the robot NMPC's cost per kPa over its pressure limit in the daemon when the file gives none: the
#: limit before the target (the controller's default, 1e-3, lets the limit give way by a few kPa for a
#: millimetre of height: a soak held A1 at 45.0 kPa, the limit itself, for seconds)
DAEMON_W_SLACK = 100.0


def chamber_rig_settings(cfg: DaemonConfig) -> RigSettings:
    """The single-chamber rig's settings ([rig], or the default rig at [sim] sensor_range_kpa), with the
    daemon's period as its sample period."""
    scn = cfg.scenario
    rs = scn.role("rig") or RigSettings(sensor_range=scn.sim.sensor_range)
    return _same_period(cfg, rs)


def robot_rig_settings(cfg: DaemonConfig) -> RobotRigSettings:
    """The robot rig's settings ([rig] as the robot scene reads it) with the daemon's period."""
    raw = cfg.scenario.sections.get("rig")
    rs = RigTable.model_validate(raw).to_robot_rig() if raw else RobotRigSettings()
    return _same_period(cfg, rs)


def _same_period(cfg: DaemonConfig, rs):
    """The rig's settings with the loop's period: a [rig] sample_period_ms other than 1000 / rate_hz is refused."""
    raw = cfg.scenario.sections.get("rig") or {}
    if "sample_period_ms" in raw and not math.isclose(rs.sample_period, cfg.period, rel_tol=1e-9):
        raise ValueError(f"[rig] sample_period_ms = {U.to_ms(rs.sample_period):g} must equal the daemon's period "
                         f"1000 / [daemon] rate_hz = {U.to_ms(cfg.period):g} ms (the loop reads and writes once per "
                         "rig sample)")
    return replace(rs, sample_period=cfg.period).validate()


def _chamber_runner(cfg: DaemonConfig) -> ChamberSystem:
    scn = cfg.scenario
    rs = chamber_rig_settings(cfg)
    return chamber_system(scn.actuator, scn.pneumatics, scn.platform, scn.role("controller"), rs,
                          estimator=estimator_from_scenario(scn, rs), realtime=True,
                          period_key="the daemon's period 1000 / [daemon] rate_hz")


def _robot_runner(cfg: DaemonConfig) -> RobotSystem:
    scn = cfg.scenario
    s = scn.role("robot")
    rp = s.pneumatics
    rs = robot_rig_settings(cfg)
    mpc, p_max = None, None
    if s.controller == "mpc":
        # a real-time loop always bounds the solver: an overrun is a failed step (the supervisor replays
        # the last plan, then the safe command), never a late command
        budget = s.mpc_budget if s.mpc_budget > 0 else DAEMON_MPC_BUDGET
        # the NMPC works to the limit less ROBOT_NOISE_MARGIN sensor sigmas: held at the limit itself, a
        # chamber's readings cross it on noise alone (a soak: 0.3 % of its readings, up to 45.6 of 45 kPa)
        p_max = rp.pressure_limit - ROBOT_NOISE_MARGIN * rs.noise_std
        w_slack = DAEMON_W_SLACK if s.mpc_w_slack is None else s.mpc_w_slack
        mpc = RobotMPCSettings(horizon=s.mpc_horizon, dt=s.mpc_dt, budget=budget, enforce_budget=True,
                               w_slack=w_slack)
    est = scn.settings.get("estimator")
    system = robot_system(s, s.targets, rs, s.controller, scn.pneumatics, mpc=mpc, p_max=p_max,
                          target_rate=DAEMON_TARGET_RATE if s.target_rate is None else s.target_rate,
                          estimator=est.filter if est is not None else "ekf",
                          window=dict(est.tuning) if est is not None else None)
    # the solver's set-up and first solve before the first deadline, not in it (a replay of a run
    # builds its runner here too, so it starts as the run did)
    system.loop.prime()
    return system


def _schedule_runner(cfg: DaemonConfig) -> ScheduleSystem:
    scn = cfg.scenario
    return ScheduleSystem(scn.role("schedule"), estimator=estimator_from_scenario(scn, chamber_rig_settings(cfg)))


def build_runner(cfg: DaemonConfig) -> ChamberSystem | RobotSystem | ScheduleSystem | BoardSystem:
    """The runner the configuration asks for (ValueError naming the key when the tables disagree); with
    ``board_controller`` the board runs the controller and the runner only sets its targets."""
    if cfg.board_controller:
        return board_system(cfg.scenario.role("controller"), chamber_rig_settings(cfg).sample_period)
    build = {"robot": _robot_runner, "schedule": _schedule_runner}.get(cfg.kind, _chamber_runner)
    return build(cfg)


def make_rig(cfg: DaemonConfig, runner):
    """The rig link the configuration names: the lockstep simulated rig (with the [[daemon.fault]]
    injections) or the serial link (to a board that runs the controller with ``board_controller``: the
    runner, a :class:`BoardSystem`, sets its targets)."""
    if cfg.rig == "serial" and cfg.board_controller:
        rig = BoardControlledRig(cfg.port, runner.n, baud=cfg.baud, sample_period=cfg.period)
        runner.link = rig
        return rig
    if cfg.rig == "serial":
        return SerialRig(cfg.port, runner.n, baud=cfg.baud, sample_period=cfg.period)
    return make_sim_rig(cfg)


def make_sim_rig(cfg: DaemonConfig):
    """The configuration's simulated (mismatched) rig in lockstep, with its [[daemon.fault]] injections:
    what ``--rig sim`` drives, and the plant a fake firmware runs behind the serial link. ValueError
    naming the table when a fault does not fit the rig."""
    scn = cfg.scenario
    if cfg.kind == "robot":
        s = scn.role("robot")
        rig = SimRig.robot(s, robot_rig_settings(cfg), scn.pneumatics, s.tip_load)
    else:
        ctrl = scn.role("controller")
        rig = SimRig.chamber(scn.actuator, scn.pneumatics, scn.platform, chamber_rig_settings(cfg),
                             ctrl.load_steps if ctrl is not None else ())
    if cfg.faults:
        rig = FaultyRig(rig, parse_faults(cfg.faults, rig.n))
    return rig


def make_monitor(cfg: DaemonConfig, runner):
    """The safety monitor of the runner's chambers: pressure cap at the runner's limit (robot: halfway
    from it to the sensor's range), the sensor's
    range, the loop watchdog at ``miss_limit`` missed deadlines in a row; the robot's leak test
    finds a burst or a leak that more than halves a pressure (its chambers' pressures fall by a share
    while pumping in normal work: past their limit point, when a neighbour takes over the load)."""
    leak = {}
    cap = runner.p_limit
    if cfg.kind == "robot":
        sensor = cfg.scenario.role("robot").pneumatics.sensor_range
        # the NMPC keeps the pressures under the limit and the supervisor cuts the supply near it, but a
        # layer that tilts onto a chamber raises its pressure with no pumping (a soak read 46.2 kPa
        # against the 45 kPa limit 50 ms after a new pose): the hard cap, which vents everything, sits
        # halfway between the limit and the sensor's range
        cap = 0.5 * (runner.p_limit + sensor)
        # a robot chamber's pressure falls while it pumps in normal work: past its limit point and when
        # a neighbour of its layer takes over its load (four soaks: falls of up to 11 kPa, 35 % of the
        # pressure, within the leak window): the leak test is one of a burst or a leak that more than
        # halves a pressure of at least ROBOT_LEAK_DROP / ROBOT_LEAK_FRACTION, on readings averaged over
        # 2 periods, not 5 (a burst's fall is over in a few periods, and the NMPC, reading it as a rising
        # membrane, opens the outlet, which ends the pumping the test needs). No pump test: a chamber
        # inflating from flat under its layer stays near 1 kPa for seconds while it pumps (soaks latched
        # false pump failures at 4.95 kPa, then 0.23 kPa up from 0.97 kPa in 0.25 s of full pumping and
        # 0.28 kPa from 0.93 kPa in 1 s); a failed robot pump is not found
        leak = {"leak_drop": ROBOT_LEAK_DROP, "leak_fraction": ROBOT_LEAK_FRACTION, "smooth_periods": 2,
                "pump_test": False}
    else:
        sensor = chamber_rig_settings(cfg).sensor_range
    return SafetyMonitor(MonitorSettings(p_max=cap, sensor_range=sensor, sample_period=cfg.period,
                                         missed_deadlines=cfg.miss_limit, **leak), runner.n)
