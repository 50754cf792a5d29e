"""``hbma-ctrl bench soak``: the rig daemon run for a long time with setpoints sent through its API.

The daemon runs as its own process (``hbma-ctrl daemon CONFIG --rig sim --speed X --duration-s T
--api 127.0.0.1:PORT``), exactly as a user starts it; this process is the API's client. Every
``every_s`` of rig time (read from ``GET /status``) it posts a random target through
``POST /setpoint``: a pose for every layer of a robot (centre 5-8 mm, bend 0-15 deg, any
direction) or a height for every chamber of a single-chamber rig (2-8 mm), drawn from ``seed``.

At the end it judges the daemon's ``daemon_stats.json`` against the soak's criteria (docs/results/soak.md):

- ``no_fault``: no fault of any kind, and the run ended by its duration;
- ``no_tick_over_period``: no runtime tick (estimator, controller, supervisor) whose work takes longer
  than the rig's period (``steps_over_period``: accelerated, by its thread's CPU time, the loop's
  module doc says why; ``deadline_misses`` counts whole steps, simulated plant included, against the
  wall period, which an accelerated simulation may never meet; ``steps_over_period_wall`` counts
  wall-clock ticks over the period, which depend on what else the machine runs). A tick over the
  period is re-timed by :func:`replay_ticks`: the run again in lockstep, the same setpoints at the
  same rig times, so the same readings and the same computation (checked against the run log); one
  whose computation takes less than the period there was the machine's, not the daemon's work (on
  a virtual machine the tick thread's CPU clock ran 10-28 ms over ticks that take 1.5 ms, with
  no preemption, no host steal the guest could see, no page fault and no garbage collection, at
  random places in the tick). The second judge is a witness outside the daemon (:class:`PauseProbe`:
  a thread of the bench's own process that sleeps 1 ms at a time): when the machine stops, every
  process stops, and the witness wakes late. A tick is the machine's when the witness's pause
  overlaps it by at least the tick's excess over the period (:func:`judge_ticks`: without that pause
  the tick would have been within the period), or when the replay says so. Each tick over the period
  is listed in ``ticks_over_period`` (the run's CPU and wall time, the overlapping pause, the
  replay's CPU time and state, and ``machine_by``: which judges found it the machine's) and counted
  in ``ticks_over_period_machine``; the verdict fails on any tick neither judge explains;
- ``pressure_limit_held``: the highest reading at or under the controller's pressure limit;
- ``rss_growth_under_10mb``: resident memory grew by less than 10 MB;
- ``safe_exit``: the safe command was written at the end;
- ``every_period_logged``: the daemon's ``log.mcap`` holds one message per period on every per-period
  topic, none dropped (``log``: :func:`hbma_ctrl.app.bench.log.log_completeness`).

Writes ``soak.json`` (the verdicts, the daemon's stats, the setpoints sent and their replies; ``replay``:
"not needed", "off", "unfinished" while it runs or when it was stopped, "done"), ``setpoints.csv`` and
``machine_pauses.csv`` (every witness gap over 5 ms) beside the daemon's own results (``daemon/``),
through :func:`hbma_ctrl.app.outputs.run_dir`; soak.json is written before a replay starts, so a
stopped replay leaves the witness's verdict.
"""

from __future__ import annotations

import csv
import json
import os
import random
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

from hbma_ctrl.app.bench.log import log_completeness
from hbma_ctrl.app.daemon.loop import COUNTED
from hbma_ctrl.app.daemon.run import LOG_MCAP
from hbma_ctrl.app.daemon.runlog import setpoint_of_event
from hbma_ctrl.app.metrics import json_safe
from hbma_ctrl.app.outputs import run_dir

__all__ = ["run_soak", "soak_verdicts", "random_target", "replay_ticks", "RSS_GROWTH_MAX_MB", "PauseProbe",
           "pauses_at_ticks", "read_events", "judge_ticks"]

#: the soak's memory criterion, MB
RSS_GROWTH_MAX_MB = 10.0


