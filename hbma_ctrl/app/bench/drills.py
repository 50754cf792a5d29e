"""``hbma-ctrl bench drills``: many fault drills through the daemon's own loop, and how many are found.

Each drill is one run of the daemon's loop (:class:`hbma_ctrl.app.daemon.loop.DaemonLoop`: the
configuration's runner, its simulated rig and safety monitor, and the runner's own fault tests such
as the robot's burst test) in lockstep on a virtual clock. One fault of ``kind`` (a
``[[daemon.fault]]`` kind with its value, e.g. ``leak`` at duty 1: an outlet stuck fully open) is
injected on a random chamber at a random rig time in ``[from_s, to_s]``, and the run goes on for
``after_s`` more. With ``every_s`` > 0 random setpoints of the soak's kind
(:func:`hbma_ctrl.app.bench.soak.random_target`) replace the file's targets every ``every_s`` from
``every_s`` on, so that the drills meet chambers held, rising and falling; 0 keeps the file's
schedule. The draws come from ``seed``: the same seed gives the same drills.

A drill is *found* when the first fault the daemon latches at or after the injection (within
``after_s`` of it) names the drilled chamber; one that names another chamber or none is recorded as
``other_fault``; a fault latched before the injection is a *false alarm* (that drill is then not
judged). The robot NMPC's wall-time budget is lifted (as the soak's replay does): its commands, and
so what each drill meets, do not depend on this machine's load.

Writes ``drills.json``: per drill the time, chamber, its reading at the injection (kPa), what was
found (kind, delay s, the reading at the find in kPa, the fault's cause) and the margins of the tests
(``monitor_margins``), and the totals: found by kind, delay median and max, false alarms.
"""

from __future__ import annotations

import json
import random
from collections import Counter
import time
from pathlib import Path

import numpy as np

from hbma_ctrl.app.bench.soak import lift_budget, random_target
from hbma_ctrl.app.daemon.build import build_runner, make_monitor, make_rig
from hbma_ctrl.app.daemon.config import load_config
from hbma_ctrl.app.daemon.faults import INJECTED_KINDS, VALUE_KEY, FaultyRig, parse_faults
from hbma_ctrl.app.daemon.loop import DaemonLoop
from hbma_ctrl.app.daemon.state import DaemonState
from hbma_ctrl.app.metrics import json_safe
from hbma_ctrl.app.schema.api import SetpointRequest
from hbma_ctrl.core import units as U
from hbma_ctrl.runtime.watchdog import FAULT_KINDS

__all__ = ["DRILL_KINDS", "DEFAULT_VALUE", "run_drills", "drill_fault", "drill_value", "check_drills"]

#: the kinds a drill can inject (a link loss ends the run: it is the daemon's own drill test's)
DRILL_KINDS = tuple(k for k in INJECTED_KINDS if k != "link_loss")
#: the value a kind takes when ``--value`` is not given (an outlet stuck fully open, a leak as large as
#: the outlet, an inlet stuck shut); offset and out_of_range need one
DEFAULT_VALUE = {"leak": 1.0, "stuck_outlet": 1.0, "stuck_inlet": 0.0}


def drill_value(kind: str, value: float | None) -> float | None:
    """The value a drill of ``kind`` injects (``value`` as given, else the kind's default; None for a
    kind that takes none); ValueError naming ``--kind`` or ``--value``."""
    if kind not in DRILL_KINDS:
        raise ValueError(f"--kind = '{kind}': allowed {', '.join(DRILL_KINDS)}")
    key = VALUE_KEY[kind]
    if key is None:
        if value is not None:
            raise ValueError(f"--value = {value:g}: kind '{kind}' takes no value")
        return None
    value = DEFAULT_VALUE.get(kind) if value is None else value
    if value is None:
        raise ValueError(f"--value: kind '{kind}' needs a value ({key})")
    return value


def drill_fault(kind: str, value: float | None, chamber: int, start: float, n: int):
    """The drill's fault as a ``[[daemon.fault]]`` table (so a bad kind or value is the table's own
    error, naming ``--kind`` / ``--value`` in the user's units) -> FaultSpec."""
    value = drill_value(kind, value)
    key = VALUE_KEY[kind]
    raw: dict = {"kind": kind, "chamber": chamber, "start_s": start}
    if key is not None:
        raw[key] = value
    try:
        return parse_faults([raw], n)[0]
    except ValueError as exc:
        msg = str(exc)
        raise ValueError(msg.replace("[daemon.fault[0]] " + (key or ""), f"--value ({key})", 1)) from None


def check_drills(kind: str, value: float | None, from_s: float, to_s: float) -> None:
    """One ValueError naming the flag for a bad kind, value or injection window (before anything runs)."""
    if not 0.0 <= from_s <= to_s < float("inf"):
        raise ValueError(f"--from-s = {from_s:g} and --to-s = {to_s:g}: 0 <= from <= to is required (s)")
    drill_fault(kind, value, 0, from_s, 1)


