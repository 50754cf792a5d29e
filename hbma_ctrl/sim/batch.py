"""The characterisation protocol's trials and batch simulation of many trials (SI inside).

Grid: loads 0, 200, 400, 600, 800 g x compressor speeds 20, 40, 60, 80, 100 % x membrane thickness
t0 2, 3 mm x retaining radius r1 7.5, 10, 12.5 mm. Each trial pumps at its speed with the inlet open
for ``t_inflate_s`` (default 3 s), then stops the pump, closes the inlet and opens the outlet until
``duration_s`` (default 6 s).

Fidelity: ``"auto"`` gives each trial its default (``Trial.default_fidelity``: 'free' for 0 g, the
paper's 'quasi_static' otherwise); 'quasi_static' or 'platform' apply to the loaded trials, the 0 g
trials always use 'free' (fewest states). Trials of one fidelity run as one batch
(:func:`hbma_ctrl.sim.simulate.simulate`); with ``workers > 1`` each worker process simulates one
chunk of the trials (not one trial), so batching is kept.
"""

from __future__ import annotations

import itertools
import re
import signal
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import nullcontext
from typing import Callable

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from hbma_ctrl.core import units as U
from hbma_ctrl.core.materials import Material, make_material
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.core.validation import did_you_mean
from hbma_ctrl.models.fidelity import FIDELITIES
from hbma_ctrl.sim.simulate import simulate
from hbma_ctrl.sim.trial import InputSchedule, Log, SimSettings, Trial

__all__ = ["PROTOCOL_DEFAULTS", "FIDELITY_CHOICES", "FIGURE_CASES", "FIGURE_TRIALS", "fidelity_for", "protocol_trials", "quiet_worker", "simulate_trials",
           "trial_name", "scenario_of"]

#: 'exact': the exact membrane (docs/concepts/model.md §9), platform model with a load, free inflation without
FIDELITY_CHOICES = ("auto",) + tuple(FIDELITIES) + ("exact",)

PROTOCOL_DEFAULTS = {
    "loads_g": [0.0, 200.0, 400.0, 600.0, 800.0],
    "speeds_pct": [20.0, 40.0, 60.0, 80.0, 100.0],
    "t0_mm": [2.0, 3.0],
    "r1_mm": [7.5, 10.0, 12.5],
    "t_inflate_s": 3.0,
    "duration_s": 6.0,
}



def fidelity_for(trial: Trial, requested: str) -> str:
    """The fidelity one trial runs with: 'auto' = the trial's default; a load-less trial is 'free'.

    Raises ValueError when 'free' is asked for a loaded trial (it would ignore the load).
    """
    if requested not in FIDELITY_CHOICES:
        raise ValueError(f"sim.fidelity = '{requested}'{did_you_mean(requested, FIDELITY_CHOICES, cutoff=0.5)}; "
                         f"allowed: {', '.join(FIDELITY_CHOICES)}")
    if requested == "auto":
        return trial.default_fidelity()
    if requested == "exact":
        return "exact"  # loaded or not: the simulator picks the exact rung's model per trial
    if trial.platform.mass <= 0:
        return "free"
    if requested == "free":
        raise ValueError(f"sim.fidelity = 'free' ignores the load of trial '{trial.name}' "
                         f"({U.to_grams(trial.platform.mass):g} g); use auto, quasi_static or platform")
    return requested


def trial_name(t0_mm: float, r1_mm: float, load_g: float, speed_pct: float) -> str:
    """File-safe trial name, e.g. 't3_r7.5_m200_s60' (edge units)."""
    return f"t{t0_mm:g}_r{r1_mm:g}_m{load_g:g}_s{speed_pct:g}"


#: the protocol trials the paper's Figs. 7 and 9 draw: (t0 mm, r1 mm, load g), each at the protocol's five speeds
FIGURE_CASES = {"fig7": (3.0, 12.5, 0.0), "fig9": (2.0, 12.5, 200.0)}
#: their trial names, by figure
FIGURE_TRIALS = {fig: [trial_name(*case, speed) for speed in PROTOCOL_DEFAULTS["speeds_pct"]]
                 for fig, case in FIGURE_CASES.items()}


def scenario_of(name: str) -> str:
    """The protocol cell (t0, r1, load) of a trial name: 't3_r7.5_m200_s60' -> 't3_r7.5_m200'.
    A name not of the protocol's form is its own scenario."""
    m = re.fullmatch(r"(t[^_]+_r[^_]+_m[^_]+)_s[^_]+", name)
    return m.group(1) if m else name


