"""The characterisation protocol of SPEC 7: 150 inflate/vent trials, simulated in batches.

Grid: loads 0, 200, 400, 600, 800 g x compressor speeds 20, 40, 60, 80, 100 % x membrane thickness
t0 2, 3 mm x retaining radius r1 7.5, 10, 12.5 mm. Each trial pumps at its speed with the inlet open
for ``t_inflate_s`` (default 3 s), then stops the pump, closes the inlet and opens the outlet until
``duration_s`` (default 6 s).

Fidelity: ``"auto"`` gives each trial its default (``Trial.default_fidelity``: 'free' for 0 g, the
paper's 'quasi_static' otherwise); 'quasi_static' or 'platform' apply to the loaded trials, the 0 g
trials always use 'free' (fewest states). Trials of one fidelity run as one batch
(:func:`hbma_ctrl.simulate.simulate`); with ``workers > 1`` each worker process simulates one
chunk of the trials (not one trial), so batching is kept.

Outputs of :func:`run_protocol` in ``out_dir``: ``summary.csv`` (one row per trial, columns
:data:`SUMMARY_COLUMNS`; ``wall_s`` is the trial's share of its batch's wall time, i.e. batch wall
time / batch size, or the trial's own time with the one-at-a-time 'radau'), ``trials/<name>.csv`` (time series in edge units, unit in each column
name, see :func:`hbma_ctrl.metrics.write_log_csv`) and, unless disabled, fig6/fig7/fig9 PNGs.
"""

from __future__ import annotations

import re

import csv
import itertools
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from . import units as U
from .materials import Material, make_material
from .params import Actuator, Platform, Pneumatics
from .simulate import InputSchedule, Log, SimSettings, Trial, simulate

__all__ = ["PROTOCOL_DEFAULTS", "SUMMARY_COLUMNS", "protocol_trials", "simulate_trials", "summary_row",
           "write_summary", "run_protocol", "trial_name"]

PROTOCOL_DEFAULTS = {
    "loads_g": [0.0, 200.0, 400.0, 600.0, 800.0],
    "speeds_pct": [20.0, 40.0, 60.0, 80.0, 100.0],
    "t0_mm": [2.0, 3.0],
    "r1_mm": [7.5, 10.0, 12.5],
    "t_inflate_s": 3.0,
    "duration_s": 6.0,
}

SUMMARY_COLUMNS = ("thickness_mm", "radius_mm", "load_g", "speed_pct", "status", "max_height_mm",
                   "max_pressure_kpa", "wall_s")


def trial_name(t0_mm: float, r1_mm: float, load_g: float, speed_pct: float) -> str:
    """File-safe trial name, e.g. 't3_r7.5_m200_s60' (edge units)."""
    return f"t{t0_mm:g}_r{r1_mm:g}_m{load_g:g}_s{speed_pct:g}"


def scenario_of(name: str) -> str:
    """The protocol cell (t0, r1, load) of a trial name: 't3_r7.5_m200_s60' -> 't3_r7.5_m200'.
    A name not of the protocol's form is its own scenario."""
    m = re.fullmatch(r"(t[^_]+_r[^_]+_m[^_]+)_s[^_]+", name)
    return m.group(1) if m else name


def protocol_trials(material: str | Material = "nh", *, loads_g=None, speeds_pct=None, t0_mm=None,
                    r1_mm=None, t_inflate_s: float | None = None, duration_s: float | None = None,
                    base: Actuator | None = None, pneumatics: Pneumatics | None = None,
                    platform: Platform | None = None) -> list[Trial]:
    """The protocol's trials (SPEC 7 grid by default), ordered t0, r1, load, speed.

    Grid values are in edge units (g, %, mm, s). ``base`` supplies V0 and the gas constants,
    ``platform`` the own mass and damping of the platform (its load is replaced per trial).
    Raises ValueError for values out of range (naming the field).
    """
    d = PROTOCOL_DEFAULTS
    loads_g = list(d["loads_g"] if loads_g is None else loads_g)
    speeds_pct = list(d["speeds_pct"] if speeds_pct is None else speeds_pct)
    t0_mm = list(d["t0_mm"] if t0_mm is None else t0_mm)
    r1_mm = list(d["r1_mm"] if r1_mm is None else r1_mm)
    t_inflate_s = d["t_inflate_s"] if t_inflate_s is None else float(t_inflate_s)
    duration_s = d["duration_s"] if duration_s is None else float(duration_s)
    mat = make_material(material) if isinstance(material, str) else material
    for name, vals, lo, hi in (("loads_g", loads_g, 0.0, 50000.0), ("speeds_pct", speeds_pct, 0.0, 100.0),
                               ("t0_mm", t0_mm, 0.0, 20.0), ("r1_mm", r1_mm, 0.0, 100.0)):
        if not vals:
            raise ValueError(f"protocol.{name} must not be empty")
        for v in vals:
            if not (lo <= v <= hi) or (name != "loads_g" and v <= 0):
                raise ValueError(f"protocol.{name}: value {v!r} is out of range "
                                 f"{'[' if name == 'loads_g' else '('}{lo:g}, {hi:g}]")
    if not 0.0 < t_inflate_s < duration_s:
        raise ValueError(f"protocol.t_inflate_s = {t_inflate_s:g} is out of range (0, duration_s = {duration_s:g})")
    base = base or Actuator()
    pneumatics = pneumatics or Pneumatics()
    platform = platform or Platform()
    trials = []
    for t0, r1, load, speed in itertools.product(t0_mm, r1_mm, loads_g, speeds_pct):
        act = Actuator(r1=U.mm(r1), t0=U.mm(t0), V0=base.V0, material=mat, R=base.R, T=base.T,
                       p_env=base.p_env)
        plat = Platform(load=U.grams(load), own_mass=platform.own_mass if load > 0 else 0.0,
                        damping=platform.damping, g=platform.g)
        sched = InputSchedule.inflate_deflate(U.pct(speed), t_inflate_s)
        trials.append(Trial(act, pneumatics, plat, sched, duration_s, trial_name(t0, r1, load, speed)).validate())
    names = [t.name for t in trials]
    if len(set(names)) != len(names):
        raise ValueError("protocol: repeated grid values give duplicate trials")
    return trials


