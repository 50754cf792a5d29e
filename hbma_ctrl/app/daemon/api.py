"""The rig daemon's local HTTP API: FastAPI on uvicorn in a daemon thread, in front of a DaemonState.

Endpoints (JSON, edge units; the messages are :mod:`hbma_ctrl.app.schema.api`):

- ``GET /status`` -> :class:`Status`: mode, per chamber height estimate and its std (mm), pressure
  read and estimated (kPa), command (speed %, inlet and outlet duty 0-1), robot layer poses (mm, deg),
  loop timing (ms), fault counts and the latest events.
- ``POST /setpoint`` :class:`SetpointRequest` -> :class:`SetpointReply`: what will be applied and what
  was clipped. 422 when the message or the loop's check refuses it, 503 before the loop takes
  setpoints, 409 once a stop has been asked for.
- ``POST /stop`` -> :class:`StopReply`: asks the loop for the safe state and its end.
- ``GET /health`` -> :class:`Health`: the API answers; the loop's mode and the age of its status.

Every error is JSON ``{"error": "<one line>", "detail": ...}``; a message that fails validation is
422 and its line names the key as written and the allowed range in the key's unit, e.g.
``[setpoint] heights_mm.0 = 500 is out of range [0, 200] mm``. A body over :data:`MAX_BODY_BYTES` is
413. When a token is set every request needs ``Authorization: Bearer <token>`` (401 otherwise).
Requests are paced to :data:`RATE_HZ` per second over all clients (a burst of :data:`BURST` at
once); one that would wait more than :data:`MAX_WAIT_S` for its turn gets 429.
:func:`serve` binds loopback only (127.0.0.0/8, ::1, localhost) unless ``allow_remote`` and a token.

The status dict the loop publishes (:meth:`DaemonState.publish`), SI, a new dict each period (the
API caches its conversion by identity); every key but ``mode`` may be left out (e.g. while
starting), a number may be None or NaN (shown as null); ``events`` may be any sequence that
supports ``reversed`` (a list or a deque)::

    {
      "mode": "starting" | "running" | "safe" | "stopped",
      "t_s": loop time of the snapshot, s,
      "monotonic_s": time.monotonic() when the snapshot was built, s (gives age_ms),
      "chambers": [                                   # one per chamber, by index
        {"name": "A1" (optional), "h": height estimate m, "h_std": its std m,
         "p": pressure reading Pa (gauge; NaN = none this period), "p_est": estimated pressure Pa,
         "u": [pump speed 0-1, inlet duty 0-1, outlet duty 0-1]},
      ],
      "layers": [{"centre": m, "bend": rad, "direction": rad}],   # robot only, by layer index
      "loop": {"rate_hz": Hz, "steps": int, "deadline_misses": int,
               "step_median_s": s, "step_p99_s": s},
      "faults": {kind: count since start},
      "events": [{"t_s": s, "kind": str, "cause": str}],       # newest last, bounded by the loop
    }

The API shows the last :data:`EVENTS_SHOWN` events. A request only reads the newest snapshot (its
conversion is cached per snapshot) or submits one setpoint, each under the state's lock for a
moment: no work grows with the run's history, and a flood of requests cannot hold the loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import ipaddress
import itertools
import math
import socket
import threading
import time
from typing import Any, Self

import uvicorn
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from starlette.datastructures import Headers
from starlette.exceptions import HTTPException

from hbma_ctrl.app.daemon.state import DaemonState
from hbma_ctrl.app.schema.api import (
    CHAMBER_INDEX_MAX,
    ChamberStatus,
    ErrorReply,
    FaultEvent,
    Faults,
    Health,
    LayerStatus,
    LoopTiming,
    SetpointApplied,
    SetpointReply,
    SetpointRequest,
    Status,
    StopReply,
)
from hbma_ctrl.app.schema.errors import format_one
from hbma_ctrl.core import units as U

__all__ = [
    "DEFAULT_PORT",
    "EVENTS_SHOWN",
    "MAX_BODY_BYTES",
    "MAX_WAIT_S",
    "RATE_HZ",
    "ApiServer",
    "is_loopback",
    "make_app",
    "request_error",
    "serve",
    "status_message",
]

DEFAULT_PORT = 8765
#: a setpoint for every chamber of a large robot is a few kB; anything larger is not a setpoint
MAX_BODY_BYTES = 16 * 1024
#: events shown by GET /status (newest last)
EVENTS_SHOWN = 10
#: connections served at once; more get 503 from uvicorn instead of queueing work behind the loop
MAX_CONNECTIONS = 64
#: requests served per second on average (all clients together) and the burst served at once: a
#: request costs ~1 ms of the daemon's CPU (and its GIL), so a flood is paced instead of starving the loop
RATE_HZ = 100.0
BURST = 50
#: a request that would wait longer than this for its turn is refused with 429 instead
MAX_WAIT_S = 2.0


def _fin(x: Any, scale: float = 1.0) -> float | None:
    """``x * scale`` as a float rounded to 1e-9, or None when x is missing or not finite (JSON has no NaN)."""
    if x is None:
        return None
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    # 1e-9 of the edge unit is far below any sensor; it drops the float noise of the conversion
    return round(v * scale, 9) if math.isfinite(v) else None


def _deg(x: Any) -> float | None:
    """Radians -> degrees, as :func:`_fin`."""
    return _fin(x, math.degrees(1.0))


def _age_ms(snapshot: dict) -> float | None:
    """Milliseconds from the loop building ``snapshot`` to now; None when the snapshot carries no stamp."""
    stamp = _fin(snapshot.get("monotonic_s"))
    if stamp is None:
        return None
    return _fin(max(0.0, time.monotonic() - stamp), U.to_ms(1.0))


def status_message(snapshot: dict) -> Status:
    """The loop's SI status dict (module doc) as the :class:`Status` message in edge units, without the
    request's ``age_ms`` and ``stop_requested`` (null and false)."""
    chambers = []
    for i, c in enumerate(snapshot.get("chambers") or ()):
        u = list(c.get("u") or ())
        u += [None] * (3 - len(u))
        chambers.append(ChamberStatus(
            index=i, name=c.get("name"), h_mm=_fin(c.get("h"), U.to_mm(1.0)),
            h_std_mm=_fin(c.get("h_std"), U.to_mm(1.0)), p_kpa=_fin(c.get("p"), U.to_kpa(1.0)),
            p_est_kpa=_fin(c.get("p_est"), U.to_kpa(1.0)), speed_pct=_fin(u[0], U.to_pct(1.0)),
            inlet_duty=_fin(u[1]), outlet_duty=_fin(u[2])))
    layers = [LayerStatus(layer=k, centre_mm=_fin(ly.get("centre"), U.to_mm(1.0)), bend_deg=_deg(ly.get("bend")),
                          direction_deg=_deg(ly.get("direction")))
              for k, ly in enumerate(snapshot.get("layers") or ())]
    lp = snapshot.get("loop") or {}
    loop = LoopTiming(rate_hz=_fin(lp.get("rate_hz")), steps=int(lp.get("steps", 0)),
                      deadline_misses=int(lp.get("deadline_misses", 0)),
                      step_ms_median=_fin(lp.get("step_median_s"), U.to_ms(1.0)),
                      step_ms_p99=_fin(lp.get("step_p99_s"), U.to_ms(1.0)))
    # the newest few only, walked from the end: the cost does not grow with what the loop keeps
    events = list(itertools.islice(reversed(snapshot.get("events") or ()), EVENTS_SHOWN))[::-1]
    faults = Faults(counts={str(k): int(v) for k, v in (snapshot.get("faults") or {}).items()},
                    latest=[FaultEvent(t_s=_fin(e.get("t_s")), kind=str(e.get("kind", "")),
                                       cause=str(e.get("cause", ""))) for e in events])
    return Status(mode=str(snapshot.get("mode", "starting")), t_s=_fin(snapshot.get("t_s")), chambers=chambers,
                  layers=layers, loop=loop, faults=faults)