def _raise_interrupt(signum, frame) -> None:
    raise KeyboardInterrupt(signal.Signals(signum).name)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def random_target(rng: random.Random, n_layers: int, n_chambers: int) -> dict:
    """One random setpoint body (edge units) for the robot's layers or the rig's chambers."""
    if n_layers:
        return {"layers": [{"layer": i, "centre_mm": round(rng.uniform(5.0, 8.0), 2),
                            "bend_deg": round(rng.uniform(0.0, 15.0), 1),
                            "direction_deg": round(rng.uniform(-180.0, 180.0), 0)} for i in range(n_layers)]}
    return {"heights_mm": {str(i): round(rng.uniform(2.0, 8.0), 2) for i in range(n_chambers)}}


def lift_budget(runner):
    """The runner's NMPC with its wall-time budget lifted, so that a lockstep run's decisions do not
    depend on this machine's load: for the robot's, (controller, its settings as they were), the
    robot's overruns being forced where a run had them (:func:`replay_ticks`); (None, None) for the
    chamber's (lifted in place: a chamber run does not log its NMPC's overruns, so none is forced) or a
    runner without a budgeted NMPC."""
    from dataclasses import replace

    ctrl = getattr(getattr(runner, "loop", None), "controller", None)
    if hasattr(ctrl, "set_enforce_budget"):
        ctrl.set_enforce_budget(False)
        return None, None
    s = getattr(ctrl, "s", None)
    if not hasattr(ctrl, "_solver") or not getattr(s, "enforce_budget", False) or not s.budget > 0.0:
        return None, None
    # lifted by the switch the NMPC's budget acts through: the replay's settings differ from the run's
    # in it alone, and _forced_outcome turns it back on for a step the run overran in
    ctrl.s = replace(s, enforce_budget=False)
    return ctrl, s


def soak_verdicts(stats: dict, ticks: list | None = None, log: dict | None = None) -> dict:
    """The soak's criteria (module doc) from a daemon_stats.json dict: {name: bool}. ``ticks``: the
    ticks over the period as judged by :func:`judge_ticks` or :func:`replay_ticks`, each with its
    ``machine`` (None: not judged, every one counts). ``log``: the run's log.mcap as judged by
    :func:`hbma_ctrl.app.bench.log.log_completeness` (None: no log, no verdict on it)."""
    rss0, rss1 = stats.get("rss_mb_start"), stats.get("rss_mb_end")
    pmax, plim = stats.get("max_pressure_kpa"), stats.get("pressure_limit_kpa")
    over = stats.get("steps_over_period")
    machine = 0 if ticks is None else sum(1 for t in ticks if t.get("machine"))
    verdicts = {
        "no_fault": not stats.get("faults") and stats.get("end_reason") == "duration",
        "no_tick_over_period": over is not None and over - machine == 0,
        "pressure_limit_held": pmax is not None and plim is not None and pmax <= plim,
        "rss_growth_under_10mb": rss0 is not None and rss1 is not None and rss1 - rss0 < RSS_GROWTH_MAX_MB,
        "safe_exit": bool(stats.get("safe_exit")),
    }
    if log is not None:
        verdicts["every_period_logged"] = bool(log["complete"])
    return verdicts


_SLOW_CPU = re.compile(r"^cpu ([0-9.]+) ms, wall ([0-9.]+) ms")
#: the robot NMPC's step status (the event's end) and its OSQP rho updates in a slow tick's event
_NMPC_STATUS = re.compile(r"nmpc status (.*)$")
_NMPC_RHO = re.compile(r"nmpc rho_updates (\d+)")
_NMPC_ITER = re.compile(r"nmpc iterations (\d+)")
_LATE = re.compile(r"^overrun \([0-9.]+ ms > [0-9.]+ ms\)$")


class _TimeLimited:
    """What OSQP returns when its time limit strikes (before its first iteration, here)."""

    class info:  # noqa: N801 - OSQP's attribute names
        status, iter, rho_updates, solve_time = "run time limit reached", 0, 0, 0.0

    x = y = None


