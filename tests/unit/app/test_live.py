"""The daemon's live page and status stream (hbma_ctrl.app.daemon.live, GET /, /live.js, /stream, /docs)
against a DaemonState the test publishes to, as the loop does. The stream's generator is driven by
hand (one ``anext`` per expected chunk, snapshots published between), so what it sends is decided by
the loop periods published, never by wall time."""

from __future__ import annotations

import asyncio
import json
import math
import threading
import time

import pytest
from fastapi.testclient import TestClient

from hbma_ctrl.app.daemon.api import make_app, status_message
from hbma_ctrl.app.daemon.live import PUBLIC_PATHS, live_events
from hbma_ctrl.app.daemon.state import RING, DaemonState
from hbma_ctrl.app.schema.api import LiveEvent, LiveQuery


def snap(steps: int, mode: str = "running", rate_hz: float | None = 100.0) -> dict:
    """A loop status at ``steps`` periods of 10 ms: values that change with the step count."""
    return {"mode": mode, "t_s": steps * 0.01, "monotonic_s": time.monotonic(),
            "chambers": [{"name": "A1", "h": 1e-5 * steps, "h_std": 1e-4, "target": 0.006, "p": 100.0 * steps,
                          "p_est": 99.0 * steps, "u": [0.5, 1.0, 0.0]},
                         {"name": "A2", "h": 0.002, "h_std": 1e-4, "target": float("nan"), "p": float("nan"),
                          "p_est": 0.0, "u": [0.0, 0.0, 1.0]}],
            "layers": [{"centre": 0.007, "bend": math.radians(12.0), "direction": math.radians(30.0)}],
            "loop": {"rate_hz": rate_hz, "steps": steps, "deadline_misses": 1, "overruns": 0,
                     "step_median_s": 0.003, "step_p99_s": 0.008},
            "faults": {"leak": 1}, "events": [{"t_s": 0.5, "kind": "leak", "cause": "A1: pressure fell"}]}


def frames(chunk: bytes) -> list[tuple[int, dict]]:
    """The (id, data) of each server-sent event in ``chunk``."""
    out = []
    for block in chunk.decode().split("\n\n"):
        if not block.strip():
            continue
        fields = dict(line.split(": ", 1) for line in block.splitlines())
        out.append((int(fields["id"]), json.loads(fields["data"])))
    return out


def no_extra(snapshot: dict) -> dict:
    return {"age_ms": None, "stop_requested": False}


def drive(state: DaemonState, rate_hz: float, script, count: int | None = None,
          closing: threading.Event | None = None) -> list:
    """Run the stream; ``script(publish_and_read)`` publishes steps and reads the chunks it expects."""
    query = LiveQuery(rate_hz=rate_hz, count=count)
    gen = live_events(state, status_message, no_extra, query, closing or threading.Event())

    async def main():
        got = [frames(await anext(gen))]

        async def read():
            got.append(frames(await anext(gen)))
            return got[-1]

        await script(read)
        return got

    return asyncio.run(main())


@pytest.fixture
def state() -> DaemonState:
    s = DaemonState()
    s.publish(snap(0))
    return s


# --- what the stream sends ------------------------------------------------------------------------------

def test_the_stream_sends_the_status_as_get_status_gives_it_with_its_decimation(state):
    state.publish(snap(37))
    c = TestClient(make_app(state), base_url="http://127.0.0.1")
    r = c.get("/stream", params={"rate_hz": 10, "count": 1})
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/event-stream")
    ((sid, ev),) = frames(r.content)
    status = c.get("/status").json()
    LiveEvent.model_validate(ev)
    assert sid == 37 and ev.pop("every_steps") == 10 and ev.pop("lost") == 0
    assert ev.pop("age_ms") is not None and status.pop("age_ms") is not None
    assert ev == status


def test_the_stream_sends_every_nth_loop_period_counted_in_periods(state):
    async def script(read):
        sent = []
        for j in range(1, 11):  # 20 Hz of a 100 Hz loop: every 5th period
            for k in range(5 * (j - 1) + 1, 5 * j + 1):
                state.publish(snap(k))
            sent += await read()
        return sent

    got = drive(state, 20.0, script)
    ids = [sid for chunk in got for sid, _ in chunk]
    assert ids == [0, 5, 10, 15, 20, 25, 30, 35, 40, 45, 50]
    assert all(ev["every_steps"] == 5 and ev["lost"] == 0 for chunk in got for _, ev in chunk)
    # each event carries the values of its own period
    assert [ev["chambers"][0]["p_kpa"] for chunk in got for _, ev in chunk] == pytest.approx(
        [0.1 * k for k in ids])


