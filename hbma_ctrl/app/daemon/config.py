"""The daemon's configuration: a scenario file with a [daemon] table, and the flags that override it (SI).

:func:`load_config` reads the file once: the scenario tables go through the scenario schema (the
same objects the scenes build), the [daemon] table through :class:`DaemonTable`; flags given on the
command line replace the keys of the same name before validation, so a bad flag and a bad key get
the same one-line error (naming the flag when it came from one).
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from hbma_ctrl.app.daemon.api import is_loopback
from hbma_ctrl.app.daemon.settings import DaemonConfig
from hbma_ctrl.app.scenario import load_scenario
from hbma_ctrl.app.shipped import resolve
from hbma_ctrl.app.schema.daemon import DaemonTable, parse_api_address
from hbma_ctrl.app.schema.errors import format_error

__all__ = ["DaemonConfig", "FLAG_KEYS", "load_config", "parse_rig_flag"]

#: command-line flag -> [daemon] key it overrides
FLAG_KEYS = {"--speed": "speed", "--duration-s": "duration_s", "--api": "api", "--allow-remote": "allow_remote",
             "--token": "token", "--board-controller": "board_controller"}
#: the flags that give a number (bounded by its key's declaration)
_NUMBERS = ("--speed", "--duration-s")


def parse_rig_flag(value: str) -> dict:
    """``--rig sim`` or ``--rig serial:PORT`` -> the [daemon] keys it sets; ValueError naming --rig."""
    v = str(value).strip()
    if v == "sim":
        return {"rig": "sim"}
    if v.startswith("serial:") and len(v) > len("serial:"):
        return {"rig": "serial", "port": v[len("serial:"):]}
    raise ValueError(f"--rig = {value!r}: allowed 'sim' or 'serial:PORT' (e.g. serial:/dev/ttyACM0)")


def _check_flag(flag: str, value: Any) -> None:
    """A flag's own range, in the user's units, before it joins the table (so the error names the flag)."""
    if flag in _NUMBERS:
        spec = DaemonTable.settings_keys[FLAG_KEYS[flag]][2]
        (lo, hi), unit = spec.user_bounds(), spec.user_unit
        number = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        if not (number and (value > lo if spec.lo_open else value >= lo) and value <= hi):
            raise ValueError(f"{flag} = {value!r} is out of range {'(' if spec.lo_open else '['}{lo:g}, {hi:g}] "
                             f"{'' if unit == '-' else unit}".rstrip() + f": {spec.doc}")
    if flag == "--api":
        parse_api_address(value, "--api")
    if flag == "--token" and not str(value).strip():
        raise ValueError("--token must not be empty")


def load_config(path: str | Path, flags: dict | None = None) -> DaemonConfig:
    """Read CONFIG.toml, apply ``flags`` ({'--speed': 20.0, '--rig': 'serial:/dev/x', ...}; None values
    are not given) and validate. ValueError / FileNotFoundError: one line naming the key or flag."""
    path = resolve(path)  # a shipped scenario's name reads the shipped file, as load_scenario does
    scn = load_scenario(path)  # also validates [daemon] as written (one '[daemon] key' line)
    with path.open("rb") as fh:
        raw = dict(tomllib.load(fh).get("daemon") or {})
    for flag, value in (flags or {}).items():
        if value is None or value is False:
            continue
        if flag == "--rig":
            raw.update(parse_rig_flag(value))
            if value == "sim":
                raw.pop("port", None)
            continue
        if flag not in FLAG_KEYS:
            raise ValueError(f"unknown flag {flag}")
        _check_flag(flag, value)
        raw[FLAG_KEYS[flag]] = value
    try:
        d = DaemonTable.model_validate(raw)
    except ValidationError as exc:
        raise ValueError(f"{path.name}: {format_error(exc, DaemonTable, 'daemon')}") from None
    except ValueError as exc:
        raise ValueError(f"{path.name}: [daemon] {exc}") from None
    robot = scn.role("robot")
    if robot is not None:
        if getattr(robot, "mode", None) != "closed_loop":
            raise ValueError(f"{path.name}: [robot] mode = {robot.mode!r}: the daemon runs mode = 'closed_loop'")
        kind = "robot"
    elif scn.role("controller") is not None:
        kind = "chamber"
    elif scn.role("schedule") is not None:
        kind = "schedule"
    else:
        raise ValueError(f"{path.name}: the daemon needs a [controller] table (one chamber), a [robot] table "
                         "with mode = 'closed_loop' or a [schedule] of pump / hold / vent steps (a recording)")
    if d.board_controller and kind != "chamber":
        raise ValueError(f"{path.name}: [daemon] board_controller = true (or --board-controller) runs a chamber's "
                         "controller on the board: the file needs a [controller] table (one chamber)")
    if d.rig == "serial" and d.speed != 1.0:
        raise ValueError(f"{path.name}: [daemon] speed = {d.speed:g} (or --speed) needs rig = 'sim'; a serial rig "
                         "runs in real time (speed 1)")
    if d.rig == "serial" and d.fault:
        raise ValueError(f"{path.name}: [[daemon.fault]] injects faults into the simulated rig only (rig = 'sim')")
    api = parse_api_address(d.api) if d.api is not None else None
    if api is not None and not is_loopback(api[0]) and not (d.allow_remote and d.token):
        raise ValueError(f"{path.name}: [daemon] api = {d.api!r} (or --api) is not a loopback address (127.0.0.1, ::1, "
                         "localhost); another address needs allow_remote = true (--allow-remote) and a token (--token)")
    given = d.si(DaemonConfig)
    if kind == "schedule" and "duration" not in given:
        given["duration"] = scn.role("schedule").length  # a recording ends with its schedule
    if "log_rotate_bytes" in given:
        given["log_rotate_bytes"] = int(given["log_rotate_bytes"])
    return DaemonConfig(scenario=scn, kind=kind, **{**given, "api": api}, faults=list(d.fault), path=path)
