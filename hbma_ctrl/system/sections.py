"""The validated scenario and its role sections as SI objects (what the schema builds, what scenes read).

:class:`Scenario` is one loaded file; :class:`ControllerSection`, :class:`EstimatorSection` and
:class:`RobotSettings` are its role tables after validation (:mod:`hbma_ctrl.app.schema` builds them
from the user's units).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from hbma_ctrl.controllers.baselines import BangBangSettings, PIDSettings
from hbma_ctrl.controllers.lqi import LQISettings
from hbma_ctrl.controllers.mpc_settings import MPCSettings
from hbma_ctrl.estimators.common import FilterSettings
from hbma_ctrl.estimators.mhe import MHESettings
from hbma_ctrl.core import units as U
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.core.settings import Settings, Spec, setting
from hbma_ctrl.models.actuation import DELAY_MAX
from hbma_ctrl.models.defaults import DEFAULT_VALVE_DELAY, DEFAULT_VALVE_MIN_ON, ROBOT_SENSOR_DELAY
from hbma_ctrl.robot.design import RobotDesign, RobotPneumatics
from hbma_ctrl.robot.plant import RobotPlantSettings
from hbma_ctrl.robot.rig import H_TARGET_MAX
from hbma_ctrl.runtime.burst import BurstTestSettings
from hbma_ctrl.runtime.calibrate import CalibrationSettings
from hbma_ctrl.sim.batch import protocol_trials
from hbma_ctrl.sim.rig import RigSettings
from hbma_ctrl.sim.trial import InputSchedule, SimSettings, Trial


@dataclass
class Scenario:
    """A loaded scenario (SI inside). ``sections`` holds the raw role tables, ``settings`` their
    parsed settings objects (by the owners' parsers); ``protocol`` the protocol grid (edge units,
    kind "protocol" only)."""

    name: str
    kind: str
    actuator: Actuator
    pneumatics: Pneumatics
    platform: Platform
    schedule: InputSchedule
    duration: float
    sim: SimSettings
    fidelity: str
    sections: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)
    protocol: dict = field(default_factory=dict)
    path: Path | None = None

    def trials(self) -> list[Trial]:
        """One trial (kind 'single') or the whole protocol grid (kind 'protocol')."""
        if self.kind == "single":
            return [Trial(self.actuator, self.pneumatics, self.platform, self.schedule, self.duration,
                          self.name).validate()]

        pr = self.protocol
        return protocol_trials(self.actuator.material, loads_g=pr["loads_g"], speeds_pct=pr["speeds_pct"],
                               t0_mm=pr["t0_mm"], r1_mm=pr["r1_mm"], t_inflate_s=pr["t_inflate_s"],
                               duration_s=self.duration, base=self.actuator,
                               pneumatics=self.pneumatics, platform=self.platform)

    def role(self, name: str):
        """Parsed settings of a role section, or None when the scenario has none."""
        return self.settings.get(name)


KINDS = ("mpc", "pid", "bang_bang", "lqi")

#: one target point of a chamber, its time and height (the scenario's targets_mm rows, the daemon API's setpoints)
TARGET_TIME = Spec(doc="time of the point", unit="s", lo=0.0, hi=1e5)
TARGET_HEIGHT = Spec(doc="target membrane height", unit="m", user="mm", lo=0.0, hi=0.2)
#: one pose target of a robot layer, its centre height and bend (the scenario's [robot.targets], the API's)
POSE_HEIGHT = Spec(doc="centre height of the layer above the one below", unit="m", user="mm", lo=0.0, hi=H_TARGET_MAX)
POSE_BEND = Spec(doc="bend angle; a negative bend is the opposite direction", unit="rad", user="deg",
                 lo=-math.pi / 3, hi=math.pi / 3)


@dataclass
class ReferenceProfile(Settings):
    """Target height over time (SI): piecewise points, optional sinusoid on top.

    points : ((t_s, h_m), ...) sorted by time; before the first point the first height holds.
    """

    WHERE = "controller"

    points: tuple = ((0.0, 2e-3),)
    interpolation: str = setting("step", choices=("step", "linear"), doc="hold each target or ramp between them")
    sine_amplitude: float = setting(0.0, lo=0.0, hi=0.1, unit="m", user="mm", doc="sinusoid added to the targets")
    sine_period: float = setting(1.0, lo=0.0, hi=1e4, lo_open=True, unit="s", key="sine_period_s", doc="sinusoid period")
    sine_start: float = setting(0.0, lo=0.0, hi=1e5, unit="s", key="sine_start_s", doc="sinusoid start")

    def check_rules(self) -> None:
        if not self.points:
            raise ValueError("controller.targets_mm must have at least one [t_s, h_mm] pair")
        ts = [p[0] for p in self.points]
        if any(b < a for a, b in zip(ts, ts[1:])):
            raise ValueError("controller.targets_mm: times must be non-decreasing")
        for t, h in self.points:
            TARGET_TIME.check("controller", "targets_mm time", t)
            TARGET_HEIGHT.check("controller", "targets_mm height", h)

    def __call__(self, t: float) -> float:
        ts = np.array([p[0] for p in self.points])
        hs = np.array([p[1] for p in self.points])
        if self.interpolation == "step":
            i = max(int(np.searchsorted(ts, t, side="right")) - 1, 0)
            h = float(hs[i])
        else:
            h = float(np.interp(t, ts, hs))
        if self.sine_amplitude > 0 and t >= self.sine_start:
            h += self.sine_amplitude * np.sin(2 * np.pi * (t - self.sine_start) / self.sine_period)
        return max(h, 0.0)

    def step_segments(self, duration: float) -> list[tuple[float, float, float]]:
        """(t_start, t_end, target) of each constant-target segment ('step' profiles, no sine)."""
        if self.interpolation != "step" or self.sine_amplitude > 0:
            return []
        pts = list(self.points)
        out = []
        for i, (t, h) in enumerate(pts):
            t_end = pts[i + 1][0] if i + 1 < len(pts) else duration
            if t_end > t:
                out.append((t, min(t_end, duration), h))
        return out


@dataclass
class ControllerSection(Settings):
    """Parsed [controller] section: which controller, its settings, the targets and load steps.

    Fields
    ------
    kind : which controller runs; mpc, pid, bang_bang, lqi : the settings of each (only the chosen one is used).
    reference : the height target profile (steps, ramps, sines), m.
    load_steps : ((t s, load mass kg), ...) put on the rig during the run.
    preview : pass the future targets to the MPC; None = only for ramps and sines.
    valve_min_on : small duties are realised on average (:class:`hbma_ctrl.runtime.pwm.MinOnTime`); at
        most the rig's sample period.
    calibration_std_floor : :class:`hbma_ctrl.runtime.calibrate.CalibrationSettings` ``handover_std_floor``.

    The MPC's wall-clock budget acts only where ``mpc.enforce_budget`` is set (the scenario's
    ``[controller] enforce_budget``; the rig daemon always sets it).
    """

    WHERE = "controller"

    kind: str = setting("mpc", choices=KINDS, doc="which controller runs")
    mpc: MPCSettings = field(default_factory=MPCSettings)
    pid: PIDSettings = field(default_factory=PIDSettings)
    bang_bang: BangBangSettings = field(default_factory=BangBangSettings)
    # out of the repr: the stored reprs of the scenario goldens (tests/test_schema.py)
    lqi: LQISettings = field(default_factory=LQISettings, repr=False)
    reference: ReferenceProfile = field(default_factory=ReferenceProfile)
    load_steps: tuple = ()  # ((t_s, mass_kg), ...)
    preview: bool | None = None  # pass the future targets to the MPC; None = for ramps/sines only
    settle_band: float = setting(0.3e-3, lo=0.0, hi=0.05, lo_open=True, unit="m", user="mm",
                                 doc="settling band of the step metrics")
    # out of the repr: tests/test_schema.py compares reprs with those of the parsers this schema replaced
    calibrate: bool = setting(True, repr=False, doc="before the loop closes, learn the pump-flow, modulus and "
                              "dead-volume factors from a pump pulse (to at most half of p_max_kpa, 17 kPa) and a vent")
    valve_min_on: float = setting(DEFAULT_VALVE_MIN_ON, lo=0.0, hi=0.1, unit="s", user="ms", repr=False,
                                  doc="the valves' minimum opening (datasheet): shorter duties are sent as pulses "
                                      "of this length often enough to pass them on average")
    calibration_std_floor: float = setting(CalibrationSettings.handover_std_floor, lo=0.0, hi=1.0, repr=False,
                                           doc="smallest sigma of each factor the calibration hands the estimator "
                                               "(its fit's own assumes the model is the chamber)")

    @property
    def chosen(self):
        """The settings of the controller that runs (``kind``)."""
        return getattr(self, self.kind)

    @property
    def sample_period(self) -> float:
        return self.chosen.sample_period

    @property
    def p_max(self) -> float:
        return self.chosen.p_max


@dataclass
class EstimatorSection:
    """Parsed ``[estimator]`` section (SI).

    filter : 'ekf' | 'ukf' | 'mhe' (the scenario's ``kind``). compare_ukf : also run the UKF. load_steps : ((t s, mass kg), ...).
    workers : processes for a protocol. seeds : Monte-Carlo repetitions. tuning : FilterSettings
    field overrides (SI); the sample period and sensor range always come from the rig.
    """

    filter: str = "ekf"
    compare_ukf: bool = False
    load_steps: tuple = ()
    workers: int = 2
    seeds: int = 1
    tuning: dict = field(default_factory=dict)


def filter_settings_for(section: EstimatorSection, rig: RigSettings) -> FilterSettings:
    """Filter settings: defaults, the rig's sample period, sensor range and noise, then the tuning
    (:class:`~hbma_ctrl.estimators.mhe.MHESettings` for the moving-horizon estimator)."""
    cls = MHESettings if section.filter == "mhe" else FilterSettings
    base = cls(sample_period=rig.sample_period, sensor_range=rig.sensor_range, noise_std=max(rig.noise_std, 1.0))
    return replace(base, **section.tuning).validate()


SCENE_MODES = ("open_loop", "closed_loop")
CONTROLLERS = ("mpc", "pressure_pid")
#: a robot's estimators ([estimator] kind): the EKF bank, or a moving-horizon window per chamber over it
ROBOT_ESTIMATORS = ("ekf", "mhe")
#: the [estimator] keys a robot scenario reads (kind = "mhe": the windows' own)
ROBOT_ESTIMATOR_KEYS = ("kind", "filter", "horizon", "huber", "reseed_cost", "qp_solver")


@dataclass(frozen=True)
class RobotSettings(Settings):
    """The ``[robot]`` scenario table, validated (SI inside; the table uses edge units; each declared
    field's unit, range and one-line doc are in its declaration).

    design, pneumatics : the robot (:class:`RobotDesign`) and its supply (:class:`RobotPneumatics`).
    inputs : per-chamber schedules {name: ((t s, speed 0-1, inlet 0-1, outlet 0-1), ...)}; chambers
        not listed keep everything closed. Safety interlocks of the open-loop scene close a chamber's
        inlet while its pressure is at the pressure limit or its stretch at ``design.max_stretch``.
    tip_force, tip_moment, sync_period : as :class:`hbma_ctrl.robot.plant.RobotPlantSettings`.

    Closed loop (mode 'closed_loop', see :mod:`hbma_ctrl.app.scenes.robot_loop`):
    controller : 'mpc' (per-chamber EKF bank + structured NMPC) or 'pressure_pid' (baseline).
    targets : {layer index: ((t s, centre height m, bend rad >= 0, direction rad), ...)}.
    tip_load : ((t s, fx N, fy N, fz N), ...) tip force from each row's time on (a disturbance the
        controller does not know).
    mpc_w_slack, target_rate : None = not given: the controller's default in a scene,
        :data:`hbma_ctrl.app.daemon.build.DAEMON_W_SLACK` and :data:`hbma_ctrl.app.daemon.build.DAEMON_TARGET_RATE`
        in the daemon.
    valve_min_on : at most the rig's sample period (:class:`hbma_ctrl.runtime.robot.RobotLoop`).
    valve_delay, sensor_delay : what the chambers' filters take
        (:class:`hbma_ctrl.estimators.robot_ekf.ChamberEKFSettings`; ``ROBOT_INSTANT`` of
        :mod:`hbma_ctrl.models.defaults` sets them and valve_min_on to 0).
    burst_sigma : the burst test's threshold (:mod:`hbma_ctrl.runtime.burst`).
    """

    WHERE = "robot"

    design: RobotDesign = field(default_factory=RobotDesign)
    pneumatics: RobotPneumatics = field(default_factory=RobotPneumatics)
    mode: str = setting("open_loop", choices=SCENE_MODES, doc="inputs by schedule or targets per layer")
    inputs: dict = field(default_factory=dict)
    tip_force: tuple = (0.0, 0.0, 0.0)
    tip_moment: tuple = (0.0, 0.0, 0.0)
    sync_period: float = 0.01
    snapshots: int = setting(8, integer=True, lo=1, hi=50, unit="shapes", doc="robot shapes in the shape plot")
    controller: str = setting("mpc", choices=CONTROLLERS, doc="closed loop: NMPC or the pressure PID")
    targets: dict = field(default_factory=dict)
    tip_load: tuple = ()
    compare_baseline: bool = setting(True, doc="also run the other controller")
    settle_time: float = setting(2.0, lo=0.0, hi=1e4, unit="s", key="settle_s",
                                 doc="RMSEs skip this long after a target change")
    mpc_horizon: int = setting(15, integer=True, lo=1, hi=100, unit="stages", key="horizon", doc="NMPC stages")
    mpc_dt: float = setting(0.02, lo=1e-3, hi=1.0, unit="s", user="ms", doc="NMPC prediction step")
    # repr=False: the stored reprs of the scenario goldens
    mpc_budget: float = setting(0.0, lo=0.0, hi=1.0, repr=False,
                                doc="NMPC wall-time budget per step as a fraction of the control period; an overrun "
                                    "is a failed step (0 = none; the daemon uses 0.8 then); in a scene it acts with "
                                    "enforce_budget")
    mpc_enforce_budget: bool = setting(False, repr=False, key="enforce_budget",
                                       doc="in a scene, make an NMPC step slower than mpc_budget a failed step, as in "
                                           "the rig daemon; off, results do not depend on the machine's load")
    target_rate: float | None = setting(None, lo=0.0, hi=1.0, unit="m/s", user="mm/s", repr=False,
                                        doc="fastest a chamber's target height moves after a new target (0 = steps; "
                                            "default: steps in a scene, 3 in the daemon)")
    mpc_w_slack: float | None = setting(None, lo=0.0, hi=1e6, unit="1/kPa", repr=False,
                                        doc="NMPC cost per kPa over its pressure limit (default: 0.001 in a scene, "
                                            "100 in the daemon: the limit first)")
    valve_min_on: float = setting(DEFAULT_VALVE_MIN_ON, lo=0.0, hi=0.1, unit="s", user="ms", repr=False,
                                  doc="the valves' shortest opening: smaller duties are realised on average over "
                                      "the periods (0 = duties sent as decided)")
    valve_delay: float = setting(DEFAULT_VALVE_DELAY, lo=0.0, hi=DELAY_MAX, unit="s", user="ms", repr=False,
                                 doc="the chambers' filters take the valves as acting this long after their "
                                     "command (0 = at once)")
    sensor_delay: float = setting(ROBOT_SENSOR_DELAY, lo=0.0, hi=DELAY_MAX, unit="s", user="ms", repr=False,
                                  doc="the chambers' filters take the pressure sensors as reading this late (0 = at once)")
    burst_sigma: float = setting(BurstTestSettings.threshold, lo=0.0, hi=1e4, unit="sigma", repr=False,
                                 doc="a chamber whose readings fall this far below its filter's prediction, summed "
                                     "over periods, is a burst: vented until a reset (0 = no burst test)")

    @property
    def plant(self) -> RobotPlantSettings:
        """The part of these settings the robot's plant needs."""
        return RobotPlantSettings(design=self.design, pneumatics=self.pneumatics, inputs=self.inputs,
                                  tip_force=self.tip_force, tip_moment=self.tip_moment,
                                  sync_period=self.sync_period)

    def check_rules(self) -> None:
        self.plant.validate()
        if self.mode == "closed_loop" and not self.targets:
            raise ValueError("robot.mode = 'closed_loop': closed-loop robot control needs robot.targets "
                             "(a table {all = [[t_s, height_mm, bend_deg, direction_deg], ...]} or one per layer)")
        for j, row in enumerate(self.tip_load):
            if len(row) != 4 or not all(math.isfinite(float(v)) for v in row) or row[0] < 0:
                raise ValueError(f"robot.tip_load_n[{j}] must be [t_s >= 0, fx, fy, fz] (finite)")

    @property
    def burst(self) -> BurstTestSettings | None:
        """The loop's burst test (None when ``burst_sigma`` is 0). Its step cap keeps the default's
        ratio to the threshold (0.4) at most, so that one or two wild readings never flag a burst alone."""
        if self.burst_sigma <= 0.0:
            return None
        d = BurstTestSettings()
        return BurstTestSettings(threshold=self.burst_sigma,
                                 step_cap=min(d.step_cap, self.burst_sigma * d.step_cap / d.threshold))

    def check_period(self, period: float) -> None:
        """ValueError naming ``[robot] valve_min_on_ms`` (as written, or its default) when the valves'
        minimum opening is longer than the loop's period ``period`` (s), the PWM period it shapes."""
        check_min_on("robot", self.valve_min_on, period)


def check_min_on(table: str, min_on: float, period: float) -> None:
    """ValueError naming ``[table] valve_min_on_ms`` and its range in ms when the valves' minimum
    opening ``min_on`` (s; as written or its default) is longer than the loop's period ``period``
    (s), the PWM period it shapes (the chamber's controller and the robot's loop)."""
    if min_on > period + 1e-12:
        raise ValueError(f"[{table}] valve_min_on_ms = {U.to_ms(min_on):g} is out of range [0, {U.to_ms(period):g}] "
                         f"ms (at most the loop's period, the rig's sample period; the default is "
                         f"{U.to_ms(DEFAULT_VALVE_MIN_ON):g})")
