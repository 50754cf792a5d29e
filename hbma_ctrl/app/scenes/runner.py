"""Run a loaded scenario: open loop here, the role tables' scenes dispatched by :data:`SCENE_DISPATCH`.

Dispatch (first match): a [robot] table -> :func:`hbma_ctrl.app.scenes.robot.run_scene`; [controller]
-> :func:`hbma_ctrl.app.scenes.controller.run_scene`; [estimator] ->
:func:`hbma_ctrl.app.scenes.estimator.run_scene`; otherwise the open-loop plant. Each scene returns a dict of role metrics; the runner merges them under stable
role keys into ``out_dir/metrics.json`` (see :mod:`hbma_ctrl.app.metrics`). Open loop also writes
``log.csv`` (edge units), ``log.mcap`` (:func:`hbma_ctrl.app.logs.scenes.write_open_loop`) and ``run.png``
(and its PDF) for a single trial, or the protocol outputs
(:func:`hbma_ctrl.app.scenes.protocol.run_protocol`) for kind "protocol".
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

from hbma_ctrl.app.metrics import (
    merge_metrics,
    physics_problems,
    plant_metrics,
    write_log_csv,
    write_metrics,
)
from hbma_ctrl.app.logs.scenes import write_open_loop
from hbma_ctrl.app.plots import plot_run
from hbma_ctrl.app.scenes.protocol import run_protocol
from hbma_ctrl.app.scenario import Scenario
from hbma_ctrl.app.scenes.controller import run_scene as run_controller_scene
from hbma_ctrl.app.scenes.estimator import run_scene as run_estimator_scene
from hbma_ctrl.app.scenes.robot import run_scene as run_robot_scene
from hbma_ctrl.core import units as U
from hbma_ctrl.sim.batch import fidelity_for, simulate_trials

__all__ = ["refuse_recording", "run_scenario", "run_open_loop", "RunFailed", "check_physics", "SCENE_DISPATCH", "LONG_RUN_STEPS", "step_count_note"]

#: fixed steps (trials x steps) above which a run says before starting how long it may take
LONG_RUN_STEPS = 2_000_000
#: a conservative cost of one trial step on one core, s (rk4, one trial; a batch shares it)
STEP_COST_S = 50e-6


class RunFailed(RuntimeError):
    """The run finished but produced nothing usable (every trial diverged); its files are still written."""

#: role section -> the function running the whole scene; checked in this order
SCENE_DISPATCH = (
    ("robot", run_robot_scene),
    ("controller", run_controller_scene),
    ("estimator", run_estimator_scene),
)


def run_open_loop(scn: Scenario, out_dir: Path) -> dict:
    """Simulate the scenario's trial(s) open loop; write log CSV(s) and plots; return {"plant": ...}."""

    t0 = time.perf_counter()
    note = step_count_note(scn)
    if note:
        print(note, file=sys.stderr, flush=True)
    if scn.kind == "protocol":
        trials = scn.trials()
        rows = run_protocol(scn.actuator.material, out_dir, scn.sim.integrator, scn.sim.dt, scn.fidelity,
                            trials=trials, plots=True, log_dt=scn.sim.log_dt)
        statuses: dict = {}
        for r in rows:
            statuses[r["status"]] = statuses.get(r["status"], 0) + 1
        failed = [r["failed_because"][0] for r in rows if r["status"] == "failed"]
        plant = {
            "n_trials": len(rows),
            "status": statuses,
            "max_height_mm": max(r["max_height_mm"] for r in rows),
            "max_pressure_kpa": max(r["max_pressure_kpa"] for r in rows),
            "summary_csv": "summary.csv",
        }
    else:
        trial = scn.trials()[0]
        fid = fidelity_for(trial, scn.fidelity)
        # a long run (the note above) shows a progress bar in model seconds with the time left
        (log,) = simulate_trials([trial], scn.sim, fid, progress=note is not None)
        write_log_csv(log, out_dir / "log.csv")
        write_open_loop(log, out_dir, scn.path, extra={"kind": "open loop", "status": log.status})
        plot_run(log, out_dir / "run.png", title=f"{scn.name}: {log.fidelity}, {scn.sim.integrator}, "
                 f"status {log.status}", sensor_range=scn.sim.sensor_range)
        plant = plant_metrics([log])
        failed = physics_problems(log, trial.actuator.material, trial.pneumatics.csv_path)
        if failed:  # a finished run whose numbers are not physics is not a result
            plant["status"] = "failed"
        plant["log_csv"] = "log.csv"
        plant["plot_png"] = "run.png"
    plant["integrator"] = scn.sim.integrator
    if scn.sim.integrator == "radau":
        plant["dt_ms"] = None  # adaptive
    elif scn.kind == "single":
        plant["dt_ms"] = U.to_ms(scn.sim.step_for(plant["fidelity"]))
    else:
        plant["dt_ms"] = U.to_ms(scn.sim.dt) if scn.sim.dt is not None else "default per fidelity"
    plant["wall_s"] = time.perf_counter() - t0
    if failed:
        plant["failed_checks"] = failed
    return {"plant": plant}


