"""``hbma-ctrl rig emulate``: an emulated rig board running the reference firmware (``firmware/``).

Registered by :mod:`hbma_ctrl.app.cli.main` through :func:`register`. ``--target host`` builds the
firmware's POSIX host board and runs it with a simulated plant (the package's
:class:`~hbma_ctrl.app.daemon.firmware.FirstOrderPlant`, one per chamber) stepped in real time, one
sample period per firmware period, or with ``--config`` the configuration's simulated (mismatched)
rig as ``python -m hbma_ctrl.app.daemon.firmware --config`` runs it; ``--target avr`` builds the Uno firmware and runs it in simavr
(the pressures then read the simulator's fixed ADC input). Either way the first line on stdout is
the serial port to give the daemon (``--rig serial:PORT``); it runs until SIGINT or SIGTERM, then
stops the board and removes its build folder.

The board drivers are here too (the tests use them): :class:`HostBoard` runs the host build and
drives its timer, ADC and outputs over the plant channel (firmware/hal/posix/main.c), and
:func:`build_firmware` runs the firmware's Makefile.
"""

from __future__ import annotations

import shutil
import signal
import socket
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Callable
from typing import Annotated, Optional

import numpy as np
import typer

from hbma_ctrl.app.cli.args import check_choice, check_range

__all__ = ["FIRMWARE_DIR", "BoardOutputs", "HostBoard", "build_firmware", "run_realtime", "register"]

#: the firmware sources, shipped with the package (``hbma_ctrl/firmware`` links to the repository's ``firmware/``)
FIRMWARE_DIR = Path(__file__).resolve().parents[2] / "firmware"


def build_firmware(target: str, out: Path, n: int = 1) -> Path:
    """Build ``target`` of firmware/Makefile into ``out`` (``host``, ``avr``, ``mega``, ``simavr``,
    ``test``); the path of the built file (the host board, the AVR ELF, the simavr runner) or the
    folder. RuntimeError with make's output when the build fails."""
    if not (FIRMWARE_DIR / "Makefile").is_file():
        raise FileNotFoundError(f"firmware sources not found at {FIRMWARE_DIR} (the package ships them: reinstall it)")
    res = subprocess.run(["make", "-s", "-C", str(FIRMWARE_DIR), target, f"O={out}", f"N={n}"],
                         capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"firmware build '{target}' failed:\n{res.stdout}{res.stderr}")
    return {"host": out / "host" / "hbma-fw-host", "avr": out / "uno" / "hbma-fw.elf",
            "mega": out / "mega" / "hbma-fw.elf", "simavr": out / "host" / "hbma-fw-simavr"}.get(target, out)


@dataclass(frozen=True)
class BoardOutputs:
    """What the host board did over the ticks of one :meth:`HostBoard.tick`: its time after them
    (``t_us``), ``mode`` (RUN or SAFE), its counters (``commands``, ``crc_errors``, ``bad_lines``,
    ``seq_gaps``, ``lines``: valid host lines) and ``u`` (3, n), the mean pump speed and the fraction of the ticks each inlet and
    outlet was open (zeros for no ticks)."""

    t_us: int
    mode: str
    commands: int
    crc_errors: int
    bad_lines: int
    seq_gaps: int
    lines: int
    u: np.ndarray


class HostBoard:
    """The firmware's POSIX host board (``exe``, from :func:`build_firmware`) in a subprocess.

    ``port`` is its UART, a pty. Time passes on the board only in :meth:`tick`. The calibration the
    board loaded (``zero``, ``gain`` per chamber: counts, mPa/count) converts pressures to the ADC
    counts :meth:`tick` takes. ``eeprom``: a file keeping the board's NVM across runs.
    """

    def __init__(self, exe: Path, n: int = 1, *, tick_us: int = 100, period_ticks: int = 100,
                 timeout_ms: int = 500, eeprom: Path | None = None) -> None:
        mine, theirs = socket.socketpair()
        cmd = [str(exe), "--plant-fd", str(theirs.fileno()), "--n", str(n), "--tick-us", str(tick_us),
               "--period-ticks", str(period_ticks), "--timeout-ms", str(timeout_ms)]
        if eeprom is not None:
            cmd += ["--eeprom", str(eeprom)]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, pass_fds=(theirs.fileno(),), text=True)
        theirs.close()
        self._sock = mine
        self._rx = mine.makefile("r", encoding="ascii", newline="\n")
        self.port = self.proc.stdout.readline().strip()
        info = self._rx.readline().split()
        if not self.port or not info or info[0] != "I":
            self.close()
            raise RuntimeError(f"the host board {exe} did not start (exit code {self.proc.poll()})")
        self.n, self.tick_us, self.period_ticks = int(info[1]), int(info[2]), int(info[3])
        self.zero = np.array([int(x) for x in info[4::2]], dtype=float)
        self.gain = np.array([int(x) for x in info[5::2]], dtype=float)
        self.period = self.tick_us * self.period_ticks * 1e-6

    def counts(self, p: np.ndarray) -> list[int]:
        """Pressures, Pa (n,), as the ADC counts the board reads for them (NaN: no reading)."""
        c = self.zero + np.asarray(p, dtype=float) * 1000.0 / self.gain
        return [0xFFFF if not np.isfinite(x) else int(np.clip(np.rint(x), 0, 0xFFFE)) for x in c]

    def tick(self, k: int, p: np.ndarray | None = None) -> BoardOutputs:
        """Run ``k`` timer ticks with the sensors reading pressures ``p``, Pa (n,) (None: unchanged)."""
        extra = "" if p is None else " " + " ".join(str(c) for c in self.counts(p))
        self._sock.sendall(f"T {int(k)}{extra}\n".encode("ascii"))
        f = self._rx.readline().split()
        if not f or f[0] != "O":
            raise RuntimeError(f"the host board stopped (exit code {self.proc.poll()})")
        v = np.array([int(x) for x in f[8:]], dtype=float).reshape(self.n, 3).T
        v[0] /= 1000.0
        u = v / k if k > 0 else np.zeros_like(v)
        return BoardOutputs(int(f[1]), f[2], int(f[3]), int(f[4]), int(f[5]), int(f[6]), int(f[7]), u)

    def close(self) -> None:
        """Stop the board (closing its plant channel ends it) and wait for it."""
        self._rx.close()
        self._sock.close()
        try:
            self.proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.proc.stdout.close()


