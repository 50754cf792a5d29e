"""A fake rig firmware speaking the line protocol (:mod:`hbma_ctrl.system.serial_link`) on a pty.

:class:`FakeFirmware` opens a pseudo-terminal (``os.openpty``); the host opens its slave path with
pyserial as it would a USB serial device. A thread plays the microcontroller: at each sample instant
it steps a plant over the period just ended with the command it held, streams a ``P`` line naming
that command, then latches the newest command received for the next period (a command arriving
mid-period waits for the next sample instant, as a timer interrupt would apply it; ``SAFE`` acts at
once); it sends ``HB`` every heartbeat period,
obeys ``HELLO``/``CMD``/``SAFE``/``HB`` lines and goes safe by itself when the host falls silent.
The plant is :class:`FirstOrderPlant` or any callable ``plant(u (3, n), dt s) -> p (n,) Pa`` (e.g. a
mismatched rig model, :class:`RigPlant`); a plant with a ``t`` attribute (its own time, s) has its
samples stamped with it, else they carry the firmware's clock. For tests it can corrupt checksums,
drop lines, stop its heartbeat, vanish (close the pty, as an unplugged cable) and reappear on a new pty; with ``link`` it keeps a symlink
pointing at its current pty (as udev's ``/dev/serial/by-id`` names), so a host configured with the
link finds it again.

Manual try: ``python -m hbma_ctrl.app.daemon.firmware --n 1 --period-ms 10 [--link /tmp/hbma-rig]``
prints the port to give the daemon's serial backend, then runs until Ctrl-C. With ``--config
CONFIG.toml [--truth-log FILE]`` its plant is the configuration's simulated (mismatched) rig
(:class:`RigPlant`), in its own process as a microcontroller would be, and the log keeps the rig's
truth, which the host never sees.
"""

from __future__ import annotations

import argparse
import os
import select
import signal
import sys
import threading
import time
import tty
from collections.abc import Callable

import numpy as np

from hbma_ctrl.system.rigio import safe_u
from hbma_ctrl.system.serial_link import (
    MAX_LINE,
    PROTOCOL_VERSION,
    SEQ_MOD,
    LineError,
    SerialRig,
    decode_line,
    encode_line,
    from_permille,
)
from hbma_ctrl.core.units import ms, to_kpa, to_mm, to_ms

__all__ = ["FirstOrderPlant", "RigPlant", "FakeFirmware", "open_fake_rig", "main"]

Plant = Callable[[np.ndarray, float], np.ndarray]


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


