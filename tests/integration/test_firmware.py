"""The reference firmware (firmware/): its C unit tests, the host board on a pty against the package's
host code, the AVR builds' size, and the Uno build in simavr.

The host board's time passes only when the test ticks it (HostBoard.tick), so the exchanges on the
raw pty are deterministic; a line the test writes is waited for by its effect (a counter or a reply),
never by a delay. The SerialRig tests tick the board in real time (run_realtime) with generous
timeouts, as the host side needs a live heartbeat.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import serial

from checkout import ROOT
from rig_links import UntilRigTime
from hbma_ctrl.app.daemon.firmware import FirstOrderPlant, HostBoard, RealtimeBoard, build_firmware
from hbma_ctrl.system.serial_link import Message, SerialRig, decode_line, encode_line

pytestmark = pytest.mark.compiling

TIMEOUT = 10.0  # generous bound for what takes milliseconds on an idle machine
PERIOD_US = 10000  # the host board's default: 100 ticks of 100 us
UNO_FLASH, UNO_RAM = 32768 - 512, 2048  # the Uno's bootloader takes 512 bytes of flash

needs_avr = pytest.mark.skipif(shutil.which("avr-gcc") is None,
                               reason="avr-gcc is not installed (apt-get install gcc-avr avr-libc)")


@pytest.fixture(scope="module")
def host_exe(tmp_path_factory):
    return build_firmware("host", tmp_path_factory.mktemp("fw"))


class Link:
    """The host's end of the board's pty, written and read line by line with the package's codec."""

    def __init__(self, port: str) -> None:
        self.ser = serial.Serial(port, 115200, timeout=0.05)
        self.buf = b""

    def send(self, kind: str, seq: int, *fields: object, end: bytes = b"\n", corrupt: bool = False) -> None:
        line = encode_line(kind, seq, *fields)
        if corrupt:
            line = line[:-2] + bytes([line[-2] ^ 0x01]) + b"\n"  # one checksum digit changed
        self.ser.write(line[:-1] + end)

    def lines(self, k: int) -> list[Message]:
        """The next ``k`` lines the board sent (each valid: decode_line raises otherwise)."""
        out: list[Message] = []
        deadline = time.monotonic() + TIMEOUT
        while len(out) < k and time.monotonic() < deadline:
            self.buf += self.ser.read(4096)
            while b"\n" in self.buf and len(out) < k:
                line, self.buf = self.buf.split(b"\n", 1)
                out.append(decode_line(line))
        assert len(out) == k, f"expected {k} lines from the board, got {out}"
        return out

    def close(self) -> None:
        self.ser.close()


def _until(board: HostBoard, pred):
    """Poll the board (no ticks) until ``pred(outputs)``; the outputs."""
    deadline = time.monotonic() + TIMEOUT
    while True:
        out = board.tick(0)
        if pred(out) or time.monotonic() > deadline:
            assert pred(out), out
            return out
        time.sleep(0.002)


@pytest.fixture()
def rig2(host_exe):
    board = HostBoard(host_exe, n=2)
    link = Link(board.port)
    yield board, link
    link.close()
    board.close()


def _session(board: HostBoard, link: Link) -> None:
    """Handshake, then tick up to mid-period 1 (calls 0..49; call 0 was the sample instant of P 1)."""
    link.send("HELLO", 0, 2)
    assert link.lines(1)[0] == Message("VER", 0, ("2", "2", str(PERIOD_US)))
    board.tick(50, p=np.zeros(2))
    assert link.lines(1)[0] == Message("P", 1, ("0", "0", "0", "0"))


def test_c_unit_tests_of_the_core_pass(tmp_path):
    build_firmware("test", tmp_path)  # runs them; a failing check fails the build with its output


