"""``hbma-ctrl bench live``: the rig daemon's loop with its live page open in headless Chromium, beside the
same run without.

The daemon runs in this process on the simulated rig in real time (speed 1, as a real rig runs), with
its API on a free loopback port, three times for ``duration_s`` each: without a client
(``without_page``); with a process reading ``GET /stream`` at ``rate_hz`` as the page does, without a
browser (``stream_only``: the server's share of the cost); and with the live page open in headless
Chromium (Debian's ``chromium``) asking for ``rate_hz`` updates per second (``with_page``). The
client starts before the daemon (a browser's start-up is not the page's cost) and opens the page as
soon as the API answers. A watcher, a process of its own, drives the browser over the DevTools pipe
and every ``sample_every_s`` reads what the page shows (the loop's step count, time and every
chamber's height, pressures and command, as displayed), then the loop's step count from
``GET /status``.

Writes ``live.json``: per run the daemon's deadline misses, overrun warnings, step, tick and jitter
p99 (ms), faults and the CPU time of the daemon's process (s); for the page, the browser's CPU time
(all its processes, s) and how the samples compare with the run log: ``matching_log`` (each shown
value equals the log's row of the step the page shows, to the digits shown) and ``lag_periods`` (how
far the loop had gone past the status the page showed when ``GET /status`` answered, in loop periods,
beside the stream's decimation ``every_steps``). Verdicts: ``no_deadline_miss_added`` (overrun
warnings with the page at most those without: misses past the controller's warm-up, whose first
solves miss alike in both runs), ``page_matches_log``, ``page_within_one_decimation_period`` (every
sample's lag at most one decimation period, plus the one period the loop may publish while the
reading is in flight) and ``no_fault``. The daemon's own results are in ``without_page/``,
``stream_only/`` and ``with_page/``. On a machine whose cores are all busy, a browser's rendering
competes with the loop for them: the numbers say what this machine gave, not what a rig PC with a
core to spare gives; ``browser_nice`` runs the browser that much below the daemon's priority (as
``nice`` does), to measure what a page costs the loop when its browser runs at a lower priority.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import queue
import resource
import socket
import time
from pathlib import Path

import numpy as np

from hbma_ctrl.app.outputs import run_dir

__all__ = ["DISPLAYED", "compare_with_log", "run_live_bench"]

#: the chamber values the page shows: its key -> (run log column stem and unit, the log's value per
#: shown unit, digits shown)
DISPLAYED = {"h_mm": ("h_est", "mm", 1.0, 3), "p_kpa": ("p", "kpa", 1.0, 2), "p_est_kpa": ("p_est", "kpa", 1.0, 2),
             "speed_pct": ("speed", "1", 100.0, 1), "inlet_duty": ("inlet", "1", 1.0, 2),
             "outlet_duty": ("outlet", "1", 1.0, 2)}

_READ_PAGE = """(() => {
  const cell = (k, i) => document.querySelector(i === undefined ? `[data-k="${k}"]` : `[data-k="${k}"][data-i="${i}"]`);
  const out = {mode: cell("mode").textContent, t_s: cell("t_s").textContent, steps: cell("steps").textContent,
               conn: document.getElementById("conn").textContent, chambers: []};
  for (let i = 0; cell("h_mm", i); i++) {
    const c = {};
    for (const k of %s) c[k] = cell(k, i).textContent;
    out.chambers.push(c);
  }
  return out;
})()""" % json.dumps(list(DISPLAYED))


def _tree_cpu_s(root: int) -> float:
    """CPU time (user + system, s) of process ``root`` and all its descendants alive now (/proc)."""
    stats, parent = {}, {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            f = (d / "stat").read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        parent[int(d.name)] = int(f[1])
        stats[int(d.name)] = (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")
    total = 0.0
    for pid, cpu in stats.items():
        p = pid
        while p > 1 and p != root:
            p = parent.get(p, 0)
        total += cpu if p == root else 0.0
    return total


def _wait_api(http, until: float) -> None:
    """Poll ``GET /health`` until the daemon's API answers (RuntimeError past ``until``, monotonic s)."""
    import httpx

    while True:
        try:
            if http.get("/health").status_code == 200:
                return
        except httpx.HTTPError:
            pass
        if time.monotonic() > until:
            raise RuntimeError("the daemon's API did not answer")
        time.sleep(0.2)


