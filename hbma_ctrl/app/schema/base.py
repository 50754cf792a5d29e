"""The base tables of a scenario file: [scenario] [actuator] [pneumatics] [load] [inputs]
[protocol] [sim], in the user's units, and their conversion to the SI objects.

Each bound is stated in the key's own unit and checked when
:func:`~hbma_ctrl.app.scenario.parse_scenario` validates a file's tables.
"""

from __future__ import annotations

from dataclasses import fields, replace
from pathlib import Path
from typing import Any, Literal, NamedTuple

from pydantic import PrivateAttr, field_validator, model_validator

from hbma_ctrl.app.outputs import MAX_NAME_BYTES, NAME_RULE, is_plain_name
from hbma_ctrl.app.schema.errors import hint
from hbma_ctrl.app.schema.fields import (
    RuleError,
    Table,
    check_rows,
    choice,
    elem,
    key_field,
    num,
    settings_table,
    shaped,
    subtable,
    text,
)
from hbma_ctrl.core import units as U
from hbma_ctrl.core.materials import MATERIALS, make_material
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics, Valve
from hbma_ctrl.core.settings import specs
from hbma_ctrl.sim.batch import PROTOCOL_DEFAULTS
from hbma_ctrl.sim.trial import InputSchedule, SimSettings

__all__ = [
    "ActuatorTable",
    "InputsTable",
    "LoadTable",
    "MaterialName",
    "PneumaticsTable",
    "ProtocolTable",
    "ScenarioTable",
    "ScheduleRow",
    "SimTable",
    "build_material",
]

MaterialName = Literal["nh", "mr", "yeoh", "gent", "ogden"]


def build_material(name: str, params: dict, table: str) -> Any:
    """make_material with the table's one-line errors: an unknown parameter named as written with the
    closest one; a value that is not the parameter's number (or list of numbers, SI) as make_material says."""
    allowed = sorted(f.name for f in fields(MATERIALS[name]))
    for key in params:
        if key not in allowed:
            raise RuleError(f"{key}: unknown parameter of material '{name}'{hint(key, allowed)}", table)
    try:
        return make_material(name, **params)
    except (TypeError, ValueError, ArithmeticError) as exc:
        raise RuleError(str(exc), table) from None


class ScenarioTable(Table):
    """[scenario]: what the run is called, how long, one trial or the protocol grid."""

    name: str | None = text(None, "run name, also the default output directory runs/<name>; default: the "
                                  "file's stem")
    duration_s: float | None = num(None, 0.0, 3600.0, "s", "run length; default 6", lo_open=True)
    kind: Literal["single", "protocol"] = choice("single", "one trial or the protocol grid")

    @field_validator("name")
    @classmethod
    def _plain_name(cls, v: str | None) -> str | None:
        # the name becomes a directory when --out is omitted: never a path that escapes runs/
        if v is not None and len(v.encode()) > MAX_NAME_BYTES:
            # checked first: a megabyte name would be echoed whole below and slows every table that titles it
            raise RuleError(f"name = '{v[:40]}...' is {len(v.encode())} characters long: at most {MAX_NAME_BYTES} "
                            "can name a folder; shorten it",
                            "scenario")
        if v is not None and not is_plain_name(v):
            raise RuleError(f"name = {v!r} must be a plain directory name: {NAME_RULE}, no path separators",
                            "scenario")
        return v


class ActuatorTable(settings_table("ActuatorKeys", (Actuator, ("r1", "t0", "V0")))):
    """[actuator]: the membrane and its clamp (edge units), material by name with SI parameters."""

    material: MaterialName = choice("nh", "strain-energy model")
    material_params: dict[str, Any] = subtable(dict, "material parameters (SI, names per material)",
                                               "{name = value, ...}")
    _material: Any = PrivateAttr(None)

    @model_validator(mode="after")
    def _build_material(self) -> ActuatorTable:
        self._material = build_material(self.material, self.material_params, "actuator.material_params")
        return self

    def to_actuator(self) -> Actuator:
        """The SI actuator (m, m^3) with the material built once."""
        return Actuator(**self.si(Actuator), material=self._material).validate()


#: the outlet valve's conductance as [pneumatics] C_out (SI, as ``hbma-ctrl fit`` names it): the valve's declaration
_C_OUT_TYPE, _C_OUT = key_field(specs(Valve)["C"], None)


