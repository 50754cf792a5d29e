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
from hbma_ctrl.app.shipped import resolve
from hbma_ctrl.system.sections import Scenario

__all__ = ["Scenario", "load_scenario", "parse_scenario"]

#: UTF-8 byte order mark: stripped, the rest must be UTF-8 TOML
BOM = b"\xef\xbb\xbf"

#: TOML data (edge units) -> :class:`Scenario`; one '[table] key ...' ValueError line on bad input
parse_scenario = parse_scenario_tables


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario TOML file (see the module docstring); a path that does not exist
    but names a shipped scenario reads that one (:func:`hbma_ctrl.app.shipped.resolve`).

    Raises FileNotFoundError for a missing file and ValueError (prefixed with the file name) for
    bad content: not UTF-8 (a leading BOM is accepted), binary, not TOML, empty, or invalid tables.
    """
    path = resolve(path)
    if path.is_dir():
        raise ValueError(f"{path}: is a folder; give a scenario file (.toml) in it, or a shipped scenario's name "
                         "('hbma-ctrl scenarios list')")
    if not path.is_file():
        raise FileNotFoundError(f"scenario file not found: {path}")
    try:
        data = tomllib.loads(_text(path))
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: not valid TOML ({exc})") from None
    if not data:  # an empty file would silently run every default: almost surely the wrong file
        raise ValueError(f"{path}: the scenario file is empty (no tables or keys); a run needs at least "
                         "[scenario] name = '...' or one other table")
    try:
        return parse_scenario_tables(data, path)
    except ValueError as exc:
        raise ValueError(f"{path.name}: {exc}") from None


def _text(path: Path) -> str:
    """The file as UTF-8 text; a leading UTF-8 BOM (Windows editors add one) is dropped, not refused."""
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ValueError(f"{path}: cannot read ({exc.strerror})") from None
    if raw.startswith(BOM):
        raw = raw[len(BOM):]
    nul = raw.find(b"\x00")
    if nul >= 0:
        raise ValueError(f"{path}: binary content (NUL byte at offset {nul}), not a TOML text file")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        raise ValueError(f"{path}: not UTF-8 text (byte 0x{raw[exc.start]:02x} at offset {exc.start}, line {line}); "
                         "save it as UTF-8") from None