def _applied_message(applied: dict) -> SetpointApplied:
    """The handler's SI ``applied`` request in edge units."""
    heights = {int(i): _fin(h, U.to_mm(1.0)) for i, h in (applied.get("heights") or {}).items()}
    layers = [LayerStatus(layer=int(k), centre_mm=_fin(c, U.to_mm(1.0)), bend_deg=_deg(th), direction_deg=_deg(ps))
              for k, (c, th, ps) in sorted((applied.get("layers") or {}).items())]
    return SetpointApplied(heights_mm=heights, layers=layers)


def request_error(err: dict) -> str:
    """One pydantic error of a request body as one line naming the key as written (schema formatter)."""
    loc = tuple(err.get("loc") or ())
    if loc and loc[0] == "body":
        loc = loc[1:]
    kind = err.get("type", "")
    if kind == "json_invalid":
        return f"[setpoint] the body is not valid JSON: {(err.get('ctx') or {}).get('error', err.get('msg'))}"
    if not loc and kind in ("missing", "model_attributes_type", "dict_type", "model_type"):
        return '[setpoint] the body must be a JSON object, e.g. {"heights_mm": {"0": 5.0}}'
    if len(loc) >= 2 and loc[-1] == "[key]":  # a bad chamber index in heights_mm
        key = ".".join(str(x) for x in loc[:-2])
        return (f"[setpoint] {key}: chamber index {err.get('input')!r} must be an integer in "
                f"[0, {CHAMBER_INDEX_MAX}]")
    return format_one({**err, "loc": loc}, SetpointRequest, "setpoint")


