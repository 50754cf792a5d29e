"""The serial rig backend: line protocol version 2 and :class:`SerialRig` (a
:class:`~hbma_ctrl.system.rigio.RigIO` over pyserial).

A rig is a microcontroller on a serial line that switches the pump and the valves of ``n`` chambers
and streams their pressures. Host and firmware exchange ASCII lines::

    BODY*CCCC\\n

``BODY`` is space-separated tokens, ``TYPE SEQ ...``; ``CCCC`` is the CRC-16/CCITT-FALSE (poly
0x1021, init 0xFFFF, no reflection, no final xor; ``123456789`` -> ``29B1``) of the ASCII bytes of
``BODY``, four upper-case hex digits. A line is at most 512 bytes. ``SEQ`` is a decimal counter,
0..65535 then back to 0, one counter per direction, each restarted at 0 by the handshake.

Host -> firmware:

=========================================  =======================================================
``HELLO seq version``                      open a session; the firmware answers ``VER`` and is safe
``CMD seq pump_1 in_1 out_1 ... out_n``    per chamber: pump speed, inlet duty, outlet duty, each an
                                           integer per-mille 0..1000 (``round half up(1000 u)``);
                                           3n integers, chambers in order; held until the next
                                           ``CMD`` or ``SAFE``; a line with a wrong count or a value
                                           out of range is ignored as a whole
``SAFE seq``                               pump off, inlets closed, outlets open, until a ``CMD``
``HB seq``                                 host heartbeat
=========================================  =======================================================

Firmware -> host:

=========================================  =======================================================
``VER seq version n period_us``            answer to ``HELLO``: protocol version, chambers, sample
                                           period (integer microseconds)
``P seq t_us held p_1 ... p_n``            one sample: firmware time since boot (integer us), the
                                           SEQ of the host line (CMD, SAFE or HELLO) whose outputs
                                           were held over the period this sample ends (``-`` when
                                           the firmware's own watchdog made it safe), gauge
                                           pressure of every chamber (integer Pa, ``NA`` = none)
``HB seq mode``                            firmware heartbeat, ``mode`` is ``RUN`` or ``SAFE``
=========================================  =======================================================

A board that runs the controller itself (the reference firmware's hosted build) answers
``VER seq version n period_us hosted``, takes ``TGT seq h_1 ... h_n`` (target heights, integer um)
instead of ``CMD``, and follows each ``P`` line with ``U seq`` and, per chamber, the command it holds
from its next sample instant (3 per-mille values), its estimated height (um) and pressure (Pa) (``NA NA``:
none) and its controller's status. :class:`hbma_ctrl.system.board_link.BoardControlledRig` is that
link's host side; each end refuses the other kind with one line (:class:`ControllerMismatchError`).

Rules. The firmware latches a received ``CMD`` or ``SAFE`` at its next sample instant and holds it
for the whole period that follows (its own watchdog going safe is latched the same way), so every
period has one command and the ``P`` line ending it names that command. The host passes the named
command to the estimator (:attr:`Readings.held`): what the plant really got, whatever the link's
and the host's delays (the last command the host sent may be one period off, by the phase of the
two clocks). The firmware streams ``P`` lines every sample period and ``HB`` lines every heartbeat period
(default 0.1 s) only after a ``HELLO`` of its own version. Any valid host line restarts the
firmware's watchdog; when none arrives for the host timeout (default 0.5 s) the firmware goes safe
by itself. The host sends ``HB`` when it has sent nothing else for a heartbeat period; when no
firmware ``HB`` arrives for
``link_timeout`` (default 0.5 s) the host drops the link. A line whose checksum is wrong, or that
does not parse, is counted and ignored (never acted on); a jump in ``SEQ`` is counted as lost lines
(a corrupted line therefore also counts as one lost line) and never acted on.

Host side: :class:`SerialRig` opens ``port`` with :func:`serial.serial_for_url` (a device path or
any pyserial URL), does the handshake (a different version raises :class:`ProtocolVersionError`),
and runs one reader thread that parses lines into the newest readings and sends heartbeats. When
the port is lost or the firmware's heartbeat stops, it closes the port and retries opening the same
``port`` with exponential backoff; meanwhile :meth:`SerialRig.read` and :meth:`SerialRig.write`
raise :class:`RigLinkError` so the daemon goes safe. Give a stable name as ``port`` (e.g. a
``/dev/serial/by-id/...`` link) so the retried open finds the rig again after a re-plug.
"""

