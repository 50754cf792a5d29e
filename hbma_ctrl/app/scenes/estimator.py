"""The ``[estimator]`` scenario section and the estimator scene (``hbma-ctrl run``).

A scene runs the rig (``[rig]`` section, :class:`hbma_ctrl.sim.rig.RigSettings`: the mismatched,
higher-fidelity truth with a noisy, saturating sensor) open loop with the scenario's inputs, feeds
the readings and the commands to the filter, and writes the estimate next to the truth:

- kind "single": ``estimate.csv`` (edge units: mm, kPa, N), ``log.mcap``
  (:func:`hbma_ctrl.app.logs.scenes.write_estimator_trial`), ``estimate.png`` and its PDF; load steps
  (``load_steps_g``) are applied to the rig mid-run;
- kind "protocol": every trial of the grid (docs/concepts/model.md §7, 150 by default), in worker processes,
  ``estimator_trials.csv`` (one row of scores per trial).

``metrics.json`` gets an ``"estimator"`` object (:func:`hbma_ctrl.app.scenes.evaluate.aggregate`):
height_nrmsd (mean over trials), height_nrmsd_open_loop (the nominal model run open loop with the
same commands and the true initial load), pressure_nrmsd, force_rmse_n, nees_mean, nis_mean,
step_us_median and worst cases; with ``compare_ukf = true`` the UKF's under ``"estimator"."ukf"``.

Section keys (edge units in the names; all optional):

==========================  ======================================================================
filter                      "ekf" (default) or "ukf"
compare_ukf                 also run the UKF on the same rig runs (bool, default false)
load_steps_g                [[t_s, mass_g], ...]: set the rig's load (single kind)
workers                     worker processes for a protocol (1-64, default 2)
seeds                       Monte-Carlo repetitions with different noise seeds (1-100, default 1)
noise_std_kpa               filter's sensor sigma (default: the rig's)
model_rel_std, flow_rel_std, flow_factor_std, modulus_std, change_threshold   filter tuning (-)
load_std_n                  load random walk, N/sqrt(s)
integrator, nsub, newton    the filter model's discretisation
compile                     compile the model to C (bool, default true)
==========================  ======================================================================
"""

from __future__ import annotations

import csv
from dataclasses import replace
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from hbma_ctrl.app.figstyle import LABELS, save
from hbma_ctrl.app.logs.scenes import write_estimator_trial

from hbma_ctrl.app.scenes.evaluate import (
    EVENT_COUNTS,
    TrialResult,
    aggregate,
    evaluate_trials,
    run_filter,
    score,
)
from hbma_ctrl.app.schema.document import parse_role
from hbma_ctrl.system.sections import EstimatorSection, filter_settings_for
from hbma_ctrl.core import units as U
from hbma_ctrl.core.interfaces import Command
from hbma_ctrl.sim.rig import Rig, RigRecord, RigSettings
from hbma_ctrl.sim.simulate import simulate
from hbma_ctrl.sim.trial import SimSettings

__all__ = ["run_scene"]



# --- single runs ----------------------------------------------------------------------------
def rig_run(scn, rig_settings: RigSettings, load_steps=()) -> RigRecord:
    """Step a :class:`Rig` through the scenario's schedule (with load steps) and record it."""
    rig = Rig(scn.actuator, scn.pneumatics, scn.platform, rig_settings)
    dt = rig_settings.sample_period
    K = int(round(scn.duration / dt)) + 1
    t = np.arange(K) * dt
    U = np.zeros((K, 3))
    meas = np.zeros(K)
    truth = {k: np.zeros(K) for k in ("h1", "h2", "h", "p", "F", "m")}
    loads = list(load_steps)
    for k in range(K):
        while loads and loads[0][0] <= t[k] + 1e-9:
            rig.set_load(loads.pop(0)[1])
        meas[k] = rig.measure()
        tr = rig.truth()
        for key in truth:
            truth[key][k] = tr[key]
        U[k] = scn.schedule.at(t[k] + 0.5 * dt)
        if k < K - 1:
            rig.apply(Command(*U[k]))
    truth["t"] = t
    return RigRecord(scn.name, t, U, meas, truth, list(rig.events), "ok")