class PauseProbe:
    """A thread of the bench's own process that sleeps 1 ms at a time and records every wake-up more
    than ``min_gap`` s late: (wall clock at the wake-up, epoch s; the gap, s). A pause of the whole
    machine (a virtual machine its host stops) delays every process alike, so a daemon tick over the
    period that falls in such a gap was the machine's, seen from outside the daemon. Keeps at most
    ``cap`` gaps (the longest)."""

    def __init__(self, min_gap: float = 0.005, cap: int = 10000):
        import threading

        self.min_gap, self.cap = float(min_gap), int(cap)
        self.gaps: list = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="pause-probe", daemon=True)

    def _run(self) -> None:
        last = time.monotonic()
        while not self._stop.is_set():
            time.sleep(0.001)
            now = time.monotonic()
            if now - last > self.min_gap:
                self.gaps.append((time.time(), now - last))
                if len(self.gaps) > 2 * self.cap:
                    self.gaps = sorted(self.gaps, key=lambda g: -g[1])[:self.cap]
            last = now

    def start(self) -> "PauseProbe":
        self._thread.start()
        return self

    def stop(self) -> list:
        """Stop; the gaps recorded, in time order."""
        self._stop.set()
        self._thread.join(timeout=1.0)
        return sorted(sorted(self.gaps, key=lambda g: -g[1])[:self.cap])


#: the witness's sleep between wake-ups, s: a gap is this sleep plus the pause
PROBE_SLEEP_S = 0.001
#: how far the logged end of a tick may be from its real end, s (the log's ms stamps and the time
#: it takes to write the event)
_STAMP_TOL_S = 0.002


def read_events(daemon_dir: Path) -> tuple[list, list]:
    """A daemon run's events.csv, read once: the setpoints applied [(rig t s, the applied dict)] and
    its slow ticks and NMPC overruns within the period, a dict each: ``t_s`` (rig time), ``key``
    (the rig time as logged), ``kind``, ``cpu_ms``, ``wall_ms``, ``end_utc`` (the wall clock, epoch
    s, when it was logged just after the tick; None if unreadable), ``counted`` (the event says
    steps_over_period counts it), ``status`` (the NMPC's, or None), ``rho_updates`` and
    ``iterations`` (OSQP's, as it reported them, or None)."""
    from datetime import datetime

    setpoints, ticks = [], []
    with open(daemon_dir / "events.csv", newline="") as fh:
        for row in csv.DictReader(fh):
            if row["kind"] == "setpoint":
                setpoints.append((float(row["t_s"]), setpoint_of_event(row)))
            elif row["kind"] in ("slow_tick", "nmpc_overrun"):
                m = _SLOW_CPU.match(row["cause"])
                if not m:
                    continue
                try:
                    end = datetime.fromisoformat(row["wall_utc"]).timestamp()
                except ValueError:
                    end = None
                st, rho = _NMPC_STATUS.search(row["cause"]), _NMPC_RHO.search(row["cause"])
                its = _NMPC_ITER.search(row["cause"])
                ticks.append({"t_s": float(row["t_s"]), "key": row["t_s"], "kind": row["kind"],
                              "cpu_ms": float(m.group(1)), "wall_ms": float(m.group(2)), "end_utc": end,
                              "counted": COUNTED in row["cause"],
                              "status": st.group(1) if st else None,
                              "rho_updates": int(rho.group(1)) if rho else None,
                              "iterations": int(its.group(1)) if its else None})
    return setpoints, ticks


def over_period(ticks: list, period: float, speed: float) -> list:
    """The ticks of :func:`read_events` the run counted over the period ``period`` (s): those its
    events say it counted; in a log from before the events said so, by their thread's CPU time when
    accelerated (``speed`` > 1), by wall time otherwise, as printed (to 0.1 ms then)."""
    if any(t["counted"] for t in ticks):
        return [t for t in ticks if t["counted"]]
    return [t for t in ticks if (t["cpu_ms"] if speed > 1.0 else t["wall_ms"]) > period * 1e3]


