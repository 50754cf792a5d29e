"""The [daemon] table: how ``hbma-ctrl daemon`` runs a scenario on a rig (Hz, s, MB, baud).

The rest of the file (actuator or robot, rig, estimator, controller) is a scenario as the scenes
read it; this table adds the loop's rate, the rig link, the API address and the run log's
settings. Command-line flags override the keys of the same name.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from hbma_ctrl.app.schema.fields import RuleError, Table, choice, flag, integer, num, text

__all__ = ["DaemonTable", "parse_api_address"]


def parse_api_address(value: str, key: str = "api") -> tuple[str, int]:
    """"HOST:PORT" (IPv6 as "[::1]:PORT") -> (host, port); ValueError naming ``key`` otherwise."""
    s = str(value).strip()
    host, sep, port = s.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"{key} = {value!r} must be HOST:PORT with PORT an integer in [0, 65535], "
                         "e.g. 127.0.0.1:8765")
    return host, int(port)


class DaemonTable(Table):
    """[daemon] in the user's units (the fields' descriptions give each unit and range)."""

    rate_hz: float = num(100.0, 1.0, 1000.0, "Hz", "loop rate: one read, tick and write per period")
    rig: Literal["sim", "serial"] = choice("sim", "rig backend: the simulated mismatched rig or the serial link")
    port: str | None = text(None, "serial port of the rig (rig = 'serial'), e.g. /dev/ttyACM0")
    baud: int = integer(115200, 1200, 4_000_000, "serial line rate", "baud")
    speed: float = num(1.0, 0.01, 1000.0, "-", "rig seconds per wall second (sim only; 1 = real time)")
    duration_s: float | None = num(None, 0.0, 1e7, "s", "rig time to run; none = until stopped", lo_open=True)
    api: str | None = text(None, "API address HOST:PORT (none = no API); loopback unless allow_remote")
    allow_remote: bool = flag(False, "let the API bind a non-loopback address (needs token)")
    token: str | None = text(None, "bearer token every API request must carry")
    log_rotate_mb: float = num(50.0, 0.01, 10000.0, "MB", "a run log part is closed at this size")
    log_flush_s: float = num(0.5, 0.01, 1.0, "s", "the run log is flushed at least this often")
    status_every: int = integer(1, 1, 1000, "publish the status to the API every this many periods")
    miss_limit: int = integer(10, 1, 100000, "missed deadlines in a row that stop the loop (loop watchdog)")
    fault: list[dict] = Field(default_factory=list, description="[[daemon.fault]] injected faults (sim only)")

    @model_validator(mode="after")
    def _rules(self) -> DaemonTable:
        if self.rig == "serial" and not self.port:
            raise RuleError("rig = 'serial' needs port = '/dev/...' (or --rig serial:PORT)")
        if self.api is not None:
            try:
                parse_api_address(self.api)
            except ValueError as exc:
                raise RuleError(str(exc)) from None
        if self.token is not None and not self.token.strip():
            raise RuleError("token must not be empty")
        return self
