"""The daemon API's guards (:mod:`hbma_ctrl.app.daemon.api` lists them) and the stop that goes first.

:class:`Checks` holds the checks that read a request's head only (Host and Origin, the bearer
token); :class:`Guard`, the ASGI middleware before the app, applies them and the limits (clients in
progress, the pace, the body's type, size and time); :class:`GuardedProtocol`, uvicorn's HTTP/1.1
protocol, closes connections that hold no request.

A stop goes first: a flood of other requests keeps the server's event loop busy, and a request
waits behind every callback and task ahead of it before the app routes it. The protocol therefore
looks at each request as soon as it has parsed it, in the read callback of its connection: a whole
``POST /stop`` without a body that :meth:`Checks.admits_stop` lets through (the same checks the
guard makes; a stop it would refuse takes the ordinary path, which refuses it) goes to the app's
stop front (:meth:`GuardedProtocol.bound`), which sends the stop on its pipe and returns the
route's answer; the protocol writes that answer at once through uvicorn's own response code, so
neither the stop nor its answer waits for the event loop's queue. A stop with a body, over the
server's connection limit (uvicorn answers 503) or not yet whole takes the ordinary path. The
request's task still runs, and :class:`Guard` sees the marks the protocol left in its scope
(:data:`STOP_SENT`, :data:`STOP_ANSWERED`): it answers a stop sent but not answered (the client had
not read its last answers yet) and nothing more for one answered.
"""

from __future__ import annotations

import asyncio
import hmac
import ipaddress
import time
from collections.abc import Callable
from typing import Any
from urllib.parse import urlsplit

from starlette.datastructures import Headers
from starlette.responses import JSONResponse, Response
from uvicorn.protocols.http.h11_impl import H11Protocol

from hbma_ctrl.app.daemon.live import PUBLIC_PATHS

__all__ = [
    "BURST",
    "MAX_BODY_BYTES",
    "MAX_CLIENTS",
    "MAX_CONNECTIONS",
    "MAX_IDLE",
    "MAX_WAIT_S",
    "RATE_HZ",
    "REQUEST_TIMEOUT_S",
    "STOP_ANSWERED",
    "STOP_SENT",
    "Checks",
    "Guard",
    "GuardedProtocol",
    "error",
    "is_loopback",
]

#: a setpoint for every chamber of a large robot is a few kB; anything larger is not a setpoint
MAX_BODY_BYTES = 16 * 1024
#: open connections at most (uvicorn answers 503 beyond); of those holding no request, the oldest is
#: closed for a new one above :data:`MAX_IDLE`, so idle clients never fill the slots
MAX_CONNECTIONS = 256
MAX_IDLE = 128
#: requests in progress (waiting for their turn included) over all clients; 429 beyond
MAX_CLIENTS = 128
#: a request head, or its body, not whole after this long closes the connection (408 for a body), s
REQUEST_TIMEOUT_S = 2.0
#: requests served per second on average (all clients together) and the burst served at once: a
#: request costs ~1 ms of a CPU, which a flood would take from the loop's core on a small rig PC
RATE_HZ = 100.0
BURST = 50
#: a request that would wait longer than this for its turn is refused with 429 instead
MAX_WAIT_S = 2.0
#: the ASGI scope's keys the protocol sets on a stop it has sent to the loop's side, and answered
STOP_SENT = "hbma_ctrl.stop_sent"
STOP_ANSWERED = "hbma_ctrl.stop_answered"


def is_loopback(host: str) -> bool:
    """True for "localhost" and any loopback address (127.0.0.0/8, ::1)."""
    if host.strip().lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def error(status: int, line: str, detail: Any = None, headers: dict | None = None) -> JSONResponse:
    """The API's error answer: JSON ``{"error": line, "detail": detail or line}`` with ``status``."""
    return JSONResponse({"error": line, "detail": line if detail is None else detail}, status_code=status,
                        headers=headers)


def _hostname(netloc: str) -> str | None:
    """The host of a ``Host`` header or an ``Origin``'s netloc (no port, no brackets); None when unparsable."""
    try:
        return urlsplit("//" + netloc).hostname
    except ValueError:
        return None