def run_realtime(board: HostBoard, plant, stop: threading.Event, max_behind: int = 10,
                 on_tick: Callable[[BoardOutputs], None] | None = None) -> None:
    """Drive ``board`` in real time until ``stop``, as its timer would: each round runs the whole
    sample periods due by the wall clock (at least one) in one batch, then the plant
    (``plant(u (3, n), dt s) -> p (n,) Pa``) over them under the outputs the board held; its
    pressures are what the board samples next. A process kept from running catches up (the board's
    heartbeat stays on time, the batch's samples repeat the pressure at its start); more than
    ``max_behind`` periods late, the board's clock slips instead (``max_behind = 1``: one period per
    round, for a plant that runs one period per call whatever ``dt``). ``on_tick`` sees every round's
    outputs."""
    p = np.zeros(board.n)
    start = time.monotonic()
    done = 0
    while not stop.is_set():
        due = int((time.monotonic() - start) / board.period) + 1
        k = max(1, due - done)
        if k > max_behind:
            start += (k - max_behind) * board.period
            k = max_behind
        out = board.tick(k * board.period_ticks, p)
        if on_tick is not None:
            on_tick(out)
        p = plant(out.u, k * board.period)
        done += k
        stop.wait(max(0.0, start + done * board.period - time.monotonic()))


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add the ``rig`` command group to ``app``."""
    rig_app = typer.Typer(add_completion=False, no_args_is_help=True,
                          help="The rig's reference firmware (firmware/): an emulated board.")
    app.add_typer(rig_app, name="rig")

    @rig_app.command("emulate")
    def emulate(
        target: Annotated[str, typer.Option(help="host (POSIX build + simulated plant) or avr (Uno build in simavr)")] = "host",
        n: Annotated[Optional[int], typer.Option("--n", help="chambers, 1..4 (avr) or 1..16 (host); default 1 or the config's")] = None,
        config: Annotated[Optional[Path], typer.Option(help="host only: a daemon CONFIG.toml whose simulated rig is the plant")] = None,
        truth_log: Annotated[Optional[Path], typer.Option(help="with --config: CSV of the rig's true state per period")] = None,
    ) -> None:
        """Run an emulated rig board; print its serial port on the first line, run until Ctrl-C/SIGTERM."""
        check_choice("--target", target, ("host", "avr"))
        check_range("--n", n, 1, 16 if target == "host" else 4, note=f"chambers of --target {target}")
        if config is not None and target != "host":
            raise ValueError("--config: the plant of a configuration runs with --target host only")
        if truth_log is not None and config is None:
            raise ValueError("--truth-log: needs --config (the first-order plant has no truth to log)")
        stop = threading.Event()
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(sig, lambda *_: stop.set())
        work = Path(tempfile.mkdtemp(prefix="hbma-rig-"))
        try:
            if target == "host":
                _emulate_host(work, n, stop, config, truth_log)
            else:
                _emulate_avr(work, n or 1, stop)
        finally:
            shutil.rmtree(work, ignore_errors=True)


def _emulate_host(work: Path, n: int | None, stop: threading.Event, config: Path | None,
                  truth_log: Path | None) -> None:
    from hbma_ctrl.app.daemon.firmware import FirstOrderPlant, _config_plant

    tick = 100e-6  # the host board's default tick, s
    plant, behind, period = FirstOrderPlant(n or 1), 10, 0.01
    if config is not None:
        plant, behind = _config_plant(str(config), truth_log), 1  # one rig period per call
        if n is not None and n != plant.n:
            plant.close()
            raise ValueError(f"--n = {n}: the config's rig has {plant.n} chambers; leave --n out with --config")
        period = plant.period
    ticks = round(period / tick)
    if not 1 <= ticks <= 65535 or abs(ticks * tick - period) > 1e-9:
        raise ValueError(f"the sample period {period * 1e3:g} ms is not a whole number of 0.1 ms ticks")
    board = HostBoard(build_firmware("host", work), plant.n, period_ticks=ticks, eeprom=work / "eeprom.bin")
    mode = ["SAFE"]
    if config is not None:
        plant.mode = lambda: mode[0]  # the truth log's mode column
    try:
        print(board.port, flush=True)
        run_realtime(board, plant, stop, behind, on_tick=lambda out: mode.__setitem__(0, out.mode))
    finally:
        board.close()
        if config is not None:
            plant.close()


def _emulate_avr(work: Path, n: int, stop: threading.Event) -> None:
    elf = build_firmware("avr", work, n)
    runner = build_firmware("simavr", work)
    proc = subprocess.Popen([str(runner), str(elf)], stdout=subprocess.PIPE, text=True)
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
