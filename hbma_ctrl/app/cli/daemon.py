"""``hbma-ctrl daemon CONFIG.toml``: the rig daemon (docs/tutorials/rig.md).

Registered by :mod:`hbma_ctrl.app.cli.main` through :func:`register`. Reads the configuration (a scenario
file with a [daemon] table; flags override its keys), builds the runtime loop, the rig link, the
safety monitor, the run log and the API, and runs :class:`hbma_ctrl.app.daemon.loop.DaemonLoop`
until the duration, ``POST /stop``, SIGINT or SIGTERM (each writes the safe command first). The
results directory goes through :func:`hbma_ctrl.app.outputs.run_dir`: while running, the run log is
in the temporary directory the command prints; at the end the directory becomes ``--out`` with
``daemon_stats.json``, ``metrics.json`` and ``manifest.json``.

Bad configuration or flags: one ``error: ...`` line, exit 2, before the rig is touched. A lost rig
link or a protocol version mismatch: the safe command, then one line, exit 2. A run that ends in
the safe state after a fault: exit 1.
"""

from __future__ import annotations

import signal
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

# the daemon (the runtime loop and its roles, fastapi and uvicorn, the rig link) is imported by the
# commands when they run
from hbma_ctrl.app.cli.args import ReportDir, check_range, finish_bench
from hbma_ctrl.app.daemon.run import link_errors, run_daemon
from hbma_ctrl.app.outputs import (
    OVERWRITE_HELP,
    cli_argv,
    default_out,
    run_dir,
)

__all__ = ["register"]


def _check_bench(config: Path, positive: dict) -> None:
    """A daemon bench's flags that must be finite and > 0 ({flag: value}) and its configuration on the
    simulated rig: a bad one is one error line before anything runs."""
    from hbma_ctrl.app.daemon.config import load_config

    for name, v in positive.items():
        if not (v > 0 and v < float("inf")):
            raise ValueError(f"{name} = {v:g} must be > 0")
    load_config(config, {"--rig": "sim"})


def daemon(
    config: Annotated[Path, typer.Argument(help="scenario file with a [daemon] table (CONFIG.toml)")],
    rig: Annotated[Optional[str], typer.Option("--rig", help="sim | serial:PORT (overrides [daemon] rig)")] = None,
    speed: Annotated[Optional[float], typer.Option("--speed", help="rig seconds per wall second (sim only)")]
    = None,
    duration_s: Annotated[Optional[float], typer.Option("--duration-s", help="rig time to run, s (default: until "
                                                                             "stopped)")] = None,
    api: Annotated[Optional[str], typer.Option("--api", help="API address HOST:PORT (port 0 = any free)")] = None,
    allow_remote: Annotated[bool, typer.Option("--allow-remote", help="let the API bind a non-loopback address "
                                                                      "(needs --token)")] = False,
    token: Annotated[Optional[str], typer.Option("--token", help="bearer token every API request must carry")]
    = None,
    board_controller: Annotated[bool, typer.Option("--board-controller", help="the rig's board runs the "
                                                   "controller (a hosted firmware): send targets, log its "
                                                   "reports (needs --rig serial:PORT)")] = False,
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="results directory (default runs/<name>)")]
    = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
) -> None:
    """Run the observer and controller in a fixed-rate loop on a simulated or serial rig."""
    from hbma_ctrl.app.daemon.config import load_config

    flags = {"--rig": rig, "--speed": speed, "--duration-s": duration_s, "--api": api,
             "--allow-remote": allow_remote, "--token": token, "--board-controller": board_controller}
    cfg = load_config(config, flags)
    dest = out or default_out(cfg.scenario.name)
    try:
        stats = run_daemon(cfg, dest, overwrite=overwrite, argv=cli_argv())
    except (ValueError, FileNotFoundError, KeyboardInterrupt):
        raise
    except Exception as exc:  # noqa: BLE001 - one line, no traceback: the loop already sent the safe command
        partial = getattr(exc, "partial_results", None)
        where = f"; partial results in {partial}" if partial else ""
        what = f"rig link: {exc}" if isinstance(exc, link_errors()) else \
            f"the loop stopped on {type(exc).__name__}: {exc}"
        raise ValueError(f"{what} (the safe command was sent){where}") from None
    faults = stats.get("faults") or {}
    typer.echo(f"daemon: {stats['steps']} steps, {stats['deadline_misses']} deadline misses, step p99 "
               f"{stats['step_ms_p99'] or float('nan'):.2f} ms, max pressure "
               f"{stats['max_pressure_kpa'] or float('nan'):.2f} / {stats['pressure_limit_kpa']:g} kPa, "
               f"faults {faults or 'none'}, safe exit {stats['safe_exit']}, ended by {stats['end_reason']}; "
               f"wrote {dest}")
    if faults:
        raise typer.Exit(1)
    if stats["end_reason"] in ("SIGINT", "SIGTERM", "SIGHUP"):  # a complete run, ended by a signal
        raise typer.Exit(128 + signal.Signals[stats["end_reason"]])