class Checks:
    """The checks on a request's head alone: its ``Host`` and ``Origin`` and, when ``token`` is set,
    its bearer token; ``allow_remote``: any Host is served (else loopback names only)."""

    def __init__(self, token: str | None, allow_remote: bool = False):
        self.token = token.encode() if token is not None else None
        self.allow_remote = allow_remote

    def authorised(self, headers: Headers) -> bool:
        """The request carries ``Authorization: Bearer <token>`` (True when no token is set)."""
        if self.token is None:
            return True
        scheme, _, given = headers.get("authorization", "").partition(" ")
        return scheme.lower() == "bearer" and hmac.compare_digest(given.strip().encode("latin-1"), self.token)

    def foreign(self, method: str, headers: Headers) -> str | None:
        """Why a request's Host or Origin is refused (one line), None when it is not."""
        host = headers.get("host", "")
        name = _hostname(host)
        if not self.allow_remote and (name is None or not is_loopback(name)):
            return (f"Host {host!r} is not a loopback name (127.0.0.1, ::1, localhost): the API answers "
                    "only its own machine's address")
        origin = headers.get("origin")
        if origin is not None and method not in ("GET", "HEAD", "OPTIONS"):
            if urlsplit(origin).netloc.lower() != host.lower():
                return f"cross-origin {method} from Origin {origin!r} to Host {host!r}: refused"
        return None

    def admits_stop(self, scope: dict) -> bool:
        """``scope`` is a ``POST /stop`` that Host, Origin and token let through (its body is the caller's
        to check: a stop that :class:`Guard` would refuse for its body must not be sent)."""
        if scope.get("type") != "http" or scope.get("method") != "POST" or scope.get("path") != "/stop":
            return False
        headers = Headers(scope=scope)
        return self.foreign("POST", headers) is None and self.authorised(headers)


class Guard:
    """ASGI middleware before the app: Host and Origin (403), the client bound and the pace (429), the
    bearer token (401), the body's type, size and time (415, 413, 408); see the API's module doc.
    ``checks``: the head's checks; ``stop_answer``: the answer to a stop the protocol has sent
    (:data:`STOP_SENT`), the same as the route's.

    Pacing is a token bucket: each request takes a token, refilled at ``rate_hz`` up to ``burst``;
    without one it sleeps (in the event loop, no CPU) until its turn. The body is read here, up to
    the limit, and handed on whole: a request never makes the app buffer more than the limit."""

    def __init__(self, app: Any, checks: Checks, stop_answer: Callable[[], Response], max_body: int,
                 rate_hz: float, burst: int, max_wait_s: float, max_clients: int = MAX_CLIENTS):
        self.app = app
        self.checks = checks
        self.stop_answer = stop_answer
        self.max_body = max_body
        self.rate = rate_hz
        self.burst = float(burst)
        self.max_wait = max_wait_s
        self.max_clients = max_clients
        # only the server's event loop touches these: no lock
        self._tokens = float(burst)
        self._last = time.monotonic()
        self._in_progress = 0

    async def _take_turn(self) -> bool:
        """Wait for this request's token; False when the wait would exceed ``max_wait``."""
        now = time.monotonic()
        self._tokens = min(self.burst, self._tokens + (now - self._last) * self.rate)
        self._last = now
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            return True
        wait = (1.0 - self._tokens) / self.rate
        if wait > self.max_wait:
            return False
        self._tokens -= 1.0  # reserved: the next request waits behind this one
        await asyncio.sleep(wait)
        return True

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        if scope.get(STOP_SENT):  # the protocol has made this guard's checks and sent the stop
            if not scope.get(STOP_ANSWERED):
                await self.stop_answer()(scope, receive, send)
            return
        headers = Headers(scope=scope)
        method = str(scope.get("method", "GET")).upper()
        why = self.checks.foreign(method, headers)
        if why is not None:
            await error(403, why)(scope, receive, send)
            return
        paced = not (method == "POST" and scope.get("path") == "/stop")  # a stop is always answered
        if paced and self._in_progress >= self.max_clients:
            await error(429, f"too many requests in progress: the API serves {self.max_clients} at once",
                        headers={"Retry-After": "1"})(scope, receive, send)
            return
        self._in_progress += paced
        try:
            if paced and not await self._take_turn():
                await error(429, f"too many requests: the API serves {self.rate:g} per second",
                            headers={"Retry-After": "1"})(scope, receive, send)
                return
            await self._serve(scope, receive, send, headers, method)
        finally:
            self._in_progress -= paced

    async def _serve(self, scope: dict, receive: Any, send: Any, headers: Headers, method: str) -> None:
        public = method in ("GET", "HEAD") and scope.get("path") in PUBLIC_PATHS
        if not public and not self.checks.authorised(headers):
            await error(401, "missing or wrong token: send 'Authorization: Bearer <token>'",
                        headers={"WWW-Authenticate": "Bearer"})(scope, receive, send)
            return
        too_big = error(413, f"the body is larger than {self.max_body} bytes")
        try:
            declared = int(headers.get("content-length", 0))
        except ValueError:
            declared = self.max_body + 1
        if declared > self.max_body:
            await too_big(scope, receive, send)
            return
        chunks, size = [], 0
        try:
            async with asyncio.timeout(REQUEST_TIMEOUT_S):
                while True:
                    msg = await receive()
                    if msg["type"] != "http.request":  # the client left
                        return
                    chunk = msg.get("body", b"")
                    size += len(chunk)
                    if size > self.max_body:
                        await too_big(scope, receive, send)
                        return
                    chunks.append(chunk)
                    if not msg.get("more_body", False):
                        break
        except TimeoutError:
            await error(408, f"the body was not whole within {REQUEST_TIMEOUT_S:g} s",
                        headers={"Connection": "close"})(scope, receive, send)
            return
        body = b"".join(chunks)
        kind = headers.get("content-type", "").partition(";")[0].strip().lower()
        if body and kind != "application/json":
            await error(415, f"Content-Type {kind or '(none)'!r}: send the body as application/json")(
                scope, receive, send)
            return
        given = False

        async def replay() -> dict:
            nonlocal given
            if not given:
                given = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