def _window(tick: dict, slack: float) -> tuple[float, float] | None:
    """A tick's wall window, epoch s: [logged - wall time - slack, logged + slack] (None: no stamp)."""
    end = tick["end_utc"]
    return None if end is None else (end - tick["wall_ms"] * 1e-3 - slack, end + slack)


def _overlap(gaps: list, tick: dict, slack: float) -> float:
    """The longest overlap, s, of a witness gap [wake-up - gap, wake-up] with the tick's wall window
    (:func:`_window`; 0: none)."""
    win = _window(tick, slack)
    if win is None:
        return 0.0
    a, b = win
    return max((min(w, b) - max(w - g, a) for w, g in gaps), default=0.0)


def pauses_at_ticks(ticks: list, gaps: list, slack: float = 0.02) -> dict:
    """For each tick of :func:`read_events` that was logged as slow: the longest witness gap
    overlapping [logged - wall time - slack, logged + slack], ms (0: none). {rig t s as logged: ms}."""
    windows = {t["key"]: _window(t, slack) for t in ticks if t["kind"] == "slow_tick"}
    return {key: 0.0 if win is None else max((g for w, g in gaps if w - g < win[1] and w > win[0]), default=0.0) * 1e3
            for key, win in windows.items()}


def judge_ticks(ticks: list, gaps: list, period: float, speed: float, replayed: list | None = None) -> list:
    """Each tick the run counted over the period (``ticks`` from :func:`read_events`), judged (module
    doc): ``t_s``, ``cpu_ms``, ``wall_ms``, ``excess_ms`` (its time over the period, the time that
    counted), ``machine_pause_ms`` (how long the witness's ``gaps`` [(wake-up, epoch s; gap, s)] show
    the machine stopped within the tick: the overlap less the witness's own sleep and the stamps'
    tolerance, so never more than the pause), ``replay_cpu_ms``, ``same_state``,
    ``first_difference``, ``overrun_not_forced`` (from ``replayed``, :func:`replay_ticks`'s result,
    None where not replayed), ``machine_by`` (["witness"] when the pause covers the excess,
    ["replay"] when the replay ran the same state within the period) and ``machine``."""
    by_t = {f"{r['t_s']:.4f}": r for r in (replayed or [])}
    out = []
    for t in over_period(ticks, period, speed):
        spent = t["cpu_ms"] if speed > 1.0 else t["wall_ms"]
        excess = spent - period * 1e3
        # the tolerance widens the window on each side; a gap that sticks out on one side gains at most
        # one tolerance from it (one that spans both is longer than the whole tick)
        pause = max(0.0, _overlap(gaps, t, _STAMP_TOL_S) - PROBE_SLEEP_S - _STAMP_TOL_S) * 1e3
        r = by_t.get(f"{t['t_s']:.4f}")
        by = (["witness"] if pause >= excess else []) + (["replay"] if r is not None and r["machine"] else [])
        out.append({"t_s": t["t_s"], "cpu_ms": t["cpu_ms"], "wall_ms": t["wall_ms"], "excess_ms": excess,
                    "machine_pause_ms": pause,
                    **{k: None if r is None else r[k]
                       for k in ("replay_cpu_ms", "same_state", "first_difference", "overrun_not_forced")},
                    "machine_by": by, "machine": bool(by)})
    return out


