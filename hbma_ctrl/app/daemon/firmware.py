"""The reference firmware's emulated boards (``firmware/``) and the plants they run.

:func:`build_firmware` runs the firmware's Makefile. :class:`HostBoard` runs the POSIX host build in a
subprocess: its UART is a pty a host opens as it would a USB serial device, and its timer, ADC and
outputs are driven over a plant channel (firmware/hal/posix/main.c); :func:`run_realtime` steps it in
real time against a plant ``plant(u (3, n), dt s) -> p (n,) Pa`` (in a thread: :class:`RealtimeBoard`;
with a host's :class:`~hbma_ctrl.system.serial_link.SerialRig` on its port: :func:`open_fake_rig`).
For tests the board injects firmware defects (:data:`DEFECTS`), corrupts or loses lines it sends, and vanishes and reappears on a
new pty (a re-plug) with a symlink kept pointing at it, as udev's ``/dev/serial/by-id`` names do.

Plants: :class:`FirstOrderPlant` (one first-order chamber per column) and :class:`RigPlant` (a daemon
configuration's simulated, mismatched rig, :func:`config_plant`), in the board's process as a
microcontroller's rig would be, with a truth log the host never sees. ``hbma-ctrl rig emulate``
(:mod:`hbma_ctrl.app.cli.rig`) runs them.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hbma_ctrl.core.units import to_kpa, to_mm, to_ms
from hbma_ctrl.system.serial_link import SerialRig

__all__ = ["FIRMWARE_DIR", "DEFECTS", "BoardOutputs", "HostBoard", "build_firmware", "run_realtime",
           "RealtimeBoard", "open_fake_rig", "FirstOrderPlant", "RigPlant", "config_plant"]

#: the firmware sources, shipped with the package (``hbma_ctrl/firmware`` links to the repository's ``firmware/``)
FIRMWARE_DIR = Path(__file__).resolve().parents[2] / "firmware"


def build_firmware(target: str, out: Path, n: int = 1, library: Path | None = None) -> Path:
    """Build ``target`` of firmware/Makefile into ``out`` (``host``, ``host-hosted``, ``avr``, ``mega``,
    ``simavr``, ``test``); the path of the built file (the host board, the AVR ELF, the simavr runner) or
    the folder. ``library``: the folder of a chamber library (``codegen --library``) that ``host-hosted``
    runs on the board; it is built with ``$HBMA_CTRL_CC_OPT`` as its optimisation when that is set.
    RuntimeError with make's output when the build fails."""
    if not (FIRMWARE_DIR / "Makefile").is_file():
        raise FileNotFoundError(f"firmware sources not found at {FIRMWARE_DIR} (the package ships them: reinstall it)")
    extra = []
    if target == "host-hosted":
        if library is None or not (Path(library) / "hbma.h").is_file():
            raise ValueError(f"--library {library}: no hbma.h there (generate a chamber library with "
                             "hbma-ctrl codegen CONFIG --library --out DIR)")
        from hbma_ctrl.core.codegen import OPT_ENV  # here: the protocol alone needs no casadi

        extra = [f"LIB={Path(library).resolve()}"]
        if os.environ.get(OPT_ENV):
            extra.append(f"OPT={os.environ[OPT_ENV]}")
    res = subprocess.run(["make", "-s", "-C", str(FIRMWARE_DIR), target, f"O={out}", f"N={n}", *extra],
                         capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"firmware build '{target}' failed:\n{res.stdout}{res.stderr}")
    return {"host": out / "host" / "hbma-fw-host", "host-hosted": out / "host" / "hbma-fw-host-hosted",
            "avr": out / "uno" / "hbma-fw.elf", "mega": out / "mega" / "hbma-fw.elf",
            "simavr": out / "host" / "hbma-fw-simavr"}.get(target, out)


#: the defects the host board can inject (``--defect``; firmware/hal/posix/main.c), in its bit order
DEFECTS = ("crc", "stuck_inlet", "inverted_pressure", "no_watchdog", "wrong_period", "no_heartbeat", "seq_repeat",
           "no_crlf", "sensor_zero", "no_crc_check", "held_seq", "version")


@dataclass(frozen=True)
class BoardOutputs:
    """What the host board did over the ticks of one :meth:`HostBoard.tick`: its time after them
    (``t_us``), ``mode`` (RUN or SAFE), its counters (``commands``, ``crc_errors``, ``bad_lines``,
    ``seq_gaps``, ``lines``: valid host lines), ``held`` (the SEQ of the host line whose command the
    outputs hold, None for the firmware's own safe state), ``u`` (3, n), the mean pump speed and the
    fraction of the ticks each inlet and outlet was open (zeros for no ticks), and ``command`` (3n
    ints), the newest command received in per-mille, chamber by chamber (latched at the next sample
    instant)."""

    t_us: int
    mode: str
    commands: int
    crc_errors: int
    bad_lines: int
    seq_gaps: int
    lines: int
    held: int | None
    u: np.ndarray
    command: tuple[int, ...]


