"""Closed-loop scenes: rig -> estimator (EKF) -> controller -> rig, the [controller] scenario section.

``[controller]`` keys (edge units: mm, kPa, ms, g, s):

==========================  ====================================================================
kind                        "mpc" (default), "pid", "bang_bang" or "lqi"
variant                     MPC: "rti_c_osqp" (default), "rti_osqp", "ipopt", "fatrop", ...
horizon                     MPC horizon N (default 20)
sample_ms                   controller period, ms (default 20; a multiple of the rig's period)
p_max_kpa                   pressure limit, kPa (default 35)
p_margin_kpa                MPC: keep the predicted pressure this far below p_max (default 1)
lam_max                     MPC: stretch limit (default 1.5)
h_max_mm                    MPC: height bound (default 20)
integrator, substeps        MPC discretisation ("rk4" / "euler")
w_height, w_terminal        MPC weights on the height error (per mm^2)
w_rate, w_input, c_input    MPC weights [speed, inlet, outlet]
budget_ms                   wall-clock budget of one MPC step (default 15; the rig daemon enforces it)
enforce_budget              a step slower than budget_ms is an overrun in the scene too (default
                            false: a scene's results do not depend on the machine's load)
codegen                     MPC: compile the RTI linearisation to C (default true)
fail_window_s               [t0, t1]: every MPC solve in this window is treated as failed (drill)
kp, ki, kd                  PID gains in 1/mm, 1/(mm s), s/mm
band_kpa                    bang-bang hysteresis half-band, kPa
q_height, q_integral        LQI weights on the height error (per mm^2) and its integral (per (mm s)^2)
r_command                   LQI weight on the command (1 = the pump's full flow at 0 kPa)
targets_mm                  [[t_s, h_mm], ...] target heights from t_s on (required)
interpolation               "step" (default) or "linear" (ramps between the points)
sine_amplitude_mm, sine_period_s, sine_start_s   a sinusoid added to the targets
load_steps_g                [[t_s, mass_g], ...]: set the rig's load to mass_g at t_s
settle_band_mm              settling band for the step metrics (default 0.3)
preview                     give the MPC the future targets over its horizon (default: for
                            ramps and sines; steps come unannounced, as an operator's would)
calibrate                   before the loop closes, a start-up calibration (vent, pump pulse to
                            min(17 kPa, p_max / 2), hold, vent; about 1.7 s) learns the pump-flow,
                            modulus and dead-volume factors for the estimator (default true)
==========================  ====================================================================

``run_scene`` writes ``closed_loop.csv`` (edge units), ``log.mcap``
(:func:`hbma_ctrl.app.logs.scenes.write_chamber_closed_loop`) and ``closed_loop.png`` with its PDF (target, truth and
estimate of the height; pressure with its limit; the three commands) and returns
``{"controller": {...}}`` with height_rmse_mm, max_pressure_kpa, pressure_limit_kpa,
solve_ms_median/p99/max, fallbacks and the settling results per target step, and with the
calibration on, ``calibration`` (see :func:`~hbma_ctrl.system.roles.calibration_summary`).
"""

from __future__ import annotations

import csv
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from hbma_ctrl.app.scenes.evaluate import NEES_FLOOR
from hbma_ctrl.app.figstyle import LABELS, save
from hbma_ctrl.app.logs.scenes import write_chamber_closed_loop
from hbma_ctrl.app.metrics import nrmsd
from hbma_ctrl.system.sections import (
    ControllerSection,
    ReferenceProfile,
)
from hbma_ctrl.core import units as U
from hbma_ctrl.core.interfaces import Estimator, check_role
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics, check_range
from hbma_ctrl.models.fidelity import make_fidelity
from hbma_ctrl.models.tables import PredictionModel
from hbma_ctrl.sim.rig import RigSettings
from hbma_ctrl.sim.simulate import Plant
from hbma_ctrl.system.chamber import chamber_system
from hbma_ctrl.system.run import run_lockstep
from hbma_ctrl.system.sim_rig import SimRig
from hbma_ctrl.system.roles import (
    default_estimator,
    estimator_from_scenario,
)

