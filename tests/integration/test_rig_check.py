"""``hbma-ctrl rig check``: every check passes on the reference firmware (the host board, and the Uno
build in simavr), and each defect the host board can inject fails the check that names it, exit 1.

The boards run in real time (a thread steps the host board against a first-order plant); the check
measures its times on the firmware's stamps, so what is asserted (which checks pass) holds on a
loaded machine."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cli_checks import one_line_error
from hbma_ctrl.app.cli.main import app
from hbma_ctrl.app.daemon.firmware import DEFECTS, FirstOrderPlant, HostBoard, RealtimeBoard, build_firmware

#: the check each injected defect must fail
NAMED = {
    "crc": "crc",
    "stuck_inlet": "inlet C1",
    "inverted_pressure": "inlet C1",
    "no_watchdog": "watchdog",
    "wrong_period": "sample period",
    "no_heartbeat": "heartbeat",
    "seq_repeat": "sequence",
    "no_crlf": "crlf",
    "sensor_zero": "sensor zero C1",
    "no_crc_check": "bad checksum ignored",
    "held_seq": "held",
    "version": "handshake",
}


@pytest.fixture(scope="module")
def host_exe(tmp_path_factory):
    return build_firmware("host", tmp_path_factory.mktemp("fw"))


def _check(port: str, out: Path, *extra: str) -> tuple[int, dict, str]:
    res = CliRunner().invoke(app, ["rig", "check", port, "--out", str(out), *extra])
    doc = json.loads((out / "check.json").read_text()) if (out / "check.json").is_file() else {}
    return res.exit_code, doc, res.output


def _check_host_board(exe: Path, out: Path, n: int, defects: tuple[str, ...] = ()) -> tuple[int, dict, str]:
    rt = RealtimeBoard(HostBoard(exe, n, defects=defects), FirstOrderPlant(n))
    try:
        return _check(rt.board.port, out)
    finally:
        rt.close()


def _failed(doc: dict) -> set[str]:
    return {c["name"] for c in doc["checks"] if not c["passed"]}


def test_every_defect_has_its_check():
    assert set(NAMED) == set(DEFECTS) and len(DEFECTS) >= 8


@pytest.mark.compiling
@pytest.mark.subprocess
def test_the_reference_firmware_passes_every_check(host_exe, tmp_path):
    code, doc, output = _check_host_board(host_exe, tmp_path / "check", 2)
    assert code == 0 and doc["passed"] and _failed(doc) == set(), output
    names = [c["name"] for c in doc["checks"]]
    assert {"inlet C2", "pump C2", "outlet C2", "sensor zero C2", "watchdog", "crlf"} <= set(names)
    assert all(set(c) == {"name", "passed", "measured", "expected"} for c in doc["checks"])
    assert "all checks passed" in output
    assert json.loads((tmp_path / "check" / "manifest.json").read_text())["command"] == "rig check"


@pytest.mark.compiling
@pytest.mark.subprocess
@pytest.mark.parametrize("defect", sorted(NAMED))
def test_each_injected_defect_fails_its_check_and_exits_1(host_exe, tmp_path, defect):
    code, doc, output = _check_host_board(host_exe, tmp_path / "check", 1, (defect,))
    assert code == 1 and not doc["passed"], output
    assert NAMED[defect] in _failed(doc), output
    if defect not in ("crc", "version"):  # these two fail the handshake: nothing else can run
        assert "handshake" not in _failed(doc), output


@pytest.mark.compiling
@pytest.mark.slow
@pytest.mark.skipif(shutil.which("avr-gcc") is None or shutil.which("simavr") is None or
                    not Path("/usr/include/simavr/sim_avr.h").is_file(),
                    reason="avr-gcc, simavr or simavr's headers are not installed "
                           "(apt-get install gcc-avr avr-libc simavr libsimavr-dev)")
def test_the_uno_build_in_simavr_passes_every_check(tmp_path):
    elf = build_firmware("avr", tmp_path / "build", 1)
    runner = build_firmware("simavr", tmp_path / "build")
    proc = subprocess.Popen([str(runner), str(elf), "--plant"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            text=True)
    try:
        port = proc.stdout.readline().strip()
        assert port.startswith("/dev/"), proc.poll()
        code, doc, output = _check(port, tmp_path / "check")
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
    assert code == 0 and doc["passed"], output


def test_an_absent_port_is_bad_input_naming_port(tmp_path):
    res = CliRunner().invoke(app, ["rig", "check", str(tmp_path / "ttyACM9"), "--out", str(tmp_path / "out")])
    one_line_error(res, f"PORT {tmp_path / 'ttyACM9'}", "no such port")
    assert not (tmp_path / "out").exists()


def test_out_follows_the_run_directory_rules(tmp_path):
    master, slave = os.openpty()
    try:
        taken = tmp_path / "taken"
        taken.mkdir()
        (taken / "notes.txt").write_text("mine")
        res = CliRunner().invoke(app, ["rig", "check", os.ttyname(slave), "--out", str(taken)])
        one_line_error(res, f"--out {taken}", "--overwrite")
        res = CliRunner().invoke(app, ["rig", "check", os.ttyname(slave), "--out", str(taken), "--overwrite"])
        one_line_error(res, f"--out {taken}", "no run of hbma-ctrl")
        assert (taken / "notes.txt").read_text() == "mine"
    finally:
        os.close(slave)
        os.close(master)
