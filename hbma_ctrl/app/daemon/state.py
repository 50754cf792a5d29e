"""What the daemon's loop and its API share, behind one lock (SI inside; the API converts at its edge).

The loop thread publishes a status snapshot every period (:meth:`DaemonState.publish`) and takes the
setpoints queued since the last period (:meth:`DaemonState.take_setpoints`). The API thread reads the
snapshot, submits setpoints and asks for the stop. A setpoint is checked and clipped to what the rig
can reach by the handler the loop registered (:meth:`DaemonState.set_setpoint_handler`) in the API's
thread, so the reply says at once what will be applied and what was clipped; the loop applies it at
its next period.

A setpoint request (SI) is a dict with either or both of
``heights``: {chamber index: membrane height, m} and
``layers``: {layer index: (centre height m, bend rad, bend direction rad)}.
The handler returns ``{"applied": <request as it will be applied>, "clipped": [messages]}`` or raises
ValueError (a request the rig cannot take at all, e.g. a chamber that does not exist).

A reset (leave the safe state after a fault) is checked the same way by the loop's reset handler
(:meth:`DaemonState.set_reset_handler`; RuntimeError with the reason when refused) and taken by the
loop at its next period (:meth:`DaemonState.take_reset`), which checks the readings again.
"""

from __future__ import annotations

import threading
from collections import deque
from typing import Callable

__all__ = ["DaemonState"]


class DaemonState:
    """Thread-safe status, setpoint queue and stop request (see module doc)."""

    def __init__(self, max_pending: int = 64):
        self._lock = threading.Lock()
        self._status: dict = {"mode": "starting"}
        self._pending: deque = deque(maxlen=max_pending)
        self._handler: Callable[[dict], dict] | None = None
        self._reset_handler: Callable[[], str] | None = None
        self._reset = False
        self._stop = threading.Event()
        self._stop_reason = ""

    # --- loop side ---------------------------------------------------------------------------------
    def publish(self, status: dict) -> None:
        """Replace the status snapshot (the loop builds a new dict each time; readers never see a half)."""
        with self._lock:
            self._status = status

    def take_setpoints(self) -> list[dict]:
        """The setpoints submitted since the last call (oldest first), as the handler returned them."""
        with self._lock:
            out = list(self._pending)
            self._pending.clear()
        return out

    def set_setpoint_handler(self, handler: Callable[[dict], dict]) -> None:
        """Register the function that checks and clips a request (called in the API's thread)."""
        with self._lock:
            self._handler = handler

    def set_reset_handler(self, handler: Callable[[], str]) -> None:
        """Register the function that checks a reset (called in the API's thread; returns what it will do,
        raises RuntimeError with the reason it cannot)."""
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
        with self._lock:
            return self._status

    def submit_setpoint(self, request: dict) -> dict:
        """Check and clip ``request`` and queue it for the loop; returns the handler's reply.
        Raises ValueError when the request cannot be taken, RuntimeError before the loop is ready or
        while the queue is full (never drops a setpoint it accepted)."""
        with self._lock:
            handler = self._handler
        if handler is None:
            raise RuntimeError("the loop is not ready for setpoints yet")
        reply = handler(request)
        with self._lock:
            # a full queue refuses instead of letting the deque drop the oldest setpoint unseen
            if len(self._pending) == self._pending.maxlen:
                raise RuntimeError(f"{len(self._pending)} setpoints are waiting for the loop; retry after a period")
            self._pending.append(reply["applied"])
        return reply

    def submit_reset(self) -> str:
        """Check a reset with the loop's handler and queue it for the loop; returns the handler's line.
        RuntimeError (with the reason) before the loop is ready or when the handler refuses."""
        with self._lock:
            handler = self._reset_handler
        if handler is None:
            raise RuntimeError("the loop is not ready yet: nothing to reset")
        line = handler()
        with self._lock:
            self._reset = True
        return line

    def request_stop(self, reason: str = "stop requested") -> None:
        """Ask the loop to send the safe command and end (idempotent; the first reason is kept)."""
        with self._lock:
            if not self._stop.is_set():
                self._stop_reason = reason
                self._stop.set()

    @property
    def stop_requested(self) -> bool:
        return self._stop.is_set()

    @property
    def stop_reason(self) -> str:
        return self._stop_reason
