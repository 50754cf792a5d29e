"""The daemon's API in a process of its own, linked to the loop's :class:`DaemonState` by pipes.

The API (:mod:`hbma_ctrl.app.daemon.api`: FastAPI on uvicorn) parses, checks, converts and answers
every request in a spawned process: its interpreter and its lock are not the loop's, so however many
clients it serves, and however slowly, the loop's thread never waits for it. What crosses (standard
library :func:`multiprocessing.Pipe` connections, pickled messages):

- to the API: the snapshots the loop publishes (:meth:`DaemonState.since`, each with the loop's
  number, only the last :data:`~hbma_ctrl.app.daemon.api.EVENTS_SHOWN` events), the stop request
  and its reason, and the answers to its requests; the API's copy of the state
  (:class:`_ApiState`) keeps them for ``/status``, ``/health`` and ``/stream``;
- from the API: ``setpoint`` and ``reset`` requests (SI), and on a pipe of their own the stops. The
  link's thread in the daemon's process (:class:`ApiServer`) submits them to the state: the loop's
  check clips a setpoint in that thread (not the loop's) and the API's request waits for that answer
  (what will be applied and what was clipped); the loop takes what was queued at its next period,
  without waiting for anyone. ``/stop`` is answered once its request is on its way; the link hands
  it to the state as soon as it arrives and the loop acts on it at its next period. A setpoint or
  reset not taken within :data:`REPLY_TIMEOUT_S` is 503 and is not applied: the state queues
  nothing checked after that deadline, and the API waits :data:`REPLY_MARGIN_S` longer for an
  answer sent before it.

The link's thread waits with the interpreter's lock released. It wakes when the loop has published
its period's status (:meth:`DaemonState.set_publish_wake`: one byte on a non-blocking socket), that
is when the loop goes to sleep, and takes the setpoints and resets waiting then and forwards the
snapshot: its work (a chamber's snapshot trims and pickles in about 4 us of CPU time; a submit is
the loop's check of the setpoint) falls in the loop's sleep, where it cannot make the loop wait for
the interpreter's lock. It also wakes on a stop, at once, and every :data:`POLL_S` when the loop
publishes nothing (starting, ended).

The API's process leaves a real-time scheduling class it inherited (:func:`leave_real_time`): on
the loop's core, the loop preempts it. Its start-up objects are frozen out of the garbage collector
(:func:`freeze_start_up`), so that no collection holds a ``/stop`` for tens of milliseconds.

Ending: the API's process ignores SIGINT, SIGTERM and SIGHUP (a terminal's or a service manager's
signal to the whole group reaches the daemon, which ends the loop in the safe state first and then
the API: :meth:`ApiServer.stop`), and ends by itself when the daemon's process is gone (its pipe
reads end of file). When the API's process ends while the daemon has not asked it to (killed, or
crashed), the loop writes the safe command and ends with the fault ``api_lost``: the rig is not left
running without the stop button and the view its operator started it with.
"""

from __future__ import annotations

import atexit
import contextlib
import gc
import itertools
import multiprocessing as mp
import os
import queue
import signal
import socket
import threading
import time
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from multiprocessing.connection import Connection, wait
from typing import Any, Self

from hbma_ctrl.app.daemon.api import DEFAULT_PORT, EVENTS_SHOWN, RATE_HZ, is_loopback
from hbma_ctrl.app.daemon.state import DaemonState, Stopping

__all__ = ["API_LOST", "POLL_S", "REPLY_TIMEOUT_S", "ApiServer", "bind", "freeze_start_up", "leave_real_time",
           "serve"]

#: how often the link looks for requests when the loop publishes nothing, wall s
POLL_S = 0.02
#: a setpoint or reset the loop's side has not taken within this long is not applied (503), s
REPLY_TIMEOUT_S = 2.0
#: how much longer the API waits for the answer than the link takes the request, s: the answer to a
#: request taken just in time still has this long to cross the pipe
REPLY_MARGIN_S = 1.0
#: the fault kind of a loop stopped because the API's process ended unasked
API_LOST = "api_lost"
#: the signals a terminal or a service manager sends a whole process group; the daemon ends the API
_GROUP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


