"""The rig daemon's local HTTP API: the FastAPI app and its guards, in front of a DaemonState (in the
daemon, the copy of the loop's state kept by the API's own process, :mod:`hbma_ctrl.app.daemon.apiproc`).

Endpoints (JSON, edge units; the messages are :mod:`hbma_ctrl.app.schema.api`):

- ``GET /status`` -> :class:`Status`: mode, per chamber height estimate and its std (mm), pressure
  read and estimated (kPa), command (speed %, inlet and outlet duty 0-1), robot layer poses (mm, deg),
  loop timing (ms), fault counts and the latest events.
- ``POST /setpoint`` :class:`SetpointRequest` -> :class:`SetpointReply`: what will be applied and what
  was clipped. 422 when the message or the loop's check refuses it, 503 while the loop takes no
  setpoints or when its side did not take this one in time (then it is not applied), 409 once a
  stop has been asked for.
- ``POST /stop`` -> :class:`StopReply`: asks the loop for the safe state and its end (answered once
  the request is on its way; the loop acts at its next period).
- ``POST /reset`` -> :class:`ResetReply`: leave the safe state after a fault once the readings are
  sane (409 with the reason otherwise, or once a stop has been asked for); the loop resumes control
  at its next period.
- ``GET /health`` -> :class:`Health`: the API answers; the loop's mode and the age of its status.
- ``GET /stream?rate_hz=R`` -> server-sent events, each a :class:`LiveEvent`: the status at R per second
  of loop time, decimated here in loop periods (:mod:`hbma_ctrl.app.daemon.live`); 422 for a bad
  query, 429 beyond :data:`hbma_ctrl.app.daemon.live.MAX_STREAMS` streams.
- ``GET /`` and ``GET /live.js``: the live page; ``GET /docs``: the endpoints as HTML, from
  ``GET /openapi.json``.

Every error is JSON ``{"error": "<one line>", "detail": ...}``; a message that fails validation is
422 and its line names the key as written and the allowed range in the key's unit, e.g.
``[setpoint] heights_mm.0 = 500 is out of range [0, 200] mm``. Before any endpoint, in this order
(:mod:`hbma_ctrl.app.daemon.guard`):

- 403 for a ``Host`` header that is not a loopback name (127.0.0.0/8, ::1, localhost) unless
  ``allow_remote``, and for a POST whose ``Origin`` is not the ``Host`` it was sent to: a web page
  open on the rig PC (another site, or a DNS name rebound to 127.0.0.1) cannot read or drive the rig;
- 429 beyond :data:`MAX_CLIENTS` requests in progress, or for a request that would wait more than
  :data:`MAX_WAIT_S` for its turn: requests are paced to :data:`RATE_HZ` per second over all clients
  (a burst of :data:`BURST` at once). ``POST /stop`` is never paced nor counted, and a whole one
  without a body that these checks let through is sent to the loop as soon as the server has parsed
  it, ahead of the requests already in progress;
- 401 when a token is set and the request lacks ``Authorization: Bearer <token>``, except a GET of the
  page, its script and the endpoints' page (:data:`hbma_ctrl.app.daemon.live.PUBLIC_PATHS`), which
  hold no data: a browser cannot send the header when it opens a page, so the page asks for the token
  and sends it with each request it makes;
- 415 for a body that is not ``Content-Type: application/json``; 413 for a body over
  :data:`MAX_BODY_BYTES`; 408 for a body not whole within :data:`REQUEST_TIMEOUT_S`.

A connection that holds no request must send a whole request head within :data:`REQUEST_TIMEOUT_S`
(:class:`~hbma_ctrl.app.daemon.guard.GuardedProtocol`), so half-open connections cannot hold the server's connection slots.
:func:`hbma_ctrl.app.daemon.apiproc.serve` runs it on uvicorn in a process of its own, bound to
loopback only unless ``allow_remote`` and a token.

The status dict the loop publishes (:meth:`DaemonState.publish`), SI, a new dict each period (the
API caches its conversion by identity); every key but ``mode`` may be left out (e.g. while
starting), a number may be None or NaN (shown as null); ``events`` may be any sequence that
supports ``reversed`` (a list or a deque)::

    {
      "mode": "starting" | "running" | "safe" | "stopped",
      "t_s": loop time of the snapshot, s,
      "monotonic_s": time.monotonic() when the snapshot was built, s (gives age_ms),
      "chambers": [                                   # one per chamber, by index
        {"name": "A1" (optional), "h": height estimate m, "h_std": its std m, "target": effective target m,
         "p": pressure reading Pa (gauge; NaN = none this period), "p_est": estimated pressure Pa,
         "u": [pump speed 0-1, inlet duty 0-1, outlet duty 0-1]},
      ],
      "layers": [{"centre": m, "bend": rad, "direction": rad}],   # robot only, by layer index
      "loop": {"rate_hz": Hz, "steps": int, "deadline_misses": int, "overruns": int,
               "step_median_s": s, "step_p99_s": s},
      "faults": {kind: count since start},
      "events": [{"t_s": s, "kind": str, "cause": str}],       # newest last, bounded by the loop
    }

The API shows the last :data:`EVENTS_SHOWN` events. A request only reads the newest snapshot (its
conversion is cached per snapshot) or submits one setpoint, each under the state's lock for a
moment: no work grows with the run's history.
"""

