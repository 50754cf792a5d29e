"""Scenario files: TOML in edge units (mm, kPa, g, %), loaded into validated SI objects.

A scenario names the pieces of one run and their settings; nothing else. Key names carry their unit
(``r1_mm``, ``dt_ms``, ``mass_g``); this module converts them once with :mod:`hbma_ctrl.units`.

Tables (all optional except where stated)::

    [scenario]   name, duration_s, kind = "single" | "protocol"
    [actuator]   r1_mm, t0_mm, V0_cm3, material = "nh"
    [actuator.material_params]   SI values, e.g. E = 130.6e3 (names per material)
    [pneumatics] compressor_csv (path, relative to the scenario file), flow_scale
    [load]       mass_g, own_mass_g, damping_ns_per_m
    [inputs]     schedule = [[t_s, speed_pct, inlet_duty, outlet_duty], ...]   (kind "single")
    [protocol]   loads_g, speeds_pct, t0_mm, r1_mm, t_inflate_s            (kind "protocol")
    [sim]        fidelity = "auto" | "free" | "quasi_static" | "platform", integrator, dt_ms,
                 log_dt_ms, sensor_range_kpa
    [rig] [estimator] [controller] [robot]   role sections, each parsed by its own parser (ROLE_SECTIONS)

Unknown tables and keys raise ``ValueError`` naming the field and the closest valid name; values
out of range raise ``ValueError`` naming ``table.key`` and the allowed range. Role sections are
validated by their owner's parser, imported lazily, so open-loop files never import estimators,
controllers or the robot.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import tomllib

from hbma_ctrl.app.robot_section import parse_section as parse_robot_section
from hbma_ctrl.app.scene_controller import parse_section as parse_controller_section
from hbma_ctrl.app.scene_estimator import parse_section as parse_estimator_section
from hbma_ctrl.core import units as U
from hbma_ctrl.core.materials import MATERIALS, make_material
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.core.validation import did_you_mean
from hbma_ctrl.sim.batch import (
    FIDELITY_CHOICES,
    PROTOCOL_DEFAULTS,
    fidelity_for,
    protocol_trials,
)
from hbma_ctrl.sim.rig import parse_rig_section
from hbma_ctrl.sim.trial import INTEGRATORS, InputSchedule, SimSettings, Trial

__all__ = ["Scenario", "load_scenario", "parse_scenario", "ROLE_SECTIONS", "FIDELITY_CHOICES",
           "KINDS", "fidelity_for"]

KINDS = ("single", "protocol")

#: role table -> its parser: takes the raw table (dict), returns a settings object or raises ValueError
ROLE_SECTIONS: dict[str, Callable[[dict], Any]] = {
    "rig": parse_rig_section,
    "estimator": parse_estimator_section,
    "controller": parse_controller_section,
    "robot": parse_robot_section,
}


@dataclass(frozen=True)
class _Key:
    """One allowed key: type, range in edge units (None = unbounded), SI conversion, choices."""

    kind: str  # 'float' | 'str' | 'floats' | 'schedule'
    lo: float | None = None
    hi: float | None = None
    unit: str = ""
    lo_open: bool = False
    choices: tuple = ()


_F = _Key
SCHEMA: dict[str, dict[str, _Key]] = {
    "scenario": {
        "name": _Key("str"),
        "duration_s": _F("float", 0.0, 3600.0, "s", lo_open=True),
        "kind": _Key("str", choices=KINDS),
    },
    "actuator": {
        "r1_mm": _F("float", 0.5, 100.0, "mm", lo_open=True),
        "t0_mm": _F("float", 0.05, 20.0, "mm", lo_open=True),
        "V0_cm3": _F("float", 0.001, 1000.0, "cm^3"),
        "material": _Key("str", choices=tuple(MATERIALS)),
        "material_params": _Key("table"),
    },
    "pneumatics": {
        "compressor_csv": _Key("str"),
        "flow_scale": _F("float", 0.0, 10.0),
    },
    "load": {
        "mass_g": _F("float", 0.0, 50000.0, "g"),
        "own_mass_g": _F("float", 0.0, 50000.0, "g"),
        "damping_ns_per_m": _F("float", 0.0, 1e5, "N s/m"),
    },
    "inputs": {
        "schedule": _Key("schedule"),
    },
    "protocol": {
        "loads_g": _F("floats", 0.0, 50000.0, "g"),
        "speeds_pct": _F("floats", 0.0, 100.0, "%", lo_open=True),
        "t0_mm": _F("floats", 0.05, 20.0, "mm", lo_open=True),
        "r1_mm": _F("floats", 0.5, 100.0, "mm", lo_open=True),
        "t_inflate_s": _F("float", 0.0, 3600.0, "s", lo_open=True),
    },
    "sim": {
        "fidelity": _Key("str", choices=FIDELITY_CHOICES),
        "integrator": _Key("str", choices=INTEGRATORS),
        "dt_ms": _F("float", 1e-4, 100.0, "ms"),
        "log_dt_ms": _F("float", 0.01, 10000.0, "ms"),
        "sensor_range_kpa": _F("float", 1.0, 1000.0, "kPa"),
    },
}


def _suggest(word: str, options) -> str:
    # a looser cutoff than the default: scenario keys are long, a typo moves them further
    return did_you_mean(word, options, cutoff=0.5)


def _range_text(k: _Key) -> str:
    left = "(" if k.lo_open else "["
    return f"{left}{k.lo:g}, {k.hi:g}] {k.unit}".rstrip()


def _check_number(where: str, value: Any, k: _Key) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{where} = {value!r} must be a number in {_range_text(k)}")
    v = float(value)
    ok = math.isfinite(v) and (v > k.lo if k.lo_open else v >= k.lo) and v <= k.hi
    if not ok:
        raise ValueError(f"{where} = {value!r} is out of range {_range_text(k)}")
    return v


def _check_table(table: str, raw: Any, schema: dict[str, _Key]) -> dict:
    """Type- and range-check one table; returns {key: checked value} (edge units)."""
    if not isinstance(raw, dict):
        raise ValueError(f"[{table}] must be a table, got {type(raw).__name__}")
    out = {}
    for key, value in raw.items():
        where = f"{table}.{key}"
        if key not in schema:
            raise ValueError(f"unknown key '{where}'{_suggest(key, schema)}; allowed: {', '.join(schema)}")
        k = schema[key]
        if k.kind == "float":
            out[key] = _check_number(where, value, k)
        elif k.kind == "str":
            if not isinstance(value, str):
                raise ValueError(f"{where} = {value!r} must be a string")
            if k.choices and value not in k.choices:
                raise ValueError(f"{where} = '{value}'{_suggest(value, k.choices)}; allowed: "
                                 f"{', '.join(k.choices)}")
            out[key] = value
        elif k.kind == "floats":
            vals = value if isinstance(value, list) else [value]
            if not vals:
                raise ValueError(f"{where} must be a non-empty list of numbers in {_range_text(k)}")
            out[key] = [_check_number(f"{where}[{i}]", v, k) for i, v in enumerate(vals)]
            if len(set(out[key])) != len(out[key]):
                raise ValueError(f"{where} = {value!r} has repeated values")
        elif k.kind == "table":
            if not isinstance(value, dict):
                raise ValueError(f"{where} must be a table")
            out[key] = dict(value)
        elif k.kind == "schedule":
            out[key] = _parse_schedule(where, value)
    return out


def _parse_schedule(where: str, value: Any) -> InputSchedule:
    """[[t_s, speed_pct, inlet_duty, outlet_duty], ...] -> InputSchedule (SI, fractions)."""
    if not isinstance(value, list) or not value:
        raise ValueError(f"{where} must be a non-empty list of [t_s, speed_pct, inlet_duty, outlet_duty]")
    rows = []
    cols = (_F("float", 0.0, 3600.0, "s"), _F("float", 0.0, 100.0, "%"), _F("float", 0.0, 1.0),
            _F("float", 0.0, 1.0))
    names = ("t_s", "speed_pct", "inlet_duty", "outlet_duty")
    last = -1.0
    for i, row in enumerate(value):
        if not isinstance(row, list) or len(row) != 4:
            raise ValueError(f"{where}[{i}] = {row!r}: need [t_s, speed_pct, inlet_duty, outlet_duty]")
        t, sp, inl, outl = (_check_number(f"{where}[{i}].{n}", v, c) for n, v, c in zip(names, row, cols))
        if i == 0 and t != 0.0:
            raise ValueError(f"{where}[0].t_s = {t:g} must be 0 (the schedule starts at t = 0 s)")
        if t <= last:
            raise ValueError(f"{where}[{i}].t_s = {t:g} must be after the previous row's {last:g} s")
        last = t
        rows.append((t, U.pct(sp), inl, outl))
    return InputSchedule(tuple(rows))


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


def _parse_role(name: str, raw: dict, roles: dict[str, Callable[[dict], Any]]):
    if not isinstance(raw, dict):
        raise ValueError(f"[{name}] must be a table")
    return roles[name](dict(raw))


def parse_scenario(data: dict, path: Path | None = None,
                   roles: dict[str, Callable[[dict], Any]] | None = None) -> Scenario:
    """Build a :class:`Scenario` from parsed TOML data (edge units); see the module docstring."""
    roles = ROLE_SECTIONS if roles is None else roles
    allowed = list(SCHEMA) + list(roles)
    for table in data:
        if table not in allowed:
            raise ValueError(f"unknown table [{table}]{_suggest(table, allowed)}; allowed: {', '.join(allowed)}")
    t = {name: _check_table(name, data.get(name, {}), schema) for name, schema in SCHEMA.items()}

    sc = t["scenario"]
    kind = sc.get("kind", "single")
    name = sc.get("name") or (path.stem if path else "scenario")

    a = t["actuator"]
    mat_name = a.get("material", "nh")
    try:
        material = make_material(mat_name, **a.get("material_params", {}))
    except TypeError as exc:
        raise ValueError(f"actuator.material_params: {exc}") from None
    except ValueError as exc:
        raise ValueError(f"actuator.material_params: {exc}") from None
    base = Actuator()
    actuator = Actuator(r1=U.mm(a.get("r1_mm", U.to_mm(base.r1))), t0=U.mm(a.get("t0_mm", U.to_mm(base.t0))),
                        V0=U.cm3(a.get("V0_cm3", U.to_cm3(base.V0))), material=material).validate()

    p = t["pneumatics"]
    csv = p.get("compressor_csv")
    if csv is not None:
        csvp = Path(csv)
        if not csvp.is_absolute() and path is not None:
            csvp = (path.parent / csvp).resolve()
        if not csvp.is_file():
            raise ValueError(f"pneumatics.compressor_csv: no such file '{csvp}'")
        csv = str(csvp)
    pneumatics = Pneumatics(compressor_csv=csv, flow_scale=p.get("flow_scale", 1.0)).validate()

    ld = t["load"]
    base_pl = Platform()
    platform = Platform(load=U.grams(ld.get("mass_g", 0.0)), own_mass=U.grams(ld.get("own_mass_g", 0.0)),
                        damping=ld.get("damping_ns_per_m", base_pl.damping)).validate()

    s = t["sim"]
    fidelity = s.get("fidelity", "auto")
    dt = U.mm(s["dt_ms"]) if "dt_ms" in s else None  # ms -> s is the same factor as mm -> m
    sim = SimSettings(integrator=s.get("integrator", "rk4"), dt=dt,
                      log_dt=s.get("log_dt_ms", 10.0) * 1e-3,
                      sensor_range=U.kpa(s.get("sensor_range_kpa", 35.0))).validate()

    protocol: dict = {}
    if kind == "single":
        if data.get("protocol"):
            raise ValueError("[protocol] is only allowed with scenario.kind = 'protocol'")
        schedule = t["inputs"].get("schedule", InputSchedule.inflate_deflate(1.0, 3.0))
        duration = sc.get("duration_s", 6.0)
        if schedule.times[-1] >= duration:
            raise ValueError(f"inputs.schedule: last switch at {schedule.times[-1]:g} s must be before "
                             f"scenario.duration_s = {duration:g} s")
        trial = Trial(actuator, pneumatics, platform, schedule, duration, name)
        fidelity_for(trial, fidelity)  # raises for 'free' with a load
        if fidelity in ("quasi_static", "platform") and platform.mass <= 0:
            raise ValueError(f"sim.fidelity = '{fidelity}' needs a load: set load.mass_g > 0 "
                             "(or use 'auto' / 'free')")
    else:
        if data.get("inputs"):
            raise ValueError("[inputs] is only allowed with scenario.kind = 'single' "
                             "(the protocol builds its own inflate/vent schedule)")

        pr = {**PROTOCOL_DEFAULTS, **t["protocol"]}
        duration = sc.get("duration_s", PROTOCOL_DEFAULTS["duration_s"])
        if pr["t_inflate_s"] >= duration:
            raise ValueError(f"protocol.t_inflate_s = {pr['t_inflate_s']:g} must be below "
                             f"scenario.duration_s = {duration:g}")
        if "mass_g" in ld:
            raise ValueError("load.mass_g is not used with scenario.kind = 'protocol'; set protocol.loads_g "
                             "(load.own_mass_g and load.damping_ns_per_m apply to every loaded trial)")
        if fidelity == "free" and any(x > 0 for x in pr["loads_g"]):
            raise ValueError("sim.fidelity = 'free' ignores the loads in protocol.loads_g; "
                             "use auto, quasi_static or platform")
        protocol = {k: pr[k] for k in ("loads_g", "speeds_pct", "t0_mm", "r1_mm", "t_inflate_s")}
        schedule = InputSchedule.inflate_deflate(1.0, pr["t_inflate_s"])

    sections = {k: data[k] for k in roles if k in data}
    settings = {k: _parse_role(k, v, roles) for k, v in sections.items()}
    return Scenario(name=name, kind=kind, actuator=actuator, pneumatics=pneumatics, platform=platform,
                    schedule=schedule, duration=duration, sim=sim, fidelity=fidelity, sections=sections,
                    settings=settings, protocol=protocol, path=path)


def load_scenario(path: str | Path, roles: dict[str, Callable[[dict], Any]] | None = None) -> Scenario:
    """Read and validate a scenario TOML file (see the module docstring).

    Raises FileNotFoundError for a missing file and ValueError (prefixed with the file name) for
    bad content.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"scenario file not found: {path}")
    try:
        with path.open("rb") as fh:
            data = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: not valid TOML ({exc})") from None
    try:
        return parse_scenario(data, path, roles)
    except ValueError as exc:
        raise ValueError(f"{path.name}: {exc}") from None