def _error(status: int, line: str, detail: Any = None, headers: dict | None = None) -> JSONResponse:
    return JSONResponse({"error": line, "detail": line if detail is None else detail}, status_code=status,
                        headers=headers)


def _json(model: Any) -> Response:
    return Response(model.model_dump_json(), media_type="application/json")


class _Guard:
    """ASGI middleware before the app: the pace (429 when the wait is too long), the bearer token
    (401), then the body size (413).

    Pacing is a token bucket: each request takes a token, refilled at ``rate_hz`` up to ``burst``;
    without one it sleeps (in the event loop, no CPU) until its turn. The body is read here, up to
    the limit, and handed on whole: a request never makes the app buffer more than the limit."""

    def __init__(self, app: Any, token: str | None, max_body: int, rate_hz: float, burst: int, max_wait_s: float):
        self.app = app
        self.token = token.encode() if token is not None else None
        self.max_body = max_body
        self.rate = rate_hz
        self.burst = float(burst)
        self.max_wait = max_wait_s
        # only the server's event loop touches the bucket: no lock
        self._tokens = float(burst)
        self._last = time.monotonic()

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

    def _authorised(self, headers: Headers) -> bool:
        scheme, _, given = headers.get("authorization", "").partition(" ")
        return scheme.lower() == "bearer" and hmac.compare_digest(given.strip().encode("latin-1"), self.token)

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        if not await self._take_turn():
            await _error(429, f"too many requests: the API serves {self.rate:g} per second",
                         headers={"Retry-After": "1"})(scope, receive, send)
            return
        headers = Headers(scope=scope)
        if self.token is not None and not self._authorised(headers):
            await _error(401, "missing or wrong token: send 'Authorization: Bearer <token>'",
                         headers={"WWW-Authenticate": "Bearer"})(scope, receive, send)
            return
        too_big = _error(413, f"the body is larger than {self.max_body} bytes")
        try:
            declared = int(headers.get("content-length", 0))
        except ValueError:
            declared = self.max_body + 1
        if declared > self.max_body:
            await too_big(scope, receive, send)
            return
        chunks, size = [], 0
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
        body = b"".join(chunks)
        given = False

        async def replay() -> dict:
            nonlocal given
            if not given:
                given = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


def _errors(**codes: str) -> dict:
    return {int(code[1:]): {"model": ErrorReply, "description": what} for code, what in codes.items()}


#: what every request may get from the guard, and a setpoint from its checks (the OpenAPI schema's errors)
_GUARD_ERRORS = _errors(s401="no or a wrong bearer token (when the daemon has one)",
                        s413=f"a body over {MAX_BODY_BYTES} bytes",
                        s429=f"the request would wait over {MAX_WAIT_S:g} s for its turn (paced requests)")
_SETPOINT_ERRORS = _errors(s409="the daemon is stopping: no new setpoints",
                           s422="the message or the loop's check refuses it (the line names the key and its range)",
                           s503="the loop does not take setpoints yet")


