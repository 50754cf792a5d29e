"""The serial rig backend: line codec, handshake, commands, link loss, reconnect, a loop over the link.

The firmware is the reference firmware's host board (firmware/, :class:`HostBoard`) stepped in real time
against a plant; its test knobs corrupt or lose lines it sends, inject defects, and unplug and re-plug
its port."""

from __future__ import annotations

import os
import subprocess
import sys
import time
import tty
from pathlib import Path

import numpy as np
import pytest
import serial

from typer.testing import CliRunner

from checkout import ROOT
from cli_checks import one_line_error
from hbma_ctrl.app.cli.main import app
from hbma_ctrl.app.daemon.firmware import (
    FirstOrderPlant,
    HostBoard,
    RealtimeBoard,
    build_firmware,
    open_fake_rig,
)
from hbma_ctrl.system.rigio import Readings, RigIO, RigLinkError, safe_u
from hbma_ctrl.system.serial_link import (
    PROTOCOL_VERSION,
    LineError,
    ProtocolVersionError,
    SerialRig,
    crc16,
    decode_line,
    encode_line,
    from_permille,
    to_permille,
)

TIMEOUT = 5.0  # generous bound for anything that should happen within ~0.5 s on an idle machine


def _crc_reference(data: bytes) -> int:
    """Bit-by-bit CRC-16/CCITT-FALSE, written from its definition as an independent oracle."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
    return crc


def _wait(pred, timeout: float = TIMEOUT) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.01)
    return bool(pred())


def _read_raises(rig: SerialRig) -> bool:
    return _link_error(rig) is not None


def _link_error(rig: SerialRig) -> RigLinkError | None:
    try:
        rig.read()
    except RigLinkError as e:
        return e
    return None


def _await_link_error(rig: SerialRig) -> RigLinkError:
    errors = []
    assert _wait(lambda: errors.append(_link_error(rig)) or errors[-1] is not None)
    return errors[-1]


SAFE_PERMILLE = (0, 0, 1000)


@pytest.fixture(scope="module")
def host_exe(tmp_path_factory):
    return build_firmware("host", tmp_path_factory.mktemp("fw"))


def Firmware(exe: Path, n: int = 1, period: float = 0.01, plant=None, **board_kw) -> RealtimeBoard:
    """The host board with ``n`` chambers sampling every ``period`` s, stepped in real time against
    ``plant`` (default :class:`FirstOrderPlant`); ``board_kw`` go to :class:`HostBoard`."""
    return RealtimeBoard(HostBoard(exe, n, period_ticks=round(period / 100e-6), **board_kw),
                         plant if plant is not None else FirstOrderPlant(n))


def _open(exe: Path, n: int = 1, period: float = 0.01, plant=None, **rig_kw) -> tuple[RealtimeBoard, SerialRig]:
    return open_fake_rig(n, period, plant, exe=exe, **rig_kw)


@pytest.fixture
def rig2(host_exe):
    fw, rig = _open(host_exe, 2)
    yield fw, rig
    rig.close()
    fw.close()


# ---- codec ---------------------------------------------------------------------------------------

def test_crc16_matches_the_ccitt_false_check_value_and_a_bitwise_reference():
    assert crc16(b"123456789") == 0x29B1
    for data in (b"", b"A", b"HB 0", b"P 65535 123456 -12 NA"):
        assert crc16(data) == _crc_reference(data)


def test_encode_decode_round_trip_wraps_seq_and_keeps_fields():
    line = encode_line("P", 65537, 123456, -12, "NA")
    assert line == b"P 1 123456 -12 NA*%04X\n" % _crc_reference(b"P 1 123456 -12 NA")
    m = decode_line(line)
    assert (m.kind, m.seq, m.fields) == ("P", 1, ("123456", "-12", "NA"))


@pytest.mark.parametrize("line, kind", [
    (b"HB 4 RUN*0000\n", "crc"),
    (b"HB 4 RUN\n", "format"),
    (b"HB 4 RUN*XYZW\n", "format"),
    (b"HB*%04X\n" % crc16(b"HB"), "format"),
    (b"HB 70000*%04X\n" % crc16(b"HB 70000"), "format"),
])
def test_decode_rejects_bad_checksum_and_framing(line, kind):
    with pytest.raises(LineError) as e:
        decode_line(line)
    assert e.value.kind == kind


def test_permille_rounds_half_up_chamber_by_chamber():
    u = np.array([[0.0, 1.0], [0.0126, 0.9996], [0.0124, 0.5]])  # rows pump, inlet, outlet
    assert to_permille(u) == [0, 13, 12, 1000, 1000, 500]
    np.testing.assert_allclose(from_permille([0, 13, 12, 1000, 1000, 500], 2),
                               [[0.0, 1.0], [0.013, 1.0], [0.012, 0.5]])
    with pytest.raises(ValueError):
        from_permille([0, 1001, 0], 1)


# ---- handshake -----------------------------------------------------------------------------------

@pytest.mark.compiling
def test_handshake_takes_the_firmware_sample_period_and_satisfies_rigio(host_exe):
    fw = Firmware(host_exe, 1, 0.02)
    try:
        rig = SerialRig(fw.port, 1)
        try:
            assert isinstance(rig, RigIO)
            assert rig.sample_period == pytest.approx(0.02)
            assert rig.connected
        finally:
            rig.close()
    finally:
        fw.close()


@pytest.mark.compiling
def test_version_mismatch_raises_protocol_version_error_naming_both_versions(host_exe):
    fw = Firmware(host_exe, 1, defects=("version",))  # it speaks version 3
    try:
        with pytest.raises(ProtocolVersionError) as e:
            SerialRig(fw.port, 1)
        msg = str(e.value)
        assert f"version {PROTOCOL_VERSION + 1}" in msg and f"version {PROTOCOL_VERSION}" in msg
        assert "\n" not in msg
    finally:
        fw.close()


@pytest.mark.compiling
def test_chamber_count_mismatch_is_a_link_error_naming_n(host_exe):
    fw = Firmware(host_exe, 2)
    try:
        with pytest.raises(RigLinkError, match="reports 2 chambers, expected n = 3"):
            SerialRig(fw.port, 3)
    finally:
        fw.close()


def test_silent_port_fails_the_handshake_with_one_clear_error():
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        with pytest.raises(RigLinkError, match="no answer to HELLO"):
            SerialRig(os.ttyname(slave), 1, handshake_timeout=0.3)
    finally:
        os.close(slave)
        os.close(master)


@pytest.mark.compiling
def test_a_second_host_cannot_open_the_same_rig(rig2):
    fw, rig = rig2
    with pytest.raises(RigLinkError, match="cannot open rig port"):
        SerialRig(fw.port, 2)
    assert rig.connected


def test_bad_settings_name_the_key():
    with pytest.raises(ValueError, match="rig n = 0"):
        SerialRig("loop://", 0)
    with pytest.raises(ValueError, match="link_timeout"):
        SerialRig("loop://", 1, heartbeat_period=0.5, link_timeout=0.2)


# ---- readings and commands -----------------------------------------------------------------------

@pytest.mark.compiling
def test_readings_arrive_with_seq_time_stamp_and_fresh_flags(rig2):
    fw, rig = rig2
    assert _wait(lambda: rig.stats["readings"] >= 3)
    r1 = rig.read()
    assert isinstance(r1, Readings) and r1.p.shape == (2,)
    assert r1.fresh.all() and r1.seq >= 0 and r1.t is not None
    again = rig.read()
    assert not again.fresh.any() and again.seq == r1.seq  # nothing new yet: a repeat, flagged stale
    assert _wait(lambda: rig.stats["readings"] >= 10)
    r2 = rig.read()
    assert r2.seq > r1.seq and r2.t > r1.t and r2.fresh.all()


@pytest.mark.compiling
def test_commands_reach_the_firmware_exactly(rig2):
    fw, rig = rig2
    u = np.array([[1.0, 0.3], [0.0126, 1.0], [0.0, 0.9994]])
    rig.write(u)
    assert _wait(lambda: fw.out.commands == 1)
    assert fw.out.command == (1000, 13, 0, 300, 1000, 999)
    assert fw.out.mode == "RUN"
    assert _wait(lambda: rig.firmware_mode == "RUN")
    with pytest.raises(ValueError):
        rig.write(np.zeros((3, 1)))


@pytest.mark.compiling
def test_safe_command_puts_the_firmware_in_the_safe_state(rig2):
    fw, rig = rig2
    rig.write(np.ones((3, 2)))
    assert _wait(lambda: fw.out.mode == "RUN")
    rig.safe()
    assert _wait(lambda: fw.out.mode == "SAFE")
    assert fw.out.command == SAFE_PERMILLE * 2


@pytest.mark.compiling
def test_corrupted_and_lost_lines_are_counted_never_used(host_exe):
    fw, rig = _open(host_exe, 1, plant=lambda u, dt: np.zeros(1))
    try:
        assert _wait(lambda: rig.stats["readings"] >= 2)
        seen = []
        fw.board.corrupt_next(5)  # a flipped bit in the body: "P .. 0" would read "P .. 1" if used
        deadline = time.monotonic() + TIMEOUT
        while rig.stats["crc_errors"] < 5 and time.monotonic() < deadline:
            seen.append(rig.read().p[0])
            time.sleep(0.005)
        assert rig.stats["crc_errors"] == 5
        assert set(seen) <= {0.0}
        # each corrupted line is also a missing sequence number, seen when the next good line arrives
        assert _wait(lambda: rig.stats["seq_gaps"] == 5)
        gaps = rig.stats["seq_gaps"]
        fw.board.drop_next(4)
        assert _wait(lambda: rig.stats["seq_gaps"] == gaps + 4)
        assert rig.connected and rig.stats["bad_lines"] == 0
    finally:
        rig.close()
        fw.close()


@pytest.mark.compiling
def test_fresh_flags_are_per_chamber_and_na_keeps_the_older_value(host_exe):
    chamber0 = [1000.0]
    fw, rig = _open(host_exe, 2, plant=lambda u, dt: np.array([chamber0[0], 2000.0]))
    try:
        assert _wait(lambda: rig.stats["readings"] >= 2)
        np.testing.assert_array_equal(rig.read().fresh, [True, True])
        chamber0[0] = np.nan  # the firmware now sends NA for chamber 0
        n0 = rig.stats["readings"]
        assert _wait(lambda: rig.stats["readings"] >= n0 + 3)
        rig.read()
        assert _wait(lambda: rig.stats["readings"] >= n0 + 6)
        r = rig.read()
        # chamber 0 repeats its older value (each within one count of the board's ADC, 6.8 Pa)
        np.testing.assert_allclose(r.p, [1000.0, 2000.0], atol=7.0)
        np.testing.assert_array_equal(r.fresh, [False, True])
    finally:
        rig.close()
        fw.close()


def _raw_session(fw: RealtimeBoard) -> serial.Serial:
    """A bare pyserial session with the firmware: HELLO sent, VER read."""
    s = serial.Serial(fw.port, 115200, timeout=TIMEOUT)
    s.write(encode_line("HELLO", 0, PROTOCOL_VERSION))
    m = decode_line(s.readline())
    assert m.kind == "VER" and m.fields[0] == str(PROTOCOL_VERSION)
    return s


@pytest.mark.compiling
def test_a_corrupted_command_is_not_applied(host_exe):
    fw = Firmware(host_exe, 1)
    try:
        s = _raw_session(fw)
        good = encode_line("CMD", 1, 1000, 1000, 0)
        bad = good.replace(b"CMD 1 1000 1000 0", b"CMD 1 1000 1000 1")  # a bit flip, old checksum
        s.write(bad)
        assert _wait(lambda: fw.out.crc_errors == 1)
        assert fw.out.mode == "SAFE" and fw.out.commands == 0 and fw.out.command == SAFE_PERMILLE
        s.write(good)
        assert _wait(lambda: fw.out.commands == 1)
        assert fw.out.command == (1000, 1000, 0)
        s.close()
    finally:
        fw.close()


# ---- heartbeats, link loss, reconnect ------------------------------------------------------------

@pytest.mark.compiling
@pytest.mark.slow
def test_host_heartbeat_keeps_the_firmware_running_and_its_loss_makes_it_safe(host_exe):
    fw, rig = _open(host_exe, 1)
    try:
        rig.write(np.array([[1.0], [1.0], [0.0]]))
        assert _wait(lambda: fw.out.mode == "RUN")
        time.sleep(1.2)  # well past the firmware's 0.5 s watchdog: only heartbeats keep it running
        assert fw.out.mode == "RUN"
    finally:
        rig.close()
    # a host that stops talking (no SAFE, no heartbeat) is caught by the firmware's watchdog
    try:
        s = _raw_session(fw)
        s.write(encode_line("CMD", 1, 1000, 1000, 0))
        assert _wait(lambda: fw.out.mode == "RUN")
        assert _wait(lambda: fw.out.mode == "SAFE")
        assert fw.out.held is None  # safe by its own watchdog: no host line set it
        assert fw.out.command == SAFE_PERMILLE
        s.close()
    finally:
        fw.close()


@pytest.mark.compiling
def test_firmware_vanishing_raises_link_error_and_the_firmware_goes_safe(rig2):
    fw, rig = rig2
    rig.write(np.ones((3, 2)))
    assert _wait(lambda: fw.out.mode == "RUN")
    fw.board.vanish()
    assert "rig link on" in str(_await_link_error(rig))
    with pytest.raises(RigLinkError):
        rig.write(np.ones((3, 2)))
    rig.safe()  # never raises, even with the link down
    assert _wait(lambda: fw.out.mode == "SAFE")


@pytest.mark.compiling
def test_firmware_heartbeat_stopping_raises_link_error(host_exe):
    fw, rig = _open(host_exe, 1, link_timeout=0.3)
    try:
        rig.write(np.array([[1.0], [1.0], [0.0]]))
        assert _wait(lambda: fw.out.mode == "RUN")
        fw.board.inject("no_heartbeat")  # pressures still stream: the heartbeat alone says the firmware is alive
        assert "no heartbeat from the firmware" in str(_await_link_error(rig))
        assert _wait(lambda: fw.out.mode == "SAFE")
    finally:
        rig.close()
        fw.close()


@pytest.mark.compiling
def test_reconnects_when_the_configured_port_returns(host_exe, tmp_path):
    link = str(tmp_path / "rig0")  # a stable name, as /dev/serial/by-id gives a re-plugged device
    fw = Firmware(host_exe, 1, link=link)
    rig = SerialRig(link, 1, backoff_max=0.2)
    try:
        first = fw.board.pty_path
        fw.board.vanish()
        assert _wait(lambda: _read_raises(rig))
        fw.board.reappear()
        assert fw.board.pty_path is not None and os.readlink(link) == fw.board.pty_path
        assert _wait(lambda: rig.connected and not _read_raises(rig))
        assert rig.stats["reconnects"] == 1
        assert _wait(lambda: rig.read().fresh.all())
        rig.write(np.array([[0.5], [0.5], [0.0]]))
        assert _wait(lambda: fw.out.command == (500, 500, 0))
        assert first  # the old device path was a different node or a reused one; either works
    finally:
        rig.close()
        fw.close()


# ---- a loop over the link ------------------------------------------------------------------------

def _p_control(p: float, ref: float, kp: float) -> np.ndarray:
    e = ref - p
    return np.array([[min(max(kp * e, 0.0), 1.0)], [1.0 if e > 0 else 0.0], [min(max(-kp * e, 0.0), 1.0)]])


@pytest.mark.compiling
@pytest.mark.slow
def test_proportional_loop_over_serial_settles_as_on_the_direct_plant(host_exe):
    ref, kp, dt = 30e3, 1e-4, 0.01
    direct = FirstOrderPlant(1)
    p = 0.0
    for _ in range(300):
        p = float(direct(_p_control(p, ref, kp), dt)[0])
    # independent check: at equilibrium fill_rate * kp * (ref - p) = p / tau_leak
    k = direct.fill_rate * kp * direct.tau_leak
    assert p == pytest.approx(ref * k / (1 + k), rel=1e-3)

    fw, rig = _open(host_exe, 1, dt)
    try:
        tail = []
        t_end = time.monotonic() + 2.0
        while time.monotonic() < t_end:
            r = rig.read()
            p_meas = 0.0 if np.isnan(r.p[0]) else float(r.p[0])
            rig.write(_p_control(p_meas, ref, kp))
            if t_end - time.monotonic() < 0.4:
                tail.append(p_meas)
            time.sleep(dt)
    finally:
        rig.close()
        fw.close()
    assert np.mean(tail) == pytest.approx(p, rel=0.03)


@pytest.mark.subprocess
@pytest.mark.compiling
def test_rig_emulate_keeps_a_link_a_rig_can_open_and_removes_it_on_the_way_out(tmp_path):
    link = str(tmp_path / "rig")
    env = {**os.environ, "PYTHONPATH": str(ROOT), "TMPDIR": str(tmp_path)}  # this checkout's package
    proc = subprocess.Popen([sys.executable, "-m", "hbma_ctrl", "rig", "emulate", "--n", "2", "--link", link],
                            stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert proc.stdout.readline().strip() == link
        rig = SerialRig(link, 2)
        try:
            assert _wait(lambda: rig.read().fresh.all())
        finally:
            rig.close()
    finally:
        proc.terminate()
        assert proc.wait(timeout=TIMEOUT) == 0
    assert not os.path.lexists(link)  # removed on the way out


def _emulate(*args: str):
    return CliRunner().invoke(app, ["rig", "emulate", *args])


def test_rig_emulate_rejects_bad_flags_with_one_line():
    one_line_error(_emulate("--n", "0"), "--n = 0")
    one_line_error(_emulate("--period-ms", "0.5"), "--period-ms = 0.5")
    one_line_error(_emulate("--defect", "wobbly"), "--defect = 'wobbly'")
    one_line_error(_emulate("--target", "avr", "--link", "/tmp/x"), "--link: runs with --target host only")


@pytest.mark.compiling
def test_p_lines_name_the_command_held_over_their_period_from_the_next_sample_instant(rig2):
    """Version 2: the firmware latches a CMD at its next sample instant; each P line names the host
    line held over the period it ends, and read() gives that command (as sent, per-mille)."""
    fw, rig = rig2
    assert _wait(lambda: rig.stats["readings"] >= 2)
    np.testing.assert_array_equal(rig.read().held, safe_u(2))  # the handshake left the rig safe
    u = np.array([[1.0, 0.3], [0.0126, 1.0], [0.0, 0.9994]])
    rig.write(u)
    assert _wait(lambda: fw.out.held not in (None, 0))  # latched at the next sample instant
    assert _wait(lambda: rig.read().held is not None and rig.read().held[0, 1] == 0.3)
    np.testing.assert_array_equal(rig.read().held, [[1.0, 0.3], [0.013, 1.0], [0.0, 0.999]])
    rig.safe()
    assert _wait(lambda: rig.read().held is not None and rig.read().held[2, 0] == 1.0)
    np.testing.assert_array_equal(rig.read().held, safe_u(2))
    assert rig.stats["held_unknown"] == 0


@pytest.mark.compiling
def test_a_p_line_naming_a_command_the_host_never_sent_is_counted_and_gives_no_held(rig2):
    fw, rig = rig2
    assert _wait(lambda: rig.stats["readings"] >= 1)
    fw.board.inject("held_seq")  # a firmware bug: P lines name the SEQ after the held command's
    assert _wait(lambda: rig.stats["held_unknown"] >= 1)
    assert _wait(lambda: rig.read().held is None)


def test_rig_emulate_with_a_config_refuses_what_does_not_fit_it_with_one_line(tmp_path):
    chamber = ROOT / "scenarios" / "daemon_chamber.toml"
    one_line_error(_emulate("--truth-log", str(tmp_path / "t.csv")), "--truth-log: needs --config")
    one_line_error(_emulate("--config", str(tmp_path / "missing.toml")), str(tmp_path / "missing.toml"))
    one_line_error(_emulate("--config", str(chamber), "--n", "3"), "--n = 3: the config's rig has 1")
    one_line_error(_emulate("--config", str(chamber), "--period-ms", "20"), "--period-ms")
    faulty = tmp_path / "faulty.toml"
    faulty.write_text(chamber.read_text() + '\n[[daemon.fault]]\nkind = "link_loss"\nstart_s = 0.5\n')
    one_line_error(_emulate("--config", str(faulty)), "[[daemon.fault]]")


def test_rig_plant_runs_one_rig_period_per_firmware_period_and_stamps_the_rigs_time(tmp_path):
    """However late the firmware's period ran (dt), the rig advances one of its periods: samples stamped
    with the rig's time stay on the physics they measured; the truth log records dt as it was."""
    from hbma_ctrl.app.daemon.build import make_sim_rig
    from hbma_ctrl.app.daemon.config import load_config
    from hbma_ctrl.app.daemon.firmware import RigPlant

    cfg = load_config(ROOT / "scenarios" / "daemon_chamber.toml")
    plant = RigPlant(make_sim_rig(cfg), tmp_path / "truth.csv")
    u = np.array([[1.0], [1.0], [0.0]])  # pumping in
    p = [plant(u, dt)[0] for dt in (0.01, 0.004, 0.027, 0.01)]
    plant.close()
    assert plant.t == pytest.approx(0.04)
    assert p[0] < p[-1]  # the chamber filled over the four periods
    rows = (tmp_path / "truth.csv").read_text().splitlines()
    assert rows[0] == "dt_ms,mode,t_s,h_C1_mm,p_C1_kpa"
    assert [r.split(",")[0] for r in rows[1:]] == ["10.000", "4.000", "27.000", "10.000"]
    assert [float(r.split(",")[2]) for r in rows[1:]] == pytest.approx([0.01, 0.02, 0.03, 0.04])


@pytest.mark.slow
def test_a_daemon_whose_port_never_opens_says_nothing_reached_the_rig_and_writes_nothing(tmp_path):
    from typer.testing import CliRunner

    from cli_checks import one_line_error
    from hbma_ctrl.app.cli.main import app

    out = tmp_path / "run"
    res = CliRunner().invoke(app, ["daemon", "daemon_chamber", "--rig", f"serial:{tmp_path / 'no-port'}",
                                   "--out", str(out)])
    line = one_line_error(res, "cannot open rig port", "nothing was sent to the rig")
    assert "safe command was sent" not in line and not list(tmp_path.iterdir())
