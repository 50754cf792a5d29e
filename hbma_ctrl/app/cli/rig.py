"""``hbma-ctrl rig``: ``emulate`` runs an emulated board of the reference firmware (``firmware/``),
``check`` runs the bring-up checklist (:mod:`hbma_ctrl.app.rigcheck`) against any firmware's port.

Registered by :mod:`hbma_ctrl.app.cli.main` through :func:`register`. ``emulate --target host`` builds
the firmware's POSIX host board and runs it (:class:`~hbma_ctrl.app.daemon.firmware.HostBoard`) with
a simulated plant stepped in real time: :class:`~hbma_ctrl.app.daemon.firmware.FirstOrderPlant`, one
per chamber, or with ``--config`` the configuration's simulated (mismatched) rig, one rig period per
board period (:func:`~hbma_ctrl.app.daemon.firmware.config_plant`); ``--defect`` injects firmware
defects. ``--target avr`` builds the Uno firmware and runs it in simavr, its sensors reading
first-order chambers driven by its pins. Either way the first line on stdout is the serial port to
give the daemon (``--rig serial:PORT``) or ``rig check``; it runs until SIGINT or SIGTERM, then stops
the board and removes its build folder.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import tempfile
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Optional

import typer

from hbma_ctrl.app.cli.args import check_choice, check_range, console, show_table
from hbma_ctrl.app.daemon.firmware import DEFECTS, HostBoard, RealtimeBoard, build_firmware
from hbma_ctrl.app.outputs import OVERWRITE_HELP, cli_argv, run_dir
from hbma_ctrl.core.units import kpa, ms

__all__ = ["register"]


def _is_truth_log(path: Path) -> bool:
    """Whether ``path`` starts as rig emulate's truth log does (its header: dt_ms,mode,t_s,...)."""
    try:
        with path.open("rb") as fh:
            return fh.readline(64).startswith(b"dt_ms,mode,t_s")
    except OSError:
        return False


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add the ``rig`` command group to ``app``."""
    rig_app = typer.Typer(add_completion=False, no_args_is_help=True,
                          help="The rig's reference firmware (firmware/): an emulated board, a bring-up check.")
    app.add_typer(rig_app, name="rig")

    @rig_app.command("emulate")
    def emulate(
        target: Annotated[str, typer.Option(help="host (POSIX build + simulated plant) or avr (Uno build in simavr)")] = "host",
        n: Annotated[Optional[int], typer.Option("--n", help="chambers, 1..4 (avr) or 1..16 (host); default 1 or the config's")] = None,
        config: Annotated[Optional[Path], typer.Option(help="host only: a daemon CONFIG.toml whose simulated rig is the plant")] = None,
        truth_log: Annotated[Optional[Path], typer.Option(help="with --config: CSV of the rig's true state per period")] = None,
        period_ms: Annotated[Optional[float], typer.Option("--period-ms", help="host only: sample period, ms, 1..1000 in 0.1 ms steps (default 10 or the config's)")] = None,
        defect: Annotated[Optional[str], typer.Option(help=f"host only: inject defects, comma-separated: {', '.join(DEFECTS)}")] = None,
        link: Annotated[Optional[Path], typer.Option(help="host only: also keep this symlink pointing at the port, and print it")] = None,
        library: Annotated[Optional[Path], typer.Option(help="host only: the board runs this chamber library (a folder from codegen --library; the daemon then needs --board-controller)")] = None,
    ) -> None:
        """Run an emulated rig board; print its serial port on the first line, run until Ctrl-C/SIGTERM."""
        check_choice("--target", target, ("host", "avr"))
        check_range("--n", n, 1, 16 if target == "host" else 4, note=f"chambers of --target {target}")
        check_range("--period-ms", period_ms, 1.0, 1000.0, unit="ms")
        for flag, given in (("--config", config), ("--period-ms", period_ms), ("--defect", defect), ("--link", link),
                            ("--library", library)):
            if given is not None and target != "host":
                raise ValueError(f"{flag}: runs with --target host only")
        defects = [d for d in (defect or "").split(",") if d]
        for d in defects:
            check_choice("--defect", d, DEFECTS)
        if link is not None and link.exists() and not link.is_symlink():
            # the link is replaced while the board runs and removed at its end: never a user's file or folder
            raise ValueError(f"--link {link}: exists and is not a symlink; give a new path (or an old link's)")
        if link is not None and not link.parent.is_dir():
            raise ValueError(f"--link {link}: the folder {link.parent} does not exist")
        if truth_log is not None and (truth_log.is_dir() or (truth_log.is_file() and not _is_truth_log(truth_log))):
            # it is rewritten from its first line: only an earlier truth log may be
            raise ValueError(f"--truth-log {truth_log}: exists and is not a truth log of rig emulate; give a new "
                             "path (or an old truth log's)")
        if truth_log is not None and config is None:
            raise ValueError("--truth-log: needs --config (the first-order plant has no truth to log)")
        if period_ms is not None and config is not None:
            raise ValueError("--period-ms: the config's rig sets the period; leave --period-ms out with --config")
        if library is not None and not (library / "hbma.h").is_file():
            raise ValueError(f"--library {library}: no hbma.h there (generate a chamber library with hbma-ctrl "
                             "codegen CONFIG --library --out DIR)")
        stop = threading.Event()
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(sig, lambda *_: stop.set())
        work = Path(tempfile.mkdtemp(prefix="hbma-rig-"))
        try:
            if target == "host":
                _emulate_host(work, n, stop, config, truth_log, period_ms, defects, link, library)
            else:
                _emulate_avr(work, n or 1, stop)
        finally:
            shutil.rmtree(work, ignore_errors=True)


    @rig_app.command("check")
    def check(
        port: Annotated[str, typer.Argument(help="the rig's serial port: a device path or a pyserial URL")],
        out: Annotated[Path, typer.Option("--out", "-o", help="output directory (check.json)")],
        n: Annotated[Optional[int], typer.Option("--n", help="chambers the rig must report (default: the firmware's)")] = None,
        baud: Annotated[int, typer.Option(help="line speed, baud")] = 115200,
        rise_kpa: Annotated[float, typer.Option("--rise-kpa", help="how much each fill step inflates a chamber, kPa")] = 5.0,
        step_s: Annotated[float, typer.Option("--step-s", help="firmware time a valve or the pump may take to move the pressure, s")] = 2.0,
        overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
    ) -> None:
        """Bring-up checklist of a rig's firmware (line protocol 2): writes check.json, exit 1 if a check fails."""
        from hbma_ctrl.app.rigcheck import CheckSettings, open_port, run_checks

        check_range("--n", n, 1, 64, note="chambers")
        check_range("--baud", baud, 1, 10_000_000, unit="baud")
        check_range("--rise-kpa", rise_kpa, 0.0, 100.0, lo_open=True, unit="kPa")
        check_range("--step-s", step_s, 0.0, 60.0, lo_open=True, unit="s")
        if "://" not in port and not os.path.exists(port):
            raise ValueError(f"PORT {port}: no such port (give the rig's device, e.g. /dev/ttyACM0)")
        settings = CheckSettings(n=n, rise=kpa(rise_kpa), step_s=step_s)
        ser = open_port(port, baud)
        try:
            with run_dir(out, command="rig check", argv=cli_argv(), overwrite=overwrite) as tmp:
                checks = run_checks(ser, settings)
                passed = all(c.passed for c in checks)
                doc = {"passed": passed, "checks": [c.as_dict() for c in checks]}
                (tmp / "check.json").write_text(json.dumps(doc, indent=1) + "\n")
        finally:
            ser.close()
        failed = sum(not c.passed for c in checks)
        con = show_table(f"rig check {port}", ("check", "passed", "measured", "expected"),
                         ((c.name, "yes" if c.passed else "NO", c.measured, c.expected) for c in checks),
                         con=console(120), left=4)
        con.print(f"{'all checks passed' if passed else f'{failed} of {len(checks)} checks failed'}; "
                  f"see {out / 'check.json'}", markup=False)
        if not passed:
            raise typer.Exit(1)


