"""What the daemon's loop and its API share (SI inside; the API converts at its edge).

The loop thread publishes a status snapshot every period (:meth:`DaemonState.publish`) and takes the
setpoints queued since the last period (:meth:`DaemonState.take_setpoints`). The API reads the
snapshot, submits setpoints and asks for the stop: in the daemon it runs in a process of its own
(:mod:`hbma_ctrl.app.daemon.apiproc`), whose link thread in the daemon's process does that here on its
behalf, and keeps a copy of the snapshots in a state of its own.

Publishing takes no lock: the snapshot is a new dict the loop never touches again, and it is put in
place by single reference stores (the newest ``(seq, snapshot)`` pair, and the same pair in a ring of
the last :data:`RING` snapshots), which a reader sees whole or not at all. So a reader, however slow
and however many, never makes the loop wait. The live stream reads the ring to send every n-th
snapshot even when it wakes after several were published (:meth:`DaemonState.since`). The setpoint
queue, the reset flag and the stop keep a lock, held for a few operations on either side. A
setpoint is checked and clipped to what the rig can reach by the handler the loop registered
(:meth:`DaemonState.set_setpoint_handler`) in the caller's thread (not the loop's), so the reply
says at once what will be applied and what was clipped; the loop applies it at its next period.

A setpoint request (SI) is a dict with either or both of
``heights``: {chamber index: membrane height, m} and
``layers``: {layer index: (centre height m, bend rad, bend direction rad)}.
The handler returns ``{"applied": <request as it will be applied>, "clipped": [messages]}`` or raises
ValueError (a request the rig cannot take at all, e.g. a chamber that does not exist).

A reset (leave the safe state after a fault) is checked the same way by the loop's reset handler
(:meth:`DaemonState.set_reset_handler`; RuntimeError with the reason when refused) and taken by the
loop at its next period (:meth:`DaemonState.take_reset`), which checks the readings again.

Once a stop has been asked for, a setpoint or a reset is refused with :class:`Stopping`.
"""

from __future__ import annotations

import socket
import threading
import time
from collections import deque
from typing import Callable

__all__ = ["DaemonState", "RING", "Stopping"]

#: snapshots the state keeps for the live stream (the newest last); a reader that falls further behind
#: than this misses the oldest and is told how many
RING = 128


class Stopping(RuntimeError):
    """A setpoint or a reset refused because the stop has been asked for (the line gives its reason)."""