def bench_soak(
    config: Annotated[Path, typer.Argument(help="daemon configuration (CONFIG.toml)")]
    = Path("scenarios/daemon_robot.toml"),
    duration_s: Annotated[float, typer.Option("--duration-s", help="rig time to run, s (> 0)")] = 3600.0,
    speed: Annotated[float, typer.Option("--speed", help="rig seconds per wall second (> 0)")] = 20.0,
    every_s: Annotated[float, typer.Option("--setpoint-every-s", help="rig time between random setpoints, "
                                                                    "s (> 0)")] = 60.0,
    seed: Annotated[int, typer.Option("--seed", help="seed of the random setpoints")] = 1,
    out: Annotated[Path, typer.Option("--out", "-o", help="results directory")] = Path("runs/bench_soak"),
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
    replay: Annotated[bool, typer.Option("--replay/--no-replay",
                                         help="when a tick over the period is not inside a machine pause "
                                              "the bench's witness saw, re-time it in a lockstep replay of "
                                              "the run (same setpoints, same state): one the replay does "
                                              "not repeat is the machine's")] = True,
    report: ReportDir = None,
) -> None:
    """The daemon on the simulated rig for a long run, setpoints sent through its API: faults, tick
    times, pressure limit, memory (soak.json)."""
    from hbma_ctrl.app.bench.soak import run_soak

    _check_bench(config, {"--duration-s": duration_s, "--speed": speed, "--setpoint-every-s": every_s})
    from hbma_ctrl.app.bench.report import open_report

    rep = open_report(report, "soak", cli_argv())  # --report checked before the run
    res = run_soak(config, out, duration_s, speed, every_s, seed, overwrite=overwrite, argv=cli_argv(),
                   echo=lambda s: print(s, file=sys.stderr, flush=True), replay=replay)
    st = res["daemon_stats"]
    failed = [k for k, ok in res["verdicts"].items() if not ok]
    typer.echo(f"soak: {st.get('rig_time_s', 0):.0f} s of rig time in {st.get('wall_s', 0):.0f} s, "
               f"{res['setpoints_accepted']}/{res['setpoints_sent']} setpoints accepted, tick median "
               f"{st.get('tick_ms_median') or float('nan'):.2f} / p99 {st.get('tick_ms_p99') or float('nan'):.2f} ms, "
               f"{st.get('steps_over_period')} over the period"
               + (f" ({res['ticks_over_period_machine']} the machine's: inside a pause of the whole "
                  "machine or not repeated by the replay)" if res.get("ticks_over_period") else "")
               + ", max pressure "
               f"{st.get('max_pressure_kpa') or float('nan'):.1f} / {st.get('pressure_limit_kpa')} kPa, RSS "
               f"{st.get('rss_mb_start') or float('nan'):.1f} -> {st.get('rss_mb_end') or float('nan'):.1f} MB, faults {st.get('faults') or 'none'}: "
               f"{'passed' if not failed else 'FAILED ' + ', '.join(failed)}; wrote {out / 'soak.json'}")
    if rep:
        from hbma_ctrl.app.bench.pages import soak_page

        typer.echo(f"wrote {rep.write(soak_page(res))}")
    if failed:
        raise typer.Exit(1)