from __future__ import annotations

import itertools
import math
import threading
import time
import weakref
from typing import Any

import uvicorn
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse, JSONResponse, Response, StreamingResponse
from starlette.exceptions import HTTPException

from hbma_ctrl.app.daemon import live
from hbma_ctrl.app.daemon.guard import (
    BURST,
    MAX_BODY_BYTES,
    MAX_CLIENTS,
    MAX_CONNECTIONS,
    MAX_IDLE,
    MAX_WAIT_S,
    RATE_HZ,
    REQUEST_TIMEOUT_S,
    STOP_SENT,
    Checks,
    Guard,
    GuardedProtocol,
    error,
    is_loopback,
)
from hbma_ctrl.app.daemon.state import DaemonState, Stopping
from hbma_ctrl.app.schema.api import (
    CHAMBER_INDEX_MAX,
    ChamberStatus,
    ErrorReply,
    FaultEvent,
    Faults,
    Health,
    LayerStatus,
    LiveEvent,
    LiveQuery,
    ResetReply,
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
    "MAX_CLIENTS",
    "MAX_CONNECTIONS",
    "MAX_IDLE",
    "MAX_WAIT_S",
    "RATE_HZ",
    "REQUEST_TIMEOUT_S",
    "EventStream",
    "is_loopback",
    "make_app",
    "request_error",
    "server_config",
    "status_message",
]