def _watch(url: str, rate_hz: float, every_s: float, duration_s: float, nice: int, out) -> None:
    """Start headless Chromium (before the daemon: its start-up is not the page's cost), open the live page
    once the API answers, read it every ``every_s`` s until the daemon stops; put "started", then the
    result (samples, the browser's CPU time) or an error line."""
    import httpx

    from hbma_ctrl.app.bench.browser import Browser

    samples: list = []
    try:
        with Browser(nice=nice) as b, httpx.Client(base_url=url, timeout=5) as http:
            b.send("Browser.getVersion")  # up and answering
            out.put("started")
            until = time.monotonic() + duration_s + 300
            _wait_api(http, until)
            page = b.open(f"{url}/?rate_hz={rate_hz:g}")
            b.wait_for(page, "document.querySelector('[data-k=\"h_mm\"][data-i=\"0\"]') !== null", timeout=120)
            cpu0, t0 = _tree_cpu_s(b._proc.pid), time.monotonic()
            nxt = time.monotonic()
            while time.monotonic() < until:
                time.sleep(max(0.0, nxt - time.monotonic()))
                nxt += every_s
                shown = b.evaluate(page, _READ_PAGE)
                try:
                    status = http.get("/status").json()
                except httpx.HTTPError:  # the daemon has ended and its API with it
                    break
                shown["status_steps"] = status["loop"]["steps"]
                shown["names"] = [c.get("name") or str(c["index"]) for c in status["chambers"]]
                samples.append(shown)
                if shown["mode"] == "stopped" or status["mode"] == "stopped":
                    break
            cpu = {"browser_cpu_s": _tree_cpu_s(b._proc.pid) - cpu0, "browser_wall_s": time.monotonic() - t0}
    except Exception as exc:  # noqa: BLE001 - the bench reports why the page could not be watched
        out.put(f"{type(exc).__name__}: {exc}")
        return
    out.put({"samples": samples, **cpu})


def _listen(url: str, rate_hz: float, duration_s: float, out) -> None:
    """Read ``GET /stream`` at ``rate_hz`` as the page does, without a browser, until the daemon stops; put
    "started", then {"events": n} or an error line."""
    import httpx

    out.put("started")
    n = 0
    try:
        with httpx.Client(base_url=url, timeout=httpx.Timeout(10.0, read=60.0)) as http:
            _wait_api(http, time.monotonic() + duration_s + 300)
            with http.stream("GET", "/stream", params={"rate_hz": rate_hz}) as r:
                for line in r.iter_lines():
                    n += line.startswith("data:")
    except Exception as exc:  # noqa: BLE001 - the end of the daemon may cut the stream
        if n == 0:
            out.put(f"{type(exc).__name__}: {exc}")
            return
    out.put({"events": n})


def compare_with_log(samples: list, columns: list[str], rows: list[list[str]]) -> list[dict]:
    """Each sample of the page against the run log's row of the step it shows (row ``steps - 1``): per
    sample the step, whether every shown value equals the log's to the digits shown (``matches_log``),
    the values that do not (``differs``) and ``lag_periods`` (the loop's steps at ``GET /status``
    minus the step shown)."""
    col = {c: i for i, c in enumerate(columns)}
    out = []
    for s in samples:
        try:
            steps = int(s["steps"])
        except (TypeError, ValueError):
            continue
        if not 1 <= steps <= len(rows) or s.get("mode") != "running":
            continue
        row = rows[steps - 1]
        differs = []
        if abs(float(row[col["t_s"]]) - float(s["t_s"])) > 0.005 + 5e-5:
            differs.append(f"t_s shown {s['t_s']}, logged {row[col['t_s']]}")
        for i, (name, shown) in enumerate(zip(s["names"], s["chambers"])):
            for key, (stem, unit, scale, digits) in DISPLAYED.items():
                cell = row[col[f"{stem}_{name}_{unit}"]]
                text = shown[key]
                if cell == "" or text == "-":
                    if (cell == "") != (text == "-"):
                        differs.append(f"{key}[{i}] shown {text}, logged {cell or 'nothing'}")
                    continue
                # the log keeps 4 decimals of its unit, the page ``digits`` of its own
                tol = 0.5 * 10.0 ** -digits + 0.5e-4 * scale + 1e-9
                if abs(float(text) - float(cell) * scale) > tol:
                    differs.append(f"{key}[{i}] shown {text}, logged {float(cell) * scale:g}")
        out.append({"steps": steps, "matches_log": not differs, "differs": differs,
                    "lag_periods": int(s["status_steps"]) - steps})
    return out


