"""The daemon's live page: the page and its script (package data, no build step, no CDN), the status
stream it reads (server-sent events, decimated on the server) and a self-hosted page of the API's
endpoints from its OpenAPI schema. :func:`hbma_ctrl.app.daemon.api.make_app` mounts them:

- ``GET /`` (:data:`PAGE`) and ``GET /live.js`` (:data:`SCRIPT`): the page, served from the package;
- ``GET /stream?rate_hz=R&count=K``: one server-sent event per n-th status the loop publishes,
  n = loop rate / R rounded (at least 1), counted in loop periods, never in wall time. Each event's
  ``data`` is a :class:`~hbma_ctrl.app.schema.api.LiveEvent` (the status as ``GET /status`` gives
  it, with ``every_steps`` and ``lost``) and its ``id`` the loop's step count; the first event is the
  newest status at once; the stream ends after ``K`` events, after the status of mode "stopped", or
  when the server stops. A bad query is one 422 line naming the key and its range
  (:func:`live_query`);
- ``GET /docs``: the endpoints, their parameters and answers, as HTML rendered here from the OpenAPI
  schema (the schema itself is ``GET /openapi.json``). Swagger UI and ReDoc load their scripts from
  a CDN, which a rig PC offline cannot reach, and no installed package carries them.

The stream never makes the loop wait: it reads the snapshots the loop published
(:meth:`hbma_ctrl.app.daemon.state.DaemonState.since`, no lock) every :data:`POLL_S` of wall time in
the server's event loop, and picks from them the first at or past each multiple of n loop periods.
A snapshot the loop published more than :data:`hbma_ctrl.app.daemon.state.RING` snapshots before
the stream read it is counted in the next event's ``lost`` (a run far faster than real time, or a
client that does not read).
"""

from __future__ import annotations

import asyncio
import html
import json
import threading
from collections.abc import AsyncIterator, Callable
from importlib import resources

from pydantic import ValidationError

from hbma_ctrl.app.daemon.state import DaemonState
from hbma_ctrl.app.schema.api import LiveEvent, LiveQuery, Status
from hbma_ctrl.app.schema.errors import format_error

__all__ = ["MAX_STREAMS", "PAGE", "POLL_S", "PUBLIC_PATHS", "SCRIPT", "docs_page", "live_events", "live_query",
           "page_headers", "static_text"]

#: the page's files in the package (hbma_ctrl/app/daemon/static/)
PAGE = "live.html"
SCRIPT = "live.js"
#: what a browser may load without the bearer token: the page, its script and the endpoints' page
#: carry no data of the rig; everything they show comes from endpoints that need it
PUBLIC_PATHS = frozenset({"/", "/live.js", "/docs"})
#: streams open at once; 429 beyond (each costs a conversion per event in the server's thread)
MAX_STREAMS = 8
#: how often a stream looks for new snapshots, wall s
POLL_S = 0.02


def static_text(name: str) -> str:
    """The text of a file of the page (:data:`PAGE`, :data:`SCRIPT`) from the installed package."""
    return resources.files("hbma_ctrl.app.daemon").joinpath("static", name).read_text(encoding="utf-8")


def page_headers() -> dict:
    """Headers of the page and its script: its own scripts and connections only, no framing by another
    site (a foreign page cannot overlay the stop button), no content sniffing, no caching."""
    return {"Content-Security-Policy": "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; "
                                       "connect-src 'self'; img-src 'self' data:; frame-ancestors 'none'; "
                                       "base-uri 'none'; form-action 'none'",
            "X-Content-Type-Options": "nosniff", "X-Frame-Options": "DENY", "Cache-Control": "no-cache",
            "Referrer-Policy": "no-referrer"}


def live_query(params: list[tuple[str, str]]) -> LiveQuery:
    """The stream's query (``[(key, value), ...]`` as sent) checked; ValueError with one line naming the key
    and its range, e.g. ``[stream] rate_hz = 500 is out of range [0.5, 50] Hz``."""
    raw: dict = {}
    for key, value in params:
        if key in raw:
            raise ValueError(f"[stream] {key} is given twice")
        try:  # a query string is text: a number is read as JSON reads it, anything else stays text
            v = json.loads(value)
            raw[key] = v if isinstance(v, (int, float)) and not isinstance(v, bool) else value
        except ValueError:
            raw[key] = value
    try:
        return LiveQuery.model_validate(raw)
    except ValidationError as exc:
        raise ValueError(format_error(exc, LiveQuery, "stream")) from None


def _steps(snap: dict) -> int:
    try:
        return int((snap.get("loop") or {}).get("steps", 0))
    except (TypeError, ValueError):
        return 0


def _every(snap: dict, rate_hz: float) -> int | None:
    """Loop periods per event for the loop rate in ``snap`` (None when it reports none)."""
    try:
        loop_hz = float((snap.get("loop") or {}).get("rate_hz"))
    except (TypeError, ValueError):
        return None
    if not loop_hz > 0:
        return None
    return max(1, round(loop_hz / rate_hz))


