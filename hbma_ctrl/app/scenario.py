"""Scenario files: TOML in edge units (mm, kPa, g, %), loaded into validated SI objects.

A scenario names the pieces of one run and their settings; nothing else. Key names carry their unit
(``r1_mm``, ``dt_ms``, ``mass_g``); every table is one pydantic model of :mod:`hbma_ctrl.app.schema`
with its bounds in those units, converted to SI once after validation.

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
    [rig] [estimator] [controller] [robot]   role tables (see each model's field descriptions)

Every bad input is one ``ValueError`` line naming the table and the key as written, the allowed
range in the user's units, and the closest valid name for a misspelt key or table.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

from hbma_ctrl.app.schema.document import parse_scenario_tables
from hbma_ctrl.app.sections import Scenario

__all__ = ["Scenario", "load_scenario", "parse_scenario"]

#: TOML data (edge units) -> :class:`Scenario`; one '[table] key ...' ValueError line on bad input
parse_scenario = parse_scenario_tables


def load_scenario(path: str | Path) -> Scenario:
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
        return parse_scenario_tables(data, path)
    except ValueError as exc:
        raise ValueError(f"{path.name}: {exc}") from None