def _open_loop_h(scn, dt: float, K: int) -> np.ndarray:
    (log,) = simulate(scn.trials(), SimSettings(integrator="rk4", log_dt=dt))
    h = np.full(K, np.nan)
    n = min(K, len(log["h"]))
    h[:n] = log["h"][:n]
    return h


def _write_series(res: TrialResult, path: Path) -> None:
    cols = [("t_s", res.t, float), ("h_true_mm", res.truth["h"], U.to_mm), ("h_est_mm", res.est["h"], U.to_mm),
            ("h_std_mm", res.est["std_h"], U.to_mm), ("h_open_loop_mm", res.open_loop_h, U.to_mm),
            ("h1_true_mm", res.truth["h1"], U.to_mm), ("h1_est_mm", res.est["h1"], U.to_mm),
            ("h2_true_mm", res.truth["h2"], U.to_mm), ("h2_est_mm", res.est["h2"], U.to_mm),
            ("F_true_n", res.truth["F"], float), ("F_est_n", res.est["F"], float), ("F_std_n", res.est["std_F"], float),
            ("p_true_kpa", res.truth["p"], U.to_kpa), ("p_meas_kpa", res.meas, U.to_kpa), ("p_est_kpa", res.est["p"], U.to_kpa),
            ("load_est_n", res.est["W"], float), ("flow_factor", res.est["b"], float), ("modulus_factor", res.est["k"], float),
            ("nees", res.nees, float), ("nis", res.nis, float),
            ("dead_volume_factor", res.est["c"], float)]  # appended: earlier columns keep their places
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow([c[0] for c in cols] + ["flags"])
        for i in range(len(res.t)):
            w.writerow([f"{c[2](c[1][i]):.6g}" for c in cols] + [";".join(sorted(res.flags[i]))])


def _plot(res: TrialResult, path: Path, title: str) -> None:
    fig = Figure(figsize=(8, 8), layout="constrained")
    ax = fig.subplots(3, 1, sharex=True)
    t = res.t
    ax[0].plot(t, U.to_mm(res.truth["h"]), "k", label="rig (truth)")
    ax[0].plot(t, U.to_mm(res.est["h"]), "C0", label="estimate")
    ax[0].fill_between(t, U.to_mm(res.est["h"] - 2 * res.est["std_h"]), U.to_mm(res.est["h"] + 2 * res.est["std_h"]),
                       color="C0", alpha=0.2, label="estimate +- 2 sigma")
    ax[0].plot(t, U.to_mm(res.open_loop_h), "C1--", label="open-loop model")
    ax[0].set_ylabel(LABELS["h"])
    ax[0].legend(fontsize=8)
    ax[1].plot(t, res.truth["F"], "k", label="rig (truth)")
    ax[1].plot(t, res.est["F"], "C0", label="estimate")
    ax[1].set_ylabel(LABELS["F"])
    ax[1].legend(fontsize=8)
    ax[2].plot(t, U.to_kpa(res.meas), ".", color="0.6", ms=2, label="sensor")
    ax[2].plot(t, U.to_kpa(res.truth["p"]), "k", label="rig (truth)")
    ax[2].plot(t, U.to_kpa(res.est["p"]), "C0", label="estimate")
    ax[2].set_ylabel(LABELS["p"])
    ax[2].set_xlabel(LABELS["t"])
    ax[2].legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    save(fig, Path(path).with_suffix(""))