def _forced_outcome(ctrl, run_settings, replay_settings, status: str | None, rho_updates: int | None,
                    iterations: int | None, parted):
    """The context for the replay's step at a tick where the run's robot NMPC overran: the same
    outcome forced (the replay's wall-time budget is lifted everywhere else, so only the run's
    overruns happen). OSQP reports a solve its time limit cut one iteration short (it stops after the
    iteration's ADMM step, before that iteration's bookkeeping: the iterate after k + 1 steps is
    reported as k; OSQP 1.x's ``osqp_solve``, pinned by a test), so the replay's solve runs up to
    ``iterations`` + 1 steps: it stops there, or earlier where the run's solve converged by itself.
    The iteration cap, not this machine's load, ends it: the replay's own time limit is lifted.
    OSQP's time limit ("overrun (run time limit reached)"): the run's solution was unusable, but its
    iterations moved OSQP's iterate, which the next step starts from when the NMPC holds no usable
    solution to warm-start from (the steps after the start-up solve of
    :meth:`hbma_ctrl.controllers.robot_mpc.RobotNMPC.prime`), and a change of OSQP's rho carries
    over to every later solve; so the replay runs the run's iterations and then returns that status,
    with nothing usable. Without the run's iteration count (a log that has none) the status alone is
    forced, and only when the run's rho did not change. "overrun (X ms > Y ms)": the solve is made
    late, and stopped where the run's stopped: OSQP's time limit can strike in a solve that still
    ends usable (its approximate test passes: "solved inaccurate"), and that late plan is the next
    step's warm start, so a replay that solved on would part from the run there. When the replay's
    solve does not end on the run's iterations or rho updates, or the outcome cannot be forced,
    ``parted()`` is called: that outcome was not reproduced. ``run_settings``: the NMPC's settings
    as the run had them; ``replay_settings``: the same with the budget not enforced."""
    import contextlib

    from hbma_ctrl.controllers.mpc_solvers import OSQP_NO_TIME_LIMIT

    if ctrl is None or not status or not status.startswith("overrun"):
        return contextlib.nullcontext()
    solver = ctrl._solver
    real = solver.solve

    def run_iterations(*a, **k):
        """The solve, capped at the run's iterations + 1 and never at this machine's wall clock."""
        cap = {} if iterations is None else {"max_iter": min(iterations + 1, run_settings.max_iter)}
        solver.update_settings(time_limit=OSQP_NO_TIME_LIMIT, **cap)
        try:
            res = real(*a, **k)
        finally:
            solver.update_settings(max_iter=run_settings.max_iter)
        if iterations is not None and (
                int(res.info.iter) not in (iterations, iterations + 1)
                or int(getattr(res.info, "rho_updates", 0)) != (rho_updates or 0)):
            parted()
        return res

    if "time limit" in status and iterations is not None:
        def solve(*a, **k):
            run_iterations(*a, **k)
            return _TimeLimited()
    elif "time limit" in status and rho_updates == 0:
        def solve(*a, **k):
            return _TimeLimited()
    elif _LATE.match(status):
        def solve(*a, **k):
            res = run_iterations(*a, **k)
            time.sleep(run_settings.budget * run_settings.sample_period)  # past the budget, solved
            return res
    else:
        parted()
        return contextlib.nullcontext()

    @contextlib.contextmanager
    def forced():
        ctrl.s = run_settings
        solver.solve = solve
        try:
            yield
        finally:
            del solver.solve
            ctrl.s = replay_settings
            solver.update_settings(time_limit=OSQP_NO_TIME_LIMIT)  # the replay's own solves are never cut

    return forced()


def _logged_rows(daemon_dir: Path, times: set) -> dict:
    """The run log's rows at the rig times ``times`` (the strings as logged), streamed part by part
    (an hour's log does not fit in memory as lists): {t_s string: {column: value}}."""
    out: dict = {}
    for part in sorted(daemon_dir.glob("run_*.csv")):
        with part.open(newline="") as fh:
            reader = csv.reader(fh)
            header = next(reader)
            for r in reader:
                if r and r[0] in times and r[1] == "running":
                    out[r[0]] = dict(zip(header, r))
    return out