def test_periods_published_between_two_reads_are_each_decimated_not_skipped(state):
    async def script(read):
        for k in range(1, 23):
            state.publish(snap(k))
        assert [sid for sid, _ in await read()] == [4, 8, 12, 16, 20]  # 25 Hz: every 4th

    drive(state, 25.0, script)


def test_a_loop_publishing_every_other_period_gets_the_first_status_at_or_past_each_multiple(state):
    async def script(read):
        for k in range(2, 31, 2):  # status_every = 2 and every 5th wanted: 6 (past 5), 10, 16 (past 15), ...
            state.publish(snap(k))
        assert [sid for sid, _ in await read()] == [6, 10, 16, 20, 26, 30]

    drive(state, 20.0, script)


def test_statuses_the_ring_no_longer_holds_are_counted_as_lost(state):
    async def script(read):
        assert RING == 128  # the steps below are its multiples
        for k in range(1, 3 * RING + 1):
            state.publish(snap(k))
        evs = await read()
        assert evs[0][1]["lost"] == 2 * RING and all(ev["lost"] == 0 for _, ev in evs[1:])
        assert evs[0][0] == 2 * RING + 1 and [sid for sid, _ in evs[1:]] == list(range(260, 3 * RING + 1, 10))

    drive(state, 10.0, script)


def test_the_stream_ends_after_the_stopped_status_and_after_count(state):
    async def script(read):
        state.publish(snap(3))
        state.publish(snap(3, mode="stopped"))
        assert [(sid, ev["mode"]) for sid, ev in await read()] == [(3, "stopped")]

    drive(state, 10.0, script)
    c = TestClient(make_app(state), base_url="http://127.0.0.1")
    assert len(frames(c.get("/stream", params={"count": 1}).content)) == 1  # and it ended: the body is whole


def test_the_stream_ends_when_the_server_closes(state):
    closing = threading.Event()

    async def script(read):
        closing.set()
        with pytest.raises(StopAsyncIteration):
            await read()

    drive(state, 10.0, script, closing=closing)


def test_the_loops_last_status_published_as_the_server_closes_is_still_sent(state):
    closing = threading.Event()

    async def script(read):
        state.publish(snap(4))
        state.publish(snap(4, mode="stopped"))
        closing.set()  # the daemon stops its API right after the loop's last status
        assert [(sid, ev["mode"]) for sid, ev in await read()] == [(4, "stopped")]
        with pytest.raises(StopAsyncIteration):
            await read()

    drive(state, 10.0, script, closing=closing)


def test_before_the_loop_reports_its_rate_the_newest_status_is_sent_then_the_grid_starts(state):
    state.publish({"mode": "starting"})

    async def script(read):
        state.publish({"mode": "starting", "t_s": 0.0})
        state.publish({"mode": "starting", "t_s": 0.01})
        assert [ev["every_steps"] for _, ev in await read()] == [None]
        for k in range(1, 12):
            state.publish(snap(k))
        assert [(sid, ev["every_steps"]) for sid, ev in await read()] == [(1, 10), (10, 10)]

    drive(state, 10.0, script)


# --- the query --------------------------------------------------------------------------------------------

BAD_QUERIES = [
    ({"rate_hz": "500"}, ["rate_hz = 500", "[0.5, 50] Hz"]),
    ({"rate_hz": "0"}, ["rate_hz = 0", "[0.5, 50] Hz"]),
    ({"rate_hz": "fast"}, ["rate_hz = 'fast'", "number", "[0.5, 50] Hz"]),
    ({"rate_hz": "NaN"}, ["rate_hz = nan", "[0.5, 50] Hz"]),
    ({"rate_hz": "true"}, ["rate_hz", "number"]),
    ({"rate": "5"}, ["rate", "unknown key", "did you mean rate_hz"]),
    ({"count": "0"}, ["count = 0", "[1, 1e+07]"]),
    ({"count": "2.5"}, ["count = 2.5", "integer"]),
    ([("rate_hz", "5"), ("rate_hz", "6")], ["rate_hz", "twice"]),
]


@pytest.mark.parametrize("params,words", BAD_QUERIES, ids=[str(q) for q, _ in BAD_QUERIES])
def test_a_bad_stream_query_is_one_422_line_naming_the_key_and_its_range(state, params, words):
    r = TestClient(make_app(state), base_url="http://127.0.0.1").get("/stream", params=params)
    assert r.status_code == 422
    err = r.json()["error"]
    assert err.startswith("[stream] ") and "\n" not in err
    for w in words:
        assert w in err, (w, err)