# --- the API's process ---------------------------------------------------------------------------------

class _ApiState(DaemonState):
    """The API's copy of the loop's state: the snapshots as the loop numbered them, the stop as the
    loop's state has it, and requests that go to the loop's side through ``send`` (one message each)
    but stops, which this state writes on ``stops`` itself (:meth:`request_stop`)."""

    def __init__(self, send, stops: Connection):
        super().__init__()
        self._send = send
        self._stops = stops
        os.set_blocking(stops.fileno(), False)  # a stop never holds the server's event loop (request_stop)
        self._stops_lock = threading.Lock()
        self._ids = itertools.count(1)
        self._waiting: dict[int, Future] = {}
        self._asked = ""  # the first reason this API asked to stop with
        self._loop_stop = (False, "")

    # --- from the loop's side
    def mirror(self, pairs: list, stop: tuple[bool, str]) -> None:
        for seq, snap in pairs:
            self.publish(snap, seq)
        self._loop_stop = stop

    def answer(self, rid: int, ok: bool, value: Any) -> None:
        fut = self._waiting.pop(rid, None)
        if fut is not None:
            fut.set_result((ok, value))

    # --- the app's requests
    def _ask(self, kind: str, payload: Any, deadline: float | None) -> Any:
        rid, fut = next(self._ids), Future()
        self._waiting[rid] = fut
        now = time.monotonic()
        deadline = now + REPLY_TIMEOUT_S if deadline is None else min(deadline, now + REPLY_TIMEOUT_S)
        self._send((kind, rid, deadline, payload))
        try:
            ok, value = fut.result(timeout=deadline - now + REPLY_MARGIN_S)
        except FutureTimeout:
            raise RuntimeError(f"the loop's side did not take the {kind} within {REPLY_TIMEOUT_S:g} s: "
                               "not applied") from None
        finally:
            self._waiting.pop(rid, None)
        if ok:
            return value
        err, line = value
        raise {"stopping": Stopping, "value": ValueError, "runtime": RuntimeError}.get(err, Exception)(line)

    def submit_setpoint(self, request: dict, deadline: float | None = None) -> dict:
        """The loop's side checks, clips and queues ``request``; its answer or its error (as
        :meth:`DaemonState.submit_setpoint`; the deadline at most :data:`REPLY_TIMEOUT_S` from now)."""
        return self._ask("setpoint", request, deadline)

    def submit_reset(self, deadline: float | None = None) -> str:
        """The loop's side checks and queues the reset; its line or its error (as
        :meth:`DaemonState.submit_reset`)."""
        return self._ask("reset", None, deadline)

    def request_stop(self, reason: str = "stop requested", fault: str | None = None) -> None:
        """Send the stop to the loop's side (every time: its state keeps the first reason) on its pipe,
        from the caller's thread: no other thread needs the interpreter's lock for it; returns at once.

        The pipe does not block: a message under ``PIPE_BUF`` bytes (4 kB; the
        reason is cut to 500 characters) is written whole or not at all, and one not written finds
        the pipe full of stops the loop's side has yet to read, so it adds nothing to them."""
        with self._stops_lock, contextlib.suppress(BlockingIOError, OSError):  # OSError: the daemon is gone
            self._stops.send(reason[:500])
        if not self._asked:
            self._asked = reason

    @property
    def stop_requested(self) -> bool:
        """The loop's state has the stop (as of its last snapshot here)."""
        return self._loop_stop[0]

    @property
    def stop_reason(self) -> str:
        """The loop's state's reason, or the first this API asked with when it does not have one yet."""
        return self._loop_stop[1] if self._loop_stop[0] else self._asked