def protocol_trials(material: str | Material = "nh", *, loads_g=None, speeds_pct=None, t0_mm=None,
                    r1_mm=None, t_inflate_s: float | None = None, duration_s: float | None = None,
                    base: Actuator | None = None, pneumatics: Pneumatics | None = None,
                    platform: Platform | None = None) -> list[Trial]:
    """The protocol's trials (docs/concepts/model.md §7 grid by default), ordered t0, r1, load, speed.

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


def _groups(trials: list[Trial], fidelity: str) -> dict[str, list[int]]:
    """Trial indices by the fidelity each runs with (:func:`fidelity_for`)."""
    groups: dict[str, list[int]] = {}
    for i, tr in enumerate(trials):
        groups.setdefault(fidelity_for(tr, fidelity), []).append(i)
    return groups


def _simulate_chunk(trials: list[Trial], settings: SimSettings, fidelity: str) -> list[Log]:
    """Simulate trials grouped by their fidelity (one batch per group); logs in input order."""
    logs: list = [None] * len(trials)
    for fname, idx in _groups(trials, fidelity).items():
        for i, log in zip(idx, simulate([trials[i] for i in idx], settings, fname)):
            logs[i] = log
    return logs


def _chunks(trials: list[Trial], n: int, fidelity: str) -> list[list[int]]:
    """Split trial indices into n chunks that share every fidelity group evenly (round robin)."""

    order = sorted(range(len(trials)), key=lambda i: fidelity_for(trials[i], fidelity))
    chunks = [order[k::n] for k in range(n)]
    return [c for c in chunks if c]


def quiet_worker() -> None:
    """ProcessPoolExecutor initializer: Ctrl-C ends a worker without a traceback.

    The terminal sends SIGINT to every process of the group; the default action ends the worker
    silently, and the parent alone reports the interruption.
    """
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def simulate_trials(trials: list[Trial], settings: SimSettings | None = None, fidelity: str = "auto",
                    workers: int = 1, progress: bool = False, label: str = "simulating",
                    on_done: Callable[[list[int], list[Log]], None] | None = None) -> list[Log]:
    """Simulate trials with the protocol's fidelity rule, serially or in ``workers`` processes.

    Serial: one batch per fidelity group. Parallel: one chunk per worker, each a batch. With
    ``progress`` a rich progress bar counts finished trials. ``on_done(indices, logs)`` is called as
    each batch finishes, with the indices into ``trials`` of its logs (e.g. to draw a figure before
    the last batch is done).
    """
    settings = (settings or SimSettings()).validate()
    if workers < 1:
        raise ValueError(f"workers = {workers} is out of range [1, inf)")

    for tr in trials:
        fidelity_for(tr, fidelity)  # validate before spending time
    logs: list = [None] * len(trials)
    if workers == 1 or len(trials) < 2:
        groups = _groups(trials, fidelity)
        # serial: the bar counts simulated seconds of each batch, so one long trial shows progress too
        total = sum(max(trials[i].duration for i in idx) for idx in groups.values())
        with progress_bar(progress) as bar:
            task = bar.add_task(f"{label} (s of model time)", total=total) if bar else None
            done = 0.0
            for fname, idx in groups.items():
                if bar:
                    bar.update(task, description=f"{label} ({fname}, {len(idx)} trials; s of model time)")
                tick = (lambda t, d=done: bar.update(task, completed=d + t)) if bar else None
                done_logs = simulate([trials[i] for i in idx], settings, fname, on_progress=tick)
                for i, log in zip(idx, done_logs):
                    logs[i] = log
                if on_done is not None:
                    on_done(idx, done_logs)
                done += max(trials[i].duration for i in idx)
                if bar:
                    bar.update(task, completed=done)
        return logs
    chunks = _chunks(trials, workers, fidelity)
    with ProcessPoolExecutor(max_workers=len(chunks), initializer=quiet_worker) as ex:
        futs = {ex.submit(_simulate_chunk, [trials[i] for i in c], settings, fidelity): c for c in chunks}

        with progress_bar(progress) as bar:
            task = bar.add_task(f"{label} ({len(chunks)} workers)", total=len(trials)) if bar else None
            for fut in as_completed(futs):
                c = futs[fut]
                done_logs = fut.result()
                for i, log in zip(c, done_logs):
                    logs[i] = log
                if on_done is not None:
                    on_done(c, done_logs)
                if bar:
                    bar.advance(task, len(c))
    return logs


def progress_bar(enabled: bool):
    """A rich progress bar, or a context that gives None when not ``enabled``."""
    if not enabled:
        return nullcontext()

    # on stderr: stdout carries the command's results
    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    TimeRemainingColumn(), transient=False, console=Console(stderr=True))