def bench_drills(
    config: Annotated[Path, typer.Argument(help="daemon configuration (CONFIG.toml)")]
    = Path("scenarios/daemon_robot.toml"),
    drills: Annotated[int, typer.Option("--drills", help="how many drills (>= 1)")] = 20,
    seed: Annotated[int, typer.Option("--seed", help="seed of the drills' times, chambers and setpoints")] = 1,
    kind: Annotated[str, typer.Option("--kind", help="the fault injected ([[daemon.fault]] kind)")] = "leak",
    value: Annotated[Optional[float], typer.Option(
        "--value", help="the fault's value in its key's units (leak / stuck valves: duty 0-1, default 1 "
                        "for leak and stuck_outlet, 0 for stuck_inlet; offset, out_of_range: kPa, required)")] = None,
    after_s: Annotated[float, typer.Option("--after-s", help="rig time run after the injection, s (> 0)")] = 1.0,
    every_s: Annotated[float, typer.Option("--setpoint-every-s", help="rig time between random setpoints, s "
                                                                    "(0 = the file's targets)")] = 5.0,
    from_s: Annotated[float, typer.Option("--from-s", help="earliest injection, rig time s")] = 1.0,
    to_s: Annotated[float, typer.Option("--to-s", help="latest injection, rig time s")] = 20.0,
    out: Annotated[Path, typer.Option("--out", "-o", help="results directory")] = Path("runs/bench_drills"),
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
    report: ReportDir = None,
) -> None:
    """Many fault drills (one fault on a random chamber at a random time) through the daemon's own loop,
    monitor and runner on the simulated rig: how many are found, by which test, how fast, and the
    false alarms before them (drills.json)."""
    from hbma_ctrl.app.bench.drills import check_drills, run_drills

    check_range("--drills", drills, 1, 10000)
    if not (every_s >= 0.0 and every_s < float("inf")):
        raise ValueError(f"--setpoint-every-s = {every_s:g} must be >= 0 s (0 = the file's targets)")
    _check_bench(config, {"--after-s": after_s})
    check_drills(kind, value, from_s, to_s)
    from hbma_ctrl.app.bench.report import open_report

    rep = open_report(report, "drills", cli_argv())  # --report checked before the run
    with run_dir(out, command="bench drills", argv=cli_argv(), scenario_path=config, overwrite=overwrite) as tmp:
        res = run_drills(config, tmp, drills, seed, kind, value, after_s, every_s, from_s, to_s,
                         on_drill=lambda r: print(
                             f"  drill {r['drill']}: {r['chamber']} at {r['start_s']:.2f} s: "
                             + ("FALSE ALARM before it, " + r["cause"] if r["false_alarm"] else
                                f"{r['found']} after {r['delay_s']:.2f} s" if r["found"] else
                                "not found" + (f" ({r['other_fault']})" if r["other_fault"] else "")),
                             file=sys.stderr, flush=True))
    kinds = ", ".join(f"{k} {v}" for k, v in res["found_by_kind"].items()) or "none"
    delay = ("" if res["delay_s_median"] is None else
             f", delay median {res['delay_s_median']:.2f} s, max {res['delay_s_max']:.2f} s")
    typer.echo(f"drills ({kind}): found {res['found']} of {res['judged']} ({kinds}){delay}; "
               f"false alarms {res['false_alarms']}; wrote {out / 'drills.json'}")
    if rep:
        from hbma_ctrl.app.bench.pages import drills_page

        typer.echo(f"wrote {rep.write(drills_page(res))}")


