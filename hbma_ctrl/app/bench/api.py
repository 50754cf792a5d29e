"""``hbma-ctrl bench api``: the rig daemon's loop under a flood of API clients, beside the same run without.

The daemon runs in this process on the simulated rig in real time (speed 1, as a real rig runs), with
its API on a free loopback port (in the API's own process, as the daemon runs it), twice for
``duration_s`` each: once quiet, once with ``clients`` loopback clients in another process, each sending its next request (``GET /status``, ``GET /health``
or a ``POST /setpoint``, in turn) as soon as the last is answered. In both runs a prober, a process of
its own, posts ``/stop`` every ``probe_every_s`` and times each answer: the stop requests the API takes
from it reach the loop's state, which counts them instead of ending the run (:class:`ProbedState`);
the API's path to them is the real one. At the end, once every probe answered has been counted
there, the bench posts the real ``/stop`` and times its answer and the loop's end.

Writes ``api.json``: per run (``quiet``, ``loaded``) the daemon's deadline misses, overrun warnings,
step and tick p99 (ms), faults, the clients' answers by HTTP status and their rate, and the ``/stop``
latencies (median, p99, max, ms, and how many came within one loop period); the verdicts
``no_deadline_miss_added`` (overrun warnings: misses past the controller's warm-up, whose first
solves miss alike in both runs), ``stop_within_a_period`` and ``no_fault``. The daemon's own results are in ``quiet/`` and
``loaded/``.
"""

from __future__ import annotations

import asyncio
import json
import multiprocessing as mp
import threading
import time
from collections import Counter
from pathlib import Path

import httpx
import numpy as np

from hbma_ctrl.app.daemon.state import DaemonState
from hbma_ctrl.app.outputs import run_dir
from hbma_ctrl.core import units as U

__all__ = ["ProbedState", "run_api_bench"]


class ProbedState(DaemonState):
    """The daemon's state with the API's stop requests counted, not acted on, while ``probing``."""

    def __init__(self) -> None:
        super().__init__()
        self.probing = True
        self.probes = 0

    def request_stop(self, reason: str = "stop requested", fault: str | None = None) -> None:
        """Count an API stop while probing; any other stop (a signal, or the API's once probing ends) acts."""
        if self.probing and reason == "api":
            self.probes += 1
            return
        super().request_stop(reason, fault)


def _flood(url: str, clients: int, duration: float, go, out) -> None:
    """``clients`` connections sending back-to-back requests for ``duration`` s from the event ``go``;
    puts {status: count} on the queue ``out``."""
    counts: Counter = Counter()
    out.put("ready")
    go.wait()
    until = time.monotonic() + duration

    async def one(j: int) -> None:
        async with httpx.AsyncClient(base_url=url, timeout=10) as c:
            k = 0
            while time.monotonic() < until:
                try:
                    if k % 3 == 0:
                        r = await c.post("/setpoint", json={"heights_mm": {"0": 2.0 + (j + k) % 5}})
                    else:
                        r = await c.get("/status" if k % 3 == 1 else "/health")
                    counts[r.status_code] += 1
                except httpx.HTTPError as exc:
                    counts[type(exc).__name__] += 1
                k += 1

    async def main() -> None:
        await asyncio.gather(*(one(j) for j in range(clients)))

    asyncio.run(main())
    out.put(dict(counts))


def _probe(url: str, every: float, duration: float, go, out) -> None:
    """POST /stop every ``every`` s for ``duration`` s from the event ``go``; puts the latencies (s;
    None: no answer)."""
    lat: list = []
    with httpx.Client(base_url=url, timeout=5) as c:
        out.put("ready")
        go.wait()
        nxt = time.monotonic()
        until = nxt + duration
        while nxt < until:
            time.sleep(max(0.0, nxt - time.monotonic()))
            t0 = time.perf_counter()
            try:
                ok = c.post("/stop").status_code == 200
            except httpx.HTTPError:
                ok = False
            lat.append(time.perf_counter() - t0 if ok else None)
            nxt += every
    out.put(lat)


def _latency(lat: list, period: float) -> dict:
    got = np.array([x for x in lat if x is not None], dtype=float)
    ms = lambda q: float(U.to_ms(np.percentile(got, q))) if got.size else None  # noqa: E731
    return {"n": len(lat), "unanswered": sum(1 for x in lat if x is None), "median_ms": ms(50), "p99_ms": ms(99),
            "max_ms": float(U.to_ms(got.max())) if got.size else None,
            "within_period": int(np.sum(got <= period))}