class GuardedProtocol(H11Protocol):
    """uvicorn's HTTP/1.1 protocol with a deadline on a connection that holds no request: a whole
    request head within :data:`REQUEST_TIMEOUT_S` of opening or of its last response, else it is
    closed (uvicorn's keep-alive timer starts only after a response and any byte stops it, so a
    half-open or trickling connection would hold its slot for ever); above :data:`MAX_IDLE` such
    connections the oldest is closed for a new one. A whole stop without a body goes to
    :attr:`stop_front` as soon as it is parsed (module doc)."""

    #: called with the scope of each whole ``POST /stop`` without a body in the read callback that parsed
    #: it; returns the answer to write when it has sent the stop, None to leave the request to the app
    stop_front: Callable[[dict], Response | None] | None = None

    @classmethod
    def bound(cls, stop_front: Callable[[dict], Response | None]) -> type[GuardedProtocol]:
        """This protocol with ``stop_front`` (uvicorn makes one protocol object per connection from a class)."""
        return type(cls.__name__, (cls,), {"stop_front": staticmethod(stop_front)})

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._opened = time.monotonic()
        self._head_timer: asyncio.TimerHandle | None = None
        self._arm()
        idle = [c for c in self.connections if isinstance(c, GuardedProtocol) and c is not self and c._idle()]
        if len(idle) > MAX_IDLE:
            min(idle, key=lambda c: c._opened).transport.close()

    def handle_events(self) -> None:
        before = self.cycle
        limit = self.limit_concurrency
        # uvicorn's own test for its 503, made as it makes it (before the request's task is counted)
        over = limit is not None and (len(self.connections) >= limit or len(self.tasks) >= limit)
        super().handle_events()
        cycle = self.cycle
        if (self.stop_front is None or cycle is before or cycle is None or over or cycle.more_body or cycle.body
                or cycle.response_started or cycle.scope.get(STOP_SENT)):
            return
        try:
            answer = self.stop_front(cycle.scope)  # its task has not run yet: the marks reach the guard
        except Exception:  # noqa: BLE001 - the request's task meets the same error and answers 500
            return
        if answer is not None and cycle.scope.get(STOP_SENT) and not self.flow.write_paused:
            self._answer_now(cycle, answer)

    def _answer_now(self, cycle: Any, answer: Response) -> None:
        """Write ``answer`` through the request's own ``send`` (uvicorn's: its headers, keep-alive and
        the next pipelined request) within this callback."""
        cycle.scope[STOP_ANSWERED] = True
        # a send waits only while the client leaves what was written unread (write_paused, False
        # here): the few hundred bytes of an answer go out without waiting
        steps = answer(cycle.scope, cycle.receive, cycle.send)
        try:
            steps.send(None)
        except StopIteration:
            return
        steps.close()  # it would have waited for a client that reads nothing: no half answer kept open
        self.transport.close()

    def _idle(self) -> bool:
        return self.cycle is None or self.cycle.response_complete

    def _arm(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
        self._head_timer = self.loop.call_later(REQUEST_TIMEOUT_S, self._head_late, self.cycle)

    def _head_late(self, cycle: Any) -> None:
        # no new request head since the timer was set, and none in progress
        if self.cycle is cycle and self._idle() and not self.transport.is_closing():
            self.transport.close()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._arm()

    def connection_lost(self, exc: Exception | None) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
        super().connection_lost(exc)
