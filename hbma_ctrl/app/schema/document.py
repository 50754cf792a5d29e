"""The whole scenario file as one model: its tables, the rules across tables, the Scenario it builds.

:func:`parse_scenario_tables` is the one entry point: TOML data (edge units) -> the same
:class:`hbma_ctrl.app.scenario.Scenario` that ``hbma_ctrl.app.scenario.parse_scenario`` builds, with every
role section validated by its table model instead of a string-dispatched parser. Every input
error is a ``ValueError`` with one line that starts with ``[table]``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from pydantic import Field, ValidationError, ValidationInfo, model_validator

from hbma_ctrl.app.schema.base import (
    ActuatorTable,
    InputsTable,
    LoadTable,
    PneumaticsTable,
    ProtocolTable,
    ScenarioTable,
    SimTable,
)
from hbma_ctrl.app.schema.controller import ControllerTable
from hbma_ctrl.app.schema.daemon import DaemonTable
from hbma_ctrl.app.schema.errors import format_error
from hbma_ctrl.app.schema.estimator import EstimatorTable
from hbma_ctrl.app.schema.fields import RuleError, Table
from hbma_ctrl.app.schema.rig import RigTable
from hbma_ctrl.app.schema.robot import RobotTable
from hbma_ctrl.app.schema.schedule import ScheduleTable
from hbma_ctrl.system.sections import ROBOT_ESTIMATOR_KEYS, ROBOT_ESTIMATORS, Scenario
from hbma_ctrl.core import units as U
from hbma_ctrl.sim.batch import PROTOCOL_DEFAULTS
from hbma_ctrl.sim.trial import MAX_STEPS, InputSchedule

__all__ = ["DEFAULT_DURATION_S", "ROLE_TABLES", "ScenarioFile", "parse_role", "parse_scenario_tables"]

#: run length of a kind "single" scenario without duration_s, s
DEFAULT_DURATION_S = 6.0


def _default_schedule() -> InputSchedule:
    # full speed for 3 s, then vent: what a kind "single" file without [inputs] runs
    return InputSchedule.inflate_deflate(1.0, 3.0)


class ScenarioFile(Table):
    """Every table a scenario file may hold (all optional), validated together."""

    scenario: ScenarioTable = Field(default_factory=ScenarioTable, description="name, duration, kind")
    actuator: ActuatorTable = Field(default_factory=ActuatorTable, description="the HBMA (mm, cm^3)")
    pneumatics: PneumaticsTable = Field(default_factory=PneumaticsTable, description="compressor map")
    load: LoadTable = Field(default_factory=LoadTable, description="load and platform (g, N s/m)")
    inputs: InputsTable = Field(default_factory=InputsTable, description="commands (kind 'single')")
    protocol: ProtocolTable = Field(default_factory=ProtocolTable, description="grid (kind 'protocol')")
    sim: SimTable = Field(default_factory=SimTable, description="simulation (ms, kPa)")
    rig: RigTable | None = Field(None, description="the simulated rig (kPa, ms)")
    estimator: EstimatorTable | None = Field(None, description="the filter and its tuning")
    controller: ControllerTable | None = Field(None, description="the controller and its targets")
    robot: RobotTable | None = Field(None, description="the robot, its inputs or targets")
    daemon: DaemonTable | None = Field(None, description="the rig daemon: rate, rig link, API, log (hbma-ctrl daemon)")
    schedule: ScheduleTable | None = Field(None, description="an open-loop recording run on the daemon: pump / hold "
                                                             "/ vent steps")

    @model_validator(mode="after")
    def _across_tables(self, info: ValidationInfo) -> ScenarioFile:
        path = (info.context or {}).get("path") if info is not None else None
        sc, ld, fid = self.scenario, self.load, self.sim.fidelity
        mass_g = U.to_grams(U.grams(ld.mass_g) + U.grams(ld.own_mass_g))
        if sc.kind == "single":
            if self.protocol.model_fields_set:
                raise RuleError("is only allowed with [scenario] kind = 'protocol'", "protocol")
            schedule = self.inputs.to_schedule()
            # a closed loop or a recording never runs the default schedule: only a written one is checked
            open_loop = self.controller is None and self.robot is None and self.schedule is None
            last = (schedule or _default_schedule()).times[-1] if schedule is not None or open_loop else 0.0
            duration = sc.duration_s if sc.duration_s is not None else DEFAULT_DURATION_S
            if last >= duration:
                which = "" if schedule is not None else " (the default schedule; set [inputs] schedule)"
                raise RuleError(f"schedule: last switch at {last:g} s{which} must be before [scenario] "
                                f"duration_s = {duration:g} s", "inputs")
            name = sc.name or (Path(path).stem if path else "scenario")
            if fid == "free" and mass_g > 0:
                raise RuleError(f"fidelity = 'free' ignores the load of trial '{name}' ({mass_g:g} g); use auto, "
                                "quasi_static or platform", "sim")
            if fid in ("quasi_static", "platform") and mass_g <= 0:
                raise RuleError(f"fidelity = '{fid}' needs a load: set [load] mass_g > 0 (or use 'auto' / 'free')",
                                "sim")
        else:
            if self.inputs.model_fields_set:
                raise RuleError("is only allowed with [scenario] kind = 'single' (the protocol builds its own "
                                "inflate/vent schedule)", "inputs")
            duration = sc.duration_s if sc.duration_s is not None else PROTOCOL_DEFAULTS["duration_s"]
            if self.protocol.t_inflate_s >= duration:
                raise RuleError(f"t_inflate_s = {self.protocol.t_inflate_s:g} must be below [scenario] "
                                f"duration_s = {duration:g}", "protocol")
            if "mass_g" in ld.model_fields_set:
                raise RuleError("mass_g is not used with [scenario] kind = 'protocol'; set [protocol] loads_g "
                                "(own_mass_g and damping_ns_per_m apply to every loaded trial)", "load")
            if fid == "free" and any(x > 0 for x in self.protocol.loads_g):
                raise RuleError("fidelity = 'free' ignores the loads in [protocol] loads_g; use auto, "
                                "quasi_static or platform", "sim")
        if self.sim.log_dt_ms > U.to_ms(duration):  # no row after t = 0: every metric would read the start
            raise RuleError(f"log_dt_ms = {self.sim.log_dt_ms!r} is out of range [0.01, {U.to_ms(duration):g}] ms (at "
                            f"most [scenario] duration_s = {duration:g} s: the log, and the peaks read from it, "
                            "would hold only t = 0)", "sim")
        dt_ms = self.sim.dt_ms
        if dt_ms is not None and U.to_ms(duration) / dt_ms > MAX_STEPS:
            raise RuleError(f"dt_ms = {dt_ms!r} is out of range [{U.to_ms(duration) / MAX_STEPS:.3g}, 100] ms: "
                            f"[scenario] duration_s = {duration:g} s would take {U.to_ms(duration) / dt_ms:,.0f} "
                            f"steps, at most {MAX_STEPS:,}", "sim")
        self._sim_sensor_used()
        self._limits_within_sensor()
        self._robot_rig_keys()
        self._robot_estimator_keys()
        if self.schedule is not None and (self.controller is not None or self.robot is not None):
            raise RuleError("a recording runs open loop on one chamber: drop [controller] and [robot] (or the "
                            "[schedule])", "schedule")
        return self

    def _robot_rig_keys(self) -> None:
        """A [robot] scene's rig is the robot's: a single-chamber [rig] key it has no use for is refused
        at load, not ignored during the run."""
        if self.robot is None or self.rig is None:
            return
        why = self.rig.not_for_a_robot()
        if why:
            raise RuleError(why, "rig")

    def _robot_estimator_keys(self) -> None:
        """A [robot] scene's [estimator] picks the robot's estimator (kind ekf or mhe) and the windows'
        own keys; the single chamber's filter tuning does not reach the robot's chambers: refused."""
        if self.robot is None or self.estimator is None:
            return
        if self.robot.mode != "closed_loop":
            raise RuleError("an open-loop [robot] scene runs no estimator: drop [estimator] (or set [robot] "
                            "mode = \"closed_loop\")", "estimator")
        which = self.estimator.kind or self.estimator.filter
        if which not in ROBOT_ESTIMATORS:
            raise RuleError(f"kind = {which!r} is not a robot's estimator: allowed {', '.join(ROBOT_ESTIMATORS)} "
                            "(in a scenario with [robot])", "estimator")
        extra = sorted(set(self.estimator.model_fields_set) - set(ROBOT_ESTIMATOR_KEYS))
        if extra:
            raise RuleError(f"{extra[0]} is not read in a scenario with [robot]: its [estimator] takes "
                            f"{', '.join(ROBOT_ESTIMATOR_KEYS[:1] + ROBOT_ESTIMATOR_KEYS[2:])}", "estimator")

    def _sim_sensor_used(self) -> None:
        """[sim] sensor_range_kpa only reaches the open-loop plant and a closed loop without [rig]."""
        if "sensor_range_kpa" not in self.sim.model_fields_set:
            return
        # the scene that runs (runner.SCENE_DISPATCH order) and the key its sensor really comes from
        if self.robot is not None:
            scene, used = "[robot]", "[robot] sensor_range_kpa"
        elif self.controller is not None:
            scene, used = "[controller] with [rig]", "[rig] sensor_range_kpa"
            if self.rig is None:
                return  # run_scene builds its rig at [sim] sensor_range_kpa
        elif self.estimator is not None:
            scene, used = "[estimator]", "[rig] sensor_range_kpa (default 35)"
        else:
            return
        raise RuleError(f"sensor_range_kpa is not used in a scenario with {scene}; its sensor range is {used}: "
                        "move the value there", "sim")

    def _limits_within_sensor(self) -> None:
        """A pressure limit above the sensor's saturation can never be seen, so never enforced: refuse it."""
        if self.controller is None or self.robot is not None:  # a [robot] scene runs its own limits
            return
        # the closed loop's rig: [rig] when written, else a default rig at [sim] sensor_range_kpa (run_scene)
        key, sensor = (("[rig] sensor_range_kpa", self.rig.sensor_range_kpa) if self.rig is not None
                       else ("[sim] sensor_range_kpa", self.sim.sensor_range_kpa))
        if self.controller.p_max_kpa > sensor:
            raise RuleError(f"p_max_kpa = {self.controller.p_max_kpa!r} is out of range (0, {sensor:g}] kPa "
                            f"(at most {key} = {sensor:g}: above it the sensor saturates and the limit is "
                            "never seen)", "controller")

    def to_scenario(self, data: dict, path: Path | None = None) -> Scenario:
        """The SI Scenario (objects built once); ``data`` is kept as the raw role sections."""
        sc = self.scenario
        name = sc.name or (path.stem if path else "scenario")
        actuator = _convert("actuator", self.actuator.to_actuator)
        pneumatics = _convert("pneumatics", lambda: self.pneumatics.to_pneumatics(path))
        platform = _convert("load", self.load.to_platform)
        sim = _convert("sim", self.sim.to_sim)
        protocol: dict = {}
        if sc.kind == "single":
            schedule = self.inputs.to_schedule() or _default_schedule()
            duration = sc.duration_s if sc.duration_s is not None else DEFAULT_DURATION_S
        else:
            protocol = self.protocol.to_grid()
            duration = sc.duration_s if sc.duration_s is not None else PROTOCOL_DEFAULTS["duration_s"]
            schedule = InputSchedule.inflate_deflate(1.0, protocol["t_inflate_s"])
        sections = {k: data[k] for k in ROLE_TABLES if k in data}
        settings = {k: _convert(k, getattr(getattr(self, k), ROLE_TABLES[k][1])) for k in sections}
        return Scenario(name=name, kind=sc.kind, actuator=actuator, pneumatics=pneumatics, platform=platform,
                        schedule=schedule, duration=duration, sim=sim, fidelity=self.sim.fidelity,
                        sections=sections, settings=settings, protocol=protocol, path=path)


