"""``hbma-ctrl rig check PORT``: a bring-up checklist for any firmware speaking the line protocol
version 2 (:mod:`hbma_ctrl.system.serial_link`).

One session on the port, with the protocol's own codec (:func:`~hbma_ctrl.system.serial_link.encode_line`,
:func:`~hbma_ctrl.system.serial_link.decode_line`). Not through
:class:`~hbma_ctrl.system.serial_link.SerialRig`: the check must see every line the firmware sends (not
the newest reading only), send lines with a wrong checksum or a ``\\r\\n`` ending, and fall silent on
purpose, none of which a working link does. The checks, in the order they run:

- ``handshake``: ``HELLO`` is answered by ``VER`` of version 2 (and ``n`` chambers when given); a
  board that runs its own controller says ``hosted`` after them.
- ``sample period`` and ``jitter``: the spacing of the ``P`` lines' time stamps against the period
  ``VER`` declared (stamps, not the host's clock: a loaded host does not move them).
- ``sensor zero Ci``: each chamber's pressure at rest, vented.
- ``bad checksum ignored``: a command with a wrong checksum is never acted on.
- ``crlf``: a command ended by ``\\r\\n`` is acted on.
- per chamber ``inlet Ci``, ``pump Ci``, ``outlet Ci``: with the other chambers vented, the pump
  running against a closed inlet holds, opening the inlet fills the chamber by ``rise`` (the other
  chambers stay put), stopping the pump stops the fill, and opening the outlet vents half of it, each
  within ``step_s`` of firmware time.
- ``watchdog``: the firmware stays in RUN while the host beats and goes safe (``P`` lines naming
  ``-``) within ``watchdog_s`` once the host falls silent.
- ``held``: every ``P`` line names a host line the check sent (or ``-``).
- ``heartbeat``: ``HB`` lines with a mode at least every ``link_timeout`` (0.5 s) of samples.
- ``crc``, ``sequence``: over the whole session no firmware line fails its checksum, and every SEQ is
  one more than the one before (no repeat, no jump).

A hosted board refuses ``CMD``: the check runs it with ``TGT`` lines of target 0 instead (the
checksum, line-end and watchdog checks), leaves out the actuator checks (its controller, not the
check, drives the valves: check them with the firmware built without ``FW_HOSTED``), and adds
``reports``: each ``P`` line is followed by the board's ``U`` report, with six fields per chamber.

Times are measured on the firmware's stamps (whole sample periods); the host's clock only bounds how
long the check waits. :func:`run_checks` returns the :class:`Check` list; the CLI writes ``check.json``.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np
import serial

from hbma_ctrl.core.units import kpa, to_kpa, to_ms
from hbma_ctrl.system.serial_link import PROTOCOL_VERSION, SEQ_MOD, LineError, decode_line, encode_line

__all__ = ["Check", "CheckSettings", "run_checks", "open_port"]

#: what a check that could not run says it measured
NOT_RUN = "not run: no session (see handshake)"


@dataclass(frozen=True)
class Check:
    """One line of the checklist: ``name``, ``passed``, what was ``measured`` and what was ``expected``
    (texts in user units)."""

    name: str
    passed: bool
    measured: str
    expected: str

    def as_dict(self) -> dict:
        """The check as check.json holds it."""
        return {**asdict(self), "passed": bool(self.passed)}


@dataclass(frozen=True)
class CheckSettings:
    """Bounds of the checks (SI units).

    n : chambers the rig must report (None: take the firmware's). rise : the fill each inlet and pump
    step aims at, Pa (kept small: a real membrane is inflated this much). tol : the largest change a
    step that must hold may show, Pa. zero_tol : the largest pressure at rest, Pa. step_s : firmware
    time a step may take to respond, s. hold_s : firmware time a holding step lasts, s. watchdog_s :
    host silence after which the firmware must be safe, s. link_timeout : the longest gap between
    heartbeats, s. period_tol : relative error of the sample period. jitter_tol : largest deviation of
    one interval from the period, relative. handshake_s : wait for ``VER``, s. rest_s : firmware time
    at rest the period and the zeros are measured over, s. max_wait_s : the longest wait for it (host
    time, s); how fast it came scales every later wait.
    """

    n: int | None = None
    rise: float = kpa(5.0)
    tol: float = kpa(1.0)
    zero_tol: float = kpa(1.0)
    step_s: float = 2.0
    hold_s: float = 0.3
    watchdog_s: float = 1.0
    link_timeout: float = 0.5
    period_tol: float = 0.01
    jitter_tol: float = 0.02
    handshake_s: float = 2.0
    rest_s: float = 0.5
    max_wait_s: float = 60.0


def open_port(port: str, baud: int = 115200):
    """Open ``port`` (a device path or a pyserial URL) exclusively; ValueError naming PORT when it cannot be."""
    try:
        return serial.serial_for_url(port, baudrate=baud, timeout=0.02, write_timeout=0.5, exclusive=True)
    except (serial.SerialException, OSError, ValueError) as e:
        raise ValueError(f"PORT {port}: cannot open it ({e})") from None


@dataclass
class _Sample:
    t: float  # firmware time, s
    held: str  # the SEQ of the held host line, or "-"
    p: np.ndarray  # Pa (n,), NaN for NA
    clean: bool  # no line lost or corrupted since the previous sample


@dataclass
class _Session:
    """The check's end of the link: every line received is recorded; HB sent while ``beat``."""

    ser: object
    beat_s: float = 0.1
    seq: int = 0
    n: int = 0
    period: float = 0.0
    lines: int = 0
    crc_bad: int = 0
    bad: int = 0
    repeats: int = 0
    skipped: int = 0
    samples: list[_Sample] = field(default_factory=list)
    beats: list[tuple[int, str]] = field(default_factory=list)  # (samples before it, mode)
    sent: set[int] = field(default_factory=set)  # SEQs of HELLO, CMD, TGT, SAFE lines
    ver: tuple[str, ...] | None = None
    hosted: bool = False  # the board runs its own controller (its VER says so)
    reports: list[int] = field(default_factory=list)  # per U line: the samples before it, -1 if malformed
    rest: np.ndarray | None = None  # each chamber's pressure at rest, vented, Pa
    _last_seq: int | None = None
    _lost: bool = False
    _buf: bytes = b""
    _last_tx: float = 0.0

    def send(self, kind: str, *fields: object, end: bytes = b"\n", corrupt: bool = False) -> int:
        """Send one line; its SEQ. ``corrupt``: a checksum one bit off (the body stays a valid line)."""
        s = self.seq
        line = encode_line(kind, s, *fields)
        if corrupt:
            line = line[:-6] + b"*%04X\n" % (int(line[-5:-1], 16) ^ 0x0001)
        if kind in ("HELLO", "CMD", "TGT", "SAFE"):
            self.sent.add(s)
        self.ser.write(line[:-1] + end)
        self.seq = (s + 1) % SEQ_MOD
        self._last_tx = time.monotonic()
        return s

    def command(self, chamber: int | None = None, pump: int = 0, inlet: int = 0, outlet: int = 1000,
                **kw) -> int:
        """``CMD`` with every chamber vented but ``chamber`` (per-mille values); its SEQ."""
        vals: list[int] = []
        for i in range(self.n):
            vals += [pump, inlet, outlet] if i == chamber else [0, 0, 1000]
        return self.send("CMD", *vals, **kw)

    def run_line(self, **kw) -> int:
        """A line that runs the board and moves nothing: every chamber vented by ``CMD``, or on a hosted
        board a ``TGT`` of 0 for every chamber; its SEQ."""
        return self.send("TGT", *([0] * self.n), **kw) if self.hosted else self.command(**kw)

    def until(self, pred, timeout: float, beat: bool = True) -> bool:
        """Read (and beat while ``beat``) until ``pred()`` or ``timeout`` s of host time; whether it held."""
        deadline = time.monotonic() + timeout
        while True:
            if pred():
                return True
            if time.monotonic() > deadline:
                return False
            chunk = self.ser.read(max(1, self.ser.in_waiting))
            *got, self._buf = (self._buf + chunk).split(b"\n")
            for line in got:
                self._receive(line)
            if beat and self.ver is not None and time.monotonic() - self._last_tx >= self.beat_s:
                self.send("HB")

    def acted(self, seq: int, since: tuple[int, int], samples: int, timeout: float) -> bool:
        """Read until the firmware shows it acted on command ``seq``: a P line names it, or an HB says
        RUN (the firmware was safe before it) after ``since`` (the lengths of ``samples`` and ``beats``
        when it was sent); whether it did within ``samples`` samples (and ``timeout`` s)."""
        did = lambda: (any(x.held == str(seq) for x in self.samples[since[0]:])  # noqa: E731
                       or any(m == "RUN" for _, m in self.beats[since[1]:]))
        self.until(lambda: did() or len(self.samples) - since[0] >= samples, timeout)
        return did()

    def mark(self) -> tuple[int, int]:
        """Where the record stands (samples, beats), for :meth:`acted`."""
        return len(self.samples), len(self.beats)

    def wait_samples(self, k: int, timeout: float, beat: bool = True) -> bool:
        """Read until ``k`` more samples arrived."""
        want = len(self.samples) + k
        return self.until(lambda: len(self.samples) >= want, timeout, beat)

    def _receive(self, line: bytes) -> None:
        try:
            m = decode_line(line)
        except LineError as e:
            if e.kind == "crc":
                self.crc_bad += 1
            else:
                self.bad += 1
            self._lost = True
            return
        self.lines += 1
        if m.kind == "VER" and self.ver is None:
            self.ver = m.fields
            self._last_seq = m.seq
            return
        if self._last_seq is not None:
            d = (m.seq - self._last_seq) % SEQ_MOD
            if d == 0:
                self.repeats += 1
            elif d != 1:
                self.skipped += 1
                self._lost = True
        self._last_seq = m.seq
        if self.ver is None:
            return
        if m.kind == "P" and len(m.fields) == self.n + 2 and m.fields[0].isdigit():
            try:
                p = np.array([np.nan if f == "NA" else float(int(f)) for f in m.fields[2:]])
            except ValueError:
                self.bad += 1
                return
            self.samples.append(_Sample(int(m.fields[0]) * 1e-6, m.fields[1], p, not self._lost))
            self._lost = False
        elif m.kind == "HB" and len(m.fields) == 1 and m.fields[0] in ("RUN", "SAFE"):
            self.beats.append((len(self.samples), m.fields[0]))
        elif m.kind == "U" and self.hosted:
            self.reports.append(len(self.samples) if len(m.fields) == 6 * self.n else -1)
        elif m.kind != "VER":
            self.bad += 1


def _kpa(x: float) -> str:
    return "NA" if not np.isfinite(x) else f"{to_kpa(x):+.2f} kPa"


def run_checks(ser, settings: CheckSettings = CheckSettings()) -> list[Check]:
    """Run the checklist on an open port ``ser`` (see the module's docstring); the checks in order.
    Leaves the firmware safe (``SAFE`` sent last)."""
    s = _Session(ser)
    cs = settings
    out: list[Check] = []
    ser.reset_input_buffer()
    s.send("HELLO", PROTOCOL_VERSION)
    s.until(lambda: s.ver is not None, cs.handshake_s, beat=False)
    out.append(_handshake(s, cs))
    names = ["sample period", "jitter", *(f"sensor zero C{i + 1}" for i in range(max(s.n, 1))),
             "bad checksum ignored", "crlf",
             *(f"{a} C{i + 1}" for i in range(max(s.n, 1)) for a in ("inlet", "pump", "outlet")),
             "watchdog", "held", "heartbeat"]
    if out[0].passed:
        try:
            out += _session_checks(s, cs)
        finally:
            s.send("SAFE")
    else:
        s.until(lambda: False, 0.5, beat=False)  # what else it sends, for the checksum and SEQ counts
        out += [Check(name, False, NOT_RUN, "") for name in names]
    total = s.lines + s.crc_bad + s.bad
    out.append(Check("crc", total > 0 and s.crc_bad == 0, f"{s.crc_bad} of {total} lines failed their checksum",
                     "0 (at least one line received)"))
    out.append(Check("sequence", s.lines > 0 and s.repeats == s.skipped == 0,
                     f"{s.repeats} repeated, {s.skipped} jumps in {s.lines} lines",
                     "every SEQ one more than the last"))
    return out


def _handshake(s: _Session, cs: CheckSettings) -> Check:
    expected = f"VER {PROTOCOL_VERSION} n period_us within {cs.handshake_s:g} s" + (
        f", n = {cs.n}" if cs.n is not None else "")
    if s.ver is None:
        got = f"no VER within {cs.handshake_s:g} s"
        if s.crc_bad or s.bad:
            got += f" ({s.crc_bad + s.bad} lines received, none valid)"
        return Check("handshake", False, got, expected)
    f = s.ver
    hosted = len(f) == 4 and f[3] == "hosted"
    ok = len(f) in (3, 4) and (len(f) == 3 or hosted) and all(x.isdigit() for x in f[:3]) \
        and int(f[0]) == PROTOCOL_VERSION and int(f[1]) >= 1 and int(f[2]) > 0 and (cs.n is None or int(f[1]) == cs.n)
    if ok:
        s.n, s.period, s.hosted = int(f[1]), int(f[2]) * 1e-6, hosted
    measured = "VER " + " ".join(f)
    if len(f) in (3, 4) and all(x.isdigit() for x in f[:3]):
        measured = f"version {f[0]}, {f[1]} chambers, period {int(f[2]) / 1000:g} ms"
        if hosted:
            measured += ("; hosted: the board runs its own controller (the actuator checks need CMD, which it "
                         "refuses: run them on the firmware built without FW_HOSTED)")
    return Check("handshake", ok, measured, expected)


def _session_checks(s: _Session, cs: CheckSettings) -> list[Check]:
    out: list[Check] = []
    n, period = s.n, s.period
    per = lambda t: max(1, int(round(t / period)))  # noqa: E731  (firmware time as samples)
    # at rest, vented: the period, its jitter, each sensor's zero; and how fast the firmware's time
    # runs against the host's (an emulated board on a loaded machine runs slower than real time)
    s.send("SAFE")
    s.wait_samples(1, cs.handshake_s)
    t0, k0 = time.monotonic(), len(s.samples)
    s.wait_samples(per(cs.rest_s), cs.max_wait_s)
    elapsed = time.monotonic() - t0
    speed = (s.samples[-1].t - s.samples[k0 - 1].t) / elapsed if len(s.samples) > k0 > 0 and elapsed > 0 else 1.0
    speed = min(1.0, max(speed, cs.rest_s / cs.max_wait_s))

    def wait(t: float) -> float:
        """Host time to wait for t s of the firmware's."""
        return (3.0 * t + 2.0) / speed

    out += _period_checks(s, cs)
    rest = s.samples[-per(min(0.2, cs.rest_s)):]
    s.rest = np.array([np.median([x.p[i] for x in rest]) if rest else np.nan for i in range(n)])
    for i in range(n):
        p = float(s.rest[i])
        out.append(Check(f"sensor zero C{i + 1}", bool(np.isfinite(p) and abs(p) <= cs.zero_tol),
                         f"{_kpa(p)} (median of {len(rest)} samples, vented)", f"|p| <= {to_kpa(cs.zero_tol):g} kPa"))
    # from the safe state, a command with a wrong checksum (all vented, so harmless if obeyed)
    since = s.mark()
    kind = "TGT" if s.hosted else "CMD"
    bad_seq = s.run_line(corrupt=True)
    obeyed = s.acted(bad_seq, since, per(cs.hold_s), wait(cs.hold_s))
    out.append(Check("bad checksum ignored", not obeyed,
                     f"{kind} {bad_seq} with a wrong checksum " + ("was acted on" if obeyed else "was not acted on"),
                     "not acted on (no P line names it, no HB says RUN)"))
    # a command ended by \r\n
    s.send("SAFE")
    since = s.mark()
    seq = s.run_line(end=b"\r\n")
    ok = s.acted(seq, since, per(cs.hold_s), wait(cs.hold_s))
    out.append(Check("crlf", ok, ("acted on" if ok else "never acted on") + f" ({kind} {seq} ended by \\r\\n)",
                     "acted on (a P line names it or an HB says RUN)"))
    if not s.hosted:
        out += [c for i in range(n) for c in _actuator_checks(s, cs, i, per, wait)]
    out.append(_watchdog(s, cs, per, wait))
    unknown = [x.held for x in s.samples if x.held != "-" and not (x.held.isdigit() and int(x.held) in s.sent)]
    out.append(Check("held", not unknown, f"{len(unknown)} of {len(s.samples)} P lines named a SEQ never sent "
                     f"as HELLO, {kind} or SAFE" + (f" (first: {unknown[0]})" if unknown else ""),
                     "each names a host line sent, or '-'"))
    out.append(_heartbeat(s, cs))
    if s.hosted:
        out.append(_reports(s))
    return out


def _reports(s: _Session) -> Check:
    """A hosted board's ``U`` reports: one after each ``P`` line, six fields per chamber."""
    expected = f"a U line after each P line, {6 * s.n} fields"
    bad = sum(k < 0 for k in s.reports)
    # the session's last P line may be read before its report: every other one has its own
    unreported = max(len(s.samples) - 1 - (len(s.reports) - bad), 0)
    return Check("reports", bool(s.samples) and bad == 0 and unreported == 0,
                 f"{len(s.reports)} U lines for {len(s.samples)} P lines, {bad} malformed", expected)


def _period_checks(s: _Session, cs: CheckSettings) -> list[Check]:
    t = np.array([x.t for x in s.samples])
    clean = np.array([x.clean for x in s.samples[1:]], dtype=bool)
    d = np.diff(t)[clean] if len(t) > 1 else np.zeros(0)
    want = s.period
    if d.size == 0:
        return [Check("sample period", False, f"{len(t)} samples", f"{to_ms(want):g} ms (VER)"),
                Check("jitter", False, f"{len(t)} samples", "")]
    med, worst = float(np.median(d)), float(np.max(np.abs(d - want)))
    return [Check("sample period", abs(med - want) <= cs.period_tol * want,
                  f"{to_ms(med):.3f} ms (median of {d.size} intervals of the stamps)",
                  f"{to_ms(want):g} ms (declared by VER) +- {cs.period_tol:.0%}"),
            Check("jitter", worst <= cs.jitter_tol * want, f"{to_ms(worst):.3f} ms (largest deviation)",
                  f"<= {to_ms(cs.jitter_tol * want):.3g} ms ({cs.jitter_tol:.0%} of the period)")]


@dataclass(frozen=True)
class _Step:
    done: bool  # the step's condition was met
    first: float  # chamber i's first pressure under the command, Pa
    last: float  # and its last, Pa
    t: float  # firmware time from the command's start to the last, s


def _step(s: _Session, i: int, cmd: tuple[int, int, int], done, limit_s: float, per, wait) -> _Step:
    """Send chamber ``i`` the command ``cmd`` (pump, inlet, outlet per-mille; the others vented) and
    read the samples under it until ``done(p_i)`` or ``limit_s`` of firmware time. Under it: from the
    first P line naming it, or (a firmware whose P lines name no command) from the third sample after
    sending it (the latching period and one in flight skipped)."""
    start = len(s.samples)
    seq = s.command(i, *cmd)

    def got() -> list[_Sample]:
        new = s.samples[start:]
        k = next((j for j, x in enumerate(new) if x.held == str(seq)), None)
        return new[k if k is not None else 2:]

    hit = lambda: bool(got()) and done(got()[-1].p[i])  # noqa: E731
    s.until(lambda: hit() or len(got()) >= per(limit_s), wait(limit_s))
    g = got()
    if not g:
        return _Step(False, float("nan"), float("nan"), 0.0)
    return _Step(hit(), float(g[0].p[i]), float(g[-1].p[i]), g[-1].t - g[0].t + s.period)


def _actuator_checks(s: _Session, cs: CheckSettings, i: int, per, wait) -> list[Check]:
    c = f"C{i + 1}"
    rest = s.rest[i]
    _step(s, i, (0, 0, 1000), lambda p: abs(p - rest) <= cs.tol, cs.step_s, per, wait)  # vented to start
    p0 = s.samples[-1].p.copy() if s.samples else np.full(s.n, np.nan)
    # the pump against a closed inlet (outlet closed): holds
    closed = _step(s, i, (1000, 0, 0), lambda p: False, cs.hold_s, per, wait)
    closed_ok = abs(closed.last - p0[i]) <= cs.tol
    # the inlet opens: fills by rise; the other chambers stay put
    fill = _step(s, i, (1000, 1000, 0), lambda p: abs(p - p0[i]) >= cs.rise, cs.step_s, per, wait)
    filled = fill.last - p0[i] >= cs.rise
    others = [j for j in range(s.n) if j != i and s.samples and abs(s.samples[-1].p[j] - p0[j]) > cs.tol]
    wrong_way = " (the wrong way: inverted sensor?)" if fill.last - p0[i] <= -cs.rise else ""
    inlet = Check(f"inlet {c}", bool(closed_ok and filled and not others),
                  f"closed: {_kpa(closed.last - p0[i])}; open: {_kpa(fill.last - p0[i])} in {fill.t:.2f} s{wrong_way}"
                  + (f"; C{others[0] + 1} moved" if others else ""),
                  f"closed: within {to_kpa(cs.tol):g} kPa; open (pump on): >= +{to_kpa(cs.rise):g} kPa "
                  f"within {cs.step_s:g} s, the other chambers within {to_kpa(cs.tol):g} kPa")
    # the pump stops (inlet still open): the fill stops
    off = _step(s, i, (0, 1000, 0), lambda p: False, cs.hold_s, per, wait)
    pump_expected = (f"on (inlet open): >= +{to_kpa(cs.rise):g} kPa within {cs.step_s:g} s; "
                     f"off: rises at most {to_kpa(cs.tol):g} kPa over {cs.hold_s:g} s")
    if filled:
        pump = Check(f"pump {c}", bool(off.last - off.first <= cs.tol),
                     f"on: {_kpa(fill.last - p0[i])} in {fill.t:.2f} s; off: {_kpa(off.last - off.first)}",
                     pump_expected)
    else:
        pump = Check(f"pump {c}", False, f"the chamber did not fill with the inlet open "
                     f"({_kpa(fill.last - p0[i])} in {fill.t:.2f} s; see inlet {c})", pump_expected)
    # the outlet opens (pump off, inlet closed): vents at least half of the fill
    top = off.last
    vent = _step(s, i, (0, 0, 1000), lambda p: p - p0[i] <= 0.5 * (top - p0[i]), cs.step_s, per, wait)
    outlet_expected = f"open: falls by half the fill within {cs.step_s:g} s"
    if top - p0[i] >= cs.rise:
        outlet = Check(f"outlet {c}", vent.done, f"open: {_kpa(vent.last - top)} in {vent.t:.2f} s",
                       outlet_expected)
    else:
        outlet = Check(f"outlet {c}", False, f"not judged: the chamber was not filled (see inlet {c})",
                       outlet_expected)
    _step(s, i, (0, 0, 1000), lambda p: abs(p - p0[i]) <= cs.tol, cs.step_s, per, wait)
    return [inlet, pump, outlet]


def _watchdog(s: _Session, cs: CheckSettings, per, wait) -> Check:
    expected = (f"RUN while the host beats ({cs.watchdog_s:g} s); safe ('-') within {cs.watchdog_s:g} s "
                "of host silence")
    s.send("SAFE")
    since = s.mark()
    seq = s.run_line()
    if not s.acted(seq, since, per(cs.hold_s), wait(cs.hold_s)):
        return Check("watchdog", False, f"{'TGT' if s.hosted else 'CMD'} {seq} was not acted on (no RUN to trip "
                     "from)", expected)
    start = len(s.samples)
    s.wait_samples(per(cs.watchdog_s), wait(cs.watchdog_s))
    early = sum(x.held == "-" for x in s.samples[start:])
    if early:
        return Check("watchdog", False, f"safe ('-') in {early} samples while the host was beating", expected)
    if not s.samples:
        return Check("watchdog", False, "no samples", expected)
    silent_from = len(s.samples)
    t0 = s.samples[-1].t
    beats_from = len(s.beats)
    tripped = lambda: (any(x.held == "-" for x in s.samples[silent_from:])  # noqa: E731
                       or any(m == "SAFE" for _, m in s.beats[beats_from:]))
    s.until(lambda: tripped() or len(s.samples) - silent_from >= per(2 * cs.watchdog_s), wait(2 * cs.watchdog_s),
            beat=False)
    after = s.samples[silent_from:]
    if not tripped():
        span = after[-1].t - t0 if after else 0.0
        return Check("watchdog", False, f"still running after {span:.2f} s of host silence", expected)
    first = next((k for k, x in enumerate(after) if x.held == "-"), len(after))
    first = min([first, *(k - silent_from for k, m in s.beats[beats_from:] if m == "SAFE")])
    t_safe = after[min(first, len(after) - 1)].t - t0 if after else 0.0
    return Check("watchdog", t_safe <= cs.watchdog_s, f"safe {t_safe:.2f} s after the host fell silent", expected)


def _heartbeat(s: _Session, cs: CheckSettings) -> Check:
    expected = f"an HB line (RUN or SAFE) at least every {cs.link_timeout:g} s of samples"
    if not s.beats:
        return Check("heartbeat", False, f"no HB line in {len(s.samples)} samples", expected)
    marks = [0, *(k for k, _ in s.beats), len(s.samples)]
    gap = max(b - a for a, b in zip(marks, marks[1:]))
    gap_s = gap * s.period
    modes = sorted({m for _, m in s.beats})
    return Check("heartbeat", gap_s <= cs.link_timeout,
                 f"every {gap} samples at most ({gap_s:.2f} s); modes {', '.join(modes)}", expected)