def _single(scn, sec: EstimatorSection, rig: RigSettings, out: Path) -> dict:
    fs = filter_settings_for(sec, rig)
    trial = scn.trials()[0]
    kinds = [sec.filter] + (["ukf"] if sec.compare_ukf and sec.filter != "ukf" else [])
    per_kind: dict = {k: [] for k in kinds}
    first = None
    for seed in range(sec.seeds):
        rec = rig_run(scn, replace(rig, seed=rig.seed + seed), sec.load_steps)
        h_ol = _open_loop_h(scn, rig.sample_period, len(rec.t))
        for kind in kinds:
            res = run_filter(kind, trial, rec, fs)
            res.open_loop_h = h_ol
            res.scores = score(res, trial)
            res.scores["rig_status"] = rec.status
            per_kind[kind].append(res)
            if first is None:
                first = res
    _write_series(first, out / "estimate.csv")
    write_estimator_trial(first, out, scn.path, extra={"kind": "estimator", "filter": sec.filter})
    _plot(first, out / "estimate.png", f"{scn.name}: {sec.filter.upper()} on the rig "
          f"(modulus x{rig.modulus_scale:g}, flow x{rig.flow_scale:g}, V0 x{rig.V0_scale:g})")
    return _metrics(per_kind, sec, rig, {"estimate_csv": "estimate.csv", "plot_png": "estimate.png"})


def _protocol(scn, sec: EstimatorSection, rig: RigSettings, out: Path) -> dict:
    fs = filter_settings_for(sec, rig)
    trials = scn.trials()
    kinds = [sec.filter] + (["ukf"] if sec.compare_ukf and sec.filter != "ukf" else [])
    per_kind: dict = {}
    for kind in kinds:
        res = []
        for seed in range(sec.seeds):
            res += evaluate_trials(trials, kind, replace(rig, seed=rig.seed + seed), fs, workers=sec.workers,
                                   with_series=False)
        per_kind[kind] = res
    keys = ("height_nrmsd", "height_nrmsd_open_loop", "pressure_nrmsd", "force_rmse_n",
            "force_steady_rel_err", "nees_mean", "nis_mean", "step_us_median", "height_rmse_mm")
    with open(out / "estimator_trials.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        # the event counts last, in EVENT_COUNTS' order: the columns before them keep their places
        w.writerow(["trial", "filter"] + list(keys) + ["rig_status"] + list(EVENT_COUNTS))
        for kind, res in per_kind.items():
            for r in res:
                w.writerow([r.name, kind] + [f"{r.scores[k]:.6g}" for k in keys] + [r.scores["rig_status"]]
                           + [int(r.scores.get(e, 0)) for e in EVENT_COUNTS])
    return _metrics(per_kind, sec, rig, {"trials_csv": "estimator_trials.csv"})


def _metrics(per_kind: dict, sec: EstimatorSection, rig: RigSettings, files: dict) -> dict:
    main = aggregate(per_kind[sec.filter])
    main.update({"filter": sec.filter, "seeds": sec.seeds,
                 "rig": {"fidelity": rig.fidelity, "modulus_scale": rig.modulus_scale,
                         "flow_scale": rig.flow_scale, "V0_scale": rig.V0_scale,
                         "noise_std_kpa": U.to_kpa(rig.noise_std), "sensor_range_kpa": U.to_kpa(rig.sensor_range),
                         "sample_period_ms": U.to_ms(rig.sample_period), "dropout_prob": rig.dropout_prob}})
    main.update(files)
    for kind, res in per_kind.items():
        if kind != sec.filter:
            main[kind] = aggregate(res)
    return {"estimator": main}


def run_scene(scn, out_dir) -> dict:
    """Run the estimator scene of a scenario (see module docstring) -> {"estimator": {...}}."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sec = scn.role("estimator") if hasattr(scn, "role") else None
    if sec is None:
        sec = scn.role("estimator") or parse_role("estimator", {})
    rig = (scn.role("rig") if hasattr(scn, "role") else None) or RigSettings()
    if scn.kind == "protocol":
        if sec.load_steps:
            raise ValueError("estimator.load_steps_g: only for kind 'single' scenarios")
        return _protocol(scn, sec, rig, out)
    return _single(scn, sec, rig, out)