class PneumaticsTable(settings_table("PneumaticsKeys", (Pneumatics, ("compressor_csv", "flow_scale")))):
    """[pneumatics]: the compressor map (CSV, relative to the scenario file) and its scale, the outlet
    valve's sonic conductance."""

    C_out: _C_OUT_TYPE = _C_OUT

    def to_pneumatics(self, path: Path | None) -> Pneumatics:
        """SI pneumatics; a relative CSV path is resolved against the scenario file's folder."""
        csv = self.compressor_csv
        if csv is not None:
            csvp = Path(csv)
            if not csvp.is_absolute() and path is not None:
                csvp = (path.parent / csvp).resolve()
            if not csvp.is_file():
                raise ValueError(f"[pneumatics] compressor_csv: no such file '{csvp}'")
            csv = str(csvp)
        outlet = {} if self.C_out is None else {"outlet": replace(Pneumatics().outlet, C=self.C_out)}
        return Pneumatics(**{**self.si(Pneumatics), "compressor_csv": csv, **outlet}).validate()


class LoadTable(settings_table("LoadKeys", (Platform, ("load", "own_mass", "damping")))):
    """[load]: the dead load on the membrane, the platform's own mass and its damping."""

    def to_platform(self) -> Platform:
        """SI platform (kg, N s/m)."""
        return Platform(**self.si(Platform)).validate()


class ScheduleRow(NamedTuple):
    """One row of [inputs] schedule."""

    t_s: elem(0.0, 3600.0, "s", "switch time")
    speed_pct: elem(0.0, 100.0, "%", "compressor speed")
    inlet_duty: elem(0.0, 1.0, "-", "inlet valve duty")
    outlet_duty: elem(0.0, 1.0, "-", "outlet valve duty")


_ROW_SHAPE = "[[t_s, speed_pct, inlet_duty, outlet_duty], ...]"


class InputsTable(Table):
    """[inputs] (kind 'single'): the piecewise-constant commands."""

    schedule: list[ScheduleRow] | None = shaped(None, "commands from each row's time on", _ROW_SHAPE,
                                                min_length=1)

    @model_validator(mode="after")
    def _times(self) -> InputsTable:
        if self.schedule is not None:
            check_rows(self.schedule, "schedule")
        return self

    def to_schedule(self) -> InputSchedule | None:
        """SI schedule (speed as a fraction), or None when not given."""
        if self.schedule is None:
            return None
        return InputSchedule(tuple((r.t_s, U.pct(r.speed_pct), r.inlet_duty, r.outlet_duty)
                                   for r in self.schedule))


def _listify(v: Any) -> Any:
    # a single number stands for a one-value grid axis (``loads_g = 200`` is ``[200]``)
    return v if isinstance(v, (list, tuple)) else [v]


class ProtocolTable(Table):
    """[protocol] (kind 'protocol'): the grid of loads, speeds, thicknesses and radii."""

    loads_g: list[elem(0.0, 50000.0, "g", "load")] = shaped(
        PROTOCOL_DEFAULTS["loads_g"], "loads of the grid (g)", "[mass_g, ...]", min_length=1)
    speeds_pct: list[elem(0.0, 100.0, "%", "compressor speed", lo_open=True)] = shaped(
        PROTOCOL_DEFAULTS["speeds_pct"], "compressor speeds of the grid (%)", "[speed_pct, ...]", min_length=1)
    t0_mm: list[elem(0.05, 20.0, "mm", "membrane thickness", lo_open=True)] = shaped(
        PROTOCOL_DEFAULTS["t0_mm"], "membrane thicknesses of the grid (mm)", "[t0_mm, ...]", min_length=1)
    r1_mm: list[elem(0.5, 100.0, "mm", "disk radius", lo_open=True)] = shaped(
        PROTOCOL_DEFAULTS["r1_mm"], "disk radii of the grid (mm)", "[r1_mm, ...]", min_length=1)
    t_inflate_s: float = num(PROTOCOL_DEFAULTS["t_inflate_s"], 0.0, 3600.0, "s",
                             "inflation time before venting", lo_open=True)

    _wrap = field_validator("loads_g", "speeds_pct", "t0_mm", "r1_mm", mode="before")(
        lambda cls, v: _listify(v))

    @model_validator(mode="after")
    def _unique(self) -> ProtocolTable:
        for key in ("loads_g", "speeds_pct", "t0_mm", "r1_mm"):
            vals = getattr(self, key)
            if len(set(vals)) != len(vals):
                raise RuleError(f"{key} = {vals!r} has repeated values")
        return self

    def to_grid(self) -> dict:
        """The grid dict ``Scenario.protocol`` holds (edge units, as written)."""
        return {k: getattr(self, k) for k in ("loads_g", "speeds_pct", "t0_mm", "r1_mm", "t_inflate_s")}


class SimTable(settings_table("SimKeys", (SimSettings, ("integrator", "dt", "log_dt", "sensor_range")))):
    """[sim]: fidelity, integrator and steps of the open-loop simulation."""

    fidelity: Literal["auto", "free", "quasi_static", "platform", "exact"] = choice(
        "auto", "plant model; auto = free without a load; exact = the exact membrane (platform with a load)")

    def to_sim(self) -> SimSettings:
        """SI simulation settings (s, Pa)."""
        return SimSettings(**self.si(SimSettings)).validate()