class HostBoard:
    """The firmware's POSIX host board (``exe``, from :func:`build_firmware`) in a subprocess.

    ``port`` is its UART, a pty (or ``link``, a symlink kept pointing at it, as udev's
    ``/dev/serial/by-id`` names a device). Time passes on the board only in :meth:`tick`. The
    calibration the board loaded (``zero``, ``gain`` per chamber: counts, mPa/count) converts
    pressures to the ADC counts :meth:`tick` takes. ``eeprom``: a file keeping the board's NVM across
    runs. ``defects``: names of :data:`DEFECTS` injected from the start. Test knobs:
    :meth:`inject`, :meth:`corrupt_next`, :meth:`drop_next`, :meth:`vanish`, :meth:`reappear`; they
    and :meth:`tick` may be called from different threads (one exchange with the board at a time).
    """

    def __init__(self, exe: Path, n: int = 1, *, tick_us: int = 100, period_ticks: int = 100,
                 timeout_ms: int = 500, eeprom: Path | None = None, defects: Sequence[str] = (),
                 link: str | Path | None = None) -> None:
        mine, theirs = socket.socketpair()
        cmd = [str(exe), "--plant-fd", str(theirs.fileno()), "--n", str(n), "--tick-us", str(tick_us),
               "--period-ticks", str(period_ticks), "--timeout-ms", str(timeout_ms)]
        if eeprom is not None:
            cmd += ["--eeprom", str(eeprom)]
        if defects:
            cmd += ["--defect", ",".join(_check_defects(defects))]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, pass_fds=(theirs.fileno(),), text=True)
        theirs.close()
        self._sock = mine
        self._rx = mine.makefile("r", encoding="ascii", newline="\n")
        self._lock = threading.Lock()
        self.link = None if link is None else str(link)
        self.pty_path: str | None = self.proc.stdout.readline().strip()
        info = self._rx.readline().split()
        if not self.pty_path or not info or info[0] != "I":
            self.close()
            raise RuntimeError(f"the host board {exe} did not start (exit code {self.proc.poll()})")
        self._relink()
        self.n, self.tick_us, self.period_ticks = int(info[1]), int(info[2]), int(info[3])
        self.zero = np.array([int(x) for x in info[4::2]], dtype=float)
        self.gain = np.array([int(x) for x in info[5::2]], dtype=float)
        self.period = self.tick_us * self.period_ticks * 1e-6

    @property
    def port(self) -> str:
        """What a host opens: the symlink when one is kept, else the pty's path."""
        return self.link if self.link is not None else self.pty_path

    def counts(self, p: np.ndarray) -> list[int]:
        """Pressures, Pa (n,), as the ADC counts the board reads for them (NaN: no reading)."""
        c = self.zero + np.asarray(p, dtype=float) * 1000.0 / self.gain
        return [0xFFFF if not np.isfinite(x) else int(np.clip(np.rint(x), 0, 0xFFFE)) for x in c]

    def tick(self, k: int, p: np.ndarray | None = None) -> BoardOutputs:
        """Run ``k`` timer ticks with the sensors reading pressures ``p``, Pa (n,) (None: unchanged)."""
        extra = "" if p is None else " " + " ".join(str(c) for c in self.counts(p))
        out = self._ask(f"T {int(k)}{extra}")
        n = self.n
        v = np.array([int(x) for x in out[9:9 + 3 * n]], dtype=float).reshape(n, 3).T
        v[0] /= 1000.0
        u = v / k if k > 0 else np.zeros_like(v)
        held = None if out[8] == "-" else int(out[8])
        return BoardOutputs(int(out[1]), out[2], *(int(x) for x in out[3:8]), held, u,
                            tuple(int(x) for x in out[9 + 3 * n:9 + 6 * n]))

    def inject(self, *defects: str) -> None:
        """From now on the board has these :data:`DEFECTS` (none: a good board again)."""
        self._ask("F " + (",".join(_check_defects(defects)) or "-"))

    def corrupt_next(self, k: int = 1) -> None:
        """Flip one bit in the body of each of the next ``k`` lines sent (their checksum no longer matches)."""
        self._ask(f"X {int(k)}")

    def drop_next(self, k: int = 1) -> None:
        """Lose the next ``k`` lines sent (their SEQ used: the host sees a gap)."""
        self._ask(f"L {int(k)}")

    def vanish(self) -> None:
        """Close the pty, as an unplugged cable; the board runs on (and goes safe on its own)."""
        self._ask("V")
        self.pty_path = None

    def reappear(self) -> None:
        """Open a new pty (a re-plug: a new device path) and re-point ``link`` at it."""
        with self._lock:
            self._sock.sendall(b"R\n")
            f = self._rx.readline().split()
        if len(f) != 2 or f[0] != "R":
            raise RuntimeError(f"the host board stopped (exit code {self.proc.poll()})")
        self.pty_path = f[1]
        self._relink()

    def _ask(self, line: str) -> list[str]:
        with self._lock:
            self._sock.sendall(line.encode("ascii") + b"\n")
            f = self._rx.readline().split()
        if not f or f[0] != "O":
            raise RuntimeError(f"the host board stopped (exit code {self.proc.poll()})")
        return f

    def _relink(self) -> None:
        if self.link is not None:
            tmp = f"{self.link}.tmp{os.getpid()}"
            os.symlink(self.pty_path, tmp)
            os.replace(tmp, self.link)  # atomic: a host never sees the link missing

    def close(self) -> None:
        """Stop the board (closing its plant channel ends it), wait for it and remove ``link``."""
        self._rx.close()
        self._sock.close()
        try:
            self.proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.proc.stdout.close()
        if self.link is not None and os.path.islink(self.link):
            os.unlink(self.link)


