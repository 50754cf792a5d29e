"""Run the rig daemon of a configuration into a results directory: the runtime loop, the rig link, the
safety monitor, the run log (CSV parts and ``log.mcap``, :mod:`hbma_ctrl.app.daemon.record`) and the API
(:func:`run_daemon`), as ``hbma-ctrl daemon`` and the daemon benches do."""

from __future__ import annotations

import json
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from hbma_ctrl.app.outputs import check_out, manifest, run_dir

if TYPE_CHECKING:
    from hbma_ctrl.app.daemon.config import DaemonConfig
    from hbma_ctrl.app.daemon.state import DaemonState

__all__ = ["link_errors", "run_daemon", "open_record", "LOG_MCAP"]

#: the MCAP log's file name in a run directory
LOG_MCAP = "log.mcap"


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


def _truth_of(rig):
    """The rig's true state as a callable (simulated rigs), None for a rig without one."""
    f = getattr(rig, "truth", None)
    if f is None:
        return None
    try:
        d = f()
        return f if "h" in d and "p" in d else None
    except (AttributeError, NotImplementedError, RuntimeError):  # a wrapped real rig has none
        return None


def open_record(cfg: DaemonConfig, runner, rig, folder: Path, argv: list | None = None):
    """The run's MCAP log (``folder/log.mcap``, a :class:`hbma_ctrl.app.daemon.record.DaemonRecord`) with
    the run's manifest and daemon settings as metadata and the configuration file attached."""
    from hbma_ctrl.app.daemon.record import DaemonRecord

    man = manifest("daemon", argv, cfg.path)
    meta = {"run": {k: "" if v is None else (v if isinstance(v, str) else json.dumps(v)) for k, v in man.items()
                    if k not in ("finished_utc", "status", "error")},
            "daemon": {"kind": cfg.kind, "rate_hz": f"{1.0 / cfg.period:g}", "speed": f"{cfg.speed:g}",
                       "rig": cfg.rig, "chambers": ",".join(runner.names),
                       "duration_s": "" if cfg.duration is None else f"{cfg.duration:g}"}}
    att = {}
    if cfg.path is not None and Path(cfg.path).is_file():
        att["config.toml"] = ("application/toml", Path(cfg.path).read_bytes())
    design = runner.design if cfg.kind == "robot" else None
    return DaemonRecord(folder / LOG_MCAP, runner.names, design=design, truth=_truth_of(rig), metadata=meta,
                        attachments=att)


def run_daemon(cfg: DaemonConfig, out: Path, overwrite: bool = False, argv: list | None = None,
               echo=None, state: DaemonState | None = None, mcap: bool = True) -> dict:
    """Run the daemon of ``cfg`` into ``out`` (see module doc); returns daemon_stats.json's content.
    ``echo``: where to print one-line notices (default stderr). ``state``: the state shared with the API.
    ``mcap``: write ``log.mcap`` too (False: the CSV run log only, as the log bench's baseline)."""
    from hbma_ctrl.app.daemon.apiproc import bind, serve
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
    record = None
    api_sock = None
    if cfg.api is not None:  # before the rig and the results directory: a busy port leaves nothing behind
        try:
            api_sock = bind(cfg.api[0], cfg.api[1])
        except OSError as exc:
            raise ValueError(f"--api / [daemon] api = {cfg.api[0]}:{cfg.api[1]}: cannot listen there "
                             f"({exc.strerror or exc}); stop what uses the port or choose another (0 = any free "
                             "port); nothing was sent to the rig") from None
    try:  # before the results directory: a rig that cannot be built leaves nothing behind
        rig = make_rig(cfg, runner)
    except link_errors() as exc:  # the port never opened: nothing, the safe command included, reached the rig
        if api_sock is not None:
            api_sock.close()
        raise ValueError(f"rig link: {exc} (nothing was sent to the rig)") from None
    with run_dir(out, command="daemon", argv=argv, scenario_path=cfg.path, overwrite=overwrite) as tmp:
        try:
            monitor = make_monitor(cfg, runner)
            layers = runner.design.n_layers if cfg.kind == "robot" else 0
            log = RunLog(tmp, chamber_columns(runner.names), cfg.log_rotate_bytes, cfg.log_flush,
                         event_fields=setpoint_columns(runner.names, layers))
            record = open_record(cfg, runner, rig, tmp, argv) if mcap else None
            loop = DaemonLoop(runner, rig, state, cfg.period, speed=cfg.speed, duration=cfg.duration, log=log,
                              monitor=monitor, status_every=cfg.status_every, miss_limit=cfg.miss_limit,
                              record=record)
            if cfg.api is not None:
                server = serve(state, cfg.api[0], cfg.api[1], allow_remote=cfg.allow_remote, token=cfg.token,
                               sock=api_sock)
                api_sock = None  # the API's process owns it now
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
            if api_sock is not None:  # the loop was never built: the socket never reached the API
                api_sock.close()
            try:
                rig.close()
            except Exception:  # noqa: BLE001 - the safe command is already out; closing must not mask why
                pass
            if record is not None:  # every queued period written, the file finished, whatever ended the loop
                logged = record.close(loop.stats() if loop is not None else None,
                                      getattr(runner, "calibration_summary", None))
        stats = loop.stats()
        if record is not None:
            stats["log_messages"] = logged["messages"]
            stats["log_dropped"] = logged["dropped"]
            for key in ("handoff_us_median", "handoff_us_p99", "handoff_cpu_us_median", "handoff_cpu_us_p99"):
                stats[f"log_{key}"] = logged[key]
            if logged["dropped"] or logged["failed"]:
                echo(f"log.mcap: {logged['dropped']} periods or events dropped (queue full), "
                     f"{logged['failed']} not written{': ' + logged['error'] if logged['error'] else ''}")
        (tmp / "daemon_stats.json").write_text(json.dumps(json_safe(stats), indent=1) + "\n")
        role = cfg.kind if cfg.kind in ("robot", "schedule") else "controller"
        metrics = {"daemon": stats, role: runner.stats()}
        (tmp / "metrics.json").write_text(json.dumps(json_safe(metrics), indent=1) + "\n")
    return stats
