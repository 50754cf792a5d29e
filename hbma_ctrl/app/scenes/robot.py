"""The robot's scenes: metrics, CSV and the open-loop scene; closed loop dispatched to its scene.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from hbma_ctrl.app.logs.scenes import write_robot_open_loop
from hbma_ctrl.app.scenes.robot_plots import plot_run, plot_shapes
from hbma_ctrl.app.scenes.robot_closed import run_closed_loop_scene
from hbma_ctrl.core import units as U
from hbma_ctrl.robot.design import LETTERS, RobotDesign
from hbma_ctrl.robot.plant import RobotRun, simulate_open_loop


def run_metrics(design: RobotDesign, run: RobotRun) -> dict:
    """The "robot" metrics object of an open-loop run (edge units).

    ``min_rim_gap_mm`` < 0 marks layers whose rigid three-point pose overlapped the layer below at
    the rim (see :meth:`~hbma_ctrl.robot.kinematics.RobotPose.rim_gap`): there the real robot rocks on its rim.
    The tracking keys required of every robot scene (chamber_height_rmse_mm, bend_angle_rmse_deg,
    tip_position_rmse_mm) are null here: an open-loop scene has no reference to track.
    """
    names = design.names
    hmax = run.h.max(0).ravel()
    counts: dict = {}
    for _, _, nm in run.events:
        counts[nm] = counts.get(nm, 0) + 1
    tip0 = run.tip[0]
    return {
        "mode": "open_loop",
        "chamber_height_rmse_mm": None, "bend_angle_rmse_deg": None, "tip_position_rmse_mm": None,
        "step_ms_median": float(U.to_ms(np.median(run.step_s))) if run.step_s.size else None,
        "step_ms_p99": float(U.to_ms(np.percentile(run.step_s, 99))) if run.step_s.size else None,
        "max_height_mm": {nm: U.to_mm(float(v)) for nm, v in zip(names, hmax)},
        "min_height_mm": {nm: U.to_mm(float(v)) for nm, v in zip(names, run.h.min(0).ravel())},
        "final_height_mm": {nm: U.to_mm(float(v)) for nm, v in zip(names, run.h[-1].ravel())},
        "max_pressure_kpa": {nm: U.to_kpa(float(v)) for nm, v in zip(names, run.p.max(0).ravel())},
        "max_stretch": {nm: float(v) for nm, v in zip(names, run.lam.max(0).ravel())},
        "max_bend_deg": {LETTERS[k]: math.degrees(float(run.bend[:, k].max())) for k in range(design.n_layers)},
        "final_bend_deg": {LETTERS[k]: math.degrees(float(run.bend[-1, k])) for k in range(design.n_layers)},
        "tip_bend_max_deg": math.degrees(float(run.tip_bend.max())),
        "final_tip_mm": U.to_mm(run.tip[-1]).tolist(),
        "max_tip_lateral_mm": U.to_mm(float(np.max(np.hypot(run.tip[:, 0] - tip0[0], run.tip[:, 1] - tip0[1])))),
        "tip_height_range_mm": [U.to_mm(float(run.tip[:, 2].min())), U.to_mm(float(run.tip[:, 2].max()))],
        "tension_chambers": [nm for nm, f in zip(names, run.tension.ravel()) if f],
        "min_rim_gap_mm": {LETTERS[k]: U.to_mm(float(run.rim_gap[:, k].min())) for k in range(design.n_layers)},
        "events": counts,
        "status": run.status,
        "sim_time_s": float(run.t[-1]),
        "wall_s": run.wall_s,
    }


def write_run_csv(design: RobotDesign, run: RobotRun, path: Path | str) -> None:
    """Write the run as CSV in edge units (mm, kPa, mg, deg), one row per sync period."""

    names = design.names
    N = design.n_layers
    cols = ["t_s"] + [f"h_{nm}_mm" for nm in names] + [f"p_{nm}_kpa" for nm in names] + \
        [f"m_{nm}_mg" for nm in names] + [f"load_{nm}_n" for nm in names] + \
        [f"bend_{LETTERS[k]}_deg" for k in range(N)] + [f"dir_{LETTERS[k]}_deg" for k in range(N)] + \
        ["tip_x_mm", "tip_y_mm", "tip_z_mm"]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for j in range(run.t.size):
            row = [run.t[j]] + list(U.to_mm(run.h[j].ravel())) + list(U.to_kpa(run.p[j].ravel())) + \
                list(U.to_mg(run.m[j].ravel())) + list(run.F[j].ravel()) + list(np.degrees(run.bend[j])) + \
                list(np.degrees(run.direction[j])) + list(U.to_mm(run.tip[j]))
            w.writerow([f"{v:.6g}" for v in row])


def run_scene(scn, out_dir) -> dict:
    """Run a scenario with a ``[robot]`` section into out_dir; returns {"robot": metrics}.

    Uses the scenario's pneumatics (compressor map, flow scale), duration and sim integrator/step;
    the robot itself (chambers included) comes from ``[robot]``, not from ``[actuator]``. Writes
    robot_log.csv, log.mcap, robot_events.json, robot_shape.png (shapes over time) and robot_series.png
    (each figure with its PDF).
    """
    s = scn.role("robot")
    if s.mode == "closed_loop":
        return run_closed_loop_scene(scn, s, out_dir)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    integ = scn.sim.integrator if scn.sim.integrator in ("euler", "rk4") else "rk4"
    dt = scn.sim.dt
    run = simulate_open_loop(s.plant, scn.pneumatics, scn.duration, integ, dt)
    metrics = run_metrics(s.design, run)
    if integ != scn.sim.integrator:
        metrics["note"] = f"sim.integrator '{scn.sim.integrator}' is not available for the robot batch; used rk4"
    write_run_csv(s.design, run, out / "robot_log.csv")
    write_robot_open_loop(s.design, run, out, scn.path, extra={"kind": "robot open loop", "status": run.status})
    (out / "robot_events.json").write_text(json.dumps(
        [{"t_s": float(t), "chamber": c, "event": e} for t, c, e in run.events], indent=1) + "\n")
    idx = np.unique(np.linspace(0, run.t.size - 1, s.snapshots).round().astype(int))
    plot_shapes(s.design, [run.h[i] for i in idx], out / "robot_shape.png",
                labels=[f"t = {run.t[i]:.1f} s" for i in idx], title=f"{scn.name}: robot shape over time")
    plot_run(s.design, run, out / "robot_series.png")
    return {"robot": metrics}
