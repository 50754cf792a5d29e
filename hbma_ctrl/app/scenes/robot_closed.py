"""The robot's closed-loop scene: metrics, CSV, plots, and the robot bench.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
from matplotlib.lines import Line2D

from hbma_ctrl.app.figstyle import LABELS, figure, legend, save
from hbma_ctrl.app.logs.scenes import write_robot_closed_loop
from hbma_ctrl.controllers.robot_mpc import RobotMPCSettings
from hbma_ctrl.app.scenes.robot_loop import ClosedLoopRun, run_closed_loop
from hbma_ctrl.system.roles import make_model
from hbma_ctrl.app.scenes.robot_plots import plot_shapes
from hbma_ctrl.app.schema.rig import RigTable
from hbma_ctrl.system.sections import RobotSettings
from hbma_ctrl.core import units as U
from hbma_ctrl.core.params import Pneumatics
from hbma_ctrl.models.bank import ChamberBank
from hbma_ctrl.robot.design import LETTERS, RobotDesign, RobotPneumatics
from hbma_ctrl.robot.kinematics import forward_kinematics
from hbma_ctrl.robot.rig import RobotRigSettings


def _normals(design: RobotDesign, H: np.ndarray, rim: list | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-sample layer normals relative to the layer below (T, N, 3) and tip positions (T, 3);
    appends each sample's rim gaps (N,) to ``rim`` if given."""
    T = H.shape[0]
    N = design.n_layers
    nrm = np.zeros((T, N, 3))
    tip = np.zeros((T, 3))
    for j in range(T):
        pose = forward_kinematics(design, np.maximum(H[j], 0.0).reshape(N, 3))
        th, ps = pose.bend, pose.direction
        nrm[j] = np.column_stack([np.sin(th) * np.cos(ps), np.sin(th) * np.sin(ps), np.cos(th)])
        tip[j] = pose.tip_position
        if rim is not None:
            rim.append(pose.rim_gap(design))
    return nrm, tip