DEFAULT_PORT = 8765
#: events shown by GET /status (newest last)
EVENTS_SHOWN = 10


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
            h_std_mm=_fin(c.get("h_std"), U.to_mm(1.0)), target_mm=_fin(c.get("target"), U.to_mm(1.0)), p_kpa=_fin(c.get("p"), U.to_kpa(1.0)),
            p_est_kpa=_fin(c.get("p_est"), U.to_kpa(1.0)), speed_pct=_fin(u[0], U.to_pct(1.0)),
            inlet_duty=_fin(u[1]), outlet_duty=_fin(u[2])))
    layers = [LayerStatus(layer=k, centre_mm=_fin(ly.get("centre"), U.to_mm(1.0)), bend_deg=_deg(ly.get("bend")),
                          direction_deg=_deg(ly.get("direction")))
              for k, ly in enumerate(snapshot.get("layers") or ())]
    lp = snapshot.get("loop") or {}
    loop = LoopTiming(rate_hz=_fin(lp.get("rate_hz")), steps=int(lp.get("steps", 0)),
                      deadline_misses=int(lp.get("deadline_misses", 0)), overruns=int(lp.get("overruns", 0)),
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


def requesterror(err: dict) -> str:
    """One pydantic error of a request body as one line naming the key as written (schema formatter)."""
    # a key that does not print (a newline, a control character) is shown quoted: the line stays one line
    loc = tuple(repr(x) if isinstance(x, str) and not x.isprintable() else x for x in err.get("loc") or ())
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


def _json(model: Any) -> Response:
    return Response(model.model_dump_json(), media_type="application/json")


def _errors(**codes: str) -> dict:
    return {int(code[1:]): {"model": ErrorReply, "description": what} for code, what in codes.items()}


#: what every request may get from the guard, and a setpoint from its checks (the OpenAPI schema's errors)
_GUARD_ERRORS = _errors(s401="no or a wrong bearer token (when the daemon has one)",
                        s403="a Host that is not a loopback name (without --allow-remote), or a cross-origin POST",
                        s408=f"a body not whole within {REQUEST_TIMEOUT_S:g} s",
                        s415="a POST body that is not application/json",
                        s413=f"a body over {MAX_BODY_BYTES} bytes",
                        s429=f"over {MAX_CLIENTS} requests in progress, or the request would wait over {MAX_WAIT_S:g} s for its turn (paced requests)")
_SETPOINT_ERRORS = _errors(s409="the daemon is stopping: no new setpoints",
                           s422="the message or the loop's check refuses it (the line names the key and its range)",
                           s503="the loop does not take setpoints (yet, or in the safe state), or did not take "
                                "this one in time (not applied)")
_RESET_ERRORS = _errors(s409="the daemon is stopping, is not in the safe state, or a reading is not sane")
_STREAM_ERRORS = _errors(s422="a bad query key or value (the line names the key and its range)")


class EventStream(StreamingResponse):
    """A stream of server-sent events."""

    media_type = "text/event-stream"


def _query_parameters() -> list[dict]:
    """GET /stream's query keys as OpenAPI parameters, from :class:`LiveQuery`."""
    schema = LiveQuery.model_json_schema()
    out = []
    for key, s in schema["properties"].items():
        s = {k: v for k, v in s.items() if k not in ("title", "description", "unit")}
        if "anyOf" in s:  # optional: the number's own schema
            s = {**next(x for x in s.pop("anyOf") if x.get("type") != "null"), **s}
        out.append({"name": key, "in": "query", "required": False, "schema": s,
                    "description": schema["properties"][key].get("description", "")})
    return out


def make_app(state: DaemonState, token: str | None = None, *, rate_hz: float = RATE_HZ, burst: int = BURST,
             max_wait_s: float = MAX_WAIT_S, allow_remote: bool = False, max_clients: int = MAX_CLIENTS) -> FastAPI:
    """The API in front of ``state`` (see the module doc); ``token``: the bearer token every request
    must carry, None for none; ``rate_hz`` (requests/s), ``burst`` and ``max_wait_s`` (s): the pace;
    ``allow_remote``: any Host is served (else loopback names only); ``max_clients``: requests in
    progress at most."""
    if token is not None and not token.strip():
        raise ValueError("token must not be empty")
    if not (rate_hz > 0 and burst >= 1 and max_wait_s >= 0):
        raise ValueError("api pace: rate_hz > 0, burst >= 1 and max_wait_s >= 0 are required")
    # FastAPI's docs pages load their scripts from a CDN: /docs is rendered here instead (live.docs_page)
    app = FastAPI(title="hbma-ctrl rig daemon", docs_url=None, redoc_url=None, responses=_GUARD_ERRORS)
    #: set when the server stops: open streams end
    app.state.closing = threading.Event()
    checks = Checks(token, allow_remote)

    def stop_answer() -> Response:
        return _json(StopReply(stop_requested=True, reason=state.stop_reason,
                               mode=str(state.status().get("mode", "starting"))))

    def stop_front(scope: dict) -> Response | None:
        """Send the stop of a whole bodiless ``POST /stop`` as soon as the server has parsed it, when the
        guard would let it through, and return its answer (:mod:`hbma_ctrl.app.daemon.guard`); None
        (nothing sent) when the guard would refuse it."""
        if not checks.admits_stop(scope):
            return None
        state.request_stop("api")
        scope[STOP_SENT] = True
        return stop_answer()

    #: what the server's protocol hands each whole bodiless stop to (:func:`server_config`)
    app.state.stop_front = stop_front
    app.add_middleware(Guard, checks=checks, stop_answer=stop_answer, max_body=MAX_BODY_BYTES, rate_hz=rate_hz,
                       burst=burst, max_wait_s=max_wait_s, max_clients=max_clients)
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

    def request_fields(snap: dict) -> dict:
        return {"age_ms": _age_ms(snap), "stop_requested": state.stop_requested}

    # the open streams' generators: one leaves the set when its response is done with it, however it ended
    # (a client gone before the first event never runs the generator's own clean-up)
    streams: weakref.WeakSet = weakref.WeakSet()

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        errs = exc.errors()
        detail = [{"loc": [str(x) for x in e.get("loc", ())], "msg": str(e.get("msg", "")),
                   "type": str(e.get("type", ""))} for e in errs]
        line = requesterror(errs[0]) if errs else "[setpoint] invalid"
        return error(422, line, detail)

    @app.exception_handler(HTTPException)
    async def _http(request: Request, exc: HTTPException) -> JSONResponse:
        return error(exc.status_code, str(exc.detail), headers=getattr(exc, "headers", None))

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

    @app.get("/stream", response_model=LiveEvent, responses={
        **_STREAM_ERRORS, 200: {"description": "server-sent events, each one's data a LiveEvent"}},
        openapi_extra={"parameters": _query_parameters()})
    async def get_stream(request: Request) -> Response:
        """The status as server-sent events at ``rate_hz`` per second of loop time (every n-th status of the
        loop, n = loop rate / rate_hz rounded, at least 1), the first at once; each event's data is a
        LiveEvent, its id the loop's step count. The stream ends after ``count`` events, after the
        status of mode stopped, or when the server stops."""
        try:
            query = live.live_query(request.query_params.multi_items())
        except ValueError as exc:
            return error(422, str(exc))
        if len(streams) >= live.MAX_STREAMS:
            return error(429, f"{live.MAX_STREAMS} streams are open: close one (another page) first",
                          headers={"Retry-After": "1"})
        events = live.live_events(state, converted, request_fields, query, app.state.closing)
        streams.add(events)
        return EventStream(events, headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})

    @app.get("/", include_in_schema=False)
    async def get_page() -> Response:
        return HTMLResponse(live.static_text(live.PAGE), headers=live.page_headers())

    @app.get("/live.js", include_in_schema=False)
    async def get_script() -> Response:
        return Response(live.static_text(live.SCRIPT), media_type="text/javascript; charset=utf-8",
                        headers=live.page_headers())

    schema_of = app.openapi

    def openapi() -> dict:
        spec = schema_of()  # built once and kept by FastAPI
        ok = spec["paths"]["/stream"]["get"]["responses"]["200"]
        if "application/json" in ok.get("content", {}):  # the events are JSON inside an event stream
            ok["content"] = {"text/event-stream": ok["content"].pop("application/json")}
        return spec

    app.openapi = openapi  # type: ignore[method-assign]
    docs_html: list = []

    @app.get("/docs", include_in_schema=False)
    async def get_docs() -> Response:
        if not docs_html:
            docs_html.append(live.docs_page(app.openapi()))
        return HTMLResponse(docs_html[0], headers=live.page_headers())

    @app.post("/setpoint", response_model=SetpointReply, responses=_SETPOINT_ERRORS)
    def post_setpoint(request: SetpointRequest) -> Response:
        """Check, clip and queue a setpoint; the reply says what will be applied and what was clipped."""
        if state.stop_requested:
            raise HTTPException(409, f"the daemon is stopping ({state.stop_reason}): no new setpoints")
        try:
            reply = state.submit_setpoint(request.to_si())
        except Stopping as exc:
            raise HTTPException(409, str(exc)) from None
        except ValueError as exc:
            raise HTTPException(422, f"[setpoint] {exc}") from None
        except RuntimeError as exc:
            raise HTTPException(503, str(exc)) from None
        return _json(SetpointReply(applied=_applied_message(reply.get("applied") or {}),
                                   clipped=[str(m) for m in reply.get("clipped") or ()]))

    @app.post("/reset", response_model=ResetReply, responses=_RESET_ERRORS)
    def post_reset() -> Response:
        """Leave the safe state after a fault once the readings are sane (the loop checks them again)."""
        if state.stop_requested:
            raise HTTPException(409, f"the daemon is stopping ({state.stop_reason}): no reset")
        try:
            line = state.submit_reset()
        except RuntimeError as exc:
            raise HTTPException(409, str(exc)) from None
        return _json(ResetReply(reset_requested=True, detail=line))

    @app.post("/stop", response_model=StopReply)
    async def post_stop() -> Response:
        """Ask the loop for the safe command and its end (idempotent; the first reason is kept)."""
        state.request_stop("api")
        return stop_answer()

    return app


def server_config(app: FastAPI) -> uvicorn.Config:
    """uvicorn's settings for ``app``: the connection guards (:class:`GuardedProtocol`, :data:`MAX_CONNECTIONS`,
    the keep-alive and head deadlines, the request head's size), its stop front (the protocol hands it
    each whole stop) and no logging of its own."""
    return uvicorn.Config(app, log_config=None, access_log=False, log_level="warning", lifespan="off",
                          http=GuardedProtocol.bound(app.state.stop_front), limit_concurrency=MAX_CONNECTIONS,
                          timeout_keep_alive=int(REQUEST_TIMEOUT_S), h11_max_incomplete_event_size=MAX_BODY_BYTES,
                          timeout_graceful_shutdown=2)