def _send_all(outbox: queue.SimpleQueue, up: Connection) -> None:
    """Write the API's messages to the daemon's side in order until None (or the daemon is gone)."""
    while (msg := outbox.get()) is not None:
        try:
            up.send(msg)
        except OSError:  # the daemon's process is gone
            return


def _receive_all(down: Connection, state: _ApiState, closing: threading.Event) -> None:
    """Take the daemon's side's messages until it says close or is gone; then ``closing`` is set."""
    try:
        while True:
            msg = down.recv()
            if msg[0] == "status":
                state.mirror(msg[1], msg[2])
            elif msg[0] == "reply":
                state.answer(*msg[1:])
            elif msg[0] == "close":
                closing.set()  # answers to requests still in progress keep coming until the daemon's end
    except (EOFError, OSError):
        pass
    closing.set()


def leave_real_time() -> bool:
    """Put this process in the ordinary scheduling class when it inherited a real-time one (the daemon
    started under ``chrt -f``): the loop then preempts it whenever its period is due, instead of
    waiting for it to block; True when it did."""
    get = getattr(os, "sched_getscheduler", None)
    if get is None or get(0) not in (os.SCHED_FIFO, os.SCHED_RR):
        return False
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))  # lowering needs no privilege
    return True


def freeze_start_up() -> None:
    """Move the objects alive now (the app, its schemas, uvicorn, the modules: about 130 000) to the
    collector's permanent generation. A full collection of them takes 80 ms of CPU time, in which the
    API answers nothing, a stop included; frozen, a collection walks only what requests allocated
    since (as the daemon's loop does, :mod:`hbma_ctrl.app.daemon.gcwatch`)."""
    gc.collect()
    gc.freeze()


def _api_main(sock: socket.socket, down: Connection, up: Connection, stops: Connection, token: str | None,
              rate_hz: float, allow_remote: bool, start_timeout: float) -> None:
    """The API's process: serve ``sock`` until the daemon's side says close or is gone."""
    import uvicorn

    from hbma_ctrl.app.daemon.api import make_app, server_config

    for s in _GROUP_SIGNALS:
        signal.signal(s, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, _GROUP_SIGNALS)  # blocked by the daemon while it started us
    leave_real_time()
    outbox: queue.SimpleQueue = queue.SimpleQueue()
    state = _ApiState(outbox.put, stops)
    sender = threading.Thread(target=_send_all, args=(outbox, up), name="hbma-api-send", daemon=True)
    sender.start()
    app = make_app(state, token, rate_hz=rate_hz, allow_remote=allow_remote)
    server = uvicorn.Server(server_config(app))
    # a thread of its own, not this process's main one: uvicorn then installs no signal handlers
    serving = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, name="hbma-api", daemon=True)
    serving.start()
    deadline = time.monotonic() + start_timeout
    while not server.started:
        if not serving.is_alive() or time.monotonic() > deadline:
            outbox.put(("failed", "uvicorn did not start"))
            outbox.put(None)
            sender.join(5)
            return
        time.sleep(0.01)
    freeze_start_up()
    closing: threading.Event = app.state.closing  # also ends the open streams
    receiver = threading.Thread(target=_receive_all, args=(down, state, closing), name="hbma-api-receive",
                                daemon=True)
    receiver.start()
    outbox.put(("started",))
    closing.wait()
    server.should_exit = True
    serving.join(10)
    if serving.is_alive():
        server.force_exit = True
        serving.join(5)
    outbox.put(None)
    sender.join(5)


# --- the daemon's process ------------------------------------------------------------------------------

def _ended(code: int | None) -> str:
    if code is None:
        return "still running"
    if code < 0:
        with contextlib.suppress(ValueError):
            return f"killed by {signal.Signals(-code).name}"
        return f"killed by signal {-code}"
    return f"exit code {code}"