def bench_poses(
    config: Annotated[Path, typer.Argument(help="daemon configuration (CONFIG.toml)")]
    = Path("scenarios/daemon_robot.toml"),
    duration_s: Annotated[float, typer.Option("--duration-s", help="rig time to run, s (> 0)")] = 600.0,
    every_s: Annotated[float, typer.Option("--setpoint-every-s", help="rig time between random setpoints, "
                                                                    "s (> 0)")] = 10.0,
    seed: Annotated[int, typer.Option("--seed", help="seed of the random setpoints (as bench soak's)")] = 1,
    target_rate: Annotated[Optional[float], typer.Option(
        "--target-rate-mm-s", help="robot targets' rate, mm/s (0 = steps; default: the file's, else the "
                                   "daemon's 3)")] = None,
    out: Annotated[Path, typer.Option("--out", "-o", help="results directory")] = Path("runs/bench_poses"),
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
    report: ReportDir = None,
) -> None:
    """Many random setpoint changes through the daemon's runner, sim rig and safety monitor in lockstep:
    the highest reading after each change, how many cross the pressure limit and the cap, and every
    fault, the monitor re-armed after each (poses.json)."""
    from hbma_ctrl.app.bench.poses import run_poses

    check_range("--target-rate-mm-s", target_rate, 0.0, 1000.0, unit="mm/s")
    _check_bench(config, {"--duration-s": duration_s, "--setpoint-every-s": every_s})
    from hbma_ctrl.app.bench.report import open_report

    rep = open_report(report, "poses", cli_argv())  # --report checked before the run
    with run_dir(out, command="bench poses", argv=cli_argv(), scenario_path=config, overwrite=overwrite) as tmp:
        res = run_poses(config, tmp, duration_s, every_s, seed, target_rate,
                        on_change=lambda c: print(f"  {c['t_s']:8.2f} s: peak {c['peak_kpa']:.2f} kPa "
                                                  f"({c['chamber']})", file=sys.stderr, flush=True))
    typer.echo(f"poses: {res['changes']} changes in {res['wall_s']:.0f} s, target rate {res['target_rate_mm_s']} mm/s; "
               f"peak reading max {res['peak_kpa_max']:.2f} kPa, p90 {res['peak_kpa_p90']:.2f}; over the "
               f"{res['pressure_limit_kpa']:g} kPa limit {res['over_limit']}, over the {res['cap_kpa']:g} kPa cap "
               f"{res['over_cap']}; faults {len(res['faults'])}; wrote {out / 'poses.json'}")
    if rep:
        from hbma_ctrl.app.bench.pages import poses_page

        typer.echo(f"wrote {rep.write(poses_page(res))}")


def bench_api(
    config: Annotated[Path, typer.Argument(help="daemon configuration (CONFIG.toml)")]
    = Path("scenarios/daemon_chamber.toml"),
    duration_s: Annotated[float, typer.Option("--duration-s", help="wall time of each run, s (> 0)")] = 60.0,
    clients: Annotated[int, typer.Option("--clients", help="API clients at full rate in the loaded run")] = 100,
    out: Annotated[Path, typer.Option("--out", "-o", help="results directory")] = Path("runs/bench_api"),
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
    report: ReportDir = None,
) -> None:
    """The daemon on the simulated rig in real time, quiet and with many loopback API clients at full
    rate: deadline misses, step p99 and /stop answer times side by side (api.json)."""
    from hbma_ctrl.app.bench.api import run_api_bench

    check_range("--clients", clients, 1, 1000)
    _check_bench(config, {"--duration-s": duration_s})
    from hbma_ctrl.app.bench.report import open_report

    rep = open_report(report, "api", cli_argv())  # --report checked before the run
    res = run_api_bench(config, out, duration_s, clients, overwrite=overwrite, argv=cli_argv(),
                        echo=lambda s: print(s, file=sys.stderr, flush=True))
    for name, r in res["runs"].items():
        d, sl = r["daemon"], r["stop_latency"]
        typer.echo(f"{name} ({r['clients']} clients, {r['requests_per_s']:.0f} requests/s): {d['steps']} steps, "
                   f"{d['deadline_misses']} deadline misses, {d['overruns']} overruns, step p99 "
                   f"{d['step_ms_p99'] or float('nan'):.2f} ms; /stop {sl['within_period']}/{sl['n']} within "
                   f"{r['period_ms']:g} ms (median {sl['median_ms'] or float('nan'):.2f}, p99 "
                   f"{sl['p99_ms'] or float('nan'):.2f}, max {sl['max_ms'] or float('nan'):.2f} ms)")
    from hbma_ctrl.app.bench.pages import api_page

    finish_bench("api", res["verdicts"], out / "api.json", rep, lambda: api_page(res))


