"""``log.mcap`` of a scene (``hbma-ctrl run``): the scene's time series as the daemon's topics
(:mod:`hbma_ctrl.app.logs.signals`), so one reader and one report serve both. Each writer takes the
scene's log (SI) and the results folder; the scenario file is attached as ``config.toml``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hbma_ctrl.app.logs.signals import SignalLog
from hbma_ctrl.app.outputs import manifest

__all__ = ["LOG_MCAP", "scene_log", "write_chamber_closed_loop", "write_estimator_trial", "write_open_loop",
           "write_robot_open_loop", "write_robot_closed_loop"]

#: the MCAP log's file name in a run directory
LOG_MCAP = "log.mcap"


def scene_log(folder: Path | str, names, groups, scenario_path=None, design=None, name: str = LOG_MCAP,
              extra: dict | None = None) -> SignalLog:
    """A :class:`SignalLog` at ``folder/name`` with the run's metadata (``run``: the manifest's keys,
    ``scene``: ``extra``) and the scenario file attached."""
    man = manifest("run", None, scenario_path)
    meta = {"run": {k: "" if v is None else str(v) for k, v in man.items()
                    if k not in ("finished_utc", "status", "error")}}
    if extra:
        meta["scene"] = {k: str(v) for k, v in extra.items()}
    att = {}
    if scenario_path is not None and Path(scenario_path).is_file():
        att["config.toml"] = ("application/toml", Path(scenario_path).read_bytes())
    return SignalLog(Path(folder) / name, names, groups, design, meta, att)


def _events(log: SignalLog, events) -> None:
    for t, kind, cause in sorted(events, key=lambda e: e[0]):
        log.event(float(t), kind, cause, block=True)


def write_chamber_closed_loop(log, folder: Path | str, scenario_path=None, extra: dict | None = None) -> dict:
    """A chamber's closed loop (:class:`hbma_ctrl.app.scenes.controller.ClosedLoopLog`): readings, estimates,
    target, command, truth, the rig's and the supervisor's events. Returns the log's counts."""
    out = scene_log(folder, ["C1"], ("readings", "estimates", "targets", "commands", "truth"), scenario_path,
                    extra=extra)
    for i in range(len(log.t)):
        t = float(log.t[i])
        out.period(t, p=[log.p_meas[i]], p_est=[log.p_est[i]], h=[log.h_est[i]], target=[log.target[i]],
                   u=np.asarray(log.u[i]).reshape(3, 1), truth=(t, [log.h_true[i]], [log.p_true[i]]), block=True)
    ev = [(t, name.split(":")[0], name) for t, name in log.events]
    ev += [(e.t, e.cause, e.detail or e.cause) for e in log.supervisor_events]
    _events(out, ev)
    return out.close()


def write_estimator_trial(res, folder: Path | str, scenario_path=None, extra: dict | None = None) -> dict:
    """A filter's run on a rig trial (:class:`hbma_ctrl.app.scenes.evaluate.TrialResult`): the readings, the
    estimates and the rig's truth. Returns the log's counts."""
    out = scene_log(folder, ["C1"], ("readings", "estimates", "truth"), scenario_path, extra=extra)
    std = res.est.get("std_h")
    for i in range(len(res.t)):
        t = float(res.t[i])
        out.period(t, p=[res.meas[i]], p_est=[res.est["p"][i]], h=[res.est["h"][i]],
                   h_std=None if std is None else [std[i]], truth=(t, [res.truth["h"][i]], [res.truth["p"][i]]),
                   block=True)
    return out.close()


def write_open_loop(log, folder: Path | str, scenario_path=None, extra: dict | None = None) -> dict:
    """An open-loop trial (:class:`hbma_ctrl.sim.trial.Log`): the plant's height and pressure as truth, the
    inputs as commands, its events. Returns the log's counts."""
    out = scene_log(folder, ["C1"], ("commands", "truth"), scenario_path, extra=extra)
    t, h, p = log["t"], log["h"], log["p"]
    u = np.vstack([log["speed"], log["inlet"], log["outlet"]])
    for i in range(t.size):
        out.period(float(t[i]), u=u[:, i:i + 1], truth=(float(t[i]), [h[i]], [p[i]]), block=True)
    _events(out, [(te, name.split(":")[0], name) for te, name in log.events])
    return out.close()


def write_robot_open_loop(design, run, folder: Path | str, scenario_path=None, extra: dict | None = None) -> dict:
    """An open-loop robot run (:class:`hbma_ctrl.robot.plant.RobotRun`): every chamber's height and pressure
    as truth (and the layers' poses), its events. Returns the log's counts."""
    out = scene_log(folder, design.names, ("truth",), scenario_path, design=design, extra=extra)
    T = run.t.size
    h, p = run.h.reshape(T, -1), run.p.reshape(T, -1)
    for i in range(T):
        out.period(float(run.t[i]), truth=(float(run.t[i]), h[i], p[i]), block=True)
    _events(out, [(t, name, f"{c}: {name}") for t, c, name in run.events])
    return out.close()


def write_robot_closed_loop(design, run, folder: Path | str, scenario_path=None, name: str = LOG_MCAP,
                            extra: dict | None = None) -> dict:
    """A closed-loop robot run (:class:`hbma_ctrl.app.scenes.robot_loop.ClosedLoopRun`): measured and true
    pressures, estimated and true heights (and poses), targets, commands (supply and outlet duty; the
    robot's pump is shared, so ``speed`` is null), the supervisor's interventions. Returns the counts."""
    out = scene_log(folder, design.names, ("readings", "estimates", "targets", "commands", "truth"), scenario_path,
                    design=design, name=name, extra=extra)
    n = len(design.names)
    nan = np.full(n, np.nan)
    for i in range(run.t.size):
        t = float(run.t[i])
        out.period(t, p=run.p_meas[i], h=run.h_est[i], target=run.h_ref[i],
                   u=np.vstack([nan, run.a[i], run.o[i]]), truth=(t, run.h[i], run.p[i]), block=True)
    where = lambda i: f"{design.names[i]}: " if i is not None and 0 <= i < n else ""  # noqa: E731
    _events(out, [(e.t, e.cause, f"{where(e.chamber)}{e.detail or e.cause}") for e in run.events])
    return out.close()