def test_handshake_then_p_lines_every_sample_period_and_a_heartbeat(rig2):
    board, link = rig2
    board.tick(250)
    link.ser.reset_input_buffer()
    link.send("HELLO", 0, 2)
    assert link.lines(1)[0] == Message("VER", 0, ("2", "2", str(PERIOD_US)))
    board.tick(50, p=np.array([1000.0, 20e3]))  # calls 250..299
    board.tick(1000)  # calls 300..1299: instants at 300, 400, ..., 1200
    got = link.lines(11)
    ps = [m for m in got if m.kind == "P"]
    assert [int(m.fields[0]) for m in ps] == [300 * 100 + k * PERIOD_US for k in range(10)]
    assert all(m.fields[1] == "0" for m in ps)  # every period held HELLO's safe state
    p = np.array([[int(x) for x in m.fields[2:]] for m in ps])
    assert np.all(np.abs(p - [1000, 20e3]) <= 7)  # within one ADC count (6.788 Pa)
    assert [m.seq for m in got] == list(range(1, 12))
    assert [m.fields for m in got if m.kind == "HB"] == [("SAFE",)]  # every 0.1 s, after its P line


def test_a_command_waits_for_the_next_sample_instant_and_holds_its_duty(rig2):
    board, link = rig2
    _session(board, link)
    link.send("CMD", 1, 600, 1000, 0, 300, 250, 1000)
    _until(board, lambda o: o.commands == 1)
    rest = board.tick(50)  # calls 50..99: the rest of the period runs on HELLO's safe state
    np.testing.assert_array_equal(rest.u, [[0, 0], [0, 0], [1, 1]])
    assert rest.mode == "RUN"  # received, not yet latched
    full = board.tick(100)  # calls 100..199: the whole period on CMD 1
    np.testing.assert_allclose(full.u, [[0.6, 0.3], [1.0, 0.25], [0.0, 1.0]])
    board.tick(1)  # call 200
    p1, p2 = link.lines(2)
    assert (p1.seq, p1.fields[:2]) == (2, ("10000", "0"))  # the period ending at call 100 held HELLO
    assert (p2.seq, p2.fields[:2]) == (3, ("20000", "1"))  # the next one CMD 1


def test_safe_acts_at_once_mid_period(rig2):
    board, link = rig2
    _session(board, link)
    link.send("CMD", 1, 1000, 1000, 0, 1000, 1000, 0)
    _until(board, lambda o: o.commands == 1)
    board.tick(80)  # calls 50..129: running on CMD 1 since call 100
    link.send("SAFE", 2)
    _until(board, lambda o: o.mode == "SAFE")
    now = board.tick(1)  # call 130, mid-period
    np.testing.assert_array_equal(now.u, [[0, 0], [0, 0], [1, 1]])
    board.tick(70)  # call 200
    assert link.lines(2)[1].fields[1] == "2"  # the period ending at 200 is named by SAFE 2


def test_the_watchdog_goes_safe_when_the_host_falls_silent(rig2):
    board, link = rig2
    _session(board, link)
    link.send("CMD", 1, 500, 1000, 0, 500, 1000, 0)
    _until(board, lambda o: o.commands == 1)
    for seq in range(2, 12):  # 1 s of board time with a heartbeat every 0.1 s: still running
        assert board.tick(1000).mode == "RUN"
        link.send("HB", seq)
        out = _until(board, lambda o, k=seq: o.lines == k + 1)  # HELLO, CMD 1, HB 2..seq received
    _lines_through(link, out.t_us)
    assert board.tick(4900).mode == "RUN"  # 0.49 s of silence: not yet
    late = board.tick(200)  # 0.5 s and one tick: safe at once, 101 ticks into these 200
    assert late.mode == "SAFE"
    np.testing.assert_allclose(late.u, [[0.25, 0.25], [0.5, 0.5], [0.5, 0.5]])
    after = board.tick(1000)
    np.testing.assert_array_equal(after.u, [[0, 0], [0, 0], [1, 1]])
    tail = _lines_through(link, after.t_us)
    assert [m.fields[1] for m in tail if m.kind == "P"][-10:] == ["-"] * 10  # the watchdog's safe state
    assert [m.fields for m in tail if m.kind == "HB"][-1] == ("SAFE",)


def _lines_through(link: Link, t_us: int) -> list[Message]:
    """The board's lines up to its P line of the last sample instant before board time ``t_us``."""
    last = (t_us - 1) // PERIOD_US * PERIOD_US
    out = link.lines(1)
    while not (out[-1].kind == "P" and int(out[-1].fields[0]) >= last):
        out += link.lines(1)
    return out


