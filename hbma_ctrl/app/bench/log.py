"""``hbma-ctrl bench log``: what writing ``log.mcap`` costs the daemon's loop, and whether the log holds
every period.

The daemon runs on the simulated rig the same configuration, duration and speed ``repeats`` times
with the MCAP log and as many without it (the CSV run log only), alternating (without, with,
without, ...) so that a change in the machine's load falls on both alike, the API on a free loopback
port with no client. Per run: steps, deadline
misses, overrun warnings, step time median and p99 (ms, wall clock: the whole period's work,
simulated plant included) and tick p99 (the runtime tick alone). For each run with the log, the
messages on each per-period topic (``/readings``, ``/estimates``, ``/targets``, ``/commands``,
``/loop``) against the periods logged (the steps and the final row written at the stop), the items
dropped on a full queue, and the median and p99 of the loop's time handing a period to the log (us,
wall clock and the loop thread's CPU time: the log's whole cost on the loop's thread; its writer
thread competes for the CPU and the interpreter, which the step times show).

Writes ``log.json``: ``runs`` (each run's numbers), ``medians`` (per variant, the median over its runs
of each number) and the verdicts ``every_period_logged`` (every topic of every run with the log holds
one message per period, none dropped) and ``no_fault``. Each run's results directory is under ``out``.
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path

from hbma_ctrl.app.logs.reader import message_counts, read_mcap
from hbma_ctrl.app.outputs import run_dir

__all__ = ["run_log_bench", "log_completeness", "PERIOD_TOPICS"]

#: the topics with one message per logged period
PERIOD_TOPICS = ("/readings", "/estimates", "/targets", "/commands", "/loop")

_KEYS = ("steps", "deadline_misses", "overruns", "step_ms_median", "step_ms_p99", "tick_ms_p99", "wall_s")


def log_completeness(folder: Path, stats: dict) -> dict:
    """Whether ``folder/log.mcap`` holds every period of the daemon run whose ``daemon_stats.json`` is
    ``stats``: ``periods_logged`` (the steps and the row written at the stop), ``messages`` on each
    per-period topic (read with the mcap library's reader: the summary's counts, or every message of a
    log cut short), ``dropped`` (items lost on a full queue), the handoff times (us), ``log_bytes`` and
    ``complete`` (every topic holds one message per period, none dropped)."""
    counts = message_counts(folder / "log.mcap")
    if counts is None:  # no summary: the file was not finished
        c = read_mcap(folder / "log.mcap")
        counts = {t: c.count(t) for t in PERIOD_TOPICS}
    periods = int(stats["steps"]) + 1  # and the row written at the stop
    row = {"periods_logged": periods, "messages": {t: counts.get(t, 0) for t in PERIOD_TOPICS},
           "dropped": stats.get("log_dropped")}
    for key in ("handoff_us_median", "handoff_us_p99", "handoff_cpu_us_median", "handoff_cpu_us_p99"):
        row[key] = stats.get(f"log_{key}")
    row["log_bytes"] = (folder / "log.mcap").stat().st_size
    row["complete"] = all(n == periods for n in row["messages"].values()) and not row["dropped"]
    return row


def _one(cfg, folder: Path, mcap: bool, argv, echo) -> dict:
    from hbma_ctrl.app.daemon.run import run_daemon

    stats = run_daemon(cfg, folder, overwrite=True, argv=argv, echo=echo, mcap=mcap)
    row = {k: stats.get(k) for k in _KEYS}
    row["faults"] = stats.get("faults") or {}
    row["mcap"] = mcap
    if mcap:
        row.update(log_completeness(folder, stats))
    return row


def run_log_bench(config: Path, out: Path, duration_s: float, speed: float, repeats: int = 2,
                  overwrite: bool = False, argv=None, echo=None) -> dict:
    """Run the bench of the module doc into ``out``; returns log.json's content."""
    from hbma_ctrl.app.daemon.config import load_config

    # the API on a free port: no client asks, and a fixed port may be another daemon's
    cfg = load_config(config, {"--rig": "sim", "--speed": speed, "--duration-s": duration_s, "--api": "127.0.0.1:0"})
    with run_dir(out, command="bench log", argv=argv, scenario_path=config, overwrite=overwrite) as tmp:
        runs = {}
        for k in range(int(repeats)):
            for mcap in (False, True):
                name = f"{'mcap' if mcap else 'csv_only'}_{k + 1}"
                runs[name] = _one(cfg, tmp / name, mcap, argv, echo)
        medians = {}
        for variant in ("csv_only", "mcap"):
            rows = [r for n, r in runs.items() if n.startswith(variant)]
            medians[variant] = {k: statistics.median(r[k] for r in rows if r[k] is not None)
                                for k in _KEYS if any(r[k] is not None for r in rows)}
        res = {"config": str(config), "duration_s": duration_s, "speed": speed, "repeats": int(repeats),
               "runs": runs, "medians": medians,
               "verdicts": {"every_period_logged": all(r["complete"] for r in runs.values() if r["mcap"]),
                            "no_fault": not any(r["faults"] for r in runs.values())}}
        (tmp / "log.json").write_text(json.dumps(res, indent=1) + "\n")
    return res