# --- the page, its script, the endpoints' page -------------------------------------------------------------

def test_the_page_and_its_script_are_served_from_the_package_with_their_types_and_policy(state):
    c = TestClient(make_app(state), base_url="http://127.0.0.1")
    page, script = c.get("/"), c.get("/live.js")
    assert page.status_code == 200 and page.headers["content-type"] == "text/html; charset=utf-8"
    assert script.status_code == 200 and script.headers["content-type"] == "text/javascript; charset=utf-8"
    assert '<script src="/live.js"></script>' in page.text and "/stream?rate_hz=" in script.text
    for r in (page, script):
        csp = r.headers["content-security-policy"]
        assert "script-src 'self'" in csp and "connect-src 'self'" in csp and "frame-ancestors 'none'" in csp
        assert r.headers["x-content-type-options"] == "nosniff"
    assert "http://" not in page.text + script.text and "https://" not in page.text + script.text  # no CDN


def test_the_endpoints_page_lists_every_endpoint_from_the_openapi_schema(state):
    c = TestClient(make_app(state), base_url="http://127.0.0.1")
    r = c.get("/docs")
    assert r.status_code == 200 and r.headers["content-type"] == "text/html; charset=utf-8"
    spec = c.get("/openapi.json").json()
    for path, ops in spec["paths"].items():
        for method in ops:
            assert f"{method.upper()} {path}" in r.text
    assert "rate_hz" in r.text and "LiveEvent" in r.text and "<script" not in r.text


def test_with_a_token_only_the_page_its_script_and_the_endpoints_page_are_served_without_it(state):
    c = TestClient(make_app(state, "secret"), base_url="http://127.0.0.1")
    for path in sorted(PUBLIC_PATHS):
        assert c.get(path).status_code == 200, path
    for path in ("/stream?count=1", "/status", "/openapi.json"):
        assert c.get(path).status_code == 401, path
    assert c.post("/", json={}).status_code == 401  # public is a GET of those paths only
    r = c.get("/stream", params={"count": 1}, headers={"Authorization": "Bearer secret"})
    assert r.status_code == 200 and len(frames(r.content)) == 1


def test_the_page_is_refused_to_a_foreign_host(state):
    c = TestClient(make_app(state), base_url="http://127.0.0.1")
    assert c.get("/", headers={"host": "evil.example"}).status_code == 403
    assert c.get("/stream", params={"count": 1}, headers={"host": "evil.example"}).status_code == 403


# --- the state the loop publishes to ---------------------------------------------------------------------

def test_publishing_never_waits_for_a_reader_holding_the_states_lock(state):
    published = threading.Event()

    def loop():
        state.publish(snap(1))
        published.set()

    with state._lock:  # a reader (a setpoint, a reset) in the middle of its turn
        t = threading.Thread(target=loop, daemon=True)
        t.start()
        assert published.wait(30)
    assert state.status()["loop"]["steps"] == 1


def test_since_gives_the_snapshots_after_a_number_in_order_and_counts_those_gone(state):
    seq0, _ = state.latest()
    for k in range(1, 6):
        state.publish(snap(k))
    got, gone = state.since(seq0)
    assert [s["loop"]["steps"] for _, s in got] == [1, 2, 3, 4, 5] and gone == 0
    assert state.since(state.latest()[0]) == ([], 0)
    for k in range(6, 6 + RING + 3):
        state.publish(snap(k))
    got, gone = state.since(seq0)
    assert len(got) == RING and gone == 5 + 3 and got[-1][1]["loop"]["steps"] == 5 + RING + 3


def test_streams_beyond_the_bound_are_429_and_other_requests_are_served(state, monkeypatch):
    from hbma_ctrl.app.daemon import live

    monkeypatch.setattr(live, "MAX_STREAMS", 0)  # every stream is beyond the bound
    c = TestClient(make_app(state), base_url="http://127.0.0.1")
    r = c.get("/stream", params={"count": 1})
    assert r.status_code == 429 and "streams are open" in r.json()["error"]
    assert c.get("/status").status_code == 200


def test_a_finished_stream_frees_its_place(state, monkeypatch):
    from hbma_ctrl.app.daemon import live

    monkeypatch.setattr(live, "MAX_STREAMS", 1)
    c = TestClient(make_app(state), base_url="http://127.0.0.1")
    for _ in range(3):
        assert c.get("/stream", params={"count": 1}).status_code == 200