from __future__ import annotations

import binascii
import contextlib
import math
import threading
import time
from dataclasses import dataclass

import numpy as np
import serial

from hbma_ctrl.system.rigio import Readings, RigLinkError, check_u, safe_u

__all__ = [
    "PROTOCOL_VERSION",
    "SEQ_MOD",
    "MAX_LINE",
    "HELD_MEMORY",
    "ProtocolVersionError",
    "ControllerMismatchError",
    "LineError",
    "Message",
    "crc16",
    "encode_line",
    "decode_line",
    "to_permille",
    "from_permille",
    "SerialRig",
]

PROTOCOL_VERSION = 2
#: host lines whose command is remembered for the ``held`` field of P lines (a P line naming an
#: older one leaves ``Readings.held`` None)
HELD_MEMORY = 256
SEQ_MOD = 65536  # sequence numbers are 0..65535 and wrap (a uint16 on the microcontroller)
MAX_LINE = 512  # bytes per line including the checksum and newline


class ProtocolVersionError(RigLinkError):
    """The firmware speaks another protocol version than this host (raised by the handshake)."""


class ControllerMismatchError(RigLinkError):
    """The board runs a controller of its own and the host expected to command it, or the other way
    round (raised by the handshake)."""


class LineError(ValueError):
    """A received line is not valid protocol (bad checksum, framing or fields); ``kind`` says which."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


@dataclass(frozen=True)
class Message:
    """One decoded line: ``kind`` (HELLO, CMD, SAFE, HB, VER, P), ``seq`` (0..65535), ``fields`` (the rest)."""

    kind: str
    seq: int
    fields: tuple[str, ...] = ()


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (poly 0x1021, init 0xFFFF), as an int 0..0xFFFF."""
    return binascii.crc_hqx(data, 0xFFFF)


def encode_line(kind: str, seq: int, *fields: object) -> bytes:
    """One protocol line ``KIND SEQ FIELDS*CCCC\\n`` as bytes (fields formatted with ``str``)."""
    body = " ".join([kind, str(int(seq) % SEQ_MOD), *(str(f) for f in fields)]).encode("ascii")
    return body + b"*%04X\n" % crc16(body)


def decode_line(line: bytes) -> Message:
    """Parse one line (with or without its newline) into a :class:`Message`; :class:`LineError` if invalid.

    ``LineError.kind`` is ``"crc"`` for a checksum mismatch and ``"format"`` for anything else.
    """
    line = line.rstrip(b"\r\n")
    if len(line) + 1 > MAX_LINE:
        raise LineError("format", f"line longer than {MAX_LINE} bytes")
    body, star, crc = line.rpartition(b"*")
    if not star or len(crc) != 4:
        raise LineError("format", "no '*CCCC' checksum at the end of the line")
    try:
        want = int(crc.decode("ascii"), 16)
    except (UnicodeDecodeError, ValueError):
        raise LineError("format", "checksum is not four hex digits") from None
    if crc16(body) != want:
        raise LineError("crc", "checksum mismatch")
    try:
        tokens = body.decode("ascii").split(" ")
    except UnicodeDecodeError:
        raise LineError("format", "line is not ASCII") from None
    if len(tokens) < 2 or not tokens[1].isdigit() or int(tokens[1]) >= SEQ_MOD:
        raise LineError("format", "no message type and sequence number 0..65535")
    return Message(tokens[0], int(tokens[1]), tuple(tokens[2:]))


def to_permille(u: np.ndarray) -> list[int]:
    """Command ``u`` (3, n) in [0, 1] -> 3n integers 0..1000, chamber by chamber (pump, inlet, outlet),
    each ``floor(1000 u + 0.5)`` (rounded half up to the nearest per-mille)."""
    a = np.asarray(u, dtype=float)
    return [int(math.floor(1000.0 * x + 0.5)) for x in a.T.ravel()]