def _check_defects(names: Sequence[str]) -> list[str]:
    for name in names:
        if name not in DEFECTS:
            raise ValueError(f"defect {name!r}: allowed {', '.join(DEFECTS)}")
    return list(names)


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


class RealtimeBoard:
    """``board`` (a :class:`HostBoard`) driven by :func:`run_realtime` against ``plant`` in a thread
    from now on (``max_behind``, ``on_tick`` as there); ``out`` is its newest :class:`BoardOutputs`
    (from the start: no ticks yet). The board's port and knobs are reachable on it too (``port``,
    ``corrupt_next``, ``vanish``, ...). :meth:`close` stops the thread, then the board, then removes
    ``work`` (a folder the board was built in), if given."""

    def __init__(self, board: HostBoard, plant, max_behind: int = 10,
                 on_tick: Callable[[BoardOutputs], None] | None = None, work: Path | None = None) -> None:
        self.board = board
        self.work = work
        self.out = board.tick(0)
        self._stop = threading.Event()

        def seen(out: BoardOutputs) -> None:
            self.out = out
            if on_tick is not None:
                on_tick(out)

        self._thread = threading.Thread(target=run_realtime, args=(board, plant, self._stop, max_behind, seen),
                                        name="host-board", daemon=True)
        self._thread.start()

    def alive(self) -> bool:
        """Whether the board still runs (its driver stops when the board does)."""
        return self._thread.is_alive()

    def __getattr__(self, name: str):
        if name.startswith("_") or name == "board":  # not set yet: no lookup on a missing board
            raise AttributeError(name)
        return getattr(self.board, name)

    def close(self) -> None:
        """Stop driving the board and close it."""
        self._stop.set()
        self._thread.join(timeout=10.0)
        self.board.close()
        if self.work is not None:
            shutil.rmtree(self.work, ignore_errors=True)


def open_fake_rig(n: int = 1, sample_period: float = 0.01, plant=None, *, exe: Path | None = None,
                  board_kw: dict | None = None, **rig_kw) -> tuple[RealtimeBoard, SerialRig]:
    """Both ends of a serial rig link without a rig: the reference firmware's host board (``exe``, else
    built into a temporary folder) with ``n`` chambers sampling every ``sample_period`` s (a whole
    number of 0.1 ms ticks), stepped in real time against ``plant`` (default :class:`FirstOrderPlant`),
    and a :class:`~hbma_ctrl.system.serial_link.SerialRig` on its port (``rig_kw``; ``board_kw`` go to
    :class:`HostBoard`). Returns (board, rig); close the rig, then the board."""
    work = None
    if exe is None:
        work = Path(tempfile.mkdtemp(prefix="hbma-rig-"))
        exe = build_firmware("host", work)
    board = HostBoard(exe, n, period_ticks=round(sample_period / 100e-6), **(board_kw or {}))
    fw = RealtimeBoard(board, plant if plant is not None else FirstOrderPlant(n), work=work)
    try:
        rig = SerialRig(fw.port, n, sample_period=sample_period, **rig_kw)
    except Exception:
        fw.close()
        raise
    return fw, rig