def _one(cfg, kind: str, value: float | None, start: float, chamber: int | None, after_s: float,
         every_s: float, rng: random.Random) -> dict:
    """One drill (module doc); ``chamber`` None draws it."""
    runner = build_runner(cfg)
    n = runner.n
    ch = rng.randrange(n) if chamber is None else chamber
    rig = FaultyRig(make_rig(cfg, runner), [drill_fault(kind, value, ch, start, n)])
    lift_budget(runner)
    clock = [0.0]
    state = DaemonState()
    loop = DaemonLoop(runner, rig, state, cfg.period, speed=1.0, duration=start + after_s, log=None,
                      monitor=make_monitor(cfg, runner), status_every=10**9, miss_limit=cfg.miss_limit,
                      clock=lambda: clock[0], sleep=lambda d: clock.__setitem__(0, clock[0] + d))
    n_layers = runner.design.n_layers if runner.kind == "robot" else 0
    t_next = [every_s if every_s > 0 else float("inf")]

    def take() -> list:
        out = []
        while loop.t + 1e-9 >= t_next[0]:
            body = random_target(rng, n_layers, n)
            out.append(runner.check_setpoint(SetpointRequest.model_validate(body).to_si())["applied"])
            t_next[0] += every_s
        return out

    state.take_setpoints = take
    readings: dict = {}
    read = rig.read

    def recorded_read():
        r = read()
        readings[round(rig.t, 6)] = np.asarray(r.p, dtype=float).reshape(n).copy()
        return r

    rig.read = recorded_read
    stats = loop.run()
    faults = [e for e in loop.events if e["kind"] in FAULT_KINDS]
    before = [e for e in faults if e["t_s"] < start - 1e-9]
    after = [e for e in faults if e["t_s"] >= start - 1e-9]
    name = runner.names[ch]
    ts = [t for t in readings if t <= start + 1e-9]
    p0 = readings[max(ts)][ch] if ts else float("nan")
    row = {"start_s": start, "chamber": name, "p_at_start_kpa": float(U.to_kpa(p0)), "false_alarm": bool(before),
           "found": None, "delay_s": None, "p_at_find_kpa": None, "cause": None, "other_fault": None,
           "max_pressure_kpa": stats.get("max_pressure_kpa"), "monitor_margins": stats.get("monitor_margins")}
    if before:
        row["cause"] = f"{before[0]['kind']} at {before[0]['t_s']:.2f} s: {before[0]['cause']}"
    elif after and after[0]["cause"].startswith(f"{name}: "):
        e = after[0]
        p = readings.get(round(e["t_s"], 6))
        row.update(found=e["kind"], delay_s=round(e["t_s"] - start, 6), cause=e["cause"],
                   p_at_find_kpa=None if p is None else float(U.to_kpa(p[ch])))
    elif after:
        # a fault after the injection that does not name the drilled chamber is not a find
        row["other_fault"] = f"{after[0]['kind']} at {after[0]['t_s']:.2f} s: {after[0]['cause']}"
    return row


def run_drills(config: Path, out: Path, drills: int, seed: int, kind: str = "leak", value: float | None = None,
               after_s: float = 1.0, every_s: float = 5.0, from_s: float = 1.0, to_s: float = 20.0,
               on_drill=None) -> dict:
    """Run the bench (module doc) into ``out`` (drills.json); returns its content. Times in s of rig time."""
    cfg = load_config(config, {"--rig": "sim"})
    check_drills(kind, value, from_s, to_s)
    value = drill_value(kind, value)
    rng = random.Random(seed)
    rows = []
    wall0 = time.perf_counter()
    for i in range(drills):
        start = round(rng.uniform(from_s, to_s), 2)
        row = _one(cfg, kind, value, start, None, after_s, every_s, random.Random(rng.getrandbits(32)))
        row["drill"] = i
        rows.append(row)
        if on_drill:
            on_drill(row)
    judged = [r for r in rows if not r["false_alarm"]]
    found = [r for r in judged if r["found"] is not None]
    by_kind = dict(Counter(r["found"] for r in found))
    delays = np.array([r["delay_s"] for r in found]) if found else np.zeros(0)
    res = {"config": str(config), "kind": kind, "value": value, "drills": drills, "seed": seed, "after_s": after_s,
           "setpoint_every_s": every_s, "from_s": from_s, "to_s": to_s,
           "found": len(found), "judged": len(judged), "false_alarms": len(rows) - len(judged),
           "found_by_kind": by_kind,
           "delay_s_median": float(np.median(delays)) if delays.size else None,
           "delay_s_max": float(delays.max()) if delays.size else None,
           "wall_s": time.perf_counter() - wall0, "per_drill": rows}
    Path(out, "drills.json").write_text(json.dumps(json_safe(res), indent=1) + "\n")
    return res