__all__ = ["closed_loop", "ClosedLoopLog", "loop_metrics", "run_scene", "plot_closed_loop"]


@dataclass
class ClosedLoopLog:
    """Closed-loop time series (SI), one row per rig sample."""

    t: np.ndarray
    target: np.ndarray
    h_true: np.ndarray
    h_est: np.ndarray
    p_true: np.ndarray
    p_meas: np.ndarray
    p_est: np.ndarray
    F_true: np.ndarray
    F_est: np.ndarray
    load: np.ndarray  # rig load mass, kg
    u: np.ndarray  # (n, 3)
    stats: dict
    events: list
    wall_s: float
    nees: np.ndarray | None = None  # estimator NEES of (h, F) per sample, where it exposes its covariance
    nis: np.ndarray | None = None  # estimator NIS per sample (NaN where no update)
    est_step_s: np.ndarray | None = None  # estimator wall time per step, s
    solve_ms: np.ndarray | None = None  # controller step times the runtime kept (ms, oldest first)
    supervisor_events: list = field(default_factory=list)  # the supervisor's interventions
    calibration: dict | None = None  # the start-up calibration's outcome (see calibration_summary)


def closed_loop(actuator: Actuator, pneumatics: Pneumatics, platform: Platform, section: ControllerSection,
                duration: float, rig_settings=None, estimator=None, controller=None,
                model: PredictionModel | None = None, calibrate: bool | None = None) -> ClosedLoopLog:
    """Run rig -> :class:`~hbma_ctrl.runtime.chamber.ChamberLoop` (estimator -> controller -> supervisor)
    -> rig for ``duration`` s and log it.

    The rig (:class:`~hbma_ctrl.sim.rig.Rig`, mismatched, noisy) is stepped at its sample period, the
    estimator at every rig sample, the controller every ``section.sample_period`` (a whole number
    of rig periods). ``estimator`` (an :class:`~hbma_ctrl.core.interfaces.Estimator`) defaults to the
    EKF on the nominal model, ``controller`` to the one the section names. The estimator is handed the
    rig first (``attach``: test oracles read the true state from it).

    ``calibrate`` (None = the section's ``calibrate``, default on): before the loop closes, run the
    :class:`~hbma_ctrl.runtime.calibrate.StartupCalibration` on the rig (pump pulse, hold, vent; never
    above the controller's p_max) and hand its factors to the estimator as its prior (when it has the
    factor states).
    The log starts when the loop closes (t = 0); ``log.calibration`` holds the outcome.
    """

    check_range("closed_loop", "duration", duration, 0.0, 1e5, "s", lo_open=True)
    rs = rig_settings or RigSettings()
    rig = SimRig.chamber(actuator, pneumatics, platform, rs)
    est = estimator or default_estimator(actuator, pneumatics, rs)
    check_role(est, Estimator, "closed_loop: estimator")
    est.attach(rig.rig)  # e.g. a test oracle that reads the rig's true state
    n = int(round(duration / rs.sample_period))
    every = max(int(round(section.sample_period / rs.sample_period)), 1)
    # the timing buffer holds every controller step of the run: the scene's medians are exact
    system = chamber_system(actuator, pneumatics, platform, section, rs, estimator=est, controller=controller,
                            model=model, calibrate=calibrate, stats_capacity=n // every + 1)
    loop = system.loop
    cols = {k: np.zeros(n) for k in ("t", "target", "h_true", "h_est", "p_true", "p_meas", "p_est",
                                     "F_true", "F_est", "load")}
    u_log = np.zeros((n, 3))
    nees, nis, est_s = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
    loads = list(section.load_steps)

    def put_loads(k: int, t: float) -> None:
        while loads and loads[0][0] <= t + 1e-9:
            rig.set_load(loads.pop(0)[1])

    def record(k: int, r, u: np.ndarray) -> None:
        e, z = loop.estimate, float(r.p[0])
        tr = rig.truth()
        for key, val in (("t", k * rs.sample_period), ("target", loop.target), ("h_true", tr["h"]), ("h_est", e.h),
                         ("p_true", tr["p"]), ("p_meas", z), ("p_est", e.p), ("F_true", tr["F"]), ("F_est", e.F),
                         ("load", rig.rig.platform.load)):
            cols[key][k] = val
        u_log[k] = u[:, 0]
        # estimator consistency, where the filter exposes its output covariance (EKF, UKF)
        C = est.last_output_cov
        if C is not None:
            err = np.array([e.h - tr["h"], e.F - tr["F"]])
            nees[k] = float(err @ np.linalg.solve(np.asarray(C)[2:4, 2:4] + np.diag(NEES_FLOOR), err))
        if est.last_nis is not None:
            nis[k] = est.last_nis
        if est.last_step_s is not None:
            est_s[k] = est.last_step_s

    t_wall = time.perf_counter()
    run_lockstep(system, rig, duration, before=put_loads, ticked=record)
    wall = time.perf_counter() - t_wall
    t_cal = 0.0 if system.t_closed is None else system.t_closed
    return ClosedLoopLog(**cols, u=u_log, stats=loop.stats(),
                         events=[(te - t_cal, name) for te, name in rig.rig.events],
                         wall_s=wall, nees=nees, nis=nis, est_step_s=est_s, solve_ms=loop.solve_ms.values(),
                         supervisor_events=loop.events(), calibration=system.calibration_summary)


def estimator_metrics(log: ClosedLoopLog, actuator: Actuator, pneumatics: Pneumatics, platform: Platform,
                      sample_period: float) -> dict:
    """The "estimator" metrics object for a closed-loop run (same keys as the estimator scene).

    height_nrmsd_open_loop drives the nominal model (the estimator's own parameters, the initial
    load, load steps unknown to it) with the commands the controller actually sent.
    """

    fname = "free" if platform.mass <= 0 else "quasi_static"
    fid = make_fidelity(fname, actuator.material, pneumatics.csv_path)
    plant = Plant(fid, fid.space.values(actuator, pneumatics, platform)[:, None], "rk4")
    h_ol = np.zeros(len(log.t))
    for k in range(len(log.t)):
        h_ol[k] = plant.output("h")[0]
        plant.advance(log.u[k][:, None], sample_period)
    finite = lambda a: float(a) if a is not None and np.isfinite(a) else None  # noqa: E731
    return {
        "height_nrmsd": finite(nrmsd(log.h_est, log.h_true)),
        "height_nrmsd_open_loop": finite(nrmsd(h_ol, log.h_true)),
        "pressure_nrmsd": finite(nrmsd(log.p_est, log.p_true)),
        "force_rmse_n": float(np.sqrt(np.mean((log.F_est - log.F_true) ** 2))),
        "nees_mean": finite(np.nanmean(log.nees)) if log.nees is not None and np.isfinite(log.nees).any() else None,
        "nis_mean": finite(np.nanmean(log.nis)) if log.nis is not None and np.isfinite(log.nis).any() else None,
        "step_us_median": (finite(U.to_us(np.nanmedian(log.est_step_s)))
                           if log.est_step_s is not None and np.isfinite(log.est_step_s).any() else None),
        "height_rmse_mm": float(U.to_mm(np.sqrt(np.mean((log.h_est - log.h_true) ** 2)))),
    }


def settle_results(log: ClosedLoopLog, reference: ReferenceProfile, band: float, min_hold: float = 0.2,
                   which: str = "truth") -> list:
    """Per constant-target segment: settle time (s after the step; None if never) and final error (mm).

    ``which`` = 'truth' (the rig's height, the real result) or 'estimate' (what the controller sees:
    the controller's own share of the error, without the estimator's bias).
    """
    h_all = log.h_true if which == "truth" else log.h_est
    out = []
    for t0, t1, h in reference.step_segments(float(log.t[-1]) + (log.t[1] - log.t[0] if len(log.t) > 1 else 0)):
        m = (log.t >= t0) & (log.t < t1)
        if m.sum() < 2:
            continue
        tt, err = log.t[m], np.abs(h_all[m] - h)
        outside = np.nonzero(err > band)[0]
        if outside.size == 0:
            ts = 0.0
        elif outside[-1] + 1 < len(tt):
            ts = float(tt[outside[-1] + 1] - t0)
        else:
            ts = None
        settled = ts is not None and (t1 - t0 - ts) >= min_hold
        out.append({"t_step_s": t0, "target_mm": U.to_mm(h), "settle_time_s": ts, "settled": bool(settled),
                    "final_error_mm": float(U.to_mm(h_all[m][-1] - h))})
    return out


def loop_metrics(log: ClosedLoopLog, section: ControllerSection) -> dict:
    """The "controller" metrics object of metrics.json (edge units)."""
    st = log.stats
    err = log.h_true - log.target
    settle = settle_results(log, section.reference, section.settle_band)
    settle_est = settle_results(log, section.reference, section.settle_band, which="estimate")
    return {
        "kind": section.kind,
        "variant": st.get("variant"),
        "horizon": st.get("horizon"),
        "height_rmse_mm": float(U.to_mm(np.sqrt(np.mean(err ** 2)))),
        "height_est_rmse_mm": float(U.to_mm(np.sqrt(np.mean((log.h_est - log.h_true) ** 2)))),
        "max_pressure_kpa": float(U.to_kpa(np.max(log.p_true))),
        "pressure_limit_kpa": U.to_kpa(section.p_max),
        "pressure_limit_respected": bool(np.max(log.p_true) <= section.p_max),
        "solve_ms_median": st["solve_ms_median"],
        "solve_ms_p99": st["solve_ms_p99"],
        "solve_ms_max": st["solve_ms_max"],
        "solve_cpu_ms_median": st.get("solve_cpu_ms_median"),
        "solve_cpu_ms_p99": st.get("solve_cpu_ms_p99"),
        "fallbacks": int(st["fallbacks"]),
        "fallback_detail": st.get("fallback_detail", {}),
        "guard_activations": st.get("guard_activations", 0),
        "target_clipped_steps": st.get("target_clipped_steps", 0),
        "settle_band_mm": U.to_mm(section.settle_band),
        "steps_settled": sum(1 for s in settle if s["settled"]),
        "steps_total": len(settle),
        "steps_settled_estimate": sum(1 for s in settle_est if s["settled"]),
        "height_rmse_estimate_mm": float(U.to_mm(np.sqrt(np.mean((log.h_est - log.target) ** 2)))),
        "settle": settle,
        "settle_estimate": settle_est,
        "wall_s": log.wall_s,
        "calibration": log.calibration,
    }


def write_closed_loop_csv(log: ClosedLoopLog, path: Path) -> None:
    """closed_loop.csv in edge units (s, mm, kPa, N, g, duty)."""
    with Path(path).open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t_s", "target_mm", "h_true_mm", "h_est_mm", "p_true_kpa", "p_meas_kpa", "p_est_kpa",
                    "F_true_n", "F_est_n", "load_g", "speed", "inlet", "outlet"])
        for i in range(len(log.t)):
            w.writerow([f"{log.t[i]:.4f}", f"{U.to_mm(log.target[i]):.4f}", f"{U.to_mm(log.h_true[i]):.4f}",
                        f"{U.to_mm(log.h_est[i]):.4f}", f"{U.to_kpa(log.p_true[i]):.4f}", f"{U.to_kpa(log.p_meas[i]):.4f}",
                        f"{U.to_kpa(log.p_est[i]):.4f}", f"{log.F_true[i]:.4f}", f"{log.F_est[i]:.4f}",
                        f"{U.to_grams(log.load[i]):.1f}", f"{log.u[i, 0]:.4f}", f"{log.u[i, 1]:.4f}", f"{log.u[i, 2]:.4f}"])


