"""The daemon's fixed-rate loop: read -> monitor -> tick -> write, on absolute deadlines (SI).

Period k starts at the wall deadline ``t0 + k * period / speed`` (time.monotonic): no drift, however
long the steps take. The loop sleeps until the deadline; the lateness of the wake-up is the jitter.
A step that ends after the next deadline is a *deadline miss*; the loop does not burst to catch
up: it goes on at the next deadline still in the future and counts the deadlines it skipped. On a
simulated rig (``rig.simulated``) the time its reads and writes take simulating the plant is no
time a real rig's I/O would take: a step is a miss when it ends after the deadline without it. Each
miss is a counted warning (``overruns``; an ``overrun_warning`` event at the first of a run); the
loop watchdog (the monitor's overrun test: ``miss_limit`` misses in a row latch the ``overrun``
fault) gets the misses in real time (speed 1); accelerated, it
gets the steps whose runtime tick took longer than the rig period (what a real rig would have
missed; the sim rig's plant simulation is not counted), so a run faster than real time is not
stopped for being faster than real time. Accelerated, the tick is judged by the CPU time of the
loop's thread, the cost of its work on a host of its own: a simulation run on a shared machine is
preempted by other jobs (a soak on a 2-core machine beside four other jobs saw wall-clock ticks of
14 ms at p99 where the work took 4), which a real-time host would not do. The wall-clock ticks are
reported too (``tick_ms_*``, ``steps_over_period_wall``). With
the lockstep simulated rig, rig time advances one period per write, so it is exact whatever the
wall clock does; ``speed`` runs that many rig seconds per wall second.

Each period:

1. the setpoints the API queued (already checked and clipped) are applied;
2. ``rig.read()``; the safety monitor checks the readings with the command sent last and whether the
   last period missed its deadline; a latched fault puts the loop in mode "safe": from then on it
   writes the safe command every period (and logs) until it is stopped;
3. the runner ticks (estimator, controller, the runtime supervisor's fallback chain; the estimator
   predicts with the command the rig reports it held, when it reports one) and the command
   is written;
4. a run log row; the status is published for the API every ``status_every`` periods.

Before the first period the objects alive are frozen out of Python's garbage collector and every
collection is timed (:mod:`hbma_ctrl.app.daemon.gcwatch`): a full collection of the start-up objects
took 3-4 periods.

A latched fault is left without a restart by a reset (the API's ``POST /reset``): asked for while the
loop is in mode "safe" and the readings are sane (finite, within the sensor's range and below the
pressure cap), checked again at the next period, it clears the monitor and the loop controls again.

The loop ends on a stop request (the API's /stop, a signal flag, the duration, the API's process
lost: a fault) or at once on an exception anywhere in the step or a lost rig link. Whatever ends it,
the safe command is written before :meth:`DaemonLoop.run` returns, and the event is logged with its
rig time and cause.
"""

from __future__ import annotations

import math
import sys
import time
from collections import deque
from typing import Callable

import numpy as np

from hbma_ctrl.app.daemon.gcwatch import GcWatch
from hbma_ctrl.app.daemon.host import rss_mb, steal_ms, thread_usage
from hbma_ctrl.system.rigio import RigLinkError, safe_u
from hbma_ctrl.app.daemon.runlog import RunLog, fmt_value, setpoint_fields
from hbma_ctrl.app.daemon.state import DaemonState
from hbma_ctrl.core import units as U
from hbma_ctrl.runtime.stats import StepStats

__all__ = ["DaemonLoop", "STATS_KEYS", "COUNTED", "GIL_SWITCH_S"]

#: the words a slow_tick event carries when steps_over_period counts its tick
COUNTED = "counted over the period"
#: a loop ticking on a streaming rig's samples wakes this fraction of a period before one is due
SAMPLE_LEAD = 0.2

#: keys of daemon_stats.json
STATS_KEYS = ("rate_hz", "steps", "deadline_misses", "step_ms_median", "step_ms_p99", "jitter_ms_p99",
              "max_pressure_kpa", "pressure_limit_kpa", "faults", "safe_exit", "rss_mb_start", "rss_mb_end")