def _emulate_host(work: Path, n: int | None, stop: threading.Event, config: Path | None,
                  truth_log: Path | None, period_ms: float | None = None, defects: Sequence[str] = (),
                  link: Path | None = None, library: Path | None = None) -> None:
    from hbma_ctrl.app.daemon.firmware import FirstOrderPlant, config_plant

    tick = 100e-6  # the host board's default tick, s
    plant, behind, period = FirstOrderPlant(n or 1), 10, 0.01 if period_ms is None else ms(period_ms)
    if config is not None:
        plant, behind = config_plant(config, truth_log), 1  # one rig period per call
        if n is not None and n != plant.n:
            plant.close()
            raise ValueError(f"--n = {n}: the config's rig has {plant.n} chambers; leave --n out with --config")
        period = plant.period
    ticks = round(period / tick)
    if not 1 <= ticks <= 65535 or abs(ticks * tick - period) > 1e-9:
        raise ValueError(f"the sample period {period * 1e3:g} ms is not a whole number of 0.1 ms ticks")
    exe = build_firmware("host", work) if library is None else build_firmware("host-hosted", work, library=library)
    board = HostBoard(exe, plant.n, period_ticks=ticks, eeprom=work / "eeprom.bin", defects=defects, link=link)
    mode = ["SAFE"]
    if config is not None:
        plant.mode = lambda: mode[0]  # the truth log's mode column
    rt = RealtimeBoard(board, plant, behind, on_tick=lambda out: mode.__setitem__(0, out.mode))
    try:
        print(board.port, flush=True)
        while not stop.wait(0.2) and rt.alive():
            pass
    finally:
        rt.close()
        if config is not None:
            plant.close()


def _emulate_avr(work: Path, n: int, stop: threading.Event) -> None:
    elf = build_firmware("avr", work, n)
    runner = build_firmware("simavr", work)
    proc = subprocess.Popen([str(runner), str(elf), "--plant"], stdout=subprocess.PIPE, text=True)
    try:
        port = proc.stdout.readline().strip()
        if not port:
            raise RuntimeError(f"simavr did not start (exit code {proc.poll()})")
        print(port, flush=True)
        while not stop.wait(0.2) and proc.poll() is None:
            pass
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
