"""The [daemon] table: how ``hbma-ctrl daemon`` runs a scenario on a rig (Hz, s, MB, baud).

The rest of the file (actuator or robot, rig, estimator, controller) is a scenario as the scenes
read it; this table adds the loop's rate, the rig link, the API address and the run log's
settings. Command-line flags override the keys of the same name.
"""

from __future__ import annotations

from pydantic import Field, model_validator

from hbma_ctrl.app.daemon.settings import DaemonConfig
from hbma_ctrl.app.schema.fields import RuleError, settings_table

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


class DaemonTable(settings_table("DaemonKeys", (DaemonConfig, (
        "rate_hz", "rig", "port", "board_controller", "baud", "speed", "duration", "api", "allow_remote", "token", "log_rotate_bytes",
        "log_flush", "status_every", "miss_limit")))):
    """[daemon] in the user's units (the keys are :class:`~hbma_ctrl.app.daemon.settings.DaemonConfig`'s
    declarations)."""

    fault: list[dict] = Field(default_factory=list, description="[[daemon.fault]] injected faults (sim only)")

    @model_validator(mode="after")
    def _rules(self) -> DaemonTable:
        if self.rig == "serial" and not self.port:
            raise RuleError("rig = 'serial' needs port = '/dev/...' (or --rig serial:PORT)")
        if self.board_controller and self.rig != "serial":
            raise RuleError("board_controller = true (or --board-controller) needs rig = 'serial' (--rig "
                            "serial:PORT): the controller runs on the rig's board")
        if self.api is not None:
            try:
                parse_api_address(self.api)
            except ValueError as exc:
                raise RuleError(str(exc)) from None
        if self.token is not None and not self.token.strip():
            raise RuleError("token must not be empty")
        return self