def step_count_note(scn: Scenario) -> str | None:
    """One line saying how many fixed steps an open-loop run takes and roughly how long (at
    :data:`STEP_COST_S` a trial step), when that is more than :data:`LONG_RUN_STEPS`; else None.
    Adaptive runs (radau) choose their own steps and get no note."""
    if scn.sim.integrator == "radau":
        return None
    trials = scn.trials()
    steps = 0
    for tr in trials:
        fid = fidelity_for(tr, scn.fidelity)
        steps += math.ceil(tr.duration / scn.sim.step_for(fid))
    if steps <= LONG_RUN_STEPS:
        return None
    hours = steps * STEP_COST_S / 3600.0
    dt_ms = U.to_ms(scn.sim.step_for(fidelity_for(trials[0], scn.fidelity)))
    return (f"note: this run takes {steps:.3g} integration steps ({len(trials)} trial(s), dt {dt_ms:g} ms): "
            f"about {hours:.2g} h at {STEP_COST_S * 1e6:g} us a step; a larger [sim] dt_ms or a shorter "
            "[scenario] duration_s is faster (Ctrl-C stops it)")


def run_scenario(scn: Scenario, out_dir: Path | str) -> dict:
    """Run a scenario into out_dir (created); returns the merged metrics written to metrics.json."""
    refuse_recording(scn)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    head = {"scenario": {"name": scn.name, "kind": scn.kind, "path": str(scn.path) if scn.path else None,
                         "fidelity": scn.fidelity, "integrator": scn.sim.integrator,
                         "roles": sorted(scn.sections)}}
    for section, run in SCENE_DISPATCH:
        if section in scn.sections:
            t0 = time.perf_counter()
            parts = run(scn, out)
            head["scenario"]["wall_s"] = time.perf_counter() - t0
            metrics = merge_metrics(head, parts)
            break
    else:
        metrics = merge_metrics(head, run_open_loop(scn, out))
    write_metrics(metrics, out / "metrics.json")
    status = metrics.get("plant", {}).get("status")
    counts = {status: 1} if isinstance(status, str) else (status or {})
    if counts and set(counts) == {"diverged"}:  # metrics of a run that never ran are not results
        n = counts["diverged"]
        which = f"all {n} trials" if n > 1 else "the trial"
        raise RunFailed(f"{which} diverged, status diverged (see the events in metrics.json)")
    check_physics(counts, metrics.get("plant", {}).get("failed_checks") or [], "metrics.json plant.failed_checks")
    return metrics


def refuse_recording(scn: Scenario) -> None:
    """ValueError for a scenario with a [schedule]: a recording runs on the rig daemon, not as a scene."""
    if "schedule" in scn.sections:
        raise ValueError("[schedule]: a recording runs on the rig daemon (hbma-ctrl daemon FILE --rig sim|serial:PORT)")


def check_physics(statuses: dict, failed: list[str], where: str) -> None:
    """:class:`RunFailed` naming the first of ``failed`` (the reasons of the trials whose status is
    'failed', from :func:`hbma_ctrl.app.metrics.physics_problems`) and ``where`` they all are; nothing
    when none failed. ``statuses``: trial status -> count."""
    if failed:
        total = sum(statuses.values())
        which = f"{len(failed)} of {total} trials" if total > 1 else "the run"
        raise RunFailed(f"{which} failed the physics checks ({where}); {failed[0]}")