def plot_closed_loop(log: ClosedLoopLog, path: Path, title: str = "", p_max: float | None = None) -> None:
    """Three panels: target/truth/estimate height; pressure (true, measured, estimate, limit); commands."""

    fig = Figure(figsize=(9, 8), layout="constrained")
    ax = fig.subplots(3, 1, sharex=True)
    ax[0].plot(log.t, U.to_mm(log.target), "k--", lw=1.2, label="target")
    ax[0].plot(log.t, U.to_mm(log.h_true), "C0", lw=1.5, label="truth (rig)")
    ax[0].plot(log.t, U.to_mm(log.h_est), "C1", lw=1.0, alpha=0.8, label="estimate (EKF)")
    ax[0].set_ylabel(LABELS["h"])
    ax[0].legend(loc="best", fontsize=8)
    ax[1].plot(log.t, U.to_kpa(log.p_meas), ".", color="0.7", ms=2, label="measured")
    ax[1].plot(log.t, U.to_kpa(log.p_true), "C0", lw=1.5, label="truth")
    ax[1].plot(log.t, U.to_kpa(log.p_est), "C1", lw=1.0, label="estimate")
    if p_max is not None:
        ax[1].axhline(U.to_kpa(p_max), color="r", lw=1, ls=":", label="limit")
    ax[1].set_ylabel(LABELS["p"])
    ax[1].legend(loc="best", fontsize=8)
    for i, (name, c) in enumerate((("pump speed", "C2"), ("inlet duty", "C3"), ("outlet duty", "C4"))):
        ax[2].step(log.t, 100.0 * log.u[:, i], where="post", color=c, lw=1, label=name)
    ax[2].set_ylabel(LABELS["duty"])
    ax[2].set_xlabel(LABELS["t"])
    ax[2].set_ylim(-5, 105)
    ax[2].legend(loc="best", fontsize=8)
    if title:
        ax[0].set_title(title, fontsize=10)
    save(fig, Path(path).with_suffix(""))