def _every_steps(samples: list) -> int | None:
    for s in reversed(samples):
        words = str(s.get("conn", "")).split()
        if len(words) > 1 and words[0] == "every" and words[1].isdigit():
            return int(words[1])
    return None


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _one_run(config: Path, out: Path, duration_s: float, client: str | None, rate_hz: float, every_s: float,
             echo, browser_nice: int = 0) -> dict:
    """One daemon run of ``duration_s`` (rig time = wall time, speed 1); ``client``: None, "stream" (a
    reader of the stream alone) or "page" (the page in Chromium), started before the daemon."""
    from hbma_ctrl.app.daemon.config import load_config
    from hbma_ctrl.app.daemon.run import run_daemon
    from hbma_ctrl.app.daemon.runlog import read_run_log

    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    cfg = load_config(config, {"--rig": "sim", "--speed": 1.0, "--api": f"127.0.0.1:{port}",
                               "--duration-s": duration_s})
    proc = q = None
    if client is not None:
        ctx = mp.get_context("spawn")  # a fresh interpreter: no copy of this process's threads or GIL
        q = ctx.Queue()
        target, args = (_watch, (url, rate_hz, every_s, duration_s, browser_nice, q)) if client == "page" else \
            (_listen, (url, rate_hz, duration_s, q))
        proc = ctx.Process(target=target, args=args, daemon=True)
        proc.start()
        first = q.get(timeout=180)
        if first != "started":
            raise RuntimeError(f"bench live: the {client} client did not start: {first}")
    ru0 = resource.getrusage(resource.RUSAGE_SELF)
    stats = run_daemon(cfg, out, echo=echo)
    ru1 = resource.getrusage(resource.RUSAGE_SELF)
    got = None
    if proc is not None:
        try:
            got = q.get(timeout=120)
        except queue.Empty:
            got = "no answer from the client"
        proc.join(30)
        if proc.is_alive():
            proc.kill()
    keys = ("steps", "deadline_misses", "overruns", "skipped_periods", "step_ms_median", "step_ms_p99",
            "tick_ms_p99", "jitter_ms_p99", "faults", "end_reason", "safe_exit")
    run = {"client": client or "none", "daemon": {k: stats.get(k) for k in keys}, "period_ms": cfg.period * 1e3,
           "daemon_cpu_s": (ru1.ru_utime + ru1.ru_stime) - (ru0.ru_utime + ru0.ru_stime),
           "client_error": got if isinstance(got, str) else None}
    if client == "stream":
        run["events"] = got.get("events") if isinstance(got, dict) else None
    if client == "page":
        samples = got.get("samples", []) if isinstance(got, dict) else []
        cols, rows = read_run_log(out)
        cmp = compare_with_log(samples, cols, rows)
        lags = np.array([c["lag_periods"] for c in cmp], dtype=float)
        every = _every_steps(samples)
        run.update({"rate_hz": rate_hz, "every_steps": every, "samples": len(samples), "compared": len(cmp),
                    "matching_log": sum(c["matches_log"] for c in cmp),
                    "differences": [d for c in cmp for d in c["differs"]][:20],
                    "lag_periods_median": float(np.median(lags)) if lags.size else None,
                    "lag_periods_max": float(lags.max()) if lags.size else None,
                    "within_one_decimation_period": (int(np.sum(lags <= every + 1)) if every and lags.size else 0),
                    "browser_cpu_s": got.get("browser_cpu_s") if isinstance(got, dict) else None,
                    "browser_wall_s": got.get("browser_wall_s") if isinstance(got, dict) else None})
    return run


def run_live_bench(config: Path, out: Path, duration_s: float, rate_hz: float = 5.0, sample_every_s: float = 1.0,
                   overwrite: bool = False, argv: list | None = None, echo=print, browser_nice: int = 0) -> dict:
    """Run the bench (module doc) into ``out``; returns live.json's content."""
    with run_dir(out, command="bench live", argv=argv, scenario_path=config, overwrite=overwrite) as tmp:
        runs = {}
        for name, client in (("without_page", None), ("stream_only", "stream"), ("with_page", "page")):
            echo(f"{name}: {duration_s:g} s")
            runs[name] = _one_run(config, tmp / name, duration_s, client, rate_hz, sample_every_s, echo, browser_nice)
        q, w = runs["without_page"], runs["with_page"]
        verdicts = {
            # past the controller's warm-up (its first solves): the start-up's misses are the same in both
            "no_deadline_miss_added": w["daemon"]["overruns"] <= q["daemon"]["overruns"],
            "page_matches_log": w["compared"] > 0 and w["matching_log"] == w["compared"],
            "page_within_one_decimation_period": w["compared"] > 0
            and w["within_one_decimation_period"] == w["compared"],
            "no_fault": not any(r["daemon"]["faults"] for r in runs.values()),
        }
        res = {"config": str(config), "duration_s": duration_s, "rate_hz": rate_hz, "sample_every_s": sample_every_s,
               "browser_nice": browser_nice, "runs": runs, "verdicts": verdicts}
        (tmp / "live.json").write_text(json.dumps(res, indent=1) + "\n")
    return res