def from_permille(values: list[int] | tuple[int, ...], n: int) -> np.ndarray:
    """3n per-mille integers (chamber by chamber) -> command (3, n) in [0, 1]; ValueError if out of range."""
    if len(values) != 3 * n:
        raise ValueError(f"command has {len(values)} values, expected {3 * n} (3 per chamber)")
    if any(v < 0 or v > 1000 for v in values):
        raise ValueError("command values must be per-mille integers 0..1000")
    return np.asarray(values, dtype=float).reshape(n, 3).T / 1000.0


class SerialRig:
    """A :class:`~hbma_ctrl.system.rigio.RigIO` over a serial line speaking protocol version 2.

    port : device path or pyserial URL (``/dev/ttyACM0``, ``/dev/serial/by-id/...``, ``socket://...``).
    n : number of chambers the rig must report.
    baud : line speed, baud.
    sample_period : the rig's sample period, s; None = take the firmware's; a firmware period more
        than 1 % away raises :class:`RigLinkError`.
    heartbeat_period : host heartbeat period, s.
    link_timeout : the link is dropped after this long without a firmware heartbeat, s.
    handshake_timeout : how long to wait for ``VER`` after ``HELLO``, s.
    backoff_max : the longest wait before a reconnection attempt, s (doubling from 0.05 s; back to
        0.05 s once a reconnected firmware's heartbeat arrives).

    The port is opened exclusively (a second process cannot drive the same rig). Opening does the
    handshake at once (``RigLinkError`` if no firmware answers,
    ``ProtocolVersionError`` if it speaks another version). ``stats`` counts, since opening:
    ``lines`` (valid lines), ``crc_errors``, ``bad_lines`` (valid checksum, invalid content),
    ``seq_gaps`` (firmware lines lost, from jumps in SEQ), ``readings`` (P lines), ``reconnects``,
    ``held_unknown`` (P lines naming a host line this host no longer remembers or never sent).
    ``firmware_mode`` is the mode of the firmware's last heartbeat (``RUN`` or ``SAFE``).
    """

    simulated = False  # a real link: its I/O time is the rig's
    #: the board runs the controller (its VER says "hosted"): this host sends targets, not commands
    board_controller = False

    def __init__(self, port: str, n: int, baud: int = 115200, sample_period: float | None = None, *,
                 heartbeat_period: float = 0.1, link_timeout: float = 0.5, handshake_timeout: float = 1.0,
                 backoff_max: float = 2.0) -> None:
        if int(n) != n or n < 1:
            raise ValueError(f"rig n = {n}: must be an integer >= 1 (chambers)")
        if int(baud) != baud or baud <= 0:
            raise ValueError(f"rig baud = {baud}: must be a positive integer")
        for key, v in (("sample_period", sample_period), ("heartbeat_period", heartbeat_period),
                       ("link_timeout", link_timeout), ("handshake_timeout", handshake_timeout),
                       ("backoff_max", backoff_max)):
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ValueError(f"rig {key} = {v}: must be a positive number of seconds")
        if link_timeout <= heartbeat_period:
            raise ValueError(f"rig link_timeout = {link_timeout} s must exceed heartbeat_period = "
                             f"{heartbeat_period} s")
        self.port = port
        self.n = int(n)
        self.baud = int(baud)
        self.heartbeat_period = float(heartbeat_period)
        self.link_timeout = float(link_timeout)
        self.handshake_timeout = float(handshake_timeout)
        self.backoff_max = float(backoff_max)
        self._want_period = sample_period
        self.sample_period = float(sample_period) if sample_period is not None else 0.0
        self.stats = {"lines": 0, "crc_errors": 0, "bad_lines": 0, "seq_gaps": 0, "readings": 0,
                      "reconnects": 0, "held_unknown": 0}
        self._lock = threading.Lock()  # guards the port, the host seq counter and the readings
        self._sample_cv = threading.Condition(self._lock)  # a P line arrived
        self._tx_lock = threading.Lock()  # one line written at a time
        self._stop = threading.Event()
        self._ser = None
        self._link_error: str | None = None
        self._link_exc: type[RigLinkError] = RigLinkError
        self._reset_readings()
        self._connect()  # raises on the first attempt: a wrong port or firmware is a start-up error
        self._thread = threading.Thread(target=self._run, name=f"serial-rig {port}", daemon=True)
        self._thread.start()

    # ---- RigIO ---------------------------------------------------------------------------------

    def read(self) -> Readings:
        """The newest pressures, Pa (n,), with the firmware's time stamp (s) and SEQ; never blocks on the
        line. ``fresh[i]`` is True when a P line carrying chamber i arrived since the previous read;
        otherwise ``p[i]`` repeats the older value (NaN before the first one). ``held`` is the command
        (3, n) the newest P line says was held over its period (None when this host does not know it).
        Raises :class:`RigLinkError` while the link is down."""
        with self._lock:
            if self._ser is None:
                raise self._link_exc(self._link_error or f"rig link on {self.port} is closed")
            held = None if self._held is None else self._held.copy()
            r = Readings(t=self._t, p=self._p.copy(), seq=self._pseq, fresh=self._fresh.copy(), held=held)
            self._fresh[:] = False
            return r

    def wait_sample(self, timeout: float) -> float | None:
        """Wait up to ``timeout`` s for a P line not yet read; the host's monotonic time (s) the newest
        unread one arrived, or None when none came (or the link is down). Lets the daemon tick on
        the rig's samples instead of beating against its clock."""
        with self._sample_cv:
            if self._ser is not None and not self._fresh.any():
                self._sample_cv.wait(timeout)
            return self._arrival if self._ser is not None and self._fresh.any() else None

    def write(self, u: np.ndarray) -> None:
        """Send ``CMD`` with ``u`` (3, n) in [0, 1] as per-mille integers; RigLinkError while the link is down."""
        a = check_u(u, self.n)
        vals = to_permille(a)
        # remembered as the firmware will hold it: the per-mille values, not the floats asked for
        self._send("CMD", *vals, held=from_permille(vals, self.n))

    def safe(self) -> None:
        """Send ``SAFE`` (pump off, inlets closed, outlets open) if the port is open; never raises."""
        # safe() is called on the way down and must not mask the cause
        with contextlib.suppress(Exception):
            self._send("SAFE", held=safe_u(self.n))

    def close(self) -> None:
        """Send ``SAFE``, stop the reader thread and release the port (idempotent)."""
        self.safe()
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        with self._lock:
            self._close_port("rig link closed")

    @property
    def connected(self) -> bool:
        """True while the port is open and the firmware's heartbeat is alive."""
        return self._ser is not None

    # ---- internals -----------------------------------------------------------------------------

    def _reset_readings(self) -> None:
        self._p = np.full(self.n, np.nan)
        self._fresh = np.zeros(self.n, dtype=bool)
        self._t: float | None = None
        self._pseq = -1
        self._held: np.ndarray | None = None
        self._arrival = 0.0
        self._sent_u: dict[int, np.ndarray] = {0: safe_u(self.n)}  # HELLO (seq 0) leaves the rig safe
        self._seq = 1  # HELLO used 0
        self._rx_expect = 1  # VER was 0
        self.firmware_mode = "SAFE"
        self._rxbuf = b""
        self._last_hb = time.monotonic()
        self._hb_seen = False
        self._last_tx = 0.0

    def _send(self, kind: str, *fields: object, held: np.ndarray | None = None) -> None:
        """Send one line; ``held``: the outputs it sets on the rig (CMD, SAFE), remembered by its SEQ."""
        # writes have their own lock: a slow write (full buffer) must not hold up read()
        with self._tx_lock:
            with self._lock:
                ser = self._ser
                if ser is None:
                    raise self._link_exc(self._link_error or f"rig link on {self.port} is closed")
                line = encode_line(kind, self._seq, *fields)
                if held is not None:
                    self._sent_u[self._seq] = held
                    self._sent_u.pop((self._seq - HELD_MEMORY) % SEQ_MOD, None)
                self._seq = (self._seq + 1) % SEQ_MOD
            try:
                ser.write(line)
            except (serial.SerialException, OSError, TypeError, AttributeError) as e:
                raise RigLinkError(self._drop(ser, f"rig link on {self.port} lost: write failed ({e})")) from None
            self._last_tx = time.monotonic()

    def _close_port(self, reason: str) -> None:
        """Close the port and record why (caller holds the lock)."""
        ser, self._ser = self._ser, None
        self._link_error = reason
        if ser is not None:
            # the port is already gone; closing is best effort
            with contextlib.suppress(Exception):
                ser.close()

    def _drop(self, ser, reason: str) -> str:
        """Close the port ``ser`` for ``reason`` unless another thread already replaced or closed it; the
        cause the link records."""
        with self._lock:
            if self._ser is ser:
                self._close_port(reason)
            return self._link_error or reason

    def _connect(self) -> None:
        """Open the port and do the handshake; raises RigLinkError / ProtocolVersionError."""
        try:
            # exclusive: two daemons must never drive one rig
            ser = serial.serial_for_url(self.port, baudrate=self.baud, timeout=0.02, write_timeout=0.5,
                                        exclusive=True)
        except (serial.SerialException, OSError, ValueError) as e:
            raise RigLinkError(f"cannot open rig port {self.port}: {e}") from None
        try:
            ser.reset_input_buffer()
            ser.write(encode_line("HELLO", 0, PROTOCOL_VERSION))
            (version, n, period_us, hosted), rest = self._await_ver(ser)
            period = period_us * 1e-6
            if version != PROTOCOL_VERSION:
                raise ProtocolVersionError(
                    f"rig firmware on {self.port} speaks line protocol version {version}, this host speaks "
                    f"version {PROTOCOL_VERSION}: flash matching firmware or use a matching hbma-ctrl")
            if hosted and not self.board_controller:
                raise ControllerMismatchError(
                    f"rig firmware on {self.port} runs its own controller (its VER says 'hosted'): run the daemon "
                    "with board_controller = true in [daemon] (--board-controller), or flash the firmware built "
                    "without FW_HOSTED (make -C firmware host / avr)")
            if self.board_controller and not hosted:
                raise ControllerMismatchError(
                    f"rig firmware on {self.port} runs no controller of its own (its VER does not say 'hosted'): "
                    "run the daemon without board_controller (--board-controller), or flash the hosted build "
                    "(make -C firmware host-hosted LIB=DIR)")
            if n != self.n:
                raise RigLinkError(f"rig on {self.port} reports {n} chambers, expected n = {self.n}")
            if self._want_period is not None and abs(period - self._want_period) > 0.01 * self._want_period:
                raise RigLinkError(f"rig on {self.port} samples every {period * 1e3:g} ms, expected "
                                   f"sample_period = {self._want_period * 1e3:g} ms")
        except (serial.SerialException, OSError) as e:
            ser.close()
            raise RigLinkError(f"rig port {self.port} failed during the handshake: {e}") from None
        except RigLinkError:
            ser.close()
            raise
        with self._lock:
            self.sample_period = period if self._want_period is None else float(self._want_period)
            self._reset_readings()
            self._rxbuf = rest  # lines that followed VER in the same read
            self._ser = ser
            self._link_error = None
            self._link_exc = RigLinkError

    def _await_ver(self, ser) -> tuple[tuple[int, int, int, bool], bytes]:
        deadline = time.monotonic() + self.handshake_timeout
        buf = b""
        while time.monotonic() < deadline:
            buf += ser.read(max(1, ser.in_waiting))
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                try:
                    m = decode_line(line)
                except LineError:
                    continue  # the tail of an older session's stream
                f = m.fields
                if (m.kind == "VER" and len(f) in (3, 4) and all(x.isdigit() for x in f[:3])
                        and (len(f) == 3 or f[3] == "hosted")):
                    return (int(f[0]), int(f[1]), int(f[2]), len(f) == 4), buf
        raise RigLinkError(f"no answer to HELLO from a rig on {self.port} within "
                           f"{self.handshake_timeout:g} s (is the firmware running and the port right?)")

    def _run(self) -> None:
        # One thread reads, beats and reconnects. pyserial's serial.threaded.ReaderThread ends at the
        # first port error and would need a second thread for heartbeats and reconnection.
        backoff = 0.05
        cause: str | None = None  # why the link went down, kept through failed reconnects
        while not self._stop.is_set():
            if self._ser is None:
                cause = cause if cause is not None else (self._link_error or "rig link down")
                # wait before every attempt, and reset the wait only once the firmware's heartbeat is
                # seen again: a firmware that answers HELLO but never beats must not flap the link
                if self._stop.wait(backoff):
                    break
                backoff = min(2 * backoff, self.backoff_max)
                try:
                    self._connect()
                except RigLinkError as e:
                    with self._lock:
                        self._link_error = f"{cause}; reconnecting: {e}"
                        self._link_exc = type(e)  # a re-flashed firmware of another version says so
                    continue
                self.stats["reconnects"] += 1
                cause = None
            self._poll()
            if self._hb_seen:
                backoff = 0.05

    def _poll(self) -> None:
        """Read what has arrived, parse it, send a heartbeat when due, drop the link when the firmware's stops."""
        ser = self._ser
        if ser is None:
            return
        try:
            chunk = ser.read(max(1, ser.in_waiting))
        except (serial.SerialException, OSError, TypeError, AttributeError) as e:
            # TypeError/AttributeError: pyserial's read on a port closed under it by close()
            self._drop(ser, f"rig link on {self.port} lost: {e}")
            return
        *lines, self._rxbuf = (self._rxbuf + chunk).split(b"\n")
        if len(self._rxbuf) > MAX_LINE:  # no newline in sight: noise, not a line
            self.stats["bad_lines"] += 1
            self._rxbuf = b""
        for line in lines:
            self._handle(line)
        now = time.monotonic()
        if now - self._last_hb > self.link_timeout:
            self._drop(ser, f"rig link on {self.port} lost: no heartbeat from the firmware for "
                            f"{now - self._last_hb:.2f} s (limit {self.link_timeout:g} s)")
            return
        if now - self._last_tx >= self.heartbeat_period:
            try:
                self._send("HB")
            except RigLinkError:
                pass  # recorded by _send; the next loop reconnects

    def _handle(self, line: bytes) -> None:
        try:
            m = decode_line(line)
        except LineError as e:
            self.stats["crc_errors" if e.kind == "crc" else "bad_lines"] += 1
            return
        self.stats["seq_gaps"] += (m.seq - self._rx_expect) % SEQ_MOD
        self._rx_expect = (m.seq + 1) % SEQ_MOD
        try:
            if m.kind == "P":
                self._on_pressure(m)
            elif m.kind == "HB":
                if len(m.fields) != 1 or m.fields[0] not in ("RUN", "SAFE"):
                    raise ValueError("HB needs a mode RUN or SAFE")
                self.firmware_mode = m.fields[0]
                self._last_hb = time.monotonic()
                self._hb_seen = True
            elif m.kind == "U" and self.board_controller:
                self._on_report(m)
            elif m.kind != "VER":  # a repeated VER is harmless
                raise ValueError(f"unknown message type {m.kind!r}")
        except ValueError:
            self.stats["bad_lines"] += 1
            return
        self.stats["lines"] += 1

    def _on_report(self, m: Message) -> None:
        raise ValueError("U lines come from a board that runs its own controller")

    def _on_pressure(self, m: Message) -> None:
        if len(m.fields) != self.n + 2 or not m.fields[0].isdigit() or not (
                m.fields[1].isdigit() or m.fields[1] == "-"):
            raise ValueError("P needs a time stamp, the held command's SEQ and one pressure per chamber")
        p = np.array([np.nan if f == "NA" else float(int(f)) for f in m.fields[2:]])
        self._publish(m.seq, int(m.fields[0]), m.fields[1], p)

    def _held_of(self, named: str) -> np.ndarray | None:
        """The command a P line's ``held`` field names (caller holds the lock); None when unknown."""
        # "-": the firmware's own watchdog made it safe (no host line set it)
        return safe_u(self.n) if named == "-" else self._sent_u.get(int(named))

    def _publish(self, seq: int, t_us: int, named: str, p: np.ndarray) -> None:
        """Make one sample the newest readings and wake :meth:`wait_sample`."""
        with self._lock:
            held = self._held_of(named)
            if held is None:
                self.stats["held_unknown"] += 1
            self._held = held
            have = ~np.isnan(p)
            self._p[have] = p[have]  # an NA keeps the older value, reported as not fresh
            self._fresh |= have
            self._t = t_us * 1e-6
            self._pseq = seq
            self._arrival = time.monotonic()
            self._sample_cv.notify_all()
        self.stats["readings"] += 1
