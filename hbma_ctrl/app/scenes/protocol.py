"""The characterisation protocol's outputs (docs/concepts/model.md §7): 150 inflate/vent trials, summarised.

The grid, the fidelity rule and the batching are :mod:`hbma_ctrl.sim.batch`'s; this module writes
the run's outputs.

Outputs of :func:`run_protocol` in ``out_dir``: ``summary.csv`` (one row per trial, columns
:data:`SUMMARY_COLUMNS`; ``wall_s`` is the trial's share of its batch's wall time, i.e. batch wall
time / batch size, or the trial's own time with the one-at-a-time 'radau'), ``trials/<name>.csv``
(time series in edge units, unit in each column name, see :func:`hbma_ctrl.app.metrics.write_log_csv`) and, unless disabled, fig6/fig7/fig9 PNGs.
"""

from __future__ import annotations

import csv
from pathlib import Path

from hbma_ctrl.app.metrics import physics_problems, write_log_csv
from hbma_ctrl.app.forked import Forked
from hbma_ctrl.core import units as U
from hbma_ctrl.core.materials import Material, make_material
from hbma_ctrl.sim.batch import FIGURE_TRIALS, progress_bar, protocol_trials, simulate_trials
from hbma_ctrl.sim.trial import Log, SimSettings, Trial

__all__ = ["SUMMARY_COLUMNS", "summary_row", "write_summary", "run_protocol"]

SUMMARY_COLUMNS = ("thickness_mm", "radius_mm", "load_g", "speed_pct", "status", "max_height_mm",
                   "max_pressure_kpa", "wall_s")


def summary_row(trial: Trial, log: Log) -> dict:
    """One summary.csv row (edge units) for a protocol trial and its log."""
    return {
        "thickness_mm": round(U.to_mm(trial.actuator.t0), 6),
        "radius_mm": round(U.to_mm(trial.actuator.r1), 6),
        "load_g": round(U.to_grams(trial.platform.load), 6),
        "speed_pct": round(U.to_pct(float(trial.schedule.rows[0][1])), 6),
        "status": log.status,
        "max_height_mm": float(U.to_mm(log["h"].max())),
        "max_pressure_kpa": float(U.to_kpa(log["p"].max())),
        "wall_s": float(log.wall_s),
    }


def write_summary(rows: list[dict], path: Path | str) -> None:
    """Write summary rows as CSV with exactly :data:`SUMMARY_COLUMNS`."""
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=SUMMARY_COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k]) for k in SUMMARY_COLUMNS})


def run_protocol(material: str | Material = "nh", out_dir: Path | str = "runs/protocol", integrator: str = "rk4",
                 dt: float | None = None, fidelity: str = "auto", workers: int = 1, *,
                 t_inflate_s: float | None = None, duration_s: float | None = None,
                 trials: list[Trial] | None = None, plots: bool = True, progress: bool = False,
                 log_dt: float = 0.01) -> list[dict]:
    """Simulate the protocol and write summary.csv, trials/*.csv and (``plots``) fig6/7/9 PNGs.

    dt is the fixed step in s (None = the default per integrator and fidelity); ``trials``
    replaces the protocol grid (e.g. a subset). Returns the summary rows (edge units).
    """

    settings = SimSettings(integrator=integrator, dt=dt, log_dt=log_dt).validate()
    if trials is None:
        trials = protocol_trials(material, t_inflate_s=t_inflate_s, duration_s=duration_s)
    out = Path(out_dir)
    (out / "trials").mkdir(parents=True, exist_ok=True)
    mat = make_material(material) if isinstance(material, str) else material
    # the figures are drawn by one forked child beside this process's work (hbma_ctrl.app.forked):
    # Fig. 6 needs no logs; each batch's logs are handed over as it finishes, so Figs. 7 and 9 are
    # drawn while the rest is simulated and written; joined before returning
    figures = Forked(_figures, out, mat, settings, fidelity, inbox=True) if plots else None
    drawn = {name for names in FIGURE_TRIALS.values() for name in names}
    logs = simulate_trials(trials, settings, fidelity, workers, progress,
                           on_done=(lambda idx, done: figures.send([log for log in done if log.name in drawn]))
                           if figures else None)
    if figures:
        figures.send(None)
    rows = [summary_row(tr, log) for tr, log in zip(trials, logs)]
    for tr, log, row in zip(trials, logs, rows):
        problems = physics_problems(log, tr.actuator.material, tr.pneumatics.csv_path)
        if problems:  # a finished trial whose numbers are not physics is not a result
            row.update(status="failed", failed_because=[f"{tr.name}: {why}" for why in problems])
    with progress_bar(progress) as bar:
        task = bar.add_task("writing trials/*.csv", total=len(trials)) if bar else None
        for log in logs:
            write_log_csv(log, out / "trials" / f"{log.name}.csv")
            if bar:
                bar.advance(task)
    # after the trial files: a summary.csv is only there when every trial it lists was written
    write_summary(rows, out / "summary.csv")
    if figures:
        figures.join()
    return rows


# matplotlib takes ~0.5 s to import: the figure child imports it, beside the parent's simulation,
# and the parent only when the child failed and it draws the figures itself
def _figures(recv, out: Path, mat: Material, settings: SimSettings, fidelity: str) -> None:
    from hbma_ctrl.app.plots import streamed_protocol_figures

    streamed_protocol_figures(recv, out, mat, settings, fidelity)