def bench_live(
    config: Annotated[Path, typer.Argument(help="daemon configuration (CONFIG.toml)")]
    = Path("scenarios/daemon_chamber.toml"),
    duration_s: Annotated[float, typer.Option("--duration-s", help="time of each run, s (> 0; speed 1)")] = 600.0,
    rate_hz: Annotated[float, typer.Option("--rate-hz", help="updates per second the page asks for (its "
                                                            "default: 5)")] = 5.0,
    sample_every_s: Annotated[float, typer.Option("--sample-every-s", help="wall time between two readings of "
                                                                          "the page, s (> 0)")] = 1.0,
    browser_nice: Annotated[int, typer.Option("--browser-nice", help="run the browser this much below the "
                                                                     "daemon's priority (nice, 0-19)")] = 0,
    out: Annotated[Path, typer.Option("--out", "-o", help="results directory")] = Path("runs/bench_live"),
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
    report: ReportDir = None,
) -> None:
    """The daemon on the simulated rig in real time, without and with its live page open in headless
    Chromium: deadline misses and step p99 side by side, and the page's values against the run log
    (live.json)."""
    from hbma_ctrl.app.bench.browser import chromium_path
    from hbma_ctrl.app.bench.live import run_live_bench
    from hbma_ctrl.app.schema.api import LIVE_RATE_HZ

    check_range("--rate-hz", rate_hz, LIVE_RATE_HZ[1], LIVE_RATE_HZ[2], unit="Hz")
    check_range("--browser-nice", browser_nice, 0, 19)
    _check_bench(config, {"--duration-s": duration_s, "--sample-every-s": sample_every_s})
    if chromium_path() is None:
        raise ValueError("bench live needs Chromium: apt-get install chromium")
    from hbma_ctrl.app.bench.report import open_report

    rep = open_report(report, "live", cli_argv())  # --report checked before the run
    res = run_live_bench(config, out, duration_s, rate_hz, sample_every_s, overwrite=overwrite, argv=cli_argv(),
                         echo=lambda s: print(s, file=sys.stderr, flush=True), browser_nice=browser_nice)
    for name, r in res["runs"].items():
        d = r["daemon"]
        line = (f"{name.replace('_', ' ')}: {d['steps']} steps, {d['deadline_misses']} deadline misses, "
                f"{d['overruns']} overruns, step p99 {d['step_ms_p99'] or float('nan'):.2f} ms, daemon CPU "
                f"{r['daemon_cpu_s']:.1f} s")
        if r["client"] == "stream":
            line += f"; {r['events']} events read"
        if r["client"] == "page":
            line += f"; browser CPU {r['browser_cpu_s'] or float('nan'):.1f} s"
            line += (f"; page: {r['matching_log']}/{r['compared']} readings equal to the log, lag median "
                     f"{r['lag_periods_median'] if r['lag_periods_median'] is not None else float('nan'):.0f} / max "
                     f"{r['lag_periods_max'] if r['lag_periods_max'] is not None else float('nan'):.0f} periods "
                     f"(updates every {r['every_steps']} periods)")
        if r.get("client_error"):
            line += f"; the client failed: {r['client_error']}"
        typer.echo(line)
    from hbma_ctrl.app.bench.pages import live_page

    finish_bench("live", res["verdicts"], out / "live.json", rep, lambda: live_page(res))


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``daemon`` to the top-level app (called by :mod:`hbma_ctrl.app.cli.main`)."""
    app.command("daemon")(daemon)
    bench_app.command("soak")(bench_soak)
    bench_app.command("drills")(bench_drills)
    bench_app.command("poses")(bench_poses)
    bench_app.command("api")(bench_api)
    bench_app.command("live")(bench_live)