async def live_events(state: DaemonState, convert: Callable[[dict], Status], extra: Callable[[dict], dict],
                      query: LiveQuery, closing: threading.Event) -> AsyncIterator[bytes]:
    """The server-sent events of ``GET /stream`` (module doc): ``convert`` turns a snapshot into its
    :class:`Status` message, ``extra`` gives the request-time fields (``age_ms``, ``stop_requested``)."""

    def frame(snap: dict, every: int | None, lost: int) -> bytes:
        msg = convert(snap)
        ev = LiveEvent.model_construct(**{**dict(msg), **extra(snap)}, every_steps=every, lost=lost)
        return f"id: {_steps(snap)}\ndata: {ev.model_dump_json()}\n\n".encode()

    seq, snap = state.latest()
    every = _every(snap, query.rate_hz)
    due = (_steps(snap) // every + 1) * every if every else None  # the next multiple of every
    sent = 1
    yield frame(snap, every, 0)
    if snap.get("mode") == "stopped" or (query.count is not None and sent >= query.count):
        return
    lost = 0
    while True:
        # the server closes right after the loop's last status: one more read sends it
        last_read = closing.is_set()
        if not last_read:
            await asyncio.sleep(POLL_S)
        pairs, missed = state.since(seq)
        lost += missed
        if not pairs:
            if last_read:
                return
            continue
        seq = pairs[-1][0]
        out = []
        for _, snap in pairs:
            steps, final = _steps(snap), snap.get("mode") == "stopped"
            if every is None:
                every = _every(snap, query.rate_hz)
                if every is not None:
                    due = steps  # the first snapshot with a rate is sent: the grid starts there
            if final or (every is not None and steps >= due) or (every is None and snap is pairs[-1][1]):
                out.append(frame(snap, every, lost))
                lost = 0
                sent += 1
                if every is not None:
                    due = (steps // every + 1) * every
                if final or (query.count is not None and sent >= query.count):
                    yield b"".join(out)
                    return
        if out:
            yield b"".join(out)
        if last_read:
            return


def _schema_name(schema: dict) -> str:
    if "$ref" in schema:
        return schema["$ref"].rsplit("/", 1)[-1]
    if schema.get("type") == "array":
        return f"list of {_schema_name(schema.get('items', {}))}"
    if "anyOf" in schema:
        return " or ".join(_schema_name(s) for s in schema["anyOf"])
    return str(schema.get("type", "any"))


def docs_page(spec: dict) -> str:
    """The API's endpoints page (``GET /docs``) from its OpenAPI schema: per endpoint its description,
    query parameters, request body and answers; per message its keys with type, range and description."""
    e = html.escape
    info = spec.get("info", {})
    out = ["<!doctype html><html lang='en'><head><meta charset='utf-8'>",
           f"<title>{e(info.get('title', 'API'))}: endpoints</title>",
           "<style>body{font:14px/1.45 system-ui,sans-serif;margin:1.5em auto;max-width:70em;padding:0 1em}"
           "table{border-collapse:collapse;margin:.4em 0 1em}td,th{border:1px solid #ccc;padding:2px 8px;"
           "text-align:left;vertical-align:top}code{background:#f3f3f3;padding:0 3px}h3{margin-bottom:.2em}</style>",
           "</head><body>", f"<h1>{e(info.get('title', 'API'))}</h1>",
           "<p>The endpoints of this daemon, from its OpenAPI schema (<a href='/openapi.json'>/openapi.json</a>); "
           "the live page is at <a href='/'>/</a>.</p><h2>Endpoints</h2>"]
    for path, ops in spec.get("paths", {}).items():
        for method, op in ops.items():
            out.append(f"<h3 id='{e(method + path)}'><code>{e(method.upper())} {e(path)}</code></h3>")
            out.append(f"<p>{e(op.get('description') or op.get('summary', ''))}</p>")
            params = op.get("parameters") or []
            if params:
                out.append("<table><tr><th>query key</th><th>type</th><th>range</th><th>description</th></tr>")
                for prm in params:
                    s = prm.get("schema", {})
                    rng = ", ".join(f"{op_} {s[k]:g}" for k, op_ in (("minimum", ">="), ("maximum", "<="))
                                    if isinstance(s.get(k), (int, float)))
                    out.append(f"<tr><td><code>{e(prm.get('name', ''))}</code></td><td>{e(_schema_name(s))}</td>"
                               f"<td>{e(rng)}</td><td>{e(prm.get('description', ''))}</td></tr>")
                out.append("</table>")
            body = op.get("requestBody", {}).get("content", {}).get("application/json", {}).get("schema")
            if body:
                name = _schema_name(body)
                out.append(f"<p>Request body: <a href='#{e(name)}'>{e(name)}</a></p>")
            out.append("<table><tr><th>status</th><th>meaning</th><th>body</th></tr>")
            for code, r in sorted(op.get("responses", {}).items()):
                kinds = r.get("content", {})
                schema = next((c.get("schema") for c in kinds.values() if c.get("schema")), None)
                name = _schema_name(schema) if schema else ""
                kind = ", ".join(kinds)
                out.append(f"<tr><td>{e(code)}</td><td>{e(r.get('description', ''))}</td>"
                           f"<td>{f'<a href={chr(39)}#{e(name)}{chr(39)}>{e(name)}</a> ({e(kind)})' if name else ''}"
                           "</td></tr>")
            out.append("</table>")
    out.append("<h2>Messages</h2>")
    for name, s in spec.get("components", {}).get("schemas", {}).items():
        if name in ("HTTPValidationError", "ValidationError") or "properties" not in s:
            continue
        out.append(f"<h3 id='{e(name)}'>{e(name)}</h3><p>{e(s.get('description', ''))}</p>")
        out.append("<table><tr><th>key</th><th>type</th><th>required</th><th>description</th></tr>")
        req = set(s.get("required", ()))
        for key, f in s["properties"].items():
            out.append(f"<tr><td><code>{e(key)}</code></td><td>{e(_schema_name(f))}</td>"
                       f"<td>{'yes' if key in req else 'no'}</td><td>{e(f.get('description', ''))}</td></tr>")
        out.append("</table>")
    out.append("</body></html>")
    return "\n".join(out)