class ApiServer:
    """The API's process and the link's thread (module doc). ``host``/``port``: the bound address;
    ``pid``: the API's process."""

    def __init__(self, state: DaemonState, proc: Any, sock: socket.socket, down: Connection, up: Connection,
                 stops: Connection):
        self._state, self._proc, self._sock, self._down, self._up = state, proc, sock, down, up
        self._stops = stops
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        state.set_publish_wake(self._wake_w)
        addr = sock.getsockname()
        self.host: str = addr[0]
        self.port: int = addr[1]
        self.pid: int = proc.pid
        self._closing = threading.Event()
        self._stopped = False
        self._thread = threading.Thread(target=self._link, name="hbma-api-link", daemon=True)
        self._thread.start()
        atexit.register(self.stop)

    @property
    def url(self) -> str:
        """Base URL, e.g. http://127.0.0.1:8765."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}"

    @property
    def running(self) -> bool:
        """The API's process is serving."""
        return self._proc.is_alive()

    @property
    def exitcode(self) -> int | None:
        """The API's process's exit code once it has ended (negative: the signal that ended it), else None."""
        return self._proc.exitcode

    # --- the link's thread
    def _forward(self, seq: int, sent_stop: tuple | None) -> tuple[int, tuple]:
        """Send the snapshots published after ``seq`` and the stop when either is new; the newest seq
        and the stop sent."""
        pairs, _ = self._state.since(seq)  # those the ring no longer holds show as a gap in the numbers
        stop = (self._state.stop_requested, self._state.stop_reason)
        if pairs or stop != sent_stop:
            shown = [(k, {**snap, "events": list(snap["events"])[-EVENTS_SHOWN:]} if "events" in snap else snap)
                     for k, snap in pairs]
            self._down.send(("status", shown, stop))
        return (pairs[-1][0] if pairs else seq), stop

    def _take(self, msg: tuple) -> None:
        """One request of the API's process."""
        kind = msg[0]
        if kind not in ("setpoint", "reset"):
            return
        _, rid, deadline, payload = msg
        try:  # past its deadline the API has answered 503 (not applied): the state then queues nothing
            value = (self._state.submit_setpoint(payload, deadline) if kind == "setpoint"
                     else self._state.submit_reset(deadline))
            reply = (rid, True, value)
        except Stopping as exc:
            reply = (rid, False, ("stopping", str(exc)))
        except ValueError as exc:
            reply = (rid, False, ("value", str(exc)))
        except RuntimeError as exc:
            reply = (rid, False, ("runtime", str(exc)))
        except Exception as exc:  # noqa: BLE001 - a bug in a check: the API answers 500, the link goes on
            reply = (rid, False, ("error", f"{type(exc).__name__}: {exc}"))
        self._down.send(("reply", *reply))

    def _link(self) -> None:
        seq, stop = 0, None
        close_sent = False
        try:
            while True:
                ready = wait([self._wake_r, self._stops, self._proc.sentinel], timeout=POLL_S)
                with contextlib.suppress(BlockingIOError):
                    self._wake_r.recv(4096)
                while self._stops.poll():
                    self._state.request_stop(str(self._stops.recv()))
                while self._up.poll():
                    self._take(self._up.recv())
                if self._proc.sentinel in ready:  # ended, its pipes read to their end: nothing more comes
                    break
                seq, stop = self._forward(seq, stop)
                if self._closing.is_set() and not close_sent:
                    self._down.send(("close",))
                    close_sent = True
        except (EOFError, OSError):  # the API's process has ended (or was ended by stop)
            pass
        if not self._closing.is_set():
            self._proc.join(5)  # reaped: no zombie
            self._state.request_stop(f"the API's process ended ({_ended(self._proc.exitcode)})", fault=API_LOST)

    def stop(self, timeout: float = 5.0) -> None:
        """End the API: open streams end with the last snapshot, requests in progress get their answers
        (up to ``timeout`` s, then the process is killed); the process is reaped and the port freed."""
        if self._stopped:
            return
        self._stopped = True
        atexit.unregister(self.stop)
        self._closing.set()
        with contextlib.suppress(OSError):
            self._wake_w.send(b"\0")
        self._thread.join(timeout + 2.0)  # the link sends close at once; uvicorn's shutdown takes <= 2 s
        if self._proc.is_alive():
            self._proc.join(timeout)
        if self._proc.is_alive() or self._thread.is_alive():
            self._proc.kill()
            self._proc.join(timeout)
            self._thread.join(timeout)
        self._state.set_publish_wake(None)
        for c in (self._down, self._up, self._stops, self._sock, self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                c.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def bind(host: str, port: int) -> socket.socket:
    """A listening-ready TCP socket bound to (host, port); port 0 = any free port. OSError when the
    address cannot be bound (e.g. the port is in use)."""
    name = "127.0.0.1" if host.strip().lower() == "localhost" else host.strip("[]")
    family, kind, proto, _, addr = socket.getaddrinfo(name, port, type=socket.SOCK_STREAM)[0]
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(addr)
    except OSError:
        sock.close()
        raise
    return sock


def serve(state: DaemonState, host: str = "127.0.0.1", port: int = DEFAULT_PORT, allow_remote: bool = False,
          token: str | None = None, rate_hz: float = RATE_HZ, start_timeout: float = 60.0,
          sock: socket.socket | None = None) -> ApiServer:
    """Start the API for ``state`` on (host, port) in a process of its own and return once it accepts
    connections (module doc). ``rate_hz``: requests served per second, all clients together (see
    :func:`hbma_ctrl.app.daemon.api.make_app`); ``start_timeout``: the process's start-up (its imports), s.

    Loopback only unless ``allow_remote`` is True and a ``token`` is given (ValueError otherwise);
    port 0 binds any free port (read it from the result); ``sock``: the socket :func:`bind` made for
    (host, port) beforehand (a caller that checks the address before it starts anything else). OSError
    when the address cannot be bound, RuntimeError when the process does not start."""
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise ValueError(f"api port = {port!r} must be an integer in [0, 65535]")
    if not is_loopback(host) and not (allow_remote and token is not None):
        raise ValueError(f"api host = {host!r} is not loopback (127.0.0.1, ::1, localhost); another address "
                         "needs --allow-remote and a token")
    if token is not None and not token.strip():
        raise ValueError("token must not be empty")
    sock = sock if sock is not None else bind(host, port)
    ctx = mp.get_context("spawn")  # a fresh interpreter: none of this process's threads, locks or state
    down_r, down_w = ctx.Pipe(duplex=False)
    up_r, up_w = ctx.Pipe(duplex=False)
    stops_r, stops_w = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_api_main, args=(sock, down_r, up_w, stops_w, token, rate_hz, allow_remote,
                                               start_timeout), name="hbma-api", daemon=True)
    # the child starts with the group's signals blocked, so that one sent during its start-up reaches
    # the daemon only; this thread gets any that came meanwhile when it unblocks them
    blocked = threading.current_thread() is threading.main_thread()
    old = signal.pthread_sigmask(signal.SIG_BLOCK, _GROUP_SIGNALS) if blocked else None
    try:
        proc.start()
    finally:
        if old is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)
        for c in (down_r, up_w, stops_w):  # the child's ends, held by it alone: each side sees the other end
            c.close()

    def fail(why: str) -> RuntimeError:
        if proc.is_alive():
            proc.kill()
        proc.join(10)
        for c in (down_w, up_r, stops_r, sock):
            c.close()
        return RuntimeError(f"the API did not start on {host}:{port}: {why}")

    try:
        if not up_r.poll(start_timeout):
            raise fail(f"no answer within {start_timeout:g} s")
        first = up_r.recv()
    except (EOFError, OSError):
        raise fail(f"its process ended ({_ended(proc.exitcode if not proc.is_alive() else None)})") from None
    if first != ("started",):
        raise fail(str(first[1]) if isinstance(first, tuple) and len(first) > 1 else repr(first))
    return ApiServer(state, proc, sock, down_w, up_r, stops_r)
