"""What the daemon runs, built from its configuration: the runtime loop wrapped for the rig (SI).

A *runner* adapts :class:`hbma_ctrl.runtime.chamber.ChamberLoop` or
:class:`hbma_ctrl.runtime.robot.RobotLoop` to the rig's view: ``tick(t, p) -> U`` with the readings
of every chamber (Pa, (n,)) and the plant input ``U`` (3, n) the rig takes; the status rows the API
shows; and setpoints: ``check_setpoint`` (the API's thread: clip to what is reachable, say what
was clipped) and ``apply_setpoint`` (the loop's thread, between periods). The runners are
:class:`ChamberRunner` and :class:`RobotRunner`.

The runners are built exactly as the scenes build their loops (:mod:`hbma_ctrl.app.scenes.controller`,
:mod:`hbma_ctrl.app.scenes.robot_loop`), so a daemon on the simulated rig runs the scene's closed loop.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import replace

import numpy as np

from hbma_ctrl.controllers.robot_mpc import RobotMPCSettings, RobotNMPC
from hbma_ctrl.controllers.robot_pid import RobotPIDSettings, RobotPressurePID
from hbma_ctrl.estimators.robot_ekf import ChamberEKFBank, ChamberEKFSettings
from hbma_ctrl.app.daemon.config import DaemonConfig
from hbma_ctrl.app.scenes.robot_loop import make_model
from hbma_ctrl.app.scenes.controller import (
    calibration_summary,
    controller_settings_of,
    estimator_from_scenario,
    make_calibration,
    make_controller,
    make_pwm,
)
from hbma_ctrl.app.schema.rig import RigTable
from hbma_ctrl.core import units as U
from hbma_ctrl.core.interfaces import Command
from hbma_ctrl.robot.kinematics import inverse_kinematics, layer_plane
from hbma_ctrl.robot.rig import RobotRigSettings
from hbma_ctrl.runtime.calibrate import StartupCalibration
from hbma_ctrl.runtime.chamber import ChamberLoop, chamber_supervisor
from hbma_ctrl.runtime.robot import RobotLoop, robot_supervisor
from hbma_ctrl.runtime.watchdog import MonitorSettings, SafetyMonitor
from hbma_ctrl.sim.rig import RigSettings

__all__ = ["ChamberRunner", "RobotRunner", "build_runner", "chamber_rig_settings", "make_monitor", "make_rig",
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


class SupervisorEpisodes:
    """The runtime supervisor's interventions as daemon events ("supervisor", "<chamber>: <cause>
    (<detail>)"), one per episode: a chamber's cause is passed on when it was not logged in the
    previous tick (the pressure guard and the stretch guard log every step they act; the run log
    would otherwise get one row per chamber and period)."""

    def __init__(self, supervisor, names):
        self.sup = supervisor
        self.names = tuple(names)
        self._seen = supervisor.logged
        self._prev: set = set()

    def take(self) -> list[tuple[str, str]]:
        """The episodes started since the last call (oldest first)."""
        sup = self.sup
        new = min(sup.logged - self._seen, len(sup.events))
        self._seen = sup.logged
        events = list(itertools.islice(reversed(sup.events), new))[::-1] if new > 0 else []
        out, cur = [], set()
        for e in events:
            key = (e.chamber, e.cause)
            if key not in self._prev and key not in cur:
                name = self.names[e.chamber] if 0 <= e.chamber < len(self.names) else str(e.chamber)
                out.append(("supervisor", f"{name}: {e.cause}" + (f" ({e.detail})" if e.detail else "")))
            cur.add(key)
        self._prev = cur
        return out


class ChamberRunner:
    """One chamber under :class:`ChamberLoop` (see module doc). ``h_range``: reachable targets (lo, hi), m.

    ``calibration``: a :class:`StartupCalibration` run first (``[controller] calibrate``), as the
    controller scene runs it: its excitation drives the chamber, its estimator is the loop's, and
    the file's target schedule starts when it ends (a setpoint sent meanwhile holds from then on).
    While it runs, ``warming`` is True: its fit (about a second in the tick that ends it, while the
    chamber vents) does not feed the loop watchdog. ``take_events()`` hands the loop what to log.
    """

    kind = "chamber"

    def __init__(self, loop: ChamberLoop, p_limit: float, h_range: tuple[float, float], names=("C1",),
                 calibration: StartupCalibration | None = None):
        self.loop = loop
        self.n = 1
        self.names = tuple(names)
        self.p_limit = float(p_limit)
        self.h_range = (float(h_range[0]), float(h_range[1]))
        self.calibration = calibration
        self.calibration_summary: dict | None = None
        self._setpoint_during_calibration = False
        self._events: list[tuple[str, str]] = []
        self._t0: float | None = None
        self._episodes = SupervisorEpisodes(loop.supervisor, self.names)

    @property
    def warming(self) -> bool:
        """True while the start-up calibration runs (its ticks do not feed the loop watchdog)."""
        return self.calibration is not None and not self.calibration.done

    def take_events(self) -> list[tuple[str, str]]:
        """(kind, cause) events since the last call (the calibration's start and outcome, the
        supervisor's interventions: :class:`SupervisorEpisodes`)."""
        ev, self._events = self._events, []
        return ev + self._episodes.take()

    def tick(self, t: float, p: np.ndarray, held: np.ndarray | None = None) -> np.ndarray:
        """One period at rig time t (s) with the reading p (Pa, (1,)) -> U (3, 1); ``held`` (3, 1): the
        command the rig reports it held over the period p ends (None: the last one returned)."""
        if self._t0 is None:
            self._t0 = float(t)
            if self.calibration is not None:
                self._events.append(("calibration", "start-up calibration: vent, pump pulse, hold, vent"))
        h = None if held is None else Command(*(float(x) for x in np.asarray(held, dtype=float).reshape(3)))
        if self.warming:
            cmd, done = self.calibration.tick(t, float(p[0]), h)
            if done:
                self._calibrated(t, cmd)
            return cmd.as_array().reshape(3, 1)
        return self.loop.tick(t, float(p[0]), h).as_array().reshape(3, 1)

    def _calibrated(self, t: float, cmd: Command) -> None:
        """The calibration ended at rig time t (s): the loop takes over from its vent command, the
        file's schedule shifted to start now (as the scene's loop starts at 0 when it closes)."""
        cal = self.calibration
        self.calibration_summary = calibration_summary(cal, t - self._t0)
        self.loop.command = cmd
        ref = self.loop.reference
        if ref is not None and not self._setpoint_during_calibration:
            self.loop.set_reference(lambda tt, ref=ref, t1=float(t): ref(tt - t1))
        s = self.calibration_summary
        facts = (f": flow x{s['flow_factor']:.3f}, modulus x{s['modulus_factor']:.3f}, dead volume "
                 f"x{s['dead_volume_factor']:.3f}" if cal.result is not None else "")
        self._events.append(("calibration", f"{cal.status} after {t - self._t0:.2f} s{facts}"))

    def targets(self) -> np.ndarray:
        """This period's target height per chamber, m (NaN = none)."""
        tg = self.loop.target
        return np.array([np.nan if tg is None else tg])

    def estimates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(height m, its std m, pressure Pa) per chamber from the estimator, NaN before the first tick."""
        e = self.loop.estimate
        if e is None:
            return (np.full(1, np.nan),) * 3
        return np.array([e.h]), np.array([float(e.std.get("h", np.nan))]), np.array([e.p])

    def layers(self) -> list:
        """No layers: a single chamber."""
        return []

    def check_setpoint(self, request: dict) -> dict:
        """Heights {0: h m} -> {"applied", "clipped"} (clipped to ``h_range``); ValueError for layers or
        another chamber."""
        if request.get("layers"):
            raise ValueError("layers: this daemon runs one chamber; send heights_mm instead")
        heights = request.get("heights") or {}
        if not heights:
            raise ValueError("no setpoint given: send heights_mm for chamber 0")
        clipped, applied = [], {}
        lo, hi = self.h_range
        for i, h in heights.items():
            if int(i) != 0:
                raise ValueError(f"heights_mm.{i}: chamber index out of range [0, 0] (one chamber)")
            h = float(h)
            if not math.isfinite(h):
                raise ValueError(f"heights_mm.{i}: must be a finite number")
            hc = min(max(h, lo), hi)
            if hc != h:
                clipped.append(f"heights_mm.{i} = {U.to_mm(h):g} clipped to {U.to_mm(hc):g} mm (reachable "
                               f"[{U.to_mm(lo):g}, {U.to_mm(hi):g}] mm)")
            applied[0] = hc
        return {"applied": {"heights": applied}, "clipped": clipped}

    def apply_setpoint(self, applied: dict, t: float) -> None:
        """Hold the applied height from now on (the file's target schedule ends)."""
        h = applied.get("heights", {}).get(0)
        if h is not None:
            self._setpoint_during_calibration = self.warming
            self.loop.set_reference(lambda _t, h=float(h): h)

    def stats(self) -> dict:
        """The controller's and the runtime's statistics (ms, counts), and ``calibration`` (the
        start-up calibration's outcome, edge units, as the controller scene reports it) when it ran."""
        out = self.loop.stats()
        if self.calibration is not None:
            out["calibration"] = self.calibration_summary or {"status": self.calibration.status}
        return out


class RobotRunner:
    """The robot under :class:`RobotLoop` (see module doc). ``h_max``: the highest chamber target, m."""

    kind = "robot"

    def __init__(self, loop: RobotLoop, p_limit: float, h_max: float):
        self.loop = loop
        self.design = loop.design
        self.n = loop.n
        self.names = tuple(self.design.names)
        self.p_limit = float(p_limit)
        self.h_max = float(h_max)
        self._t = 0.0
        self._episodes = SupervisorEpisodes(loop.supervisor, self.names)
        self._bursts_reported = np.zeros(self.n, dtype=bool)

    def take_events(self) -> list[tuple[str, str]]:
        """(kind, cause) events since the last call: the supervisor's interventions
        (:class:`SupervisorEpisodes`: interlocks, vents, a lost estimate, fallbacks)."""
        return self._episodes.take()

    def clear_faults(self) -> None:
        """Re-arm the runner's own fault tests (a bench that records a fault and goes on): the burst
        latches of the supervisor and the burst test cleared."""
        self.loop.supervisor.burst[:] = False
        if self.loop.burst is not None:
            self.loop.burst.reset()
        self._bursts_reported[:] = False

    def burst_peak(self) -> float | None:
        """The burst test's largest sum over the chambers so far, sigma (its margin to the threshold;
        None without the test)."""
        b = self.loop.burst
        return None if b is None else float(b.peak.max())

    def take_faults(self) -> list[tuple[str, int, str]]:
        """(kind, chamber, cause) faults found since the last call, which the daemon latches: the
        chambers the loop's burst test flagged (:mod:`hbma_ctrl.runtime.burst`)."""
        new = self.loop.supervisor.burst & ~self._bursts_reported
        self._bursts_reported |= new
        why = self.loop.burst.why if self.loop.burst is not None else [""] * self.n
        return [("burst", int(i), f"{self.names[i]}: {why[i] or 'flagged'} (a burst membrane or an outlet stuck open)")
                for i in np.nonzero(new)[0]]

    def tick(self, t: float, p: np.ndarray, held: np.ndarray | None = None) -> np.ndarray:
        """One period at rig time t (s) with the readings p (Pa, (n,)) -> U (3, n); ``held`` (3, n): the
        valve inputs the rig reports it held over the period p ends (None: the last ones returned)."""
        self._t = t
        self.loop.tick(t, p, held)
        return self.loop.valve_commands.copy()

    def targets(self) -> np.ndarray:
        """This period's target height per chamber, m: what the controller worked to (moving towards
        the setpoint at ``[robot] target_rate_mm_s``)."""
        h = self.loop.href
        return np.asarray(self.loop.chamber_targets(self._t) if h is None else h, dtype=float)

    def estimates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(height m, its std m, pressure Pa) per chamber from the EKF bank, NaN before the first tick."""
        e = self.loop.estimate
        if e is None:
            return (np.full(self.n, np.nan),) * 3
        return (np.asarray(e["h"], float), np.asarray(e.get("h_std", np.full(self.n, np.nan)), float),
                np.asarray(e["p"], float))

    def layers(self) -> list:
        """The estimated pose of every layer: {"centre" m, "bend" rad, "direction" rad}."""
        h, _, _ = self.estimates()
        if not np.all(np.isfinite(h)):
            return []
        hh = np.maximum(h, 0.0).reshape(-1, 3)
        out = []
        for k in range(self.design.n_layers):
            c, b, d = layer_plane(self.design, hh[k])
            out.append({"centre": c, "bend": b, "direction": d})
        return out

    def _pose_now(self, k: int) -> tuple[float, float, float]:
        rows = self.loop.targets[k]
        cur = rows[0]
        for r in rows:
            if self._t + 1e-9 >= r[0]:
                cur = r
        return float(cur[1]), float(cur[2]), float(cur[3])

    def check_setpoint(self, request: dict) -> dict:
        """Layer poses {k: (centre m, bend rad, direction rad)} -> {"applied", "clipped"}: chamber heights
        from the inverse kinematics clipped to [0, h_max], the pose those heights give reported back."""
        if request.get("heights"):
            raise ValueError("heights_mm: the robot takes layer poses (layers) as setpoints")
        layers = request.get("layers") or {}
        if not layers:
            raise ValueError("no setpoint given: send layers")
        N = self.design.n_layers
        applied, clipped = {}, []
        for k, pose in layers.items():
            k = int(k)
            if not 0 <= k < N:
                raise ValueError(f"layers: layer {k} is out of range [0, {N - 1}]")
            c, b, d = (float(x) for x in pose)
            if not all(math.isfinite(x) for x in (c, b, d)):
                raise ValueError(f"layers.{k}: centre, bend and direction must be finite")
            if not 0.0 <= b < math.pi / 2:
                raise ValueError(f"layers.{k}: bend_deg = {math.degrees(b):g} is out of range [0, 90) deg")
            h = inverse_kinematics(self.design, np.full(N, c), np.full(N, b), np.full(N, d))[k]
            hc = np.clip(h, 0.0, self.h_max)
            if np.any(hc != h):
                c2, b2, d2 = layer_plane(self.design, hc)
                bad = ", ".join(f"{self.names[3 * k + i]} {U.to_mm(h[i]):.2f} mm" for i in range(3) if hc[i] != h[i])
                clipped.append(f"layers.{k}: chamber heights {bad} outside the reachable [0, {U.to_mm(self.h_max):g}] "
                               f"mm; applied centre {U.to_mm(c2):.2f} mm, bend {math.degrees(b2):.2f} deg, "
                               f"direction {math.degrees(d2):.1f} deg")
                c, b, d = float(c2), float(b2), float(d2)
            applied[k] = (c, b, d)
        return {"applied": {"layers": applied}, "clipped": clipped}

    def apply_setpoint(self, applied: dict, t: float) -> None:
        """Hold the applied layer poses from now on; the other layers hold their current targets."""
        new = applied.get("layers") or {}
        targets = {}
        for k in range(self.design.n_layers):
            pose = new.get(k, self._pose_now(k))
            targets[k] = ((0.0, *(float(x) for x in pose)),)
        self.loop.set_targets(targets)

    def stats(self) -> dict:
        """The loop's statistics (ms, counts)."""
        return self.loop.stats()


def _chamber_runner(cfg: DaemonConfig) -> ChamberRunner:
    scn = cfg.scenario
    section = scn.role("controller")
    rs = chamber_rig_settings(cfg)
    est = estimator_from_scenario(scn, rs)
    if est is None:
        from hbma_ctrl.estimators.ekf import EKF, EKFSettings
        est = EKF(scn.actuator, scn.pneumatics, EKFSettings(sample_period=rs.sample_period,
                                                            noise_std=max(rs.noise_std, 1.0),
                                                            sensor_range=rs.sensor_range))
    if section.kind == "mpc":
        # a real-time loop always bounds the solver: an overrun is a failed step (the supervisor replays
        # the last plan, then the safe command), never a late command
        section = replace(section, mpc=replace(section.mpc, enforce_budget=True))
    ctrl = make_controller(section, scn.actuator, scn.pneumatics)
    ratio = section.sample_period / rs.sample_period
    every = int(round(ratio))
    if every < 1 or abs(ratio - every) > 1e-6:
        raise ValueError(f"[controller] sample_ms = {U.to_ms(section.sample_period):g} must be a whole multiple of the "
                         f"daemon's period 1000 / [daemon] rate_hz = {U.to_ms(rs.sample_period):g} ms")
    settings = getattr(ctrl, "settings", None) or controller_settings_of(section)
    loop = ChamberLoop(est, ctrl, chamber_supervisor(settings), reference=section.reference, every=every,
                       pwm=make_pwm(section, rs.sample_period))
    h_min = float(getattr(settings, "h_min", 0.0) or 0.0)
    h_max = float(getattr(settings, "h_max", U.mm(20.0)))
    cal = None
    if section.calibrate:
        cal = make_calibration(scn.actuator, scn.pneumatics, scn.platform, section, rs, est)
    return ChamberRunner(loop, section.p_max, (h_min, h_max), calibration=cal)


def _robot_runner(cfg: DaemonConfig) -> RobotRunner:
    scn = cfg.scenario
    s = scn.role("robot")
    d, rp = s.design, s.pneumatics
    rs = robot_rig_settings(cfg)
    n = 3 * d.n_layers
    model = make_model(d, scn.pneumatics, rp.topology)
    Ts = rs.sample_period
    s.check_period(Ts)
    bank = ChamberEKFBank(model, n, ChamberEKFSettings(sample_period=Ts, noise_std=max(rs.noise_std, 1.0),
                                                        sensor_range=rp.sensor_range, valve_delay=s.valve_delay,
                                                        sensor_delay=s.sensor_delay))
    if s.controller == "mpc":
        # a real-time loop always bounds the solver: an overrun is a failed step (the supervisor replays
        # the last plan, then the safe command), never a late command
        budget = s.mpc_budget if s.mpc_budget > 0 else DAEMON_MPC_BUDGET
        # the NMPC works to the limit less ROBOT_NOISE_MARGIN sensor sigmas: held at the limit itself, a
        # chamber's readings cross it on noise alone (a soak: 0.3 % of its readings, up to 45.6 of 45 kPa)
        p_max = rp.pressure_limit - ROBOT_NOISE_MARGIN * rs.noise_std
        w_slack = DAEMON_W_SLACK if s.mpc_w_slack is None else s.mpc_w_slack
        ms = replace(RobotMPCSettings(horizon=s.mpc_horizon, dt=s.mpc_dt), sample_period=Ts, p_max=p_max,
                     budget=budget, enforce_budget=True, w_slack=w_slack)
        ctrl = RobotNMPC(model, n, ms)
    else:
        ctrl = RobotPressurePID(model, n, replace(RobotPIDSettings(), sample_period=Ts))
    sup = robot_supervisor(rp.pressure_limit, n, plan_period=ctrl.s.dt if s.controller == "mpc" else None)
    rate = DAEMON_TARGET_RATE if s.target_rate is None else s.target_rate
    loop = RobotLoop(d, model, bank, ctrl, sup, s.targets, cautious=(0.75, 0.03, 0.3) if s.controller == "mpc" else None,
                     target_rate=rate, valve_min_on=s.valve_min_on, burst=s.burst)
    # the solver's set-up and first solve before the first deadline, not in it (a replay of a run
    # builds its runner here too, so it starts as the run did)
    loop.prime()
    return RobotRunner(loop, rp.pressure_limit, model.h_table_max)


def build_runner(cfg: DaemonConfig) -> ChamberRunner | RobotRunner:
    """The runner the configuration asks for (ValueError naming the key when the tables disagree)."""
    return _robot_runner(cfg) if cfg.kind == "robot" else _chamber_runner(cfg)


def make_rig(cfg: DaemonConfig, runner):
    """The rig link the configuration names: the lockstep simulated rig (with the [[daemon.fault]]
    injections) or the serial link. ValueError when a backend is not available."""
    if cfg.rig == "serial":
        try:
            from hbma_ctrl.system.serial_link import SerialRig
        except ImportError as exc:
            raise ValueError(f"--rig serial: the serial backend is not available ({exc})") from None
        return SerialRig(cfg.port, runner.n, baud=cfg.baud, sample_period=cfg.period)
    return make_sim_rig(cfg)


def make_sim_rig(cfg: DaemonConfig):
    """The configuration's simulated (mismatched) rig in lockstep, with its [[daemon.fault]] injections:
    what ``--rig sim`` drives, and the plant a fake firmware runs behind the serial link. ValueError
    when the backend is not available or a fault does not fit the rig."""
    try:
        from hbma_ctrl.system.sim_rig import SimRig
    except ImportError as exc:
        raise ValueError(f"--rig sim: the simulated rig backend is not available ({exc})") from None
    scn = cfg.scenario
    if cfg.kind == "robot":
        s = scn.role("robot")
        rig = SimRig.robot(s, robot_rig_settings(cfg), scn.pneumatics, s.tip_load)
    else:
        rig = SimRig.chamber(scn.actuator, scn.pneumatics, scn.platform, chamber_rig_settings(cfg),
                             scn.role("controller").load_steps)
    if cfg.faults:
        from hbma_ctrl.app.daemon.faults import FaultyRig, parse_faults
        try:
            rig = FaultyRig(rig, parse_faults(cfg.faults, rig.n))
        except ValueError as exc:
            msg = str(exc)
            raise ValueError(msg if msg.startswith("[") else f"[daemon.fault] {msg}") from None
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
