"""Run the rig daemon of a configuration into a results directory: the runtime loop, the rig link, the
safety monitor, the run log and the API (:func:`run_daemon`), as ``hbma-ctrl daemon`` and the daemon
benches do."""

from __future__ import annotations

import json
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from hbma_ctrl.app.outputs import check_out, run_dir

if TYPE_CHECKING:
    from hbma_ctrl.app.daemon.config import DaemonConfig
    from hbma_ctrl.app.daemon.state import DaemonState

__all__ = ["link_errors", "run_daemon"]


def link_errors() -> tuple:
    """The exceptions that mean the rig link is gone or speaks another protocol version."""
    from hbma_ctrl.system.rigio import RigLinkError

    errs: list = [RigLinkError]
    try:
        from hbma_ctrl.system.serial_link import ProtocolVersionError
        errs.append(ProtocolVersionError)
    except ImportError:
        pass
    return tuple(errs)


def run_daemon(cfg: DaemonConfig, out: Path, overwrite: bool = False, argv: list | None = None,
               echo=None, state: DaemonState | None = None) -> dict:
    """Run the daemon of ``cfg`` into ``out`` (see module doc); returns daemon_stats.json's content.
    ``echo``: where to print one-line notices (default stderr). ``state``: the state shared with the API."""
    from hbma_ctrl.app.daemon.api import serve
    from hbma_ctrl.app.daemon.build import build_runner, make_monitor, make_rig
    from hbma_ctrl.app.daemon.loop import DaemonLoop
    from hbma_ctrl.app.daemon.runlog import RunLog, chamber_columns, setpoint_columns
    from hbma_ctrl.app.daemon.state import DaemonState
    from hbma_ctrl.app.metrics import json_safe

    echo = echo or (lambda s: print(s, file=sys.stderr, flush=True))
    check_out(out, overwrite)
    runner = build_runner(cfg)
    state = state or DaemonState()
    server = None
    loop = None
    try:  # before the results directory: a rig that cannot be built leaves nothing behind
        rig = make_rig(cfg, runner)
    except link_errors() as exc:  # the port never opened: nothing, the safe command included, reached the rig
        raise ValueError(f"rig link: {exc} (nothing was sent to the rig)") from None
    with run_dir(out, command="daemon", argv=argv, scenario_path=cfg.path, overwrite=overwrite) as tmp:
        try:
            monitor = make_monitor(cfg, runner)
            layers = runner.design.n_layers if cfg.kind == "robot" else 0
            log = RunLog(tmp, chamber_columns(runner.names), cfg.log_rotate_bytes, cfg.log_flush,
                         event_fields=setpoint_columns(runner.names, layers))
            loop = DaemonLoop(runner, rig, state, cfg.period, speed=cfg.speed, duration=cfg.duration, log=log,
                              monitor=monitor, status_every=cfg.status_every, miss_limit=cfg.miss_limit)
            if cfg.api is not None:
                server = serve(state, cfg.api[0], cfg.api[1], allow_remote=cfg.allow_remote, token=cfg.token)
                echo(f"api: {server.url}")
            echo(f"run log: {tmp}")

            def on_signal(signum, frame):  # only sets a flag: the loop writes the safe command and ends
                loop.signal_stop = signal.Signals(signum).name

            old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
            try:
                loop.run()
            finally:
                for s, h in old.items():
                    signal.signal(s, h)
        finally:
            if server is not None:
                server.stop()
            try:
                rig.close()
            except Exception:  # noqa: BLE001 - the safe command is already out; closing must not mask why
                pass
        stats = loop.stats()
        (tmp / "daemon_stats.json").write_text(json.dumps(json_safe(stats), indent=1) + "\n")
        role = cfg.kind if cfg.kind in ("robot", "schedule") else "controller"
        metrics = {"daemon": stats, role: runner.stats()}
        (tmp / "metrics.json").write_text(json.dumps(json_safe(metrics), indent=1) + "\n")
    return stats