def test_crlf_line_ends_are_accepted(rig2):
    board, link = rig2
    link.send("HELLO", 0, 2, end=b"\r\n")
    assert link.lines(1)[0].kind == "VER"
    link.send("CMD", 1, 600, 1000, 0, 0, 0, 1000, end=b"\r\n")
    out = _until(board, lambda o: o.commands == 1)
    assert (out.crc_errors, out.bad_lines) == (0, 0)
    np.testing.assert_allclose(board.tick(200).u[0], [0.6, 0.0])  # latched at the first instant, call 0


def test_a_line_with_a_bad_checksum_is_counted_and_never_acted_on(rig2):
    board, link = rig2
    _session(board, link)
    link.send("CMD", 1, 1000, 1000, 0, 1000, 1000, 0, corrupt=True)
    out = _until(board, lambda o: o.crc_errors == 1)
    assert out.commands == 0
    np.testing.assert_array_equal(board.tick(250).u, [[0, 0], [0, 0], [1, 1]])
    link.send("CMD", 2, 1000, 1000, 0, 1000, 1000, 0)  # the next valid one counts the lost SEQ 1
    out = _until(board, lambda o: o.commands == 1)
    assert out.seq_gaps == 1


def test_calibration_persists_in_the_boards_nvm(host_exe, tmp_path):
    eeprom = tmp_path / "eeprom.bin"
    board = HostBoard(host_exe, n=2, eeprom=eeprom)
    link = Link(board.port)
    try:
        assert list(board.zero) == [655, 655]
        link.send("HELLO", 0, 2)
        link.lines(1)
        link.send("CAL", 1, 1, 800, 5000)  # a bench tool's extension line
        _until(board, lambda o: eeprom.is_file())
        assert board.tick(0).bad_lines == 0
    finally:
        link.close()
        board.close()
    again = HostBoard(host_exe, n=2, eeprom=eeprom)
    try:
        assert (list(again.zero), list(again.gain)) == ([655, 800], [6788, 5000])
    finally:
        again.close()


def _hold(rig: SerialRig, u: np.ndarray, count: int):
    """Write ``u`` every sample until ``count`` samples said they held it; the last reading."""
    held = 0
    deadline = time.monotonic() + 4 * TIMEOUT
    while held < count and time.monotonic() < deadline:
        rig.write(u)
        rig.wait_sample(1.0)
        r = rig.read()
        if r.held is not None and np.array_equal(r.held, u):
            held += 1
    assert held == count, rig.stats
    return r


def test_serial_rig_closes_the_loop_through_the_host_board(host_exe):
    rt = RealtimeBoard(HostBoard(host_exe, n=2), FirstOrderPlant(2))
    rig = None
    try:
        rig = SerialRig(rt.board.port, 2, sample_period=0.01, link_timeout=TIMEOUT, handshake_timeout=TIMEOUT)
        assert rig.sample_period == pytest.approx(0.01)
        r = _hold(rig, np.array([[0.6, 0.0], [1.0, 0.0], [0.0, 1.0]]), 30)
        assert r.p[0] > 1000.0 and abs(r.p[1]) <= 7  # chamber 0 fills, chamber 1 stays vented
        assert rig.firmware_mode == "RUN"
        assert (rig.stats["crc_errors"], rig.stats["bad_lines"], rig.stats["held_unknown"]) == (0, 0, 0)
    finally:
        if rig is not None:
            rig.close()
        rt.close()


def _avr_size(elf, mcu: str) -> tuple[int, int]:
    out = subprocess.run(["avr-size", "--format=avr", f"--mcu={mcu}", str(elf)], capture_output=True,
                         text=True, check=True).stdout
    return (int(re.search(r"Program:\s+(\d+) bytes", out).group(1)),
            int(re.search(r"Data:\s+(\d+) bytes", out).group(1)))