def replay_ticks(config: Path, daemon_dir: Path, speed: float, echo=print, events: tuple | None = None) -> list[dict]:
    """Re-time a daemon run's ticks over the period (module doc): the run again in lockstep on a virtual
    clock (same configuration, the setpoints of its events.csv applied at their rig times), up to its
    last slow tick. ``events``: :func:`read_events`'s result for the run when already read. Returns
    one dict per slow tick: ``t_s``, ``cpu_ms`` and ``wall_ms`` (the run's),
    ``replay_cpu_ms``, ``same_state`` (the replay's readings and height estimates at that tick equal the
    run log's, as logged; else ``first_difference`` names the column and both values),
    ``overrun_not_forced`` (the run's NMPC overran at this tick or before it in a way the replay could
    not reproduce, see :func:`_forced_outcome`), ``machine`` (same state and the replay's tick within the period)."""
    from hbma_ctrl.app.daemon.build import build_runner, make_monitor, make_rig
    from hbma_ctrl.app.daemon.config import load_config
    from hbma_ctrl.app.daemon.loop import DaemonLoop
    from hbma_ctrl.app.daemon.runlog import fmt_value
    from hbma_ctrl.app.daemon.state import DaemonState
    from hbma_ctrl.core import units as U

    cfg = load_config(config, {"--rig": "sim", "--speed": float(speed)})
    period = cfg.period
    setpoints, events = read_events(daemon_dir) if events is None else events
    slow = [(e["t_s"], e["cpu_ms"], e["wall_ms"]) for e in over_period(events, period, speed)]
    if not slow:
        return []
    outcome = {f"{e['t_s']:.4f}": (e["status"], e["rho_updates"], e["iterations"]) for e in events}
    runner = build_runner(cfg)
    rig = make_rig(cfg, runner)
    state = DaemonState()
    clock = [0.0]
    until = max(t for t, _, _ in slow) + period
    loop = DaemonLoop(runner, rig, state, period, speed=speed, duration=until, log=None,
                      monitor=make_monitor(cfg, runner), status_every=10**9, miss_limit=cfg.miss_limit,
                      clock=lambda: clock[0], sleep=lambda d: clock.__setitem__(0, clock[0] + d))
    pending = list(setpoints)

    def take() -> list:
        # the daemon applies a setpoint at the start of a period, logged at the previous period's time
        out = []
        while pending and pending[0][0] <= loop.t + 1e-6:
            out.append(pending.pop(0)[1])
        return out

    state.take_setpoints = take
    # the NMPC's wall-time budget would let the replay's own load change its decisions: lifted, and the
    # robot's run's overruns forced where they happened (_forced_outcome)
    ctrl, run_settings = lift_budget(runner)
    replay_settings = None if ctrl is None else ctrl.s
    unforced: set = set()
    wanted = {f"{t:.4f}": (t, cpu, wall) for t, cpu, wall in slow}
    seen: dict = {}
    step = loop._step
    last_note = [time.monotonic()]

    def timed_step(k: int, missed: bool) -> None:
        clock[0] += 1e-6  # the virtual wall clock moves, never to a deadline: no waiting
        # this period's rig time (the lockstep rig's clock is the period count)
        nxt = f"{k * period:.4f}"
        if nxt in outcome:
            with _forced_outcome(ctrl, run_settings, replay_settings, *outcome[nxt],
                                 parted=lambda: unforced.add(nxt)):
                step(k, missed)
        else:
            step(k, missed)
        key = f"{loop.t:.4f}"
        if key in wanted:
            h = runner.estimates()[0]
            seen[key] = {"cpu_ms": loop._last_tick_cpu * 1e3,
                         "p": [fmt_value(v, U.to_kpa(1.0)) for v in loop.readings_p],
                         "h": [fmt_value(v, U.to_mm(1.0)) for v in h]}
        if time.monotonic() - last_note[0] > 60.0:
            last_note[0] = time.monotonic()
            echo(f"soak replay: rig time {loop.t:.0f} / {until:.0f} s")

    loop._step = timed_step
    loop.run()
    logged = _logged_rows(daemon_dir, set(wanted))
    out = []
    for key, (t, cpu, wall) in sorted(wanted.items(), key=lambda kv: kv[1][0]):
        r, row = seen.get(key), logged.get(key)
        if r is None or row is None:
            diff = "the replay did not reach this tick" if r is None else "no run log row at this tick"
        else:
            diff = next((f"{col}: run {row.get(col)}, replay {v}" for i, nm in enumerate(runner.names)
                         for col, v in ((f"p_{nm}_kpa", r["p"][i]), (f"h_est_{nm}_mm", r["h"][i]))
                         if row.get(col) != v), "")
        rc = None if r is None else r["cpu_ms"]
        out.append({"t_s": t, "cpu_ms": cpu, "wall_ms": wall, "replay_cpu_ms": rc, "same_state": not diff,
                    "first_difference": diff, "overrun_not_forced": any(float(u) <= t + 1e-9 for u in unforced),
                    "machine": bool(not diff and rc is not None and rc <= period * 1e3)})
    return out


