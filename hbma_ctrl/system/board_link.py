"""The host side of a board that runs the controller itself (SI): :class:`BoardControlledRig`, a
:class:`~hbma_ctrl.system.serial_link.SerialRig` that sends targets (``TGT``) instead of commands and
pairs each ``P`` line with the board's ``U`` report (:class:`BoardReport`). The lines are in
:mod:`hbma_ctrl.system.serial_link`'s docstring and ``docs/reference/line-protocol.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hbma_ctrl.system.rigio import safe_u
from hbma_ctrl.system.serial_link import SEQ_MOD, Message, SerialRig, from_permille

__all__ = ["BoardReport", "BoardControlledRig", "HEIGHT_MAX_UM"]

HEIGHT_MAX_UM = 1_000_000  # largest target height a TGT line carries, um


@dataclass(frozen=True)
class BoardReport:
    """What a board that runs the controller reported for one sample: ``u`` (3, n) the command it holds
    from its next sample instant, in [0, 1]; ``height`` (n,) its estimated heights, m, and ``pressure``
    (n,) its estimated pressures, Pa (NaN: none); ``status`` (n,) its controller's status codes (0 ok, 1
    the controller's step failed and its supervisor's fallback is out, negative a library error: the
    board holds that chamber vented)."""

    u: np.ndarray
    height: np.ndarray
    pressure: np.ndarray
    status: tuple[int, ...]


class BoardControlledRig(SerialRig):
    """The host side of a board that runs the controller itself (the reference firmware's hosted
    build, ``VER ... hosted``): :meth:`set_target` holds the target heights that :meth:`write` sends as
    ``TGT``; the board's command, estimate and status for each sample are :meth:`report`. A board that
    does not say ``hosted`` is refused at the handshake
    (:class:`~hbma_ctrl.system.serial_link.ControllerMismatchError`).

    A sample becomes readable (:meth:`read`, :meth:`wait_sample`) when its ``U`` line has followed its
    ``P`` line, so the readings and the report are of one sample; a sample whose ``U`` line was lost is
    counted in ``stats["unreported"]`` and skipped. ``Readings.held`` is the command the board reported
    two samples earlier (what it latched at the start of the period that ends), or the safe command for
    a period its ``P`` line names ``SAFE``, ``HELLO`` or its watchdog. Arguments as :class:`SerialRig`.
    """

    board_controller = True

    def __init__(self, *args, **kw) -> None:
        self._target: np.ndarray | None = None
        self._report: BoardReport | None = None
        super().__init__(*args, **kw)

    def _reset_readings(self) -> None:
        super()._reset_readings()
        self.stats.setdefault("unreported", 0)  # here: the reader thread starts inside SerialRig.__init__
        self._pending_p: tuple | None = None  # the newest P line, waiting for its U line
        self._reported_u: list[np.ndarray] = []  # the last two reports' commands, oldest first
        self._report = None

    def set_target(self, height: np.ndarray) -> None:
        """The target heights, m (n,), that :meth:`write` sends from now on; ValueError when one is not
        finite or outside [0, HEIGHT_MAX_UM] um."""
        h = np.asarray(height, dtype=float).reshape(self.n)
        if not (np.all(np.isfinite(h)) and np.all(h >= 0) and np.all(h * 1e6 <= HEIGHT_MAX_UM)):
            raise ValueError(f"target heights {h * 1e3} mm: each must be in [0, {HEIGHT_MAX_UM / 1e3:g}] mm")
        self._target = h.copy()

    def write(self, u: np.ndarray) -> None:
        """Send the target heights as ``TGT`` (the board's controller decides the command: ``u`` is not
        sent); before any target, a heartbeat. RigLinkError while the link is down."""
        if self._target is None:
            self._send("HB")
            return
        self._send("TGT", *(int(math.floor(x * 1e6 + 0.5)) for x in self._target), held="board")

    def write_safe(self) -> None:
        """Send ``SAFE``; RigLinkError while the link is down (:meth:`safe` never raises)."""
        self._send("SAFE", held=safe_u(self.n))

    def report(self) -> BoardReport | None:
        """The board's report of the newest readable sample (None before the first)."""
        with self._lock:
            return self._report

    def _held_of(self, named: str) -> np.ndarray | None:
        held = super()._held_of(named)
        if isinstance(held, str):  # a TGT: the board held what it reported two samples earlier
            return self._reported_u[0] if len(self._reported_u) == 2 else None
        return held

    def _on_pressure(self, m: Message) -> None:
        if len(m.fields) != self.n + 2 or not m.fields[0].isdigit() or not (
                m.fields[1].isdigit() or m.fields[1] == "-"):
            raise ValueError("P needs a time stamp, the held command's SEQ and one pressure per chamber")
        if self._pending_p is not None:
            self.stats["unreported"] += 1
        p = np.array([np.nan if f == "NA" else float(int(f)) for f in m.fields[2:]])
        self._pending_p = (m.seq, int(m.fields[0]), m.fields[1], p)

    def _on_report(self, m: Message) -> None:
        f = m.fields
        if len(f) != 6 * self.n:
            raise ValueError("U needs per chamber 3 per-mille values, a height, a pressure and a status")
        vals = [int(x) for k in range(self.n) for x in f[6 * k:6 * k + 3]]
        u = from_permille(vals, self.n)
        est = [(np.nan, np.nan) if f[6 * k + 3] == "NA" else (int(f[6 * k + 3]) * 1e-6, float(int(f[6 * k + 4])))
               for k in range(self.n)]
        status = tuple(int(f[6 * k + 5]) for k in range(self.n))
        pending, self._pending_p = self._pending_p, None
        if pending is None or pending[0] != (m.seq - 1) % SEQ_MOD:
            self.stats["unreported"] += pending is not None
            return  # its P line was lost: no sample to pair it with
        with self._lock:
            self._report = BoardReport(u, np.array([e[0] for e in est]), np.array([e[1] for e in est]), status)
        self._publish(*pending)
        with self._lock:
            self._reported_u = (self._reported_u + [u])[-2:]