class FakeFirmware:
    """The microcontroller of an ``n``-chamber rig, speaking protocol ``version`` on a pty.

    n : chambers. sample_period : s between P lines. plant : ``plant(u (3, n), dt s) -> p (n,) Pa``
    (default :class:`FirstOrderPlant`), its samples stamped with ``plant.t`` (s) when it has one. heartbeat_period : s between HB lines. host_timeout : s of
    host silence after which it goes safe. link : optional symlink path kept pointing at its pty.

    ``pty_path`` is the current pty's device path. State for tests: ``mode`` (``RUN``/``SAFE``),
    ``u`` (the newest command received, (3, n), latched at the next sample instant), ``held`` (the
    command applied over the current period) and ``held_seq`` (the SEQ of the host line that set it,
    ``"-"`` for the firmware's own safe state), ``p`` (the last pressures, Pa), ``last_cmd`` (the last
    CMD's per-mille integers), ``safe_reason``, and ``stats`` (``crc_errors``, ``bad_lines``,
    ``seq_gaps``, ``commands``, ``dropped_tx``). Knobs: ``send_heartbeats``, :meth:`corrupt_next`,
    :meth:`drop_next`, :meth:`vanish`, :meth:`reappear`.
    """

    def __init__(self, n: int = 1, sample_period: float = 0.01, plant: Plant | None = None, *,
                 version: int = PROTOCOL_VERSION, heartbeat_period: float = 0.1, host_timeout: float = 0.5,
                 link: str | None = None) -> None:
        if int(n) != n or n < 1:
            raise ValueError(f"firmware n = {n}: must be an integer >= 1 (chambers)")
        for key, v in (("sample_period", sample_period), ("heartbeat_period", heartbeat_period),
                       ("host_timeout", host_timeout)):
            if not v > 0:
                raise ValueError(f"firmware {key} = {v}: must be a positive number of seconds")
        self.n = int(n)
        self.sample_period = sample_period
        self.plant = plant if plant is not None else FirstOrderPlant(n)
        self.version = version
        self.heartbeat_period = heartbeat_period
        self.host_timeout = host_timeout
        self.link = link
        self.mode = "SAFE"
        self.u = safe_u(n)
        self.u_seq: int | str = "-"
        self.held = safe_u(n)
        self.held_seq: int | str = "-"
        self.p = np.zeros(n)
        self.last_cmd: tuple[int, ...] | None = None
        self.safe_reason = "boot"
        self.send_heartbeats = True
        self.stats = {"crc_errors": 0, "bad_lines": 0, "seq_gaps": 0, "commands": 0, "dropped_tx": 0}
        self._lock = threading.Lock()
        self._corrupt = 0
        self._drop = 0
        self._t0 = time.monotonic()
        self._stop = threading.Event()
        self._vanish_req = threading.Event()
        self._master: int | None = None
        self._slave: int | None = None
        self._open_pty()
        self._thread = threading.Thread(target=self._run, name="fake-firmware", daemon=True)
        self._thread.start()

    @property
    def port(self) -> str:
        """What the host should open: the symlink when one is kept, else the pty's slave path."""
        return self.link if self.link is not None else self.pty_path

    # ---- test knobs ----------------------------------------------------------------------------

    def corrupt_next(self, k: int = 1) -> None:
        """Flip one bit in the body of each of the next ``k`` lines (their checksum no longer matches)."""
        with self._lock:
            self._corrupt += k

    def drop_next(self, k: int = 1) -> None:
        """Lose the next ``k`` lines (their sequence numbers are used, so the host sees a gap)."""
        with self._lock:
            self._drop += k

    def vanish(self) -> None:
        """Close the pty, as an unplugged cable; the firmware keeps running (and goes safe on its own)."""
        if self._thread.is_alive():
            # the firmware thread closes the fds itself: closing them under its select() could let the
            # number be reused by another open and read from a stranger's file
            self._vanish_req.set()
            deadline = time.monotonic() + 2.0
            while self._vanish_req.is_set() and self._thread.is_alive() and time.monotonic() < deadline:
                time.sleep(0.002)
        if self._master is not None:
            with self._lock:
                self._close_fds()

    def _close_fds(self) -> None:
        for fd in (self._master, self._slave):
            if fd is not None:
                os.close(fd)
        self._master = self._slave = None
        self._session = False

    def reappear(self) -> None:
        """Open a new pty (a re-plug: a new device path) and re-point ``link`` at it; needs a new HELLO."""
        with self._lock:
            if self._master is None:
                self._open_pty()

    def close(self) -> None:
        """Stop the firmware and close its pty."""
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.vanish()
        if self.link is not None and os.path.islink(self.link):
            os.unlink(self.link)

    # ---- the microcontroller -------------------------------------------------------------------

    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line editing: bytes pass as on a UART
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self.pty_path = os.ttyname(slave)
        self._session = False
        self._rxbuf = b""
        self._txseq = 0
        self._rx_expect: int | None = None
        self._go_safe("new port")
        if self.link is not None:
            tmp = f"{self.link}.tmp{os.getpid()}"
            os.symlink(self.pty_path, tmp)
            os.replace(tmp, self.link)  # atomic: the host never sees the link missing

    def _go_safe(self, reason: str, seq: int | str = "-") -> None:
        """Safe from the next sample instant; ``seq`` the host line that asked for it ("-": none)."""
        self.mode = "SAFE"
        self.u = safe_u(self.n)
        self.u_seq = seq
        self.safe_reason = reason

    def _tx(self, kind: str, *fields: object) -> None:
        """Send one line (caller holds the lock); a full pty buffer (host not reading) drops it."""
        line = encode_line(kind, self._txseq, *fields)
        self._txseq = (self._txseq + 1) % SEQ_MOD
        if self._drop > 0:
            self._drop -= 1
            return
        if self._corrupt > 0:
            self._corrupt -= 1
            body, _, crc = line.rpartition(b"*")
            line = body[:-1] + bytes([body[-1] ^ 0x01]) + b"*" + crc  # one bit flipped, old checksum
        try:
            os.write(self._master, line)
        except (BlockingIOError, OSError):
            self.stats["dropped_tx"] += 1

    def _run(self) -> None:
        next_t = last = last_hb = time.monotonic()
        while not self._stop.is_set():
            if self._vanish_req.is_set():
                with self._lock:
                    self._close_fds()
                self._vanish_req.clear()
            master = self._master
            wait = max(0.0, next_t - time.monotonic())
            if master is None:
                self._stop.wait(wait)
            else:
                try:
                    ready, _, _ = select.select([master], [], [], wait)
                    data = os.read(master, 4096) if ready else b""
                except OSError:
                    data = b""
                if data:
                    with self._lock:
                        if self._master == master:
                            self._receive(data)
            now = time.monotonic()
            if now < next_t:
                continue
            next_t = max(next_t + self.sample_period, now)
            with self._lock:
                # the period just ended ran on the command latched at its start
                self.p = np.asarray(self.plant(self.held.copy(), min(now - last, 10 * self.sample_period)), float)
                ended_on = self.held_seq
                last = now
                if self.mode == "RUN" and now - self._last_rx > self.host_timeout:
                    self._go_safe("host heartbeat lost")
                self.held, self.held_seq = self.u.copy(), self.u_seq  # for the period that starts now
                if self._master is None or not self._session:
                    continue
                # a plant with its own clock (a simulated rig) is sampled at its time; else the firmware's
                t_plant = getattr(self.plant, "t", None)
                t_us = int(round(t_plant * 1e6)) if t_plant is not None else int((now - self._t0) * 1e6)
                self._tx("P", t_us, ended_on, *("NA" if not np.isfinite(x) else int(round(x)) for x in self.p))
                if self.send_heartbeats and now - last_hb >= self.heartbeat_period:
                    self._tx("HB", self.mode)
                    last_hb = now

    def _receive(self, data: bytes) -> None:
        buf = self._rxbuf + data
        lines = buf.split(b"\n")
        self._rxbuf = lines.pop()
        if len(self._rxbuf) > MAX_LINE:
            self._rxbuf = b""
            self.stats["bad_lines"] += 1
        for line in lines:
            try:
                m = decode_line(line)
            except LineError as e:
                self.stats["crc_errors" if e.kind == "crc" else "bad_lines"] += 1
                continue
            if m.kind == "HELLO":
                self._hello(m)
                continue
            if not self._session:
                self.stats["bad_lines"] += 1  # no session: a line from before the handshake
                continue
            if self._rx_expect is not None:
                self.stats["seq_gaps"] += (m.seq - self._rx_expect) % SEQ_MOD
            self._rx_expect = (m.seq + 1) % SEQ_MOD
            if m.kind == "CMD":
                try:
                    vals = tuple(int(f) for f in m.fields)
                    u = from_permille(vals, self.n)
                except ValueError:
                    self.stats["bad_lines"] += 1
                    continue
                self.u, self.u_seq, self.mode, self.last_cmd = u, m.seq, "RUN", vals
                self.stats["commands"] += 1
            elif m.kind == "SAFE":
                # at once, not at the next sample instant: the safe state must not wait
                self._go_safe("SAFE command", m.seq)
                self.held, self.held_seq = self.u.copy(), self.u_seq
            elif m.kind != "HB":
                self.stats["bad_lines"] += 1
                continue
            self._last_rx = time.monotonic()

    def _hello(self, m) -> None:
        self._txseq = 0
        self._go_safe("HELLO", m.seq)
        period_us = int(round(self.sample_period * 1e6))
        self._tx("VER", self.version, self.n, period_us)
        ok = len(m.fields) == 1 and m.fields[0] == str(self.version)
        self._session = ok
        self._rx_expect = (m.seq + 1) % SEQ_MOD
        self._last_rx = time.monotonic()

    _last_rx = 0.0


