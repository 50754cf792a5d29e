"""The daemon API's stop path on a real server (uvicorn in a thread of this process, the daemon's own
settings, :func:`hbma_ctrl.app.daemon.api.server_config`): a stop is sent from the read callback that
parsed it, before any task, and keeps every guard of the ordinary path."""

from __future__ import annotations

import asyncio
import socket
import threading
import time

import httpx
import pytest
import uvicorn

from hbma_ctrl.app.daemon.api import make_app, server_config
from hbma_ctrl.app.daemon.state import DaemonState


class RecordingState(DaemonState):
    """A state that records each stop asked of it and whether the event loop ran a task then (None: the
    stop was sent from a callback, before any task)."""

    def __init__(self) -> None:
        super().__init__()
        self.stops: list[tuple[str, object]] = []

    def request_stop(self, reason: str = "stop requested", fault: str | None = None) -> None:
        try:
            task = asyncio.current_task()
        except RuntimeError:  # no event loop in this thread
            task = "no loop"
        self.stops.append((reason, task))
        super().request_stop(reason, fault)


class Server:
    """The API of ``state`` served on a free loopback port by uvicorn in a thread, until closed."""

    def __init__(self, state: DaemonState, **app_kw):
        self.app = make_app(state, **app_kw)
        self.server = uvicorn.Server(server_config(self.app))
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self.sock.getsockname()[1]}"
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True)
        self.thread.start()
        end = time.monotonic() + 60  # a bound for a loaded machine, not a measure
        while not self.server.started:
            assert self.thread.is_alive() and time.monotonic() < end, "uvicorn did not start"
            time.sleep(0.01)

    def close(self) -> None:
        self.app.state.closing.set()
        self.server.should_exit = self.server.force_exit = True  # requests still waiting are dropped
        self.thread.join(30)
        self.sock.close()

    def __enter__(self) -> Server:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@pytest.fixture
def state() -> RecordingState:
    return RecordingState()


def test_a_stop_is_sent_from_the_callback_that_parsed_it_and_answered_as_the_route_does(state):
    with Server(state) as srv, httpx.Client(base_url=srv.url, timeout=30) as c:
        r = c.post("/stop")
        again = c.post("/stop")  # the same connection after a fast answer: keep-alive holds
    assert r.status_code == 200 and again.status_code == 200
    assert r.headers["content-type"] == "application/json"
    assert r.json() == {"stop_requested": True, "reason": "api", "mode": "starting"}
    assert state.stops == [("api", None), ("api", None)]  # once per request, before any task ran


def test_a_stop_with_a_body_takes_the_ordinary_path_and_is_sent_once(state):
    with Server(state) as srv:
        r = httpx.post(f"{srv.url}/stop", json={}, timeout=30)
    assert r.status_code == 200 and r.json()["reason"] == "api"
    assert len(state.stops) == 1 and state.stops[0][1] is not None  # sent by the route's task


@pytest.mark.parametrize("headers", [
    {"Host": "evil.example"},                                         # a foreign Host
    {"Host": "127.0.0.1", "Origin": "http://evil.example"},           # a cross-origin POST
    {"Host": "localhost:1", "Origin": "http://127.0.0.1:1"},          # an Origin that is not the Host
], ids=["foreign host", "foreign origin", "origin not the host"])
def test_a_stop_from_a_foreign_host_or_origin_is_403_and_not_sent(state, headers):
    with Server(state) as srv:
        r = httpx.post(f"{srv.url}/stop", headers=headers, timeout=30)
    assert r.status_code == 403 and r.json()["error"]
    assert state.stops == [] and not state.stop_requested


def test_a_stop_without_the_token_is_401_and_not_sent_and_with_it_is_sent(state):
    with Server(state, token="s3cret", allow_remote=True) as srv:
        missing = httpx.post(f"{srv.url}/stop", headers={"Host": "rig.example"}, timeout=30)
        wrong = httpx.post(f"{srv.url}/stop", headers={"Host": "rig.example", "Authorization": "Bearer nope"},
                           timeout=30)
        assert state.stops == []
        right = httpx.post(f"{srv.url}/stop", headers={"Host": "rig.example", "Authorization": "Bearer s3cret"},
                           timeout=30)
    assert missing.status_code == 401 and wrong.status_code == 401
    assert right.status_code == 200 and state.stops == [("api", None)]


@pytest.mark.parametrize("kind, body, code", [("text/plain", b"stop", 415), ("application/json", b"x" * 20_000, 413)],
                         ids=["not json", "too large"])
def test_a_stop_whose_body_the_guard_refuses_is_refused_and_not_sent(state, kind, body, code):
    with Server(state) as srv:
        r = httpx.post(f"{srv.url}/stop", content=body, headers={"Content-Type": kind}, timeout=30)
    assert r.status_code == code and state.stops == []


def test_a_stop_is_sent_and_answered_while_a_flood_waits_for_its_turn(state):
    # a pace of one request per 100 s after a burst of one: the flood's requests all wait for their
    # turn (up to max_wait_s) in the server's event loop, and the stop is asked after all of them
    n = 40
    with Server(state, rate_hz=0.01, burst=1, max_wait_s=1e6) as srv:
        order: list[str] = []

        async def flood() -> None:
            async with httpx.AsyncClient(base_url=srv.url, timeout=60,
                                         limits=httpx.Limits(max_connections=n + 1)) as c:
                async def one(k: int) -> None:
                    r = await c.get("/health")
                    order.append(f"health {r.status_code}")

                tasks = [asyncio.create_task(one(k)) for k in range(n)]
                # every flood request is in the server before the stop: one served, the others waiting
                while not order or len(srv.server.server_state.tasks) < n - 1:
                    await asyncio.sleep(0.01)
                r = await c.post("/stop")
                order.append(f"stop {r.status_code}")
                for t in tasks:
                    t.cancel()
                await asyncio.gather(*tasks, return_exceptions=True)

        asyncio.run(flood())
    assert order == ["health 200", "stop 200"]  # answered while every other flood request waits its turn
    assert state.stops == [("api", None)]


def test_a_stop_on_a_full_pipe_returns_at_once_and_every_stop_written_arrives_whole():
    import multiprocessing as mp

    from hbma_ctrl.app.daemon.apiproc import _ApiState

    r, w = mp.Pipe(duplex=False)
    s = _ApiState(lambda msg: None, w)
    n = 20_000  # far more than a pipe holds: nobody reads until the end
    for k in range(n):
        s.request_stop(f"stop {k}")
    got = []
    while r.poll():
        got.append(r.recv())
    assert 0 < len(got) < n  # the pipe filled and the rest returned without waiting
    assert got == [f"stop {k}" for k in range(len(got))]  # none torn, none out of order
    assert s.stop_reason == "stop 0"  # the first asked is the reason this API shows


def test_a_long_stop_reason_crosses_the_pipe_cut_to_500_characters_in_one_piece():
    import multiprocessing as mp

    from hbma_ctrl.app.daemon.apiproc import _ApiState

    r, w = mp.Pipe(duplex=False)
    _ApiState(lambda msg: None, w).request_stop("\u00e9" * 10_000)  # 2 bytes each in UTF-8
    assert r.recv() == "\u00e9" * 500 and not r.poll()