def run_scene(scn, out_dir: Path | str) -> dict:
    """Run a scenario with a [controller] section; write CSV + plot; return the "controller" and
    "estimator" metrics objects (the EKF runs in the loop, so its accuracy is reported too)."""

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    section = scn.role("controller")
    rs = scn.role("rig") or RigSettings(sensor_range=scn.sim.sensor_range)
    est = estimator_from_scenario(scn, rs)
    log = closed_loop(scn.actuator, scn.pneumatics, scn.platform, section, scn.duration, rs, estimator=est)
    write_closed_loop_csv(log, out / "closed_loop.csv")
    st = log.stats
    title = (f"{scn.name}: {section.kind} {st.get('variant') or ''} N={st.get('horizon')}, "
             f"load {U.to_grams(scn.platform.load):g} g")
    plot_closed_loop(log, out / "closed_loop.png", title=title, p_max=section.p_max)
    write_chamber_closed_loop(log, out, scn.path, extra={"kind": "chamber closed loop", "p_max_kpa": U.to_kpa(section.p_max)})
    m = loop_metrics(log, section)
    m["log_csv"] = "closed_loop.csv"
    m["plot_png"] = "closed_loop.png"
    em = estimator_metrics(log, scn.actuator, scn.pneumatics, scn.platform, rs.sample_period)
    em["filter"] = type(est).__name__ if est is not None else "EKF"
    return {"controller": m, "estimator": em}