def open_fake_rig(n: int = 1, sample_period: float = 0.01, plant: Plant | None = None, *,
                  firmware_kw: dict | None = None, **rig_kw) -> tuple[FakeFirmware, SerialRig]:
    """Start a :class:`FakeFirmware` and open a :class:`SerialRig` on it (``rig_kw`` go to the rig,
    ``firmware_kw`` to the firmware); returns (firmware, rig). Close the rig, then the firmware."""
    fw = FakeFirmware(n, sample_period, plant, **(firmware_kw or {}))
    try:
        rig = SerialRig(fw.port, n, sample_period=sample_period, **rig_kw)
    except Exception:
        fw.close()
        raise
    return fw, rig


def main(argv: list[str] | None = None) -> int:
    """Run a fake firmware until Ctrl-C or SIGTERM, printing the port to open; exit code 2 on bad
    flags or a bad configuration (one line naming it)."""
    ap = argparse.ArgumentParser(prog="python -m hbma_ctrl.app.daemon.firmware",
                                 description="A fake HBMA rig firmware on a pseudo-terminal.")
    ap.add_argument("--n", type=int, default=None, help="chambers, 1..16 (default 1, or the config's)")
    ap.add_argument("--period-ms", type=float, default=None,
                    help="sample period, ms, 1..1000 (default 10, or the config's)")
    ap.add_argument("--config", default=None,
                    help="a daemon CONFIG.toml: the plant is its simulated (mismatched) rig, as --rig sim")
    ap.add_argument("--truth-log", default=None, help="with --config: CSV of the rig's true state per period")
    ap.add_argument("--link", default=None, help="also keep this symlink pointing at the pty")
    a = ap.parse_args(argv)
    plant: RigPlant | None = None
    if a.config is not None:
        try:
            plant = _config_plant(a.config, a.truth_log)
        except (ValueError, OSError) as exc:
            print(f"error: --config {a.config}: {exc}", file=sys.stderr)
            return 2
        for flag, given, own in (("--n", a.n, plant.n), ("--period-ms", a.period_ms, to_ms(plant.period))):
            if given is not None and abs(given - own) > 1e-9:
                print(f"error: {flag} = {given:g}: the config's rig has {own:g}; leave {flag} out with --config",
                      file=sys.stderr)
                plant.close()
                return 2
        n, period = plant.n, plant.period
    elif a.truth_log is not None:
        print("error: --truth-log: needs --config (the first-order plant has no truth to log)", file=sys.stderr)
        return 2
    else:
        n = 1 if a.n is None else a.n
        period = ms(10.0 if a.period_ms is None else a.period_ms)
    if not 1 <= n <= 16:
        print(f"error: --n = {n}: must be 1..16 chambers", file=sys.stderr)
        return 2
    if not 1.0 <= to_ms(period) <= 1000.0:
        print(f"error: --period-ms = {to_ms(period):g}: must be 1..1000 ms", file=sys.stderr)
        return 2
    fw = FakeFirmware(n, period, plant, link=a.link)
    if plant is not None:
        plant.mode = lambda: fw.mode
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))  # a kill also removes the link
    print(fw.port, flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        fw.close()
        if plant is not None:
            plant.close()
    return 0


def _config_plant(path: str, truth_log: str | None) -> RigPlant:
    """The simulated rig of a daemon configuration as a plant (ValueError on a bad file)."""
    # imported here: the protocol alone (tests, a bare firmware) needs none of the model stack
    from hbma_ctrl.app.daemon.build import make_sim_rig
    from hbma_ctrl.app.daemon.config import load_config

    cfg = load_config(path, {"--rig": "sim"})
    if cfg.faults:
        # link faults have no meaning inside the firmware; sensor and actuator faults are the sim's
        raise ValueError("[[daemon.fault]]: faults are injected by --rig sim; the fake firmware runs the "
                         "rig without them (remove the tables)")
    return RigPlant(make_sim_rig(cfg), truth_log)


if __name__ == "__main__":
    sys.exit(main())