class DaemonState:
    """Thread-safe status, setpoint queue and stop request (see module doc)."""

    def __init__(self, max_pending: int = 64):
        self._lock = threading.Lock()
        self._latest: tuple[int, dict] = (0, {"mode": "starting"})
        self._ring: list[tuple[int, dict] | None] = [None] * RING
        self._pending: deque = deque(maxlen=max_pending)
        self._handler: Callable[[dict], dict] | None = None
        self._reset_handler: Callable[[], str] | None = None
        self._reset = False
        self._stop = threading.Event()
        self._stop_reason = ""
        self._stop_fault: str | None = None
        self._wake: socket.socket | None = None

    # --- loop side ---------------------------------------------------------------------------------
    def publish(self, status: dict, seq: int | None = None) -> None:
        """Replace the status snapshot (the loop builds a new dict each time and never changes it after).
        Called from one thread (the loop's); takes no lock (module doc). ``seq``: its number, for a copy
        that keeps another state's numbers (a gap counts as snapshots lost); default the next."""
        if seq is None:
            seq = self._latest[0] + 1
        pair = (seq, status)
        self._ring[seq % RING] = pair
        self._latest = pair  # one reference store: a reader sees the old pair or the new one
        wake = self._wake
        if wake is not None:
            try:
                wake.send(b"\0")
            except OSError:  # full (its reader has not drained it yet: it wakes all the same) or closed
                pass

    def set_publish_wake(self, wake: socket.socket | None) -> None:
        """A non-blocking socket sent one byte after each publish, so that a reader in another thread can
        wait for the loop's period to end instead of polling (None: none)."""
        if wake is not None and wake.getblocking():
            raise ValueError("the publish wake socket must be non-blocking: the loop never waits on it")
        self._wake = wake

    def take_setpoints(self) -> list[dict]:
        """The setpoints submitted since the last call (oldest first), as the handler returned them."""
        with self._lock:
            out = list(self._pending)
            self._pending.clear()
        return out

    def set_setpoint_handler(self, handler: Callable[[dict], dict]) -> None:
        """Register the function that checks and clips a request (called in the submitter's thread)."""
        with self._lock:
            self._handler = handler

    def set_reset_handler(self, handler: Callable[[], str]) -> None:
        """Register the function that checks a reset (called in the submitter's thread; returns what it
        will do, raises RuntimeError with the reason it cannot)."""
        with self._lock:
            self._reset_handler = handler

    def take_reset(self) -> bool:
        """Whether a reset was asked for since the last call."""
        with self._lock:
            asked, self._reset = self._reset, False
        return asked

    # --- API side ----------------------------------------------------------------------------------
    def status(self) -> dict:
        """The newest status snapshot (do not mutate it)."""
        return self._latest[1]

    def latest(self) -> tuple[int, dict]:
        """The newest snapshot with its sequence number (1 for the first published, 0 before any)."""
        return self._latest

    def since(self, seq: int) -> tuple[list[tuple[int, dict]], int]:
        """The snapshots published after number ``seq``, oldest first, as (seq, snapshot) pairs, and how
        many of them the ring no longer holds (published more than :data:`RING` before this call)."""
        newest = self._latest[0]
        first = max(seq + 1, newest - RING + 1)
        out = []
        for k in range(first, newest + 1):
            pair = self._ring[k % RING]
            # the loop may have written a newer snapshot into this slot since ``newest`` was read
            if pair is not None and pair[0] == k:
                out.append(pair)
        return out, max(0, newest - seq) - len(out) if newest > seq else 0

    def submit_setpoint(self, request: dict, deadline: float | None = None) -> dict:
        """Check and clip ``request`` and queue it for the loop; returns the handler's reply.
        Raises ValueError when the request cannot be taken, :class:`Stopping` once the stop has been
        asked for, RuntimeError before the loop is ready, while the queue is full (never drops a
        setpoint it accepted) or when the check ended after ``deadline`` (time.monotonic(), s; None:
        none), which then queues nothing: its sender has stopped waiting for the answer."""
        with self._lock:
            handler = self._handler
        self._refuse_when_stopping("no new setpoints")
        if handler is None:
            raise RuntimeError("the loop is not ready for setpoints yet")
        self._refuse_when_late(deadline, "setpoint")
        reply = handler(request)
        self._refuse_when_late(deadline, "setpoint")
        with self._lock:
            # a full queue refuses instead of letting the deque drop the oldest setpoint unseen
            if len(self._pending) == self._pending.maxlen:
                raise RuntimeError(f"{len(self._pending)} setpoints are waiting for the loop; retry after a period")
            self._pending.append(reply["applied"])
        return reply

    def submit_reset(self, deadline: float | None = None) -> str:
        """Check a reset with the loop's handler and queue it for the loop; returns the handler's line.
        :class:`Stopping` once the stop has been asked for, RuntimeError (with the reason) before the
        loop is ready, when the handler refuses or when it ended after ``deadline`` (as
        :meth:`submit_setpoint`)."""
        with self._lock:
            handler = self._reset_handler
        self._refuse_when_stopping("no reset")
        if handler is None:
            raise RuntimeError("the loop is not ready yet: nothing to reset")
        self._refuse_when_late(deadline, "reset")
        line = handler()
        self._refuse_when_late(deadline, "reset")
        with self._lock:
            self._reset = True
        return line

    @staticmethod
    def _refuse_when_late(deadline: float | None, what: str) -> None:
        if deadline is not None and time.monotonic() > deadline:
            raise RuntimeError(f"the {what} was checked too late for its sender: not applied")

    def _refuse_when_stopping(self, what: str) -> None:
        if self._stop.is_set():
            raise Stopping(f"the daemon is stopping ({self._stop_reason}): {what}")

    def request_stop(self, reason: str = "stop requested", fault: str | None = None) -> None:
        """Ask the loop to send the safe command and end (idempotent; the first reason is kept).
        ``fault``: the fault kind the loop counts for this stop (None: an ordinary stop)."""
        with self._lock:
            if not self._stop.is_set():
                self._stop_reason = reason
                self._stop_fault = fault
                self._stop.set()

    @property
    def stop_requested(self) -> bool:
        return self._stop.is_set()

    @property
    def stop_reason(self) -> str:
        return self._stop_reason

    @property
    def stop_fault(self) -> str | None:
        """The fault kind the first stop request named, None for an ordinary stop."""
        return self._stop_fault
