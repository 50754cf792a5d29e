"""``hbma-ctrl bench poses``: many setpoint changes through the daemon's own runner, rig and safety
monitor, in lockstep in this process, and how high each change drives the pressures.

The soak (:mod:`hbma_ctrl.app.bench.soak`) runs the daemon as a user does and stops at its first
fault; this bench asks how often a change of setpoint drives a reading over the pressure limit, or
trips the monitor, over many changes: every ``every_s`` of rig time a random target of the soak's
kind (:func:`hbma_ctrl.app.bench.soak.random_target`, the same draws for the same seed) goes through
the runner's own check and clip (as ``POST /setpoint``), the loop ticks on the simulated rig
(the configuration's ``[rig]``) and the monitor checks every reading with
the command sent last, and the runner's own tests (the robot's burst test) run. A fault is recorded
and the monitor and those tests re-armed (a daemon would have stopped;
here the run goes on, so one run gives a rate). ``target_rate_mm_s`` overrides ``[robot]
target_rate_mm_s`` (None: the configuration's, else the daemon's default).

Writes ``poses.json``: per change the highest reading (kPa) and its chamber until the next change,
the counts over the controller's limit and over the monitor's cap, the faults (rig time, kind,
chamber, cause) and the wall time.
"""

from __future__ import annotations

import json
import math
import random
import time
from pathlib import Path

import numpy as np

from hbma_ctrl.app.bench.soak import random_target
from hbma_ctrl.app.daemon.build import build_runner, make_monitor, make_rig
from hbma_ctrl.app.daemon.config import load_config
from hbma_ctrl.system.rigio import safe_u
from hbma_ctrl.app.metrics import json_safe
from hbma_ctrl.app.schema.api import SetpointRequest
from hbma_ctrl.core import units as U

__all__ = ["run_poses"]


def run_poses(config: Path, out: Path, duration_s: float, every_s: float, seed: int,
              target_rate_mm_s: float | None = None, on_change=None) -> dict:
    """Run the bench (module doc) into ``out`` (poses.json); returns its content. Times in s of rig time."""
    cfg = load_config(config, {"--rig": "sim"})
    runner = build_runner(cfg)
    if target_rate_mm_s is not None:
        if cfg.kind != "robot":
            raise ValueError("--target-rate-mm-s applies to a robot configuration ([robot] table)")
        runner.loop.target_rate = U.mm(float(target_rate_mm_s))
    rig = make_rig(cfg, runner)
    monitor = make_monitor(cfg, runner)
    n, period = runner.n, cfg.period
    n_layers = runner.design.n_layers if cfg.kind == "robot" else 0
    rng = random.Random(seed)
    u_last = safe_u(n)
    changes: list[dict] = []
    faults: list[dict] = []
    peak = np.full(n, -np.inf)
    t_next = every_s
    wall0 = time.perf_counter()
    steps = int(round(duration_s / period))

    def close_change():
        if changes:
            i = int(np.argmax(peak))
            changes[-1].update(peak_kpa=float(U.to_kpa(peak[i])), chamber=runner.names[i])
            if on_change:
                on_change(changes[-1])

    for k in range(steps):
        t = k * period
        if t >= t_next - 1e-9:
            close_change()
            body = random_target(rng, n_layers, n)
            reply = runner.check_setpoint(SetpointRequest.model_validate(body).to_si())
            runner.apply_setpoint(reply["applied"], t)
            changes.append({"t_s": round(t, 6), "body": body, "clipped": list(reply["clipped"])})
            peak[:] = -np.inf
            t_next += every_s
        r = rig.read()
        p = np.asarray(r.p, dtype=float).reshape(n)
        if changes:
            peak = np.fmax(peak, p)
        for f in monitor.check(t, r, u_last, False) or ():
            i = f.chamber
            faults.append({"t_s": round(t, 6), "kind": f.kind, "chamber": runner.names[i] if i is not None else None,
                           "cause": f.cause})
        if monitor.latched:
            # a daemon stops here; the bench re-arms and goes on, so one run counts every fault
            monitor.reset()
        u = runner.tick(t, p)
        found = runner.take_faults()
        for kind, i, cause in found:
            faults.append({"t_s": round(t, 6), "kind": kind, "chamber": runner.names[i], "cause": cause})
        if found:
            # the runner's own tests (the robot's burst test) re-armed too, the chamber no longer vented
            runner.clear_faults()
        rig.write(u)
        u_last = u
    close_change()
    limit, cap = runner.p_limit, monitor.settings.p_max
    peaks = np.array([c["peak_kpa"] for c in changes]) if changes else np.zeros(0)
    res = {"config": str(config), "duration_s": duration_s, "every_s": every_s, "seed": seed,
           "target_rate_mm_s": (U.to_mm(runner.loop.target_rate) if cfg.kind == "robot" else None),
           "changes": len(changes), "pressure_limit_kpa": float(U.to_kpa(limit)), "cap_kpa": float(U.to_kpa(cap)),
           "over_limit": int(np.sum(peaks > U.to_kpa(limit))), "over_cap": int(np.sum(peaks >= U.to_kpa(cap))),
           "peak_kpa_max": float(peaks.max()) if peaks.size else math.nan,
           "peak_kpa_p90": float(np.percentile(peaks, 90)) if peaks.size else math.nan,
           "faults": faults, "wall_s": time.perf_counter() - wall0, "per_change": changes}
    Path(out, "poses.json").write_text(json.dumps(json_safe(res), indent=1) + "\n")
    return res