def _one_run(config: Path, out: Path, duration_s: float, clients: int, probe_every_s: float, echo) -> dict:
    """One daemon run for ``duration_s`` (wall) with ``clients`` flooding its API (0 = quiet)."""
    from hbma_ctrl.app.daemon.run import run_daemon
    from hbma_ctrl.app.daemon.config import load_config

    cfg = load_config(config, {"--rig": "sim", "--speed": 1.0, "--api": "127.0.0.1:0"})
    state = ProbedState()
    urls: list[str] = []
    res: dict = {}
    ctx = mp.get_context("spawn")  # a fresh interpreter: no copy of this process's threads or GIL

    def drive() -> None:
        while not urls:
            time.sleep(0.01)
        url = urls[0]
        q, go = ctx.Queue(), ctx.Event()
        procs = [ctx.Process(target=_probe, args=(url, probe_every_s, duration_s, go, q), daemon=True)]
        if clients:
            procs.append(ctx.Process(target=_flood, args=(url, clients, duration_s, go, q), daemon=True))
        for p in procs:
            p.start()
        for _ in procs:  # every process started (its imports take seconds) before the clock starts
            q.get(timeout=120)
        go.set()
        got = [q.get(timeout=duration_s + 120) for _ in procs]
        for p in procs:
            p.join(30)
        res["stop_latency_s"] = next(g for g in got if isinstance(g, list))
        res["requests"] = next((g for g in got if isinstance(g, dict)), {})
        # each answered probe is on its way to the loop's state: counted there before the real stop
        answered = sum(1 for x in res["stop_latency_s"] if x is not None)
        until = time.monotonic() + 30
        while state.probes < answered and time.monotonic() < until:
            time.sleep(0.01)
        state.probing = False
        t0 = time.perf_counter()
        r = httpx.post(f"{url}/stop", timeout=10)
        res["final_stop"] = {"status": r.status_code, "answer_ms": U.to_ms(time.perf_counter() - t0)}

    def echo_url(line: str) -> None:
        if line.startswith("api: "):
            urls.append(line[5:].strip())
        echo(line)

    t = threading.Thread(target=drive, name="bench-api", daemon=True)
    t.start()
    stats = run_daemon(cfg, out, echo=echo_url, state=state)
    t.join(60)
    period = cfg.period
    keys = ("steps", "deadline_misses", "overruns", "skipped_periods", "step_ms_median", "step_ms_p99",
            "tick_ms_p99", "jitter_ms_p99", "faults", "end_reason", "safe_exit")
    total = sum(v for k, v in res.get("requests", {}).items() if isinstance(v, int))
    return {"clients": clients, "daemon": {k: stats.get(k) for k in keys},
            "requests": {str(k): v for k, v in sorted(res.get("requests", {}).items(), key=str)},
            "requests_per_s": total / duration_s, "stop_probes_taken": state.probes,
            "stop_latency": _latency(res.get("stop_latency_s", []), period), "final_stop": res.get("final_stop"),
            "period_ms": U.to_ms(period)}


def run_api_bench(config: Path, out: Path, duration_s: float, clients: int, probe_every_s: float = 0.05,
                  overwrite: bool = False, argv: list | None = None, echo=print) -> dict:
    """Run the bench (module doc) into ``out``; returns api.json's content."""
    with run_dir(out, command="bench api", argv=argv, scenario_path=config, overwrite=overwrite) as tmp:
        runs = {}
        for name, n in (("quiet", 0), ("loaded", clients)):
            echo(f"{name}: {n} clients for {duration_s:g} s")
            runs[name] = _one_run(config, tmp / name, duration_s, n, probe_every_s, echo)
        q, ld = runs["quiet"], runs["loaded"]
        verdicts = {
            # past the controller's warm-up (its first solves): the start-up's misses are the same in both
            "no_deadline_miss_added": ld["daemon"]["overruns"] <= q["daemon"]["overruns"],
            "stop_within_a_period": all(r["stop_latency"]["within_period"] == r["stop_latency"]["n"]
                                        and r["final_stop"] and r["final_stop"]["status"] == 200
                                        for r in runs.values()),
            "no_fault": not q["daemon"]["faults"] and not ld["daemon"]["faults"],
        }
        res = {"config": str(config), "duration_s": duration_s, "clients": clients, "probe_every_s": probe_every_s,
               "runs": runs, "verdicts": verdicts}
        (tmp / "api.json").write_text(json.dumps(res, indent=1) + "\n")
    return res