@needs_avr
@pytest.mark.parametrize("n", [1, 4])
def test_the_uno_build_fits_with_room_for_the_stack(tmp_path, n):
    flash, ram = _avr_size(build_firmware("avr", tmp_path, n), "atmega328p")
    print(f"Uno, n = {n}: flash {flash} of 32768 bytes, RAM {ram} of 2048 bytes (static)")
    assert flash < UNO_FLASH
    assert ram < UNO_RAM - 512  # the stack: the tick's frame, a line on fw_poll's stack


@needs_avr
def test_an_avr_build_that_would_host_the_library_stops_at_a_clear_error(tmp_path):
    from hbma_ctrl.app.daemon.firmware import FIRMWARE_DIR

    res = subprocess.run(["make", "-s", "-C", str(FIRMWARE_DIR), "avr", f"O={tmp_path}", "DEFS=-DFW_HOSTED"],
                         capture_output=True, text=True)
    assert res.returncode != 0
    assert "#error" in res.stderr and "needs about 240 KB of RAM" in res.stderr, res.stderr
    assert not (tmp_path / "uno" / "hbma-fw.elf").exists()


@needs_avr
def test_the_mega_build_compiles(tmp_path):
    flash, ram = _avr_size(build_firmware("mega", tmp_path, 4), "atmega2560")
    assert flash < 256 * 1024 and ram < 8192


@needs_avr
@pytest.mark.skipif(shutil.which("simavr") is None or not Path("/usr/include/simavr/sim_avr.h").is_file(),
                    reason="simavr and its library headers are not installed (apt-get install simavr libsimavr-dev)")
def test_the_uno_build_in_simavr_talks_to_serial_rig(tmp_path):
    elf = build_firmware("avr", tmp_path, 1)
    runner = build_firmware("simavr", tmp_path)
    # 1100 mV on the sensor: 225 per conversion, 3600 counts (16 summed) -> 19.99 kPa by the default calibration
    proc = subprocess.Popen([str(runner), str(elf), "--adc-mv", "1100"], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    rig = None
    try:
        port = proc.stdout.readline().strip()
        assert port.startswith("/dev/"), proc.poll()
        rig = SerialRig(port, 1, sample_period=0.01, link_timeout=TIMEOUT, handshake_timeout=TIMEOUT)
        assert rig.sample_period == pytest.approx(0.01)
        r = _hold(rig, np.array([[0.6], [1.0], [0.0]]), 10)
        assert abs(r.p[0] - 20.0e3) < 100.0  # one 10-bit LSB is 108 Pa
        assert _wait(lambda: rig.firmware_mode == "RUN")
        rig.safe()
        assert _wait(lambda: rig.firmware_mode == "SAFE")
        assert (rig.stats["crc_errors"], rig.stats["bad_lines"], rig.stats["held_unknown"]) == (0, 0, 0)
    finally:
        if rig is not None:
            rig.close()
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=TIMEOUT)


def _wait(pred) -> bool:
    deadline = time.monotonic() + TIMEOUT
    while not pred() and time.monotonic() < deadline:
        time.sleep(0.01)
    return bool(pred())