class FirstOrderPlant:
    """A chamber per column, first order in gauge pressure p (Pa):
    ``dp/dt = fill_rate * pump * inlet - outlet * p / tau_vent - p / tau_leak``.

    fill_rate : pressure rise at full pump and open inlet, Pa/s. tau_vent : venting time constant
    through a fully open outlet, s. tau_leak : leak time constant, s. Call ``plant(u, dt)`` to step it.
    """

    def __init__(self, n: int, fill_rate: float = 100e3, tau_vent: float = 0.2, tau_leak: float = 2.0) -> None:
        self.n = n
        self.fill_rate = fill_rate
        self.tau_vent = tau_vent
        self.tau_leak = tau_leak
        self.p = np.zeros(n)

    def __call__(self, u: np.ndarray, dt: float) -> np.ndarray:
        """Step by ``dt`` s (exactly, as the model is linear for a held command) under ``u`` (3, n);
        the new pressures, Pa (n,)."""
        u = np.asarray(u, dtype=float)
        a = u[2] / self.tau_vent + 1.0 / self.tau_leak  # decay rate, 1/s
        p_inf = self.fill_rate * u[0] * u[1] / a
        self.p = p_inf + (self.p - p_inf) * np.exp(-a * dt)
        return self.p.copy()


class RigPlant:
    """A lockstep rig (``write(u)`` holds ``u`` for one of its periods, ``read().p`` its newest
    pressures, ``truth()``; e.g. the daemon's simulated rig) as a firmware plant: ``plant(u, dt)`` runs
    one rig period under ``u`` and returns its pressures, Pa (n,), NaN where the sensor gave none;
    ``t`` is the rig's time, s, which the firmware stamps its samples with.

    Why one period per call whatever ``dt``: a microcontroller's timer keeps its period exactly, a
    process on a shared machine does not. Running the rig for the time the process took (in whole
    periods) would put the samples up to half a period off the physics they stamp, a timing error no
    rig has, and one the start-up calibration's pump-flow fit is sensitive to. Here a late period
    delays the rig as a whole; it never stretches or shortens its physics.

    truth_log : optional CSV path, one row per call: the firmware period as the process ran it
    (``dt_ms``), the firmware's mode then (``mode``: a callable set once the firmware exists; ``-``
    before), rig time (``t_s``), each chamber's true height (``h_C<i>_mm``) and pressure
    (``p_C<i>_kpa``). It judges a closed loop over the link against the rig's truth, which the host
    never sees. Call :meth:`close` to flush it.
    """

    def __init__(self, rig, truth_log: str | os.PathLike | None = None) -> None:
        self.rig = rig
        self.n = int(rig.n)
        self.period = float(rig.sample_period)
        self.mode: Callable[[], str] = lambda: "-"
        self._log = None
        if truth_log is not None:
            self._log = open(truth_log, "w", buffering=1)  # line-buffered: a killed firmware keeps its rows
            cols = [f"h_C{i + 1}_mm" for i in range(self.n)] + [f"p_C{i + 1}_kpa" for i in range(self.n)]
            self._log.write(",".join(["dt_ms", "mode", "t_s", *cols]) + "\n")

    @property
    def t(self) -> float:
        """The rig's time, s: the time of its newest sample."""
        return float(self.rig.t)

    def __call__(self, u: np.ndarray, dt: float) -> np.ndarray:
        """Run the rig one period under ``u`` (3, n) (``dt``, s, only logged); its pressures, Pa."""
        self.rig.write(u)
        p = np.asarray(self.rig.read().p, dtype=float)
        if self._log is not None:
            tr = self.rig.truth()
            h, pt = np.atleast_1d(tr["h"]), np.atleast_1d(tr["p"])
            vals = [f"{to_ms(dt):.3f}", self.mode(), f"{self.t:.4f}",
                    *(f"{to_mm(x):.4f}" for x in h), *(f"{to_kpa(x):.4f}" for x in pt)]
            self._log.write(",".join(vals) + "\n")
        return p

    def close(self) -> None:
        """Close the truth log (idempotent)."""
        if self._log is not None:
            self._log.close()
            self._log = None


def config_plant(path: str | os.PathLike, truth_log: str | os.PathLike | None = None) -> RigPlant:
    """The simulated rig of a daemon configuration as a plant (ValueError on a bad file)."""
    # imported here: the protocol alone (tests, a bare firmware) needs none of the model stack
    from hbma_ctrl.app.daemon.build import make_sim_rig
    from hbma_ctrl.app.daemon.config import load_config

    cfg = load_config(path, {"--rig": "sim"})
    if cfg.faults:
        # link faults have no meaning inside the firmware; sensor and actuator faults are the sim's
        raise ValueError("[[daemon.fault]]: faults are injected by --rig sim; the emulated board runs the "
                         "rig without them (remove the tables)")
    return RigPlant(make_sim_rig(cfg), truth_log)