def make_app(state: DaemonState, token: str | None = None, *, rate_hz: float = RATE_HZ, burst: int = BURST,
             max_wait_s: float = MAX_WAIT_S) -> FastAPI:
    """The API in front of ``state`` (see the module doc); ``token``: the bearer token every request
    must carry, None for none; ``rate_hz`` (requests/s), ``burst`` and ``max_wait_s`` (s): the pace."""
    if token is not None and not token.strip():
        raise ValueError("token must not be empty")
    if not (rate_hz > 0 and burst >= 1 and max_wait_s >= 0):
        raise ValueError("api pace: rate_hz > 0, burst >= 1 and max_wait_s >= 0 are required")
    app = FastAPI(title="hbma-ctrl rig daemon", docs_url=None, redoc_url=None, responses=_GUARD_ERRORS)
    app.add_middleware(_Guard, token=token, max_body=MAX_BODY_BYTES, rate_hz=rate_hz, burst=burst,
                       max_wait_s=max_wait_s)
    # the last converted snapshot: many requests per loop period convert it once
    cache: list = [None, None]
    cache_lock = threading.Lock()

    def converted(snapshot: dict) -> Status:
        with cache_lock:
            if cache[0] is snapshot:
                return cache[1]
        msg = status_message(snapshot)
        with cache_lock:
            cache[0], cache[1] = snapshot, msg
        return msg

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        errs = exc.errors()
        detail = [{"loc": [str(x) for x in e.get("loc", ())], "msg": str(e.get("msg", "")),
                   "type": str(e.get("type", ""))} for e in errs]
        line = request_error(errs[0]) if errs else "[setpoint] invalid"
        return _error(422, line, detail)

    @app.exception_handler(HTTPException)
    async def _http(request: Request, exc: HTTPException) -> JSONResponse:
        return _error(exc.status_code, str(exc.detail), headers=getattr(exc, "headers", None))

    @app.get("/status", response_model=Status)
    async def get_status() -> Response:
        """The loop's newest status in edge units."""
        snap = state.status()
        msg = converted(snap)
        return _json(msg.model_copy(update={"age_ms": _age_ms(snap), "stop_requested": state.stop_requested}))

    @app.get("/health", response_model=Health)
    async def get_health() -> Response:
        """The API answers; the loop's mode and the age of its last status (ms)."""
        snap = state.status()
        return _json(Health(ok=True, mode=str(snap.get("mode", "starting")), age_ms=_age_ms(snap)))

    @app.post("/setpoint", response_model=SetpointReply, responses=_SETPOINT_ERRORS)
    def post_setpoint(request: SetpointRequest) -> Response:
        """Check, clip and queue a setpoint; the reply says what will be applied and what was clipped."""
        if state.stop_requested:
            raise HTTPException(409, f"the daemon is stopping ({state.stop_reason}): no new setpoints")
        try:
            reply = state.submit_setpoint(request.to_si())
        except ValueError as exc:
            raise HTTPException(422, f"[setpoint] {exc}") from None
        except RuntimeError as exc:
            raise HTTPException(503, str(exc)) from None
        return _json(SetpointReply(applied=_applied_message(reply.get("applied") or {}),
                                   clipped=[str(m) for m in reply.get("clipped") or ()]))

    @app.post("/stop", response_model=StopReply)
    async def post_stop() -> Response:
        """Ask the loop for the safe command and its end (idempotent; the first reason is kept)."""
        state.request_stop("api")
        return _json(StopReply(stop_requested=True, reason=state.stop_reason,
                               mode=str(state.status().get("mode", "starting"))))

    return app


def is_loopback(host: str) -> bool:
    """True for "localhost" and any loopback address (127.0.0.0/8, ::1)."""
    if host.strip().lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def _bind(host: str, port: int) -> socket.socket:
    """A listening-ready TCP socket bound to (host, port); port 0 = any free port."""
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


class ApiServer:
    """A running API: uvicorn in a daemon thread. ``host``/``port`` are the bound address."""

    def __init__(self, server: uvicorn.Server, thread: threading.Thread, sock: socket.socket):
        self._server = server
        self._thread = thread
        self._sock = sock
        addr = sock.getsockname()
        self.host: str = addr[0]
        self.port: int = addr[1]

    @property
    def url(self) -> str:
        """Base URL, e.g. http://127.0.0.1:8765."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}"

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def stop(self, timeout: float = 5.0) -> None:
        """Stop serving and join the thread (open connections get up to ``timeout`` s, then are cut)."""
        self._server.should_exit = True
        self._thread.join(timeout)
        if self._thread.is_alive():
            self._server.force_exit = True
            self._thread.join(timeout)
        with contextlib.suppress(OSError):
            self._sock.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def serve(state: DaemonState, host: str = "127.0.0.1", port: int = DEFAULT_PORT, allow_remote: bool = False,
          token: str | None = None, rate_hz: float = RATE_HZ, start_timeout: float = 10.0) -> ApiServer:
    """Start the API on (host, port) in a daemon thread and return once it accepts connections.
    ``rate_hz``: requests served per second, all clients together (see :func:`make_app`).

    Loopback only unless ``allow_remote`` is True and a ``token`` is given (ValueError otherwise);
    port 0 binds any free port (read it from the result). OSError when the address cannot be bound."""
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise ValueError(f"api port = {port!r} must be an integer in [0, 65535]")
    if not is_loopback(host) and not (allow_remote and token is not None):
        raise ValueError(f"api host = {host!r} is not loopback (127.0.0.1, ::1, localhost); another address "
                         "needs --allow-remote and a token")
    app = make_app(state, token, rate_hz=rate_hz)
    sock = _bind(host, port)
    config = uvicorn.Config(app, log_config=None, access_log=False, log_level="warning", lifespan="off",
                            limit_concurrency=MAX_CONNECTIONS, timeout_graceful_shutdown=2)
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, name="hbma-api", daemon=True)
    thread.start()
    deadline = time.monotonic() + start_timeout
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            server.should_exit = True
            sock.close()
            raise RuntimeError(f"the API did not start on {host}:{port}")
        time.sleep(0.01)
    return ApiServer(server, thread, sock)