@pytest.mark.subprocess
@pytest.mark.parametrize("target", ["host", "avr"])
def test_rig_emulate_prints_its_port_serves_the_host_and_cleans_up_on_sigterm(tmp_path, target):
    if target == "avr" and (shutil.which("avr-gcc") is None or shutil.which("simavr") is None or
                            not Path("/usr/include/simavr/sim_avr.h").is_file()):
        pytest.skip("avr-gcc, simavr or simavr's headers are not installed")
    env = dict(os.environ, PYTHONPATH=str(ROOT), TMPDIR=str(tmp_path))
    proc = subprocess.Popen([sys.executable, "-m", "hbma_ctrl", "rig", "emulate", "--target", target, "--n", "2"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    rig = None
    try:
        port = proc.stdout.readline().strip()
        assert port.startswith("/dev/"), proc.stderr.read() if proc.poll() is not None else port
        rig = SerialRig(port, 2, sample_period=0.01, link_timeout=TIMEOUT, handshake_timeout=TIMEOUT)
        assert rig.wait_sample(TIMEOUT) is not None
        assert np.all(np.isfinite(rig.read().p))
    finally:
        if rig is not None:
            rig.close()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=4 * TIMEOUT)
    assert proc.returncode == 0, err
    assert list(tmp_path.iterdir()) == []  # the build folder is gone



def _through_the_host_board(tmp: Path, text: str, duration: float,
                            library: Path | None = None) -> tuple[dict, object, dict, list[dict]]:
    """The daemon's loop <-> SerialRig <-> pty <-> C firmware <-> the configuration ``text``'s simulated
    rig (``rig emulate --config``, its own process) for ``duration`` s of the board's time: (loop stats, the
    runner, the link's stats, the rig's true state per period from the firmware's truth log).
    ``library``: the board hosts this chamber library (``rig emulate --library``) and the daemon runs
    with ``--board-controller``.
    As in test_daemon.py's serial test, the loop's watchdogs of real time (heartbeat, stale samples,
    missed deadlines) are relaxed: on a loaded machine a late process is the machine's load, not the
    link's."""
    import csv
    from dataclasses import replace

    from hbma_ctrl.app.daemon.build import build_runner, make_monitor, make_rig
    from hbma_ctrl.app.daemon.config import load_config
    from hbma_ctrl.app.daemon.loop import DaemonLoop
    from hbma_ctrl.app.daemon.state import DaemonState
    from hbma_ctrl.runtime.watchdog import SafetyMonitor

    tmp.mkdir(parents=True, exist_ok=True)
    cfg_path, truth = tmp / "cfg.toml", tmp / "truth.csv"
    assert "log_flush_s = 0.5" in text
    cfg_path.write_text(text.replace("log_flush_s = 0.5", "log_flush_s = 0.5\nmiss_limit = 100000"))
    (tmp / "tmp").mkdir()
    env = dict(os.environ, PYTHONPATH=str(ROOT), TMPDIR=str(tmp / "tmp"))
    hosted = [] if library is None else ["--library", str(library)]
    proc = subprocess.Popen([sys.executable, "-m", "hbma_ctrl", "rig", "emulate", "--config", str(cfg_path),
                             "--truth-log", str(truth), *hosted], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env)
    try:
        port = proc.stdout.readline().strip()
        assert port.startswith("/dev/"), proc.stderr.read() if proc.poll() is not None else port
        cfg = load_config(cfg_path, {"--rig": f"serial:{port}", "--board-controller": library is not None})
        runner = build_runner(cfg)
        rig = make_rig(cfg, runner)
        rig.link_timeout = 60.0
        monitor = SafetyMonitor(replace(make_monitor(cfg, runner).settings, stale_periods=10**6,
                                        same_value_periods=None), runner.n)
        state = DaemonState()
        # the run covers ``duration`` s of the board's time: an emulated board that a loaded machine runs
        # late streams fewer samples in as many of the loop's periods
        loop = DaemonLoop(runner, UntilRigTime(rig, state, duration), state, cfg.period, monitor=monitor)
        try:
            stats = loop.run()
        finally:
            rig.close()
        deadline = time.monotonic() + 60.0  # the SAFE close() sent reaches the board a little later
        while (_truth_modes(truth) or ["-"])[-1] != "SAFE" and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=60)
    assert proc.returncode == 0 and list((tmp / "tmp").iterdir()) == []
    with truth.open() as fh:
        rows = list(csv.DictReader(fh))
    return stats, runner, dict(rig.stats), rows


@pytest.mark.slow
@pytest.mark.subprocess
def test_the_daemon_loop_runs_through_the_host_board_on_the_configs_rig(tmp_path):
    """The shipped chamber file through the C firmware's host build: calibrated from the commands the
    board held, no fault, a link that lost or garbled nothing, the board in RUN from the loop's first
    command to its last and SAFE at the end."""
    stats, runner, link, rows = _through_the_host_board(
        tmp_path, (ROOT / "scenarios" / "daemon_chamber.toml").read_text(), 4.0)
    assert stats["safe_exit"] and stats["faults"] == {}, stats
    assert runner.stats()["calibration"]["status"] == "ok"  # fitted from the commands the board held
    assert (link["crc_errors"], link["bad_lines"], link["held_unknown"]) == (0, 0, 0)
    modes = [r["mode"] for r in rows]
    first, last = modes.index("RUN"), len(modes) - 1 - modes[::-1].index("RUN")
    assert set(modes[first:last + 1]) == {"RUN"} and modes[-1] == "SAFE"  # never went safe on its own


