"""What the daemon runs with (SI), each setting declared once: the [daemon] table
(:class:`hbma_ctrl.app.schema.daemon.DaemonTable`) and the flags' checks read these declarations."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from hbma_ctrl.core.settings import Settings, setting
from hbma_ctrl.system.sections import Scenario

__all__ = ["DaemonConfig"]


@dataclass
class DaemonConfig(Settings):
    """Everything the daemon runs with (SI; each setting's unit, range and one-line doc are in its
    declaration).

    scenario : the validated scenario (actuator or robot, rig, estimator, controller).
    kind : 'chamber' (a [controller] table), 'robot' (a [robot] table in closed loop) or 'schedule' (a
        [schedule] of open-loop steps on one chamber: a recording).
    api : (host, port) of the API, None = no API (the table's key is "HOST:PORT").
    faults : the [[daemon.fault]] tables as written (edge units; parsed by the fault injector).
    path : the configuration file.
    """

    WHERE = "daemon"

    scenario: Scenario
    kind: str
    rate_hz: float = setting(100.0, lo=1.0, hi=1000.0, unit="Hz", doc="loop rate: one read, tick and write per period")
    rig: str = setting("sim", choices=("sim", "serial"),
                       doc="rig backend: the simulated mismatched rig or the serial link")
    port: str | None = setting(None, text=True, doc="serial port of the rig (rig = 'serial'), e.g. /dev/ttyACM0")
    board_controller: bool = setting(False, doc="the rig's board runs the controller (a hosted firmware): the "
                                     "daemon sends targets and logs what the board reports")
    baud: int = setting(115200, integer=True, lo=1200, hi=4_000_000, unit="baud", doc="serial line rate")
    speed: float = setting(1.0, lo=0.01, hi=1000.0, doc="rig seconds per wall second (sim only; 1 = real time)")
    duration: float | None = setting(None, lo=0.0, hi=1e7, lo_open=True, unit="s", key="duration_s",
                                     doc="rig time to run; none = until stopped")
    api: tuple[str, int] | None = setting(None, text=True,
                                          doc="API address HOST:PORT (none = no API); loopback unless allow_remote")
    allow_remote: bool = setting(False, doc="let the API bind a non-loopback address (needs token)")
    token: str | None = setting(None, text=True, doc="bearer token every API request must carry")
    log_rotate_bytes: int = setting(50_000_000, lo=1e4, hi=1e10, unit="B", user="MB", key="log_rotate_mb",
                                    doc="a run log part is closed at this size")
    log_flush: float = setting(0.5, lo=0.01, hi=1.0, unit="s", key="log_flush_s",
                               doc="the run log is flushed at least this often")
    status_every: int = setting(1, integer=True, lo=1, hi=1000,
                                doc="publish the status to the API every this many periods")
    miss_limit: int = setting(10, integer=True, lo=1, hi=100000,
                              doc="missed deadlines in a row that latch the overrun fault (loop watchdog; "
                                  "fewer are counted warnings)")
    faults: list = field(default_factory=list)
    path: Path | None = None

    @property
    def period(self) -> float:
        """Loop period, s."""
        return 1.0 / self.rate_hz