#: events kept for the status (the run log keeps all)
EVENTS_KEPT = 100
#: the interpreter's switch interval while the loop runs, s: a thread that wants the GIL (the loop's,
#: back from its sleep or a solver call) waits at most this long for another (the run log's writer,
#: the API's link) to hand it over; Python's default is 5 ms, half a period at 100 Hz
GIL_SWITCH_S = 2e-4


class DaemonLoop:
    """The loop of the module doc.

    Parameters
    ----------
    runner : a :class:`hbma_ctrl.app.daemon.build.ChamberSystem` or ``RobotSystem``.
    rig : a :class:`hbma_ctrl.system.rigio.RigIO` with ``runner.n`` chambers.
    state : the :class:`DaemonState` shared with the API.
    period : rig time per period, s.
    speed : rig seconds per wall second.
    duration : rig time to run, s; None = until stopped.
    log : the :class:`RunLog`, None = no log.
    record : the MCAP log's :class:`hbma_ctrl.app.daemon.record.DaemonRecord` (each period and event is
        queued to it; its own thread writes them), None = none.
    monitor : the :class:`hbma_ctrl.runtime.watchdog.SafetyMonitor` (``check(t, readings, u_sent,
        deadline_missed) -> faults``, ``latched``, ``faults``, ``counts``), None = none (the loop then
        latches 'overrun' itself after ``miss_limit`` missed deadlines in a row).
    status_every : publish the status every this many periods.
    miss_limit : missed deadlines in a row that latch the 'deadline' fault.
    warmup_periods : the first periods of the controller (its first solves set up its solver; counted
        after a runner's start-up work such as the chamber's calibration, whose periods do not feed
        the watchdog either) are timed and counted but do not feed the loop watchdog.
    clock, sleep : the monotonic clock (s) and the sleep; replaceable in tests.
    """

    def __init__(self, runner, rig, state: DaemonState, period: float, speed: float = 1.0,
                 duration: float | None = None, log: RunLog | None = None, monitor=None, status_every: int = 1,
                 miss_limit: int = 10, warmup_periods: int = 50, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep, record=None):
        if rig.n != runner.n:
            raise ValueError(f"the rig has {rig.n} chambers, the configuration {runner.n}")
        self.runner, self.rig, self.state, self.log, self.monitor = runner, rig, state, log, monitor
        self.record = record
        self.period, self.speed, self.duration = float(period), float(speed), duration
        self.status_every, self.miss_limit = int(status_every), int(miss_limit)
        self.warmup_periods = int(warmup_periods)
        self.clock, self.sleep = clock, sleep
        self.n = runner.n
        #: set by a signal handler (a plain attribute: a handler must not take the state's lock)
        self.signal_stop: str | None = None
        self.mode = "starting"
        self.steps = 0
        self.deadline_misses = 0
        self.overruns = 0  # deadline misses past the warm-up: each a warning, a run of miss_limit a fault
        self._io_s = 0.0  # this step's time in a simulated rig's reads and writes, s (0 on a real rig)
        #: the rig's reads and writes simulate the plant (RigIO.simulated; a link without it is real),
        #: read from the rig the run starts with
        self._sim_io = False
        self.skipped_periods = 0
        self.over_budget = 0
        self.repeated_samples = 0
        self._last_tick = 0.0
        self._last_tick_cpu = 0.0
        self.over_wall = 0  # ticks whose wall time exceeded the rig period
        self.step_s = StepStats(8192)
        self.jitter_s = StepStats(8192)
        #: the runtime tick alone (estimator, controller, supervisor): the step without the rig's I/O,
        #: which on the simulated rig includes simulating the plant
        self.tick_s = StepStats(8192)
        self.tick_cpu_s = StepStats(8192)
        self.max_pressure = -math.inf
        self.events: deque = deque(maxlen=EVENTS_KEPT)
        self.fault_counts: dict = {}
        self.safe_exit = False
        self.end_reason = ""
        self.t = 0.0
        self._warming = False
        self._ctrl_steps = 0  # periods the runner ticked past its start-up work (calibration)
        self.u_last = safe_u(self.n)
        self.readings_p = np.full(self.n, np.nan)
        self.rss_start = rss_mb()
        self.rss_end = float("nan")
        self.wall_s = 0.0
        self._miss_run = 0
        self._t_origin: float | None = None
        self._ticked = False  # the runner has ticked on a sample
        self._steal_before: float | None = None
        self._parts_seen = None  # the controller step whose overrun was last checked (_overrun_within_period)
        self._ru_before = None
        #: the collector's pauses (frozen start-up objects, see :mod:`hbma_ctrl.app.daemon.gcwatch`),
        #: set while :meth:`run` runs
        self.gc: GcWatch | None = None
        self._gc_before = (0, 0.0)

    # --- events ------------------------------------------------------------------------------------
    def event(self, kind: str, cause: str, fields: dict | None = None) -> None:
        """Record an event at the current rig time (status, run log; ``fields``: its run log columns)."""
        ev = {"t_s": float(self.t), "kind": kind, "cause": cause}
        self.events.append(ev)
        if self.log is not None:
            self.log.event(self.t, kind, cause, fields)
        if self.record is not None:
            self.record.event(self.t, kind, cause, fields)

    def _fault(self, kind: str, cause: str) -> None:
        self.fault_counts[kind] = self.fault_counts.get(kind, 0) + 1
        self.event(kind, cause)

    def _enter_safe(self, kinds) -> None:
        """Mode "safe" from now on, with the event naming the fault kinds that latched it."""
        self.mode = "safe"
        self.event("safe", "fault latched: " + ", ".join(kinds))

    def _latched_kinds(self) -> list[str]:
        """The kinds the monitor reported since it latched (sorted), [] when it has not."""
        if self.monitor is None or not self.monitor.latched:
            return []
        return sorted({f.kind for f in self.monitor.faults})

    def faults(self) -> dict:
        """Fault counts by kind: the monitor's and the loop's own (deadline, exception, link)."""
        out = dict(self.fault_counts)
        for k, v in (self.monitor.counts if self.monitor is not None else {}).items():
            if v:
                out[str(k)] = out.get(str(k), 0) + int(v)
        return out

    # --- the rig -----------------------------------------------------------------------------------
    def _write(self, u: np.ndarray) -> None:
        c0 = self.clock()
        self.rig.write(u)
        if self._sim_io:
            self._io_s += self.clock() - c0
        self.u_last = u

    def _write_safe(self) -> None:
        """Write the safe command as a period's command: through the rig's ``write_safe`` when it has one
        (a board that runs the controller takes SAFE, not a command), else ``write``."""
        write_safe = getattr(self.rig, "write_safe", None)
        if write_safe is None:
            self._write(safe_u(self.n))
            return
        write_safe()
        self.u_last = safe_u(self.n)

    def _go_safe(self) -> None:
        """Write the safe command (never raises)."""
        try:
            self.rig.safe()
            self.u_last = safe_u(self.n)
            self.safe_exit = True
        except Exception as exc:  # noqa: BLE001 - the loop is ending; record why the vent failed
            self.safe_exit = False
            self.event("safe_failed", f"{type(exc).__name__}: {exc}")

    # --- status ------------------------------------------------------------------------------------
    def status(self) -> dict:
        """The status dict the API converts (see :mod:`hbma_ctrl.app.daemon.api`)."""
        h, hs, pe = self.runner.estimates()
        tg = self.runner.effective_targets() if self.mode == "running" else np.full(self.n, np.nan)
        u = self.u_last
        chambers = [{"name": nm, "h": float(h[i]), "h_std": float(hs[i]), "p": float(self.readings_p[i]),
                     "p_est": float(pe[i]), "target": float(tg[i]),
                     "u": [float(u[0, i]), float(u[1, i]), float(u[2, i])]}
                    for i, nm in enumerate(self.runner.names)]
        st = self.step_s.summary()
        return {"mode": self.mode, "t_s": float(self.t), "monotonic_s": time.monotonic(), "chambers": chambers,
                "layers": self.runner.layers(),
                "loop": {"rate_hz": 1.0 / self.period, "steps": self.steps, "deadline_misses": self.deadline_misses,
                         "overruns": self.overruns, "step_median_s": st["median"], "step_p99_s": st["p99"]},
                "faults": self.faults(), "events": list(self.events)}

    def _log_row(self, step_s: float) -> None:
        if self.log is None and self.record is None:
            return
        h, hs, pe = self.runner.estimates()
        tg = self.runner.targets() if self.mode == "running" else np.full(self.n, np.nan)
        u = self.u_last
        latched = ";".join(self._latched_kinds())
        if self.record is not None:
            self.record.step(self.t, self.mode, self.readings_p, pe, h, hs, tg, u, step_s, latched)
        if self.log is None:
            return
        row: list = [f"{self.t:.4f}", self.mode]
        for i in range(self.n):
            row += [fmt_value(self.readings_p[i], U.to_kpa(1.0)), fmt_value(pe[i], U.to_kpa(1.0)), fmt_value(h[i], U.to_mm(1.0)),
                    fmt_value(hs[i], U.to_mm(1.0)), fmt_value(tg[i], U.to_mm(1.0)), f"{u[0, i]:.4f}", f"{u[1, i]:.4f}",
                    f"{u[2, i]:.4f}"]
        row += [fmt_value(step_s, 1e3, 3), latched]
        self.log.row(row)

    # --- one period --------------------------------------------------------------------------------
    def _step(self, k: int, missed_last: bool) -> None:
        self._io_s = 0.0
        for sp in self.state.take_setpoints():
            self.runner.apply_setpoint(sp, self.t)
            self.event("setpoint", *setpoint_fields(sp, self.runner.names))
        c0 = self.clock()
        r = self.rig.read()
        if self._sim_io:
            self._io_s += self.clock() - c0
        p = np.asarray(r.p, dtype=float).reshape(self.n)
        self.readings_p = p
        if self.state.take_reset():
            self._reset(p)
        fresh = np.asarray(r.fresh, dtype=bool)
        waiting = fresh.size == self.n and not fresh.any()  # no new sample since the last period
        if r.t is None:
            # a rig without time stamps is timed by the loop's periods; before its first sample the
            # clock stays at 0 (the periods spent waiting for it are no rig time anything happened in)
            if self._ticked or not waiting:
                self.t = k * self.period
        else:
            # the rig's clock starts at its own boot: the scenario's schedule starts at the first reading
            if self._t_origin is None:
                self._t_origin = float(r.t)
            # a repeated or reordered packet never moves the loop's clock back (the estimator refuses that)
            self.t = max(float(r.t) - self._t_origin, self.t)
        if np.isfinite(p).any():
            self.max_pressure = max(self.max_pressure, float(np.nanmax(p)))
        if self.monitor is not None:
            # the controller's first solves set up its solver: those misses do not feed the watchdog
            missed = missed_last and self._ctrl_steps > self.warmup_periods
            for f in self.monitor.check(self.t, r, self.u_last, missed) or ():
                i = f.chamber
                # the chamber by the name the API and the log use, so a person can find it on the rig
                where = f"{self.runner.names[i]}: " if i is not None and 0 <= i < len(self.runner.names) else ""
                self.event(f.kind, where + f.cause)
            if self.monitor.latched and self.mode == "running":
                self._enter_safe(self._latched_kinds())
        if self.mode == "safe":
            # written like any command: a lockstep rig advances on writes, a serial rig keeps its heartbeat
            self._write_safe()
            return
        if waiting:
            # no new sample since the last period (the rig's clock has not moved): the estimator would
            # count one reading twice at one time; the command stands (rewritten: the link's heartbeat).
            # Before the rig's first sample there is nothing to tick on either: a tick then (a dropout at
            # t = 0) and another on the first sample (whose stamp is the clock's origin, t = 0 again)
            # would give the runner two ticks at one time
            self.repeated_samples += int(self._ticked)
            self._write(self.u_last)
            return
        self._ticked = True
        self._steal_before = steal_ms()
        self._ru_before = thread_usage()
        self._gc_before = self.gc.mark() if self.gc is not None else (0, 0.0)
        c0, cpu0 = self.clock(), time.thread_time()
        held = r.held
        # a runner's start-up work (the chamber's calibration and its fit) is not judged by the watchdog
        self._warming = bool(self.runner.warming)
        # only a rig that reports what it held passes it: a runner may take (t, p) alone
        u = self.runner.tick(self.t, p) if held is None else self.runner.tick(self.t, p, held)
        self._last_tick = self.clock() - c0
        self._last_tick_cpu = time.thread_time() - cpu0
        if max(self._last_tick, self._last_tick_cpu) > self.period and not self._warming:
            self._slow_tick()
        else:
            self._overrun_within_period()
        self._ctrl_steps += int(not self._warming)
        self.tick_s.add(self._last_tick)
        self.tick_cpu_s.add(self._last_tick_cpu)
        for kind, cause in self.runner.take_events():
            self.event(kind, cause)
        # faults the runner's own tests found (the robot's burst test on its filters) latch the safe
        # state as the monitor's do, from this period on
        found = self.runner.take_faults()
        for kind, i, cause in found:
            if self.monitor is not None:
                self.monitor.raise_fault(self.t, kind, cause, chamber=i)
                self.event(kind, cause)
            else:
                self._fault(kind, cause)
        if found and self.mode == "running":
            self._enter_safe(self._latched_kinds() or sorted({k for k, _, _ in found}))
            self._write_safe()
            return
        self._write(u)

    def _tick_over_period(self) -> bool:
        """The last tick counts as over the period (``steps_over_period``): by its thread's CPU time when
        accelerated, by wall time in real time (module doc)."""
        return self._last_tick_cpu > self.period if self.speed > 1.0 else self._last_tick > self.period

    def _overrun_within_period(self) -> None:
        """Log a controller overrun in a tick that stayed within the period (event ``nmpc_overrun``,
        the slow tick's report): the robot NMPC's budget is shorter than the period, so its fallback
        can strike without a slow tick, and a replay of the run must take it where the run did."""
        parts = self.runner.controller_report()
        if parts is None or parts is self._parts_seen:
            return
        self._parts_seen = parts  # each controller step makes a new dict: one event per step
        if str(parts.get("status", "")).startswith("overrun"):
            self._slow_tick("nmpc_overrun")

    def _slow_tick(self, kind: str = "slow_tick") -> None:
        """Log a tick longer than the period (event ``slow_tick``) with where its time went: the
        runtime loop's estimator and controller parts when it reports them (``last_timing``: step,
        estimator, controller, s), the host's steal time during it (ms, from /proc/stat, read before
        every tick: on a virtual machine a thread's CPU time counts time the host took the core) and the
        garbage collector's pauses during it (any thread's: a collection holds the interpreter)."""
        parts = self.runner.tick_timing()
        text = f"cpu {self._last_tick_cpu * 1e3:.3f} ms, wall {self._last_tick * 1e3:.3f} ms"
        # whether steps_over_period counts it, said outright: a reader comparing the printed times with
        # the period would misjudge a tick within the printing's rounding of it
        if kind == "slow_tick" and self._tick_over_period():
            text += f", {COUNTED}"
        if parts is not None and len(parts) == 3:
            text += f" (estimator {parts[1] * 1e3:.1f} ms, controller {parts[2] * 1e3:.1f} ms)"
        steal = steal_ms()
        if steal is not None and self._steal_before is not None:
            text += f"; host steal during it {steal - self._steal_before:.0f} ms (10 ms steps)"
        if self.gc is not None:
            n, d = self.gc.since(self._gc_before)
            text += f"; garbage collector {d * 1e3:.1f} ms in {n} collection{'' if n == 1 else 's'}"
        ru = thread_usage()
        if ru is not None and self._ru_before is not None:
            b = self._ru_before
            text += (f"; thread user {(ru.ru_utime - b.ru_utime) * 1e3:.1f} ms, system "
                     f"{(ru.ru_stime - b.ru_stime) * 1e3:.1f} ms, {ru.ru_minflt - b.ru_minflt} minor and "
                     f"{ru.ru_majflt - b.ru_majflt} major page faults, "
                     f"{ru.ru_nivcsw - b.ru_nivcsw} preemptions")
        more = self.runner.tick_parts()
        if more:
            text += "; " + ", ".join(f"{k} {v * 1e3:.2f} ms" if isinstance(v, float) else f"{k} {v}"
                                     for k, v in more.items())
        self.event(kind, text)

    def _check_setpoint(self, request: dict) -> dict:
        """The runner's check (the submitter's thread, not the loop's); refused (RuntimeError: 503) once
        the loop is not running: in the safe state the loop writes only the safe command, so a setpoint
        would never be applied."""
        if self.mode != "running":
            raise RuntimeError(f"the daemon is in mode '{self.mode}' (safe command only, after "
                               f"{', '.join(self._latched_kinds()) or 'a stop'}): setpoints are not applied")
        return self.runner.check_setpoint(request)

    def _insane(self, p: np.ndarray) -> str:
        """Why the readings ``p`` (Pa) are not sane for a reset ('' when they are): each must be finite,
        within the sensor's range and below the pressure cap (the monitor's; the runner's limit without one)."""
        s = self.monitor.settings if self.monitor is not None else None
        lo, hi = (s.vacuum_floor, min(s.sensor_range, s.p_max)) if s is not None else (-math.inf, self.runner.p_limit)
        bad = [f"{nm} reads {fmt_value(p[i], U.to_kpa(1.0), 2) or 'nothing'} kPa" for i, nm in enumerate(self.runner.names)
               if not (math.isfinite(p[i]) and lo <= p[i] < hi)]
        return "; ".join(bad) + (f" (sane: [{U.to_kpa(lo):g}, {U.to_kpa(hi):g}) kPa)" if bad else "")

    def _check_reset(self) -> str:
        """The API's reset check (the submitter's thread): RuntimeError with the reason unless the loop is
        in mode "safe" with sane readings."""
        if self.mode != "safe":
            raise RuntimeError(f"the daemon is in mode '{self.mode}': there is no fault to reset")
        why = self._insane(self.readings_p)
        if why:
            raise RuntimeError(f"the readings are not sane: {why}")
        return "the loop leaves the safe state at its next period if the readings are still sane"

    def _reset(self, p: np.ndarray) -> None:
        """A reset asked for through the API, at the start of a period with the readings ``p`` (Pa)."""
        if self.mode != "safe":
            return
        why = self._insane(p)
        if why:
            self.event("reset_refused", why)
            return
        if self.monitor is not None:
            self.fault_counts = self.faults()  # the run keeps counting the faults the monitor forgets
            self.monitor.reset()
        self._miss_run = 0
        self.mode = "running"
        self.event("reset", "the safe state left on request: the readings are sane")

    def _should_stop(self) -> bool:
        """True (and the stop event logged) on a signal, a stop request or the end of the duration."""
        if self.signal_stop:
            self.state.request_stop(self.signal_stop)
        if self.state.stop_requested:
            self.end_reason = self.state.stop_reason
            if self.state.stop_fault:  # a stop for a fault (the API's process lost) counts as one
                self._fault(self.state.stop_fault, self.end_reason)
            self.event("stop", self.end_reason)
            return True
        if self.duration is not None and self.steps * self.period >= self.duration - 1e-9:
            self.end_reason = "duration"
            self.event("stop", f"duration {self.duration:g} s reached")
            return True
        return False

    def run(self) -> dict:
        """Run until stopped (module doc); returns the stats (:data:`STATS_KEYS` and more)."""
        self.state.set_setpoint_handler(self._check_setpoint)
        self.state.set_reset_handler(self._check_reset)
        # before the first period: one collection, then the start-up objects frozen (gcwatch's doc)
        self.gc = GcWatch()
        switch = sys.getswitchinterval()
        sys.setswitchinterval(GIL_SWITCH_S)
        self.mode = "running"
        self._sim_io = bool(getattr(self.rig, "simulated", False))
        self.event("start", f"rate {1.0 / self.period:g} Hz, speed {self.speed:g}")
        wp = self.period / self.speed
        t0 = self.clock()
        # a rig that streams on its own clock (serial) in real time: ticks follow its samples
        wait = getattr(self.rig, "wait_sample", None) if self.speed <= 1.0 else None
        k = 0
        missed_last = False
        try:
            while True:
                if self._should_stop():
                    break
                deadline = t0 + k * wp
                now = self.clock()
                wake = deadline - (SAMPLE_LEAD * wp if wait is not None else 0.0)
                if now < wake:
                    self.sleep(wake - now)
                    now = self.clock()
                    if self._should_stop():  # a stop asked during the sleep ends before another command
                        break
                if wait is not None:
                    # tick on the rig's sample: wake SAMPLE_LEAD of a period before it is due, wait for
                    # it, and take its arrival as this period's deadline, so the loop follows the rig's
                    # clock instead of beating against it (which leaves periods with no new sample and
                    # samples never read)
                    arrived = wait(wp)
                    now = self.clock()
                    if arrived is not None:
                        t0, deadline = arrived - k * wp, arrived
                self.jitter_s.add(max(0.0, now - deadline))
                start = now
                self._step(k, missed_last)
                end = self.clock()
                step = end - start
                self.step_s.add(step)
                self.steps += 1
                next_deadline = t0 + (k + 1) * wp
                late = end > next_deadline
                # the controller's deadline: a simulated rig's plant time is not the controller's
                late_ctrl = end - self._io_s > next_deadline
                # the watchdog judges real time: accelerated (speed > 1), a step is late when its
                # runtime tick's work (its thread's CPU time) overruns the rig period, the budget a
                # real rig would give it (the sim rig's write, which simulates the plant, is no work a
                # real host would do; module doc)
                over = self._tick_over_period()
                missed_last = (late_ctrl if self.speed <= 1.0 else over) and not self._warming
                self.over_budget += int(over and not self._warming)
                self.over_wall += int(self._last_tick > self.period and not self._warming)
                self._warming = False
                self._last_tick = self._last_tick_cpu = 0.0
                self.deadline_misses += int(late_ctrl)
                if late:
                    k_next = int(math.floor((end - t0) / wp)) + 1
                    self.skipped_periods += k_next - (k + 1)
                    k = k_next
                else:
                    k += 1
                if missed_last and self._ctrl_steps > self.warmup_periods:
                    self.overruns += 1
                    if self._miss_run == 0:
                        self.event("overrun_warning", f"step {U.to_ms(step - self._io_s):.2f} ms of the "
                                   f"{U.to_ms(wp):g} ms period past its deadline (a warning: {self.miss_limit} in a "
                                   "row latch the overrun fault)")
                if missed_last:
                    self._miss_run += 1 if self._ctrl_steps > self.warmup_periods else 0
                    # with a monitor, its overrun test (fed above) is the loop watchdog
                    if self.monitor is None and self._miss_run == self.miss_limit and self.mode == "running":
                        self._fault("overrun", f"{self.miss_limit} deadlines missed in a row (period "
                                               f"{U.to_ms(wp):g} ms wall)")
                        self.mode = "safe"
                else:
                    self._miss_run = 0
                self._log_row(step)
                if self.steps % self.status_every == 0:
                    self.state.publish(self.status())
        except RigLinkError as exc:
            self.end_reason = "link lost"
            self._fault("link_loss", str(exc))
            raise
        except BaseException as exc:
            self.end_reason = f"exception: {type(exc).__name__}"
            self._fault("exception", f"{type(exc).__name__}: {exc}")
            raise
        finally:
            sys.setswitchinterval(switch)
            self._go_safe()
            self.mode = "stopped"
            self.event("safe_exit" if self.safe_exit else "unsafe_exit", self.end_reason or "ended")
            self.wall_s = self.clock() - t0
            self.rss_end = rss_mb()
            self.gc.close()  # its counts stay for the stats
            self._log_row(float("nan"))
            self.state.publish(self.status())
            if self.log is not None:
                self.log.close()
        return self.stats()

    def stats(self) -> dict:
        """daemon_stats.json: :data:`STATS_KEYS` (ms, kPa, MB) and end_reason, skipped_periods,
        steps_over_period (ticks longer than the rig period: by wall time in real time, by the loop
        thread's CPU time when accelerated, module doc), steps_over_period_wall (by wall time), step_ms_max,
        tick_ms_median and tick_ms_p99 (the runtime tick without the rig's I/O, wall time),
        tick_cpu_ms_median and tick_cpu_ms_p99 (its thread's CPU time), speed, rig_time_s, wall_s,
        monitor_margins: how near the supervisor's trend tests came to firing (leak_drop_kpa,
        leak_fraction, pump_rise_kpa; see :attr:`hbma_ctrl.runtime.watchdog.SafetyMonitor.closest`) and
        the robot loop's burst test (burst_sigma: its largest sum, sigma; None without the test), and
        the garbage collector's pauses in any thread (gc_collections by generation, gc_pause_ms_max,
        gc_pause_ms_total, gc_frozen; :meth:`hbma_ctrl.app.daemon.gcwatch.GcWatch.stats`)."""
        st, jt, tk = self.step_s.summary(), self.jitter_s.summary(), self.tick_s.summary()
        tc = self.tick_cpu_s.summary()
        ms = lambda x: None if not math.isfinite(x) else float(U.to_ms(x))  # noqa: E731
        return {"rate_hz": 1.0 / self.period, "steps": self.steps, "deadline_misses": self.deadline_misses,
                "overruns": self.overruns,
                "step_ms_median": ms(st["median"]), "step_ms_p99": ms(st["p99"]), "jitter_ms_p99": ms(jt["p99"]),
                "max_pressure_kpa": float(U.to_kpa(self.max_pressure)) if math.isfinite(self.max_pressure) else None,
                "pressure_limit_kpa": float(U.to_kpa(self.runner.p_limit)), "faults": self.faults(),
                "safe_exit": bool(self.safe_exit), "rss_mb_start": self.rss_start, "rss_mb_end": self.rss_end,
                "end_reason": self.end_reason, "skipped_periods": self.skipped_periods,
                "steps_over_period": self.over_budget, "repeated_samples": self.repeated_samples,
                "step_ms_max": ms(st["max"]), "tick_ms_median": ms(tk["median"]), "tick_ms_p99": ms(tk["p99"]),
                "steps_over_period_wall": self.over_wall, "tick_cpu_ms_median": ms(tc["median"]),
                "tick_cpu_ms_p99": ms(tc["p99"]),
                "speed": self.speed, "rig_time_s": float(self.t),
                "wall_s": float(self.wall_s), "monitor_margins": self._margins(),
                **(self.gc.stats() if self.gc is not None else {})}

    def _margins(self) -> dict:
        c = self.monitor.closest if self.monitor is not None else {}
        kpa = lambda x: float(U.to_kpa(x)) if math.isfinite(x) else None  # noqa: E731
        return {"leak_drop_kpa": kpa(c.get("leak_drop", math.nan)), "leak_fraction": c.get("leak_fraction"),
                "pump_rise_kpa": kpa(c.get("pump_rise", math.nan)),
                "burst_sigma": self.runner.burst_peak()}