#: the 5 mm step through the board: the shipped chamber file, 2 -> 7 mm at 3 s of the schedule
STEP_5MM = ("targets_mm = [[0.0, 2.0], [3.0, 6.0]]", "targets_mm = [[0.0, 2.0], [3.0, 7.0]]")


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.parametrize("seed", [*range(3), *(pytest.param(s, marks=pytest.mark.sweep) for s in range(3, 10))])
def test_a_5mm_step_through_the_host_board_settles_within_0p6mm_for_each_of_10_rig_seeds(tmp_path, seed):
    """The daemon's closed loop through the C firmware's host build, its plant the file's rig (the 400 g
    load, noise and the rig's own draws from ``seed``), 11 s of loop time: the loop closes after its
    start-up calibration (under 3 s: its rig time grows with the periods a loaded machine makes the
    loop miss), the 5 mm step (2 -> 7 mm) comes 3 s later, and over the last 3 s (the firmware's truth
    log, at least 2 s after the step) the true height stays within 0.6 mm of 7 mm. A pass rate over 10 rig
    seeds with every one required (one test a seed, so that the workers share them): CI runs seeds 0-2,
    the by-hand sweep set (`-m sweep`) the other seven."""
    text = (ROOT / "scenarios" / "daemon_chamber.toml").read_text()
    assert STEP_5MM[0] in text and "\nseed = 1\n" in text
    text = text.replace(*STEP_5MM).replace("\nseed = 1\n", f"\nseed = {seed}\n")
    stats, runner, link, rows = _through_the_host_board(tmp_path, text, 11.0)
    assert stats["faults"] == {} and stats["safe_exit"], stats
    assert (link["crc_errors"], link["bad_lines"], link["held_unknown"]) == (0, 0, 0), link
    # the loop closed (the rig's time of its readings, from the loop's start) early enough that the
    # window starts at least 2 s after the step
    assert runner.stats()["calibration"]["status"] == "ok" and runner.t_closed < 3.0, runner.t_closed
    run = [(float(r["t_s"]), float(r["h_C1_mm"])) for r in rows if r["mode"] == "RUN"]
    h = np.array([h for t, h in run if t >= run[-1][0] - 3.0])
    assert h.size >= 250, h.size  # the firmware's periods over the last 3 s (a late process loses a few)
    assert np.all(np.abs(h - 7.0) <= 0.6), f"the true height left 7 +- 0.6 mm: {h.min():.2f}-{h.max():.2f} mm"


def _truth_modes(path: Path) -> list[str]:
    import csv

    with path.open() as fh:
        return [row["mode"] for row in csv.DictReader(fh)]


# ---- the board hosts the controller (FW_HOSTED) -------------------------------------------------------

#: the hosted board's closed loop: the shipped chamber file with a shorter horizon (its library builds in a
#: few seconds) and one target, 7 mm from the board's first TGT on: the board rests vented until that TGT,
#: so when it arrives in the board's time (later on a loaded machine) changes nothing the board does after it
HOSTED_EDITS = (("horizon = 20", "horizon = 8"), ("targets_mm = [[0.0, 2.0], [3.0, 6.0]]", "targets_mm = [[0.0, 7.0]]"))


def _hosted_text() -> str:
    text = (ROOT / "scenarios" / "daemon_chamber.toml").read_text()
    for old, new in HOSTED_EDITS:
        assert old in text
        text = text.replace(old, new)
    return text