def run_soak(config: Path, out: Path, duration_s: float, speed: float, every_s: float, seed: int,
             overwrite: bool = False, argv: list | None = None, echo=print, replay: bool = True) -> dict:
    """Run the soak (module doc) into ``out``; returns soak.json's content. Times in s of rig time.
    ``replay``: re-time the ticks over the period in a lockstep replay (:func:`replay_ticks`) when the
    witness leaves one unexplained; without it only the witness judges them."""
    rng = random.Random(seed)
    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    with run_dir(out, command="bench soak", argv=argv, scenario_path=config, overwrite=overwrite) as tmp:
        cmd = [sys.executable, "-m", "hbma_ctrl", "daemon", str(config), "--rig", "sim", "--speed", repr(speed),
               "--duration-s", repr(duration_s), "--api", f"127.0.0.1:{port}", "--out", str(tmp / "daemon")]
        err_path = tmp / "daemon_stderr.txt"
        sent: list[dict] = []
        probe = PauseProbe().start()
        with open(err_path, "w") as err:
            proc = subprocess.Popen(cmd, stdout=err, stderr=subprocess.STDOUT, env=dict(os.environ))
            # a stop (Ctrl-C, or SIGTERM/SIGINT to a soak started in the background, where the shell
            # ignores SIGINT) stops the daemon too, through its own safe exit
            old = {sig: signal.signal(sig, _raise_interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
            try:
                _drive(proc, url, rng, every_s, duration_s, sent, echo, speed)
                rc = proc.wait()
            except BaseException:
                # the daemon writes the safe command on SIGTERM; the soak's results stay readable
                proc.send_signal(signal.SIGTERM)
                proc.wait(timeout=30)
                raise
            finally:
                for sig, h in old.items():
                    signal.signal(sig, h)
                gaps = probe.stop()
        stats_path = tmp / "daemon" / "daemon_stats.json"
        if not stats_path.exists():
            tail = err_path.read_text().strip().splitlines()[-1:] or ["(no output)"]
            raise ValueError(f"the daemon ended (exit {rc}) without daemon_stats.json: {tail[0]}")
        stats = json.loads(stats_path.read_text())
        period = 1.0 / float(stats["rate_hz"])
        run_events = read_events(tmp / "daemon")
        events = run_events[1]
        ticks = judge_ticks(events, gaps, period, speed)
        unexplained = sum(1 for t in ticks if not t["machine"])
        with open(tmp / "setpoints.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["rig_t_s", "status", "body", "reply"])
            w.writerows([f"{s['rig_t_s']:.2f}", s["status"], json.dumps(s["body"]), json.dumps(s["reply"])]
                        for s in sent)
        # the witness's record, whole: it exists only in this process until written
        with open(tmp / "machine_pauses.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["wake_utc_epoch_s", "gap_ms"])
            w.writerows([f"{t:.4f}", f"{g * 1e3:.2f}"] for t, g in gaps)
        log = (log_completeness(tmp / "daemon", stats) if (tmp / "daemon" / LOG_MCAP).exists() else None)
        head = {"config": str(config), "duration_s": duration_s, "speed": speed, "setpoint_every_s": every_s,
                "seed": seed, "daemon_exit_code": rc, "setpoints_sent": len(sent),
                "setpoints_accepted": sum(1 for s in sent if s["status"] == 200), "log": log}
        tail = {  # an independent witness: the bench's own 1 ms sleeper woke late at the same moment
                "slow_tick_machine_pause_ms": pauses_at_ticks(events, gaps),
                "machine_pauses": {"over_5ms": len(gaps), "over_10ms": sum(1 for _, g in gaps if g > 0.01),
                                   "max_ms": max((g for _, g in gaps), default=0.0) * 1e3,
                                   "longest": [[time.strftime("%H:%M:%S", time.gmtime(w)) + f"{w % 1:.3f}"[1:],
                                                g * 1e3] for w, g in sorted(gaps, key=lambda x: -x[1])[:50]]},
                "daemon_stats": stats}

        def write(ticks: list, replay_state: str) -> dict:
            verdicts = soak_verdicts(stats, ticks, log)
            res = {**head, "verdicts": verdicts, "passed": all(verdicts.values()), "replay": replay_state,
                   "ticks_over_period": ticks, "ticks_over_period_machine": sum(1 for t in ticks if t["machine"]),
                   **tail}
            (tmp / "soak.json").write_text(json.dumps(json_safe(res), indent=1) + "\n")
            return res

        if replay and unexplained:
            # written first: the replay takes about as long as the run, and a stopped replay must not
            # lose the run's verdict (the witness's alone, "replay": "unfinished")
            write(ticks, "unfinished")
            echo(f"soak: {len(ticks)} ticks over the period, {unexplained} not inside a machine pause; "
                 "re-timing them in a lockstep replay (soak.json has the witness's verdict meanwhile)")
            replayed = replay_ticks(config, tmp / "daemon", speed, echo, events=run_events)
            ticks = judge_ticks(events, gaps, period, speed, replayed)
            result = write(ticks, "done")
        else:
            result = write(ticks, "not needed" if replay else "off")
    return result


def _drive(proc: subprocess.Popen, url: str, rng: random.Random, every_s: float, duration_s: float,
           sent: list, echo, speed: float = 1.0) -> None:
    """Post a random setpoint each ``every_s`` of rig time until the daemon ends (the rig runs ``speed``
    times faster than the wall clock)."""
    n_layers = n_chambers = None
    next_t = every_s
    last_note = time.monotonic()
    # a few polls per setpoint interval of wall time (at most 2 per second): polled every 0.5 s, a fast
    # rig (speed 4, a setpoint a second) passed two setpoint times between polls and sent one
    poll = min(0.5, every_s / max(speed, 1e-9) / 4)
    with httpx.Client(base_url=url, timeout=5.0) as client:
        while proc.poll() is None:
            time.sleep(poll)
            try:
                st = client.get("/status").json()
            except (httpx.HTTPError, ValueError):
                continue  # not up yet, or ending
            if st.get("mode") != "running" or st.get("t_s") is None:
                continue
            if n_layers is None:
                n_layers, n_chambers = len(st.get("layers") or []), len(st.get("chambers") or [])
            t = float(st["t_s"])
            if t >= next_t and t < duration_s - 1.0:
                body = random_target(rng, n_layers, n_chambers)
                try:
                    r = client.post("/setpoint", json=body)
                    sent.append({"rig_t_s": t, "status": r.status_code, "body": body, "reply": r.json()})
                except (httpx.HTTPError, ValueError) as exc:
                    sent.append({"rig_t_s": t, "status": None, "body": body, "reply": str(exc)})
                next_t = (int(t // every_s) + 1) * every_s
            if time.monotonic() - last_note > 60.0:
                last_note = time.monotonic()
                echo(f"soak: rig time {t:.0f} / {duration_s:g} s, {len(sent)} setpoints, mode {st.get('mode')}, "
                     f"faults {st.get('faults', {}).get('counts') or 'none'}")
