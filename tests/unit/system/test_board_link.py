"""The host side of a board that runs the controller (board_link.BoardControlledRig): its handshake, the
pairing of each P line with the board's U report, the targets it sends, and the refusal of a board of
the other kind. The board is scripted on a raw pty: the test writes the lines a hosted firmware would."""

from __future__ import annotations

import os
import threading
import time
import tty

import numpy as np
import pytest

from hbma_ctrl.system.board_link import BoardControlledRig
from hbma_ctrl.system.serial_link import (
    ControllerMismatchError,
    SerialRig,
    decode_line,
    encode_line,
)

TIMEOUT = 10.0  # generous bound for what takes milliseconds


class ScriptedBoard:
    """The board's end of a raw pty: answers the first HELLO with ``ver`` (VER's fields after the SEQ)
    and sends the lines a test gives; ``received`` holds the host's decoded lines."""

    def __init__(self, ver: tuple) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.port = os.ttyname(self.slave)
        self.ver = ver
        self.received: list = []
        self.seq = 1
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        buf = b""
        while not self._stop.is_set():
            try:
                buf += os.read(self.master, 4096)
            except OSError:
                return
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                m = decode_line(line)
                self.received.append(m)
                if m.kind == "HELLO":
                    os.write(self.master, encode_line("VER", 0, *self.ver))

    def send(self, kind: str, *fields) -> None:
        os.write(self.master, encode_line(kind, self.seq, *fields))
        self.seq += 1

    def close(self) -> None:
        self._stop.set()
        os.close(self.slave)
        os.close(self.master)


@pytest.fixture
def board():
    b = ScriptedBoard((2, 1, 10000, "hosted"))
    yield b
    b.close()


def _rig(port: str, cls=BoardControlledRig):
    return cls(port, 1, sample_period=0.01, link_timeout=60.0, handshake_timeout=TIMEOUT)


def _wait(pred) -> bool:
    deadline = time.monotonic() + TIMEOUT
    while not pred() and time.monotonic() < deadline:
        time.sleep(0.002)
    return pred()


def test_a_sample_is_read_with_the_boards_report_once_its_u_line_follows_its_p_line(board):
    rig = _rig(board.port)
    try:
        board.send("P", 10000, 0, 1500)
        assert rig.wait_sample(0.2) is None  # its report has not come: not readable yet
        board.send("U", 600, 1000, 0, 2500, 1480, 0)
        assert rig.wait_sample(TIMEOUT) is not None
        r, rep = rig.read(), rig.report()
        assert (r.t, float(r.p[0]), bool(r.fresh[0])) == (0.01, 1500.0, True)
        np.testing.assert_allclose(rep.u, [[0.6], [1.0], [0.0]])
        np.testing.assert_allclose([rep.height[0], rep.pressure[0]], [2.5e-3, 1480.0])
        assert rep.status == (0,)
        board.send("P", 20000, 0, 1600)
        board.send("U", 500, 1000, 0, "NA", "NA", 1)
        assert _wait(lambda: rig.stats["readings"] == 2)
        rep = rig.report()
        assert np.isnan(rep.height[0]) and rep.status == (1,)
        assert (rig.stats["bad_lines"], rig.stats["unreported"]) == (0, 0)
    finally:
        rig.close()


def test_a_p_line_whose_report_is_lost_is_counted_and_never_read(board):
    rig = _rig(board.port)
    try:
        board.send("P", 10000, 0, 1500)
        board.seq += 1  # its U line lost
        board.send("P", 20000, 0, 1600)
        board.send("U", 0, 0, 1000, 0, 0, 0)
        assert _wait(lambda: rig.stats["readings"] == 1)
        assert float(rig.read().p[0]) == 1600.0
        assert rig.stats["unreported"] == 1
    finally:
        rig.close()


def test_held_is_the_command_reported_two_samples_before_a_period_named_by_a_target(board):
    rig = _rig(board.port)
    try:
        rig.set_target(np.array([7e-3]))
        rig.write(np.zeros((3, 1)))  # TGT 1: the command given is not sent
        assert _wait(lambda: any(m.kind == "TGT" for m in board.received))
        assert [m for m in board.received if m.kind == "TGT"][0].fields == ("7000",)
        for k, pump in enumerate((100, 200, 300)):
            board.send("P", 10000 * (k + 1), 1, 0)
            board.send("U", pump, 1000, 0, 1000, 0, 0)
            assert _wait(lambda k=k: rig.stats["readings"] == k + 1)
        held = rig.read().held
        np.testing.assert_allclose(held, [[0.1], [1.0], [0.0]])  # what the first report announced
        board.send("P", 40000, "-", 0)  # the board's watchdog
        board.send("U", 0, 0, 1000, 1000, 0, 0)
        assert _wait(lambda: rig.stats["readings"] == 4)
        np.testing.assert_allclose(rig.read().held, [[0.0], [0.0], [1.0]])
    finally:
        rig.close()


def test_a_target_out_of_range_is_refused_in_mm():
    with pytest.raises(ValueError, match=r"\[0, 1000\] mm"):
        BoardControlledRig.set_target(type("R", (), {"n": 1})(), np.array([1.5]))


def test_each_kind_of_host_refuses_the_other_kind_of_board_with_one_line(board):
    with pytest.raises(ControllerMismatchError, match="runs its own controller") as e:
        _rig(board.port, SerialRig)
    assert "\n" not in str(e.value) and "--board-controller" in str(e.value)
    plain = ScriptedBoard((2, 1, 10000))
    try:
        with pytest.raises(ControllerMismatchError, match="runs no controller of its own"):
            _rig(plain.port)
    finally:
        plain.close()