@pytest.fixture(scope="session")
def hosted(tmp_path_factory, worker_id):
    """(the hosted host board's executable, its library's folder, the configuration it was generated from):
    the chamber library of :func:`_hosted_text` generated and built (unoptimised) and the board built with
    it, once for all of a run's xdist workers (in their shared base folder, under a lock)."""
    import fcntl

    from hbma_ctrl.app.codegen.library import library_spec, write_library
    from hbma_ctrl.app.scenario import load_scenario

    base = tmp_path_factory.getbasetemp()
    work = (base if worker_id == "master" else base.parent) / "hosted"
    work.mkdir(exist_ok=True)
    cfg, lib, exe = work / "cfg.toml", work / "lib", work / "fw" / "host" / "hbma-fw-host-hosted"
    with open(work / "lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        if not (work / "done").is_file():
            cfg.write_text(_hosted_text())
            write_library(library_spec(load_scenario(cfg)), lib)
            build_firmware("host-hosted", work / "fw", library=lib)
            (work / "done").write_text("")
    return exe, lib, cfg


@pytest.fixture()
def hosted_board(hosted):
    board = HostBoard(hosted[0], n=1)
    link = Link(board.port)
    yield board, link
    link.close()
    board.close()


def test_a_target_line_is_counted_and_refused_by_a_board_without_a_controller(rig2):
    board, link = rig2
    _session(board, link)
    link.send("TGT", 1, 5000, 5000)
    out = _until(board, lambda o: o.bad_lines == 1)
    assert (out.mode, out.commands) == ("SAFE", 0)
    np.testing.assert_array_equal(board.tick(200).u, [[0, 0], [0, 0], [1, 1]])


@pytest.mark.slow
def test_the_hosted_board_runs_its_controller_on_a_target_and_safe_and_the_watchdog_stop_it_at_once(hosted_board):
    """Through the real library: VER says hosted, a CMD is refused, a TGT runs the board on the library's
    commands (U lines after every P, the pump on from the period after the target's first tick); SAFE
    mid-period and 0.5 s of host silence make it safe at once, and the library's commands stay out."""
    board, link = hosted_board
    link.send("HELLO", 0, 2)
    assert link.lines(1)[0] == Message("VER", 0, ("2", "1", str(PERIOD_US), "hosted"))
    link.send("CMD", 1, 1000, 1000, 0)
    assert _until(board, lambda o: o.bad_lines == 1).commands == 0
    link.send("TGT", 2, 7000)
    _until(board, lambda o: o.commands == 1)
    out = board.tick(300, p=np.zeros(1))  # three samples at 0 Pa below a 7 mm target: it pumps
    assert out.mode == "RUN" and out.u[0, 0] > 0 and out.u[1, 0] > 0, out
    got = link.lines(6)
    assert [m.kind for m in got] == ["P", "U"] * 3 and all(len(m.fields) == 6 for m in got[1::2])
    assert int(got[-1].fields[0]) > 0  # the command it announced pumps
    board.tick(30)
    link.send("SAFE", 3)
    _until(board, lambda o: o.mode == "SAFE")
    np.testing.assert_array_equal(board.tick(1).u, [[0], [0], [1]])  # at once, mid-period
    np.testing.assert_array_equal(board.tick(300).u, [[0], [0], [1]])  # the library's commands stay out
    link.send("TGT", 4, 7000)
    _until(board, lambda o: o.commands == 2)
    assert board.tick(250).u[0, 0] > 0
    assert board.tick(4700).mode == "RUN"  # 0.495 s of silence since TGT 4: not yet
    late = board.tick(200)
    assert late.mode == "SAFE" and late.held is None  # the watchdog's own safe state
    np.testing.assert_array_equal(board.tick(300).u, [[0], [0], [1]])


@pytest.mark.slow
def test_host_and_board_refuse_a_hosted_mismatch_with_one_line(hosted, host_exe, tmp_path):
    """A host that would command a board running its own controller, and a host that would send targets
    to a board without one, are each refused at the handshake with one line; the daemon given
    --board-controller on a board without a controller stops before its loop with that line as its one
    error line, leaving no results directory."""
    from typer.testing import CliRunner

    from cli_checks import one_line_error
    from hbma_ctrl.app.cli.main import app
    from hbma_ctrl.system.board_link import BoardControlledRig
    from hbma_ctrl.system.serial_link import ControllerMismatchError

    for exe, link_cls, needle in ((hosted[0], SerialRig, "runs its own controller"),
                                  (host_exe, BoardControlledRig, "runs no controller of its own")):
        rt = RealtimeBoard(HostBoard(exe, n=1), FirstOrderPlant(1))
        try:
            with pytest.raises(ControllerMismatchError, match=needle) as e:
                link_cls(rt.port, 1, sample_period=0.01, handshake_timeout=TIMEOUT)
            assert "\n" not in str(e.value) and "--board-controller" in str(e.value)
            if link_cls is BoardControlledRig:  # the daemon's runner is cheap to build in this direction
                res = CliRunner().invoke(app, ["daemon", str(hosted[2]), "--rig", f"serial:{rt.port}",
                                               "--board-controller", "--duration-s", "1", "--out",
                                               str(tmp_path / "run")])
                one_line_error(res, needle, "--board-controller")
                assert not (tmp_path / "run").exists()
        finally:
            rt.close()


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.parametrize("seed", [1, *(pytest.param(s, marks=pytest.mark.sweep) for s in range(2, 11))])
def test_a_7mm_target_from_rest_settles_within_0p6mm_under_the_controller_the_board_hosts(hosted, tmp_path, seed):
    """The daemon with --board-controller, the board hosting the file's chamber library (a horizon of 8),
    its plant the file's simulated rig (its draws from ``seed``): the daemon sends the target and runs no
    controller; from rest the true height settles within 0.6 mm of the 7 mm target over the last 2 s of
    the 6 s run (the board's time); the run's keys are filled from the board's reports. A pass rate over
    10 rig seeds, every one required: CI runs seed 1, the by-hand sweep set (`-m sweep`) the other nine."""
    exe, lib, cfg = hosted
    text = cfg.read_text()
    assert "\nseed = 1\n" in text
    stats, runner, link, rows = _through_the_host_board(tmp_path, text.replace("\nseed = 1\n", f"\nseed = {seed}\n"),
                                                        6.0, library=lib)
    assert stats["faults"] == {} and stats["safe_exit"], stats
    assert (link["crc_errors"], link["bad_lines"], link["unreported"]) == (0, 0, 0), link
    st = runner.stats()
    assert st["board_controller"] and st["steps"] > 0 and st["board_errors"] == 0, st
    assert st["solve_ms_median"] is None  # not on the line
    run = [(float(r["t_s"]), float(r["h_C1_mm"])) for r in rows if r["mode"] == "RUN"]
    h = np.array([h for t, h in run if t >= run[-1][0] - 2.0])
    assert h.size >= 150, h.size
    assert np.all(np.abs(h - 7.0) <= 0.6), f"the true height left 7 +- 0.6 mm: {h.min():.2f}-{h.max():.2f} mm"
    assert np.isfinite(runner.estimates()[0]).all()


@pytest.mark.slow
def test_rig_check_passes_a_hosted_board_on_targets_and_leaves_its_actuator_checks_out(hosted, tmp_path):
    """A hosted board refuses CMD: the checklist runs it with TGT lines, checks each P line's U report,
    and names why the actuator checks are not run."""
    import json

    from typer.testing import CliRunner

    from hbma_ctrl.app.cli.main import app

    rt = RealtimeBoard(HostBoard(hosted[0], n=1), FirstOrderPlant(1))
    try:
        res = CliRunner().invoke(app, ["rig", "check", rt.board.port, "--out", str(tmp_path / "check")])
    finally:
        rt.close()
    doc = json.loads((tmp_path / "check" / "check.json").read_text())
    checks = {c["name"]: c for c in doc["checks"]}
    assert res.exit_code == 0 and doc["passed"], res.output
    assert {"bad checksum ignored", "crlf", "watchdog", "held", "reports"} <= set(checks)
    assert not any(name.startswith(("inlet", "pump", "outlet")) for name in checks)
    assert "hosted" in checks["handshake"]["measured"] and "FW_HOSTED" in checks["handshake"]["measured"]
    assert "TGT" in checks["crlf"]["measured"]