#: role table -> (its model, the method that builds its SI settings object)
ROLE_TABLES: dict[str, tuple[type[Table], str]] = {
    "rig": (RigTable, "to_settings"),
    "estimator": (EstimatorTable, "to_section"),
    "controller": (ControllerTable, "to_section"),
    "robot": (RobotTable, "to_settings"),
    "schedule": (ScheduleTable, "to_schedule"),
}


def _convert(table: str, build: Callable[[], Any]) -> Any:
    """Run one SI conversion; an error from an SI validate() still comes out as one '[table]' line."""
    try:
        return build()
    except ValueError as exc:
        msg = str(exc)
        raise ValueError(msg if msg.startswith("[") else f"[{table}] {msg}") from None


def parse_scenario_tables(data: dict, path: Path | None = None) -> Scenario:
    """Scenario TOML data (edge units) -> validated SI :class:`Scenario`; ValueError: one '[table]' line."""
    try:
        doc = ScenarioFile.model_validate(data, context={"path": path})
    except ValidationError as exc:
        raise ValueError(format_error(exc, ScenarioFile)) from None
    return doc.to_scenario(data, path)


def parse_role(name: str, raw: dict) -> Any:
    """One role table alone ("rig", "estimator", "controller", "robot"; edge units) -> its SI settings."""
    if name not in ROLE_TABLES:
        raise ValueError(f"[{name}]: not a role table; allowed: {', '.join(ROLE_TABLES)}")
    model, method = ROLE_TABLES[name]
    try:
        table = model.model_validate(raw)
    except ValidationError as exc:
        raise ValueError(format_error(exc, model, name)) from None
    return _convert(name, getattr(table, method))