def _simulate_chunk(trials: list[Trial], settings: SimSettings, fidelity: str) -> list[Log]:
    """Simulate trials grouped by their fidelity (one batch per group); logs in input order."""
    from .scenario import fidelity_for

    groups: dict[str, list[int]] = {}
    for i, tr in enumerate(trials):
        groups.setdefault(fidelity_for(tr, fidelity), []).append(i)
    logs: list = [None] * len(trials)
    for fname, idx in groups.items():
        for i, log in zip(idx, simulate([trials[i] for i in idx], settings, fname)):
            logs[i] = log
    return logs


def _chunks(trials: list[Trial], n: int, fidelity: str) -> list[list[int]]:
    """Split trial indices into n chunks that share every fidelity group evenly (round robin)."""
    from .scenario import fidelity_for

    order = sorted(range(len(trials)), key=lambda i: fidelity_for(trials[i], fidelity))
    chunks = [order[k::n] for k in range(n)]
    return [c for c in chunks if c]


def simulate_trials(trials: list[Trial], settings: SimSettings | None = None, fidelity: str = "auto",
                    workers: int = 1, progress: bool = False, label: str = "simulating") -> list[Log]:
    """Simulate trials with the protocol's fidelity rule, serially or in ``workers`` processes.

    Serial: one batch per fidelity group. Parallel: one chunk per worker, each a batch. With
    ``progress`` a rich progress bar counts finished trials.
    """
    settings = (settings or SimSettings()).validate()
    if workers < 1:
        raise ValueError(f"workers = {workers} is out of range [1, inf)")
    from .scenario import fidelity_for

    for tr in trials:
        fidelity_for(tr, fidelity)  # validate before spending time
    logs: list = [None] * len(trials)
    if workers == 1 or len(trials) < 2:
        groups: dict[str, list[int]] = {}
        for i, tr in enumerate(trials):
            groups.setdefault(fidelity_for(tr, fidelity), []).append(i)
        with _progress(progress) as bar:
            task = bar.add_task(label, total=len(trials)) if bar else None
            for fname, idx in groups.items():
                if bar:
                    bar.update(task, description=f"{label} ({fname}, {len(idx)} trials)")
                for i, log in zip(idx, simulate([trials[i] for i in idx], settings, fname)):
                    logs[i] = log
                if bar:
                    bar.advance(task, len(idx))
        return logs
    chunks = _chunks(trials, workers, fidelity)
    with ProcessPoolExecutor(max_workers=len(chunks)) as ex:
        futs = {ex.submit(_simulate_chunk, [trials[i] for i in c], settings, fidelity): c for c in chunks}
        from concurrent.futures import as_completed

        with _progress(progress) as bar:
            task = bar.add_task(f"{label} ({len(chunks)} workers)", total=len(trials)) if bar else None
            for fut in as_completed(futs):
                c = futs[fut]
                for i, log in zip(c, fut.result()):
                    logs[i] = log
                if bar:
                    bar.advance(task, len(c))
    return logs


class _NoBar:
    def __enter__(self):
        return None

    def __exit__(self, *exc):
        return False


def _progress(enabled: bool):
    if not enabled:
        return _NoBar()
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    transient=False)


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
    replaces the SPEC 7 grid (e.g. a subset). Returns the summary rows (edge units).
    """
    from .metrics import write_log_csv

    settings = SimSettings(integrator=integrator, dt=dt, log_dt=log_dt).validate()
    if trials is None:
        trials = protocol_trials(material, t_inflate_s=t_inflate_s, duration_s=duration_s)
    out = Path(out_dir)
    (out / "trials").mkdir(parents=True, exist_ok=True)
    logs = simulate_trials(trials, settings, fidelity, workers, progress)
    rows = [summary_row(tr, log) for tr, log in zip(trials, logs)]
    write_summary(rows, out / "summary.csv")
    with _progress(progress) as bar:
        task = bar.add_task("writing trials/*.csv", total=len(trials)) if bar else None
        for log in logs:
            write_log_csv(log, out / "trials" / f"{log.name}.csv")
            if bar:
                bar.advance(task)
    if plots:
        from .plots import protocol_figures

        mat = make_material(material) if isinstance(material, str) else material
        protocol_figures(out, mat, trials, logs, settings, fidelity)
    return rows
