"""Run estimators against the rig over open-loop trials and score them (SI inside).

For each trial: the rig (:func:`hbma_ctrl.sim.rig.simulate_rig`, mismatched, platform fidelity, noisy
saturating sensor) gives the readings and the truth; the nominal model run open loop with the same
commands and the true load (:func:`hbma_ctrl.sim.simulate.simulate`, the paper's model) gives the
open-loop baseline; the filter runs on the readings and the commands only.

Metrics per trial (:func:`score`): height NRMSD of the filter and of the open-loop model (docs/concepts/model.md §7
eq. 16 against the rig's true height), pressure NRMSD of the filter's pressure, RMSE of the contact
force, the steady-contact force error relative to the true load (mean over the last second of
inflation while in contact), NEES of (h, F) and NIS (means over the run), the median wall time of
a step, the steps whose estimate breaks a hard constraint (``constraint_violations``:
:func:`hbma_ctrl.estimators.mhe.constraint_violations`) and the height's NRMSD within
:data:`EVENT_WINDOW` of the true lift-off and touch-down (``height_nrmsd_liftoff``,
``height_nrmsd_touchdown``, :func:`contact_events`; normalised by the run's range). :func:`aggregate` turns them into the ``"estimator"`` metrics object: means over the
trials, the worst trial (``height_ratio_to_open_loop_max``, ``worst_ratio_trial``) and, per
protocol scenario (the t0 x r1 x load cell, mean over its speeds; :func:`~hbma_ctrl.sim.batch.scenario_of`),
``n_scenarios``, ``scenarios_at_half_open_loop`` and ``scenario_ratio_to_open_loop_max`` /
``worst_ratio_scenario``.
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np

from hbma_ctrl.estimators.baselines import FilterpyEKF, ReferenceEKF
from hbma_ctrl.estimators.common import FilterSettings
from hbma_ctrl.estimators.ekf import EKF
from hbma_ctrl.estimators.innovation import innovation_test
from hbma_ctrl.estimators.mhe import MHE, constraint_violations
from hbma_ctrl.estimators.steady import SteadyStateKF
from hbma_ctrl.estimators.ukf import UKF
from hbma_ctrl.app.metrics import nrmsd
from hbma_ctrl.core import units as U
from hbma_ctrl.sim.batch import quiet_worker, scenario_of
from hbma_ctrl.sim.rig import RigRecord, RigSettings, simulate_rig
from hbma_ctrl.sim.simulate import simulate
from hbma_ctrl.sim.trial import SimSettings, Trial

__all__ = ["EVENT_COUNTS", "EVENT_WINDOW", "LIFT_HEIGHT", "contact_events", "BENCH_FILTERS", "TrialResult", "run_filter", "run_and_score", "evaluate_trials", "score", "aggregate", "make_filter",
           "FILTERS", "NEES_FLOOR"]

FILTERS = ("ekf", "ukf", "mhe")
#: per-run counts of the filter's rarer events, score key -> the Estimate flag counted (steps raising
#: it): lift-offs a load prior ruled out (hbma_ctrl.estimators.ekf_step.LIFT_PRIOR_SIGMAS), lift-offs the flow
#: and dead-volume factors' ratio showed (flat_ratio_min), load changes the excess sum declared
#: (EXCESS_THRESHOLD). estimator_trials.csv has them as its last columns, in this order
EVENT_COUNTS = {"lift_offs_implausible": "lift_off_implausible", "lift_offs_ratio": "lift_off_ratio",
                "load_changes_excess": "load_excess"}
#: the filters ``bench ekf`` compares: the two above, the EKF's reference path and filterpy's EKF
BENCH_FILTERS = ("ekf", "ekf_reference", "filterpy", "ukf")
#: variance floors of (h, F) in the NEES, m^2 and N^2 (a flat membrane's h = 0 is exactly known)
NEES_FLOOR = np.array([(0.05e-3) ** 2, 0.02 ** 2])


def make_filter(kind: str, trial: Trial, settings: FilterSettings):
    """An EKF, UKF or MHE for the trial's nominal actuator and pneumatics (and, with
    ``settings.load_prior == 'nominal'``, the trial's nominal load as the initial load guess).
    The bench's baselines: ``ekf_reference`` (:class:`ReferenceEKF`) and ``filterpy``
    (:class:`FilterpyEKF`, the trial's nominal load as its initial load) and ``dlqe``
    (:class:`~hbma_ctrl.estimators.steady.SteadyStateKF`, python-control's steady-state gain)."""
    if kind == "filterpy":
        return FilterpyEKF(trial.actuator, trial.pneumatics, settings, load=trial.platform.weight)
    if settings.load_prior == "nominal":
        W = trial.platform.weight
        settings = replace(settings, load_init=W, load_init_std=settings.load_prior_rel_std * W + 0.01)
    if kind == "ekf":
        return EKF(trial.actuator, trial.pneumatics, settings)
    if kind == "ekf_reference":
        return ReferenceEKF(trial.actuator, trial.pneumatics, settings)
    if kind == "ukf":
        return UKF(trial.actuator, trial.pneumatics, settings)
    if kind == "mhe":
        return MHE(trial.actuator, trial.pneumatics, settings)
    if kind == "dlqe":
        return SteadyStateKF(trial.actuator, trial.pneumatics, settings)
    raise ValueError(f"estimator.filter = '{kind}': allowed {', '.join(FILTERS)}")


@dataclass
class TrialResult:
    """Series (SI) and scores of one filter run on one rig trial."""

    name: str
    t: np.ndarray
    est: dict
    truth: dict
    meas: np.ndarray
    open_loop_h: np.ndarray | None
    nees: np.ndarray
    nis: np.ndarray
    step_s: np.ndarray
    flags: list
    scores: dict = field(default_factory=dict)
    #: per step: the estimate is the estimator's own (False: the MHE's EKF gave it, window filling or fallback)
    own: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    #: the estimator's counts after the run (its ``stats()``)
    counts: dict = field(default_factory=dict)


def run_filter(kind: str, trial: Trial, rec: RigRecord, settings: FilterSettings,
               init: tuple | None = None, start: int = 0) -> TrialResult:
    """Run a filter over a rig record from sample ``start``; ``init`` = (mean, cov) at that sample."""
    f = make_filter(kind, trial, settings)
    K = len(rec.t)
    keys = ("h1", "h2", "h", "F", "p", "W", "b", "k", "c", "std_h", "std_F")
    rows = np.full((K, len(keys)), np.nan)
    C = np.zeros((K, 2, 2))
    C[:, 0, 0] = C[:, 1, 1] = 1.0
    innov = np.full(K, np.nan)
    nis = np.full(K, np.nan)
    step_s = np.full(K, np.nan)
    flags: list = [frozenset()] * K
    own = np.ones(K, dtype=bool)
    if init is not None:
        f.reset(rec.t[start], init[0], init[1])
    t_s = rec.t.tolist()
    meas = rec.meas.tolist()
    u0 = np.zeros(3)
    for k in range(start, K):
        # the command array as recorded (the rig's, already checked): a Command per step would
        # re-check the same numbers 150 x 600 times in the protocol
        e = f.step(t_s[k], meas[k], rec.u[k - 1] if k > 0 else u0)
        step_s[k] = f.last_step_s
        own[k] = getattr(f, "last_status", 0) >= 0
        m = e.mean
        rows[k] = (e.h1, e.h2, e.h, e.F, e.p, m[1], m[2], m[3], m[4], e.std["h"], e.std["F"])
        flags[k] = e.flags
        C[k] = f.last_output_cov[2:4, 2:4]
        if f.last_nis is not None:
            nis[k] = f.last_nis
        r = f.last_innovation
        if r is not None:
            innov[k] = r  # normalised innovation nu / sqrt(S), for the innovation test
    est = {name: rows[:, i].copy() for i, name in enumerate(keys)}
    # NEES of (h, F) per step, the 2 x 2 solve in closed form over the whole run
    C = C + np.diag(NEES_FLOOR)
    eh, eF = est["h"] - rec.truth["h"], est["F"] - rec.truth["F"]
    det = C[:, 0, 0] * C[:, 1, 1] - C[:, 0, 1] * C[:, 1, 0]
    nees = (eh * (C[:, 1, 1] * eh - C[:, 0, 1] * eF) + eF * (C[:, 0, 0] * eF - C[:, 1, 0] * eh)) / det
    nees[:start] = np.nan
    est["innov"] = innov
    counts = f.stats() if hasattr(f, "stats") else {}
    return TrialResult(trial.name, rec.t, est, rec.truth, rec.meas, None, nees, nis, step_s, flags, own=own,
                       counts=counts)


def score(res: TrialResult, trial: Trial, start: int = 0) -> dict:
    """Scores of one run (see module docstring); series compared from sample ``start`` on."""
    sl = slice(start, None)
    h, ht = res.est["h"][sl], res.truth["h"][sl]
    out = {
        "height_nrmsd": nrmsd(h, ht),
        "height_nrmsd_open_loop": nrmsd(res.open_loop_h[sl], ht) if res.open_loop_h is not None else float("nan"),
        "pressure_nrmsd": nrmsd(res.est["p"][sl], res.truth["p"][sl]),
        "force_rmse_n": float(np.sqrt(np.nanmean((res.est["F"][sl] - res.truth["F"][sl]) ** 2))),
        "nees_mean": float(np.nanmean(res.nees[sl])),
        "nis_mean": float(np.nanmean(res.nis[sl])) if np.any(np.isfinite(res.nis[sl])) else float("nan"),
        "step_us_median": float(U.to_us(np.nanmedian(res.step_s[sl]))),
        "height_rmse_mm": float(U.to_mm(np.sqrt(np.mean((h - ht) ** 2)))),
    }
    # the steps whose estimate breaks a hard constraint (h, h2, h1 - h2, F, the load state >= 0)
    out["constraint_violations"] = float(constraint_violations(res.est["h1"][sl], res.est["h2"][sl], h,
                                                               res.est["F"][sl], res.est["W"][sl]))
    # the height around the truth's lift-off and touch-down (EVENT_WINDOW either side), normalised by
    # the run's range as the NRMSD
    for key, i in zip(("height_nrmsd_liftoff", "height_nrmsd_touchdown"), contact_events(ht)):
        out[key] = float("nan")
        if i is not None:
            w = int(round(EVENT_WINDOW / max(float(np.median(np.diff(res.t))), 1e-6)))
            a, b = max(i - w, 0), min(i + w + 1, len(ht))
            span = float(np.max(ht) - np.min(ht))
            if span > 0:
                out[key] = float(np.sqrt(np.mean((h[a:b] - ht[a:b]) ** 2)) / span)
    # the detectors' rarer events, counted per run (EVENT_COUNTS)
    for key, flag in EVENT_COUNTS.items():
        out[key] = float(sum(flag in f for f in res.flags[sl]))
    # model-form check on the innovations alone (hbma_ctrl.estimators.innovation): the run's largest windowed
    # self-normalised innovation mean, and whether it exceeds the test's threshold
    if "innov" in res.est:
        it = innovation_test(res.est["innov"][sl])
        # no full window (a run shorter than the window): no verdict, left out of the flag rate
        out["innovation_stat"] = it["stat"]
        out["innovation_flag"] = float(it["flag"]) if math.isfinite(it["stat"]) else float("nan")
    W = trial.platform.weight
    t_inf = trial.schedule.times[1] if len(trial.schedule.times) > 1 else trial.duration
    win = (res.t >= t_inf - 1.0) & (res.t < t_inf) & (res.truth["h"] > 0.5e-3)
    win[:start] = False
    if W > 0 and win.sum() >= 10:
        out["force_steady_rel_err"] = float(abs(np.mean(res.est["F"][win]) - W) / W)
    else:
        out["force_steady_rel_err"] = float("nan")
    return out


#: half-width of the lift-off and touch-down windows of the scores, s
EVENT_WINDOW = 0.2
#: the truth's height above this is off the rig (lift-off, touch-down), m
LIFT_HEIGHT = 0.2e-3


def contact_events(h_true: np.ndarray) -> tuple:
    """(lift-off, touch-down) sample indices of a true height series (m): the first sample above
    :data:`LIFT_HEIGHT` after one at or below it, and the first at or below it after the last lift;
    None where there is no such sample."""
    up = np.asarray(h_true) > LIFT_HEIGHT
    rise = np.flatnonzero(~up[:-1] & up[1:])
    fall = np.flatnonzero(up[:-1] & ~up[1:])
    lift = int(rise[0]) + 1 if rise.size else None
    down = int(fall[-1]) + 1 if fall.size and (lift is None or fall[-1] + 1 > lift) else None
    return lift, down


def run_and_score(kind: str, trial: Trial, rec: RigRecord, settings: FilterSettings,
                  open_loop_h: np.ndarray) -> TrialResult:
    """Run a filter over a rig record and score it against the truth and the open-loop height."""
    r = run_filter(kind, trial, rec, settings)
    n = min(len(open_loop_h), len(rec.t))
    r.open_loop_h = np.full(len(rec.t), np.nan)
    r.open_loop_h[:n] = open_loop_h[:n]
    r.scores = score(r, trial)
    r.scores["rig_status"] = rec.status
    return r


def _open_loop(trials: list[Trial], dt: float) -> list[np.ndarray]:
    logs = simulate(trials, SimSettings(integrator="rk4", log_dt=dt))
    return [lg["h"] for lg in logs]


def _chunk(args) -> list[TrialResult]:
    kind, trials, rig, fs, with_series, ids = args
    recs = simulate_rig(trials, rig, ids)
    ol = _open_loop(trials, rig.sample_period)
    out = []
    for tr, rec, h_ol in zip(trials, recs, ol):
        r = run_and_score(kind, tr, rec, fs, h_ol)
        if not with_series:
            r.est, r.meas, r.nees, r.nis, r.step_s, r.flags = {}, np.zeros(0), r.nees[:0], r.nis[:0], \
                r.step_s[:0], []
            r.truth = {}
        out.append(r)
    return out


def evaluate_trials(trials: list[Trial], kind: str = "ekf", rig: RigSettings | None = None,
                    settings: FilterSettings | None = None, workers: int = 1,
                    with_series: bool = True) -> list[TrialResult]:
    """Rig + open-loop model + filter over trials (chunks of trials per worker process)."""
    rig = (rig or RigSettings()).validate()
    fs = (settings or FilterSettings()).validate()
    workers = max(1, min(int(workers), len(trials), os.cpu_count() or 1))
    if workers == 1:
        return _chunk((kind, trials, rig, fs, with_series, None))
    # interleave so each chunk has a mix of loaded and unloaded trials (balanced cost)
    chunks = [trials[i::workers] for i in range(workers)]
    order = [list(range(len(trials)))[i::workers] for i in range(workers)]
    res: list = [None] * len(trials)
    with ProcessPoolExecutor(max_workers=workers, initializer=quiet_worker) as ex:
        for idx, part in zip(order, ex.map(_chunk, [(kind, c, rig, fs, with_series, o)
                                                          for c, o in zip(chunks, order)])):
            for i, r in zip(idx, part):
                res[i] = r
    return res


def aggregate(results: list[TrialResult]) -> dict:
    """The metrics.json ``"estimator"`` object: means over trials, worst cases, counts."""
    keys = ("height_nrmsd", "height_nrmsd_open_loop", "pressure_nrmsd", "force_rmse_n", "nees_mean",
            "nis_mean", "step_us_median", "height_rmse_mm", "height_nrmsd_liftoff", "height_nrmsd_touchdown")
    S = {k: np.array([r.scores.get(k, np.nan) for r in results], dtype=float) for k in keys}
    # a key no trial has (no touch-down in any trial, say) is NaN in metrics.json, without numpy's warning
    out = {k: float(np.nanmean(v)) if np.isfinite(v).any() else float("nan") for k, v in S.items()}
    ratio = S["height_nrmsd"] / S["height_nrmsd_open_loop"]
    fse = np.array([r.scores["force_steady_rel_err"] for r in results], dtype=float)
    flagged = np.array([r.scores.get("innovation_flag", np.nan) for r in results], dtype=float)
    flagged = flagged[np.isfinite(flagged)]  # runs with a verdict (hbma_ctrl.estimators.innovation)
    # per scenario (the protocol's t0 x r1 x load cell, mean over speeds and seeds; trials whose
    # membrane never lifts have no NRMSD and are left out)
    cells: dict = {}
    for r, e, o in zip(results, S["height_nrmsd"], S["height_nrmsd_open_loop"]):
        if math.isfinite(e) and math.isfinite(o):
            cells.setdefault(scenario_of(r.name), []).append((e, o))
    cell_ratio = {c: float(np.mean([e for e, _ in v]) / np.mean([o for _, o in v])) for c, v in cells.items()}
    worst_cell = max(cell_ratio, key=cell_ratio.get) if cell_ratio else None
    out.update({
        "n_trials": len(results),
        "n_scenarios": len(cell_ratio),
        "scenarios_at_half_open_loop": int(sum(v <= 0.5 for v in cell_ratio.values())),
        "scenario_ratio_to_open_loop_max": cell_ratio[worst_cell] if worst_cell else float("nan"),
        "worst_ratio_scenario": worst_cell,
        "height_nrmsd_max": float(np.nanmax(S["height_nrmsd"])),
        "height_nrmsd_open_loop_max": float(np.nanmax(S["height_nrmsd_open_loop"])),
        "height_ratio_to_open_loop_max": float(np.nanmax(ratio)),
        "worst_ratio_trial": results[int(np.nanargmax(ratio))].name if np.any(np.isfinite(ratio)) else None,
        "force_steady_rel_err_mean": float(np.nanmean(fse)) if np.any(np.isfinite(fse)) else float("nan"),
        # share of the trials whose innovations the model-form test flags (hbma_ctrl.estimators.innovation)
        "innovation_flag_rate": float(np.mean(flagged)) if flagged.size else float("nan"),
        # the detectors' rarer events summed over the trials (EVENT_COUNTS), and the trials with a
        # lift-off the load prior ruled out
        **{key: int(sum(r.scores.get(key, 0) for r in results)) for key in EVENT_COUNTS},
        # steps whose estimate broke a hard constraint, summed over the trials
        "constraint_violations": int(sum(r.scores.get("constraint_violations", 0) for r in results)),
        # the moving-horizon estimator's failed steps the EKF took over (0 for the filters)
        "fallbacks": int(sum(r.counts.get("fallbacks", 0) for r in results)),
        "trials_with_implausible_lift_off": int(sum(r.scores.get("lift_offs_implausible", 0) > 0 for r in results)),
        "force_steady_rel_err_max": float(np.nanmax(fse)) if np.any(np.isfinite(fse)) else float("nan"),
        "rig_status": {s: sum(r.scores["rig_status"] == s for r in results)
                       for s in sorted({r.scores["rig_status"] for r in results})},
    })
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in out.items()}