def closed_loop_metrics(design: RobotDesign, run: ClosedLoopRun, pressure_limit: float, settle_time: float = 2.0,
                        h_tol: float = 0.5e-3, bend_tol: float = math.radians(2.0), model=None) -> dict:
    """The "robot" metrics of a closed-loop run (edge units), on the TRUE shape.

    RMSEs are over the settled windows: samples at least ``settle_time`` after the last target
    change or tip-load change (the transients of a step are not tracking errors). Per target segment: the errors at
    its end (mean over its last 0.5 s), whether it settled within ``h_tol`` (every chamber) and
    ``bend_tol`` (every layer), and the settling time (first time from which both stay inside).
    """
    rim: list = []
    nt, tt = _normals(design, run.h, rim)
    nr, tr = _normals(design, run.h_ref)
    bend_err = np.degrees(np.arccos(np.clip((nt * nr).sum(-1), -1.0, 1.0)))  # (T, N)
    h_err = U.to_mm(np.abs(run.h - run.h_ref))  # mm
    tip_err = U.to_mm(np.linalg.norm(tt - tr, axis=1))
    ch = run.changes
    last_change = ch[np.searchsorted(ch, run.t + 1e-9, side="right") - 1]
    settled = run.t - last_change >= settle_time
    rm = lambda e: float(np.sqrt(np.mean(e[settled] ** 2))) if settled.any() else None  # noqa: E731
    segs = []
    bounds = list(ch) + [run.t[-1] + 1e-9]
    for s0, s1 in zip(bounds[:-1], bounds[1:]):
        m = (run.t >= s0) & (run.t < s1)
        if m.sum() < 2:
            continue
        end = m & (run.t >= s1 - 0.5)
        inside = (h_err.max(1) <= U.to_mm(h_tol)) & (bend_err.max(1) <= math.degrees(bend_tol))
        idx = np.nonzero(m)[0]
        ok = inside[idx]
        t_set = None
        if ok[-1]:
            bad = np.nonzero(~ok)[0]
            first = idx[bad[-1] + 1] if bad.size else idx[0]
            t_set = float(run.t[first] - s0)
        segs.append({"t_start_s": float(s0), "t_end_s": float(min(s1, run.t[-1])),
                     "final_height_err_mm": float(h_err[end].mean(0).max()) if end.any() else None,
                     "peak_height_err_mm": float(h_err[m].max()),
                     "peak_bend_err_deg": float(bend_err[m].max()),
                     "final_bend_err_deg": float(bend_err[end].mean(0).max()) if end.any() else None,
                     "settled": bool(ok[-1]), "settle_time_s": t_set,
                     "target_heights_mm": np.round(U.to_mm(run.h_ref[idx[-1]]), 2).tolist()})
    names = design.names
    peak_h = None
    if model is not None:
        peak_h = np.array([model.peak(max(w, 1e-3))[0] for w in run.loads[-1]])
    far = [nm for i, nm in enumerate(names) if peak_h is not None and run.h[:, i].max() > peak_h[i] + 1e-4]
    out = {
        "mode": "closed_loop",
        "controller": run.controller,
        "chamber_height_rmse_mm": rm(h_err),
        "bend_angle_rmse_deg": rm(bend_err),
        "tip_position_rmse_mm": rm(tip_err),
        "step_ms_median": float(U.to_ms(np.median(run.step_s))),
        "step_ms_p99": float(U.to_ms(np.percentile(run.step_s, 99))),
        "step_ms_max": float(U.to_ms(run.step_s.max())),
        "ekf_ms_median": float(U.to_ms(np.median(run.ekf_s))),
        "controller_ms_median": float(U.to_ms(np.median(run.ctrl_s))),
        "chamber_height_rmse_all_mm": float(np.sqrt(np.mean(h_err ** 2))),
        "estimate_height_rmse_mm": float(U.to_mm(np.sqrt(np.mean((run.h_est[1:] - run.h[1:]) ** 2)))),
        "max_pressure_kpa": U.to_kpa(float(run.p.max())),
        "max_pressure_measured_kpa": U.to_kpa(float(np.nanmax(run.p_meas))),
        "pressure_limit_kpa": U.to_kpa(pressure_limit),
        "pressure_limit_exceeded": bool(run.p.max() > pressure_limit),
        "max_height_mm": {nm: U.to_mm(float(v)) for nm, v in zip(names, run.h.max(0))},
        "far_branch_chambers": far,
        "max_stretch": float(run.lam.max()),
        # < 0: the rigid three-point pose would overlap the layer below at the rim (a real layer
        # rocks on its rim there; see hbma_ctrl.robot.RobotPose.rim_gap)
        "min_rim_gap_mm": {LETTERS[k]: float(U.to_mm(np.min(np.array(rim)[:, k]))) for k in range(design.n_layers)},
        "stretch_exceeded_chambers": [nm for i, nm in enumerate(names) if run.lam[:, i].max() > design.max_stretch],
        "segments": segs,
        "all_segments_settled": bool(all(s["settled"] for s in segs)),
        "interlocks": run.interlocks,
        "stretch_interlocks": run.stretch_interlocks,
        "lost_estimate_steps": run.lost_estimate_steps,
        "burst_chambers": [names[i] for i in run.bursts],
        "burst_peak_sigma": run.burst_peak_sigma,
        "cautious_steps": run.cautious_steps,
        "fallbacks": run.fallbacks,
        "qp_not_solved": run.inaccurate,
        "status": run.status,
        "sim_time_s": float(run.t[-1]),
        "wall_s": run.wall_s,
        "settle_time_s": settle_time,
        "tolerances": {"height_mm": U.to_mm(h_tol), "bend_deg": math.degrees(bend_tol)},
    }
    return out


# ---------------------------------------------------------------------------------------------
# plots and CSV
# ---------------------------------------------------------------------------------------------
def write_closed_csv(design: RobotDesign, run: ClosedLoopRun, path) -> None:
    """Write a closed-loop run as CSV in edge units (mm, kPa; one column per chamber and quantity)."""
    names = design.names
    cols = ["t_s"] + [f"{k}_{nm}_{u}" for k, u in (("h", "mm"), ("h_ref", "mm"), ("h_est", "mm"), ("p", "kpa"),
                                                     ("p_meas", "kpa"), ("supply", "1"), ("outlet", "1"))
                      for nm in names]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for j in range(run.t.size):
            row = [run.t[j]] + list(U.to_mm(run.h[j])) + list(U.to_mm(run.h_ref[j])) + list(U.to_mm(run.h_est[j])) + \
                list(run.p[j] / 1e3) + list(run.p_meas[j] / 1e3) + list(run.a[j]) + list(run.o[j])
            w.writerow([f"{v:.6g}" for v in row])


def plot_closed_loop(design: RobotDesign, runs: list, path, pressure_limit: float, title: str = "") -> list[Path]:
    """One column per controller: per layer its chambers' heights (target dashed, estimate solid, true
    dotted) and pressures (with the limit), then the layers' bend (target dashed, true solid); -> PNG and
    PDF (``path`` with its suffix replaced). Returns the files."""
    N = design.n_layers
    fig = figure(7.5 * len(runs) + 1.5, 1.9 * (2 * N + 1) + 1.0)
    axs = fig.subplots(2 * N + 1, len(runs), squeeze=False, sharex=True)
    styles = (("target", dict(ls="--", lw=1.0)), ("estimate", dict(ls="-", lw=1.3)), ("true", dict(ls=":", lw=1.2)))
    for c, run in enumerate(runs):
        for k in range(N):
            ax, axp = axs[k, c], axs[N + k, c]
            for i in range(3):
                j = 3 * k + i
                for (words, st), y in zip(styles, (run.h_ref[:, j], run.h_est[:, j], run.h[:, j])):
                    ax.plot(run.t, U.to_mm(y), color=f"C{i}", **st)
                axp.plot(run.t, U.to_kpa(run.p_meas[:, j]), color=f"C{i}", lw=0.9, label=design.names[j])
            axp.axhline(U.to_kpa(pressure_limit), color="tab:red", ls="-.", lw=1.0, label="pressure limit")
            ax.set_ylabel(LABELS["h"])
            ax.set_title(f"Layer {LETTERS[k]}: chamber heights", fontsize=9)
            axp.set_ylabel(LABELS["p"])
            axp.set_title(f"Layer {LETTERS[k]}: measured chamber pressures", fontsize=9)
            keys = [Line2D([], [], color=f"C{i}", lw=2, label=design.names[3 * k + i]) for i in range(3)]
            keys += [Line2D([], [], color="0.2", label=w, **st) for w, st in styles]
            ax.legend(handles=keys, fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
            legend(axp, loc="center left", bbox_to_anchor=(1.01, 0.5))
        ax = axs[2 * N, c]
        nt, _ = _normals(design, run.h[::5])
        nr, _ = _normals(design, run.h_ref[::5])
        for k in range(N):
            ax.plot(run.t[::5], np.degrees(np.arccos(np.clip(nt[:, k, 2], -1, 1))), color=f"C{k}", lw=1.2,
                    label=f"layer {LETTERS[k]}")
            ax.plot(run.t[::5], np.degrees(np.arccos(np.clip(nr[:, k, 2], -1, 1))), color=f"C{k}", ls="--", lw=0.9)
        ax.set_ylabel(LABELS["bend"])
        ax.set_xlabel(LABELS["t"])
        ax.set_title("Bend of each layer (true solid, target dashed)", fontsize=9)
        legend(ax, loc="center left", bbox_to_anchor=(1.01, 0.5))
        axs[0, c].annotate(f"controller: {_CONTROLLER_WORDS.get(run.controller, run.controller)}", (0.5, 1.35),
                           xycoords="axes fraction", ha="center", fontsize=10, weight="bold")
        for a in axs[:, c]:
            a.grid(alpha=0.3)
    fig.suptitle(f"{title}: chamber heights, pressures and layer bends" if title else
                 "Chamber heights, pressures and layer bends")
    return save(fig, Path(path).with_suffix(""))


#: the controllers by the names a reader knows them by
_CONTROLLER_WORDS = {"mpc": "model predictive control (NMPC)", "pressure_pid": "pressure PID"}


# ---------------------------------------------------------------------------------------------
# scene and bench
# ---------------------------------------------------------------------------------------------
def scene_parts(scn, settings: RobotSettings) -> tuple:
    """(RobotRigSettings, ChamberBank model, RobotMPCSettings) of the closed-loop scene: the scenario's
    ``[rig]`` as the robot rig, the nominal model and the NMPC's settings from ``[robot]``."""
    s = settings
    raw_rig = scn.sections.get("rig")
    rig = RigTable.model_validate(raw_rig).to_robot_rig() if raw_rig else RobotRigSettings()
    model = make_model(s.design, scn.pneumatics, s.pneumatics.topology)
    mpc = RobotMPCSettings(horizon=s.mpc_horizon, dt=s.mpc_dt, budget=s.mpc_budget,
                           enforce_budget=s.mpc_enforce_budget)
    if s.mpc_w_slack is not None:
        mpc = replace(mpc, w_slack=s.mpc_w_slack)
    return rig, model, mpc


def estimator_metrics(run: ClosedLoopRun, kind: str) -> dict:
    """The robot's "estimator" metrics object (a scenario with [estimator]): its kind, the estimated
    heights' RMSE against the rig's (mm, every chamber and period after the first), its step time per
    tick (ms: median, p99) and its counts (fallbacks per chamber for the MHE)."""
    e = run.h_est[1:] - run.h[1:]
    return {"kind": kind, "estimate_height_rmse_mm": float(U.to_mm(np.sqrt(np.mean(e ** 2)))),
            "step_ms_median": float(U.to_ms(np.median(run.ekf_s))),
            "step_ms_p99": float(U.to_ms(np.percentile(run.ekf_s, 99))), "counts": run.estimator_stats}


def run_closed_loop_scene(scn, settings: RobotSettings, out_dir) -> dict:
    """The closed-loop ``[robot]`` scene: metrics {"robot": {...}} (+ the baseline's beside it); writes
    ``robot_<controller>_log.csv`` and ``log.mcap`` (the baseline's ``log_<controller>.mcap``,
    :func:`hbma_ctrl.app.logs.scenes.write_robot_closed_loop`), robot_series.png and robot_shape.png with
    their PDFs, robot_segments.json. With ``[estimator]`` (kind ekf or mhe) both runs use that estimator
    and the metrics get its object (:func:`estimator_metrics`)."""

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    s = settings
    d = s.design
    rig, model, mpc = scene_parts(scn, s)
    est_sec = scn.settings.get("estimator")
    estimator = est_sec.filter if est_sec is not None else "ekf"
    window = dict(est_sec.tuning) if est_sec is not None else {}
    kinds = [s.controller]
    if s.compare_baseline:
        kinds.append("pressure_pid" if s.controller == "mpc" else "mpc")
    runs, mets = [], []
    for kind in kinds:
        run = run_closed_loop(s, s.targets, scn.duration, kind, scn.pneumatics, rig, mpc, model=model,
                              tip_load=s.tip_load, estimator=estimator, window=window)
        runs.append(run)
        mets.append(closed_loop_metrics(d, run, s.pneumatics.pressure_limit, s.settle_time, model=model))
        write_closed_csv(d, run, out / f"robot_{kind}_log.csv")
        write_robot_closed_loop(d, run, out, scn.path, name="log.mcap" if not runs[:-1] else f"log_{kind}.mcap",
                                extra={"kind": "robot closed loop", "controller": kind,
                                       "pressure_limit_kpa": U.to_kpa(s.pneumatics.pressure_limit)})
    metrics = dict(mets[0])
    if est_sec is not None:
        metrics["estimator"] = estimator_metrics(runs[0], estimator)
    metrics["topology"] = s.pneumatics.topology
    metrics["n_layers"] = d.n_layers
    if len(mets) > 1:
        metrics["baseline"] = {k: mets[1][k] for k in (
            "controller", "chamber_height_rmse_mm", "bend_angle_rmse_deg", "tip_position_rmse_mm",
            "chamber_height_rmse_all_mm", "max_pressure_kpa", "pressure_limit_exceeded", "all_segments_settled",
            "far_branch_chambers", "max_stretch", "stretch_exceeded_chambers", "interlocks", "stretch_interlocks", "lost_estimate_steps", "step_ms_median", "step_ms_p99", "segments", "status")}
    plot_closed_loop(d, runs, out / "robot_series.png", s.pneumatics.pressure_limit, scn.name)
    r0 = runs[0]
    idx = np.unique(np.concatenate([np.searchsorted(r0.t, np.append(r0.changes[1:], r0.t[-1] + 1)) - 1]))
    idx = idx[(idx > 0) & (idx < r0.t.size)]
    if idx.size:
        plot_shapes(d, [r0.h[i].reshape(-1, 3) for i in idx], out / "robot_shape.png",
                    labels=[f"t = {r0.t[i]:.1f} s" for i in idx], title=f"{scn.name}: {r0.controller} shape over time")
    (out / "robot_segments.json").write_text(json.dumps({k: m["segments"] for k, m in zip(kinds, mets)}, indent=1))
    return {"robot": metrics}


def bench_robot(layers=(1, 2, 3, 4, 5, 6), duration: float = 3.0, topology: str = "per_chamber",
                horizon: int = 15, pneumatics: Pneumatics | None = None, model: ChamberBank | None = None,
                mpc: RobotMPCSettings | None = None) -> list[dict]:
    """Step time of the whole robot (EKF bank + load sharing + NMPC) per layer count, on a closed-loop
    run of ``duration`` s (straight 6 mm, then bend 15 deg at t = duration / 2). Returns table rows,
    with the RMSE of the true chamber heights from their targets over the whole run (mm: what tells
    NMPC settings apart on the same run). ``mpc``: the NMPC settings (default: the defaults at
    ``horizon``)."""

    pn = (pneumatics or Pneumatics()).validate()
    rows = []
    for N in layers:
        d = RobotDesign(n_layers=int(N)).validate()
        s = RobotSettings(design=d, pneumatics=RobotPneumatics(topology=topology)).validate()
        model = model or make_model(d, pn, topology)
        # straight at 6 mm, then a 15 deg bend about x at 7 mm: (t s, centre m, bend rad, direction rad)
        pose = ((0.0, U.mm(6.0), 0.0, 0.0), (duration / 2, U.mm(7.0), math.radians(15.0), 0.0))
        tg = {k: pose for k in range(d.n_layers)}
        ms = mpc if mpc is not None else RobotMPCSettings(horizon=horizon)
        run = run_closed_loop(s, tg, duration, "mpc", pn, mpc=ms, model=model)
        st = U.to_ms(run.step_s[5:])  # the first periods include casadi/OSQP setup
        rows.append({"layers": int(N), "chambers": 3 * int(N), "qp_variables": (3 * ms.horizon + 1) * 3 * int(N),
                     "height_rmse_mm": float(U.to_mm(np.sqrt(np.mean((run.h - run.h_ref) ** 2)))),
                     "step_ms_median": float(np.median(st)), "step_ms_p99": float(np.percentile(st, 99)),
                     "step_ms_max": float(st.max()), "ekf_ms_median": float(np.median(U.to_ms(run.ekf_s[5:]))),
                     "mpc_ms_median": float(np.median(U.to_ms(run.ctrl_s[5:]))), "steps": int(st.size),
                     "fallbacks": run.fallbacks, "max_pressure_kpa": float(run.p.max() / 1e3)})
    return rows
