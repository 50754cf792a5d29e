"""``hbma-ctrl tune SCENARIO --role estimator|controller``: optuna tuning, scored on held-out seeds.

Registered by :mod:`hbma_ctrl.app.cli.main` through :func:`register`; the work is in
:mod:`hbma_ctrl.app.tuning.tune`. The study lives in ``--storage`` (default: the SQLite file
``<out>.study.db`` beside ``--out``, so that it outlives any one results directory); rerunning the
same command continues the study with ``--trials`` more trials and replaces the results in
``--out`` (a directory holding the results of another study is refused as usual, unless
``--overwrite``). Bad input raises ValueError: one ``error: ...`` line, exit code 2.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import time
import tomllib
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

# optuna and the tuning itself (it runs scenarios: every role) are imported by the command when it runs
from hbma_ctrl.app.cli.args import cap_workers, check_choice, check_range, show_table
from hbma_ctrl.app.outputs import OVERWRITE_HELP, check_out, cli_argv, default_out, run_dir

if TYPE_CHECKING:
    import optuna

    from hbma_ctrl.app.tuning.tune import TuneSpec

__all__ = ["register", "tune_cmd", "check_objective"]


def check_objective(role: str, objective: str | None) -> str:
    """``role.key`` (a bare key gets the role prefix); ValueError listing the valid keys of the role."""
    from hbma_ctrl.app.tuning.tune import DEFAULT_OBJECTIVE, OBJECTIVES

    if objective is None:
        return DEFAULT_OBJECTIVE[role]
    key = objective.split(".", 1)[1] if objective.startswith(f"{role}.") else objective
    if key not in OBJECTIVES[role]:
        valid = ", ".join(f"{role}.{k}" for k in OBJECTIVES[role])
        raise ValueError(f"--objective = '{objective}' is not a metric of role {role}; allowed: {valid}")
    return f"{role}.{key}"


def _shares(n: int, k: int) -> list[int]:
    return [n // k + (1 if i < n % k else 0) for i in range(k) if n // k + (1 if i < n % k else 0) > 0]


def tune_cmd(
    scenario: Annotated[Path, typer.Argument(help="scenario TOML file with a rig table and the role's table")],
    role: Annotated[str, typer.Option("--role", help="estimator | controller (required)")],
    trials: Annotated[int, typer.Option("--trials", help="trials to add to the study in this run")] = 20,
    objective: Annotated[Optional[str], typer.Option(
        "--objective", help="metrics.json key of the role to minimise (default controller.height_rmse_mm "
                            "+ penalty, estimator.height_nrmsd)")] = None,
    storage: Annotated[Optional[str], typer.Option(
        "--storage", help="optuna storage URL (sqlite:///f.db, postgresql://..., journal:PATH); default "
                          "sqlite beside --out: <out>.study.db")] = None,
    study: Annotated[Optional[str], typer.Option("--study", help="study name (default <scenario>-<role>)")] = None,
    workers: Annotated[int, typer.Option("--workers", help="processes working the study")] = 1,
    train_seeds: Annotated[str, typer.Option("--train-seeds", help="rig seeds of the tuning runs, e.g. 0-9")] = "0-4",
    test_seeds: Annotated[str, typer.Option("--test-seeds", help="held-out rig seeds, e.g. 10-19")] = "10-14",
    param_set: Annotated[Optional[list[str]], typer.Option(
        "--param-set", help="tune this key of the role table (repeatable; NAME or NAME=LO:HI in its unit); "
                            "default: a set per role")] = None,
    duration_s: Annotated[Optional[float], typer.Option(
        "--duration-s", help="shorten every run to this, s (default: the scenario's)")] = None,
    seed: Annotated[int, typer.Option("--seed", help="sampler seed")] = 0,
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="results directory (default "
                                                                    "runs/tune-<scenario>-<role>)")] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
) -> None:
    """Tune the role's settings with optuna (TPE, median pruning) on train seeds; score default and
    best on held-out seeds; write tuned.toml, tune.json, history.png, importance.png."""
    import optuna

    from hbma_ctrl.app.scenario import _text, load_scenario
    from hbma_ctrl.app.shipped import resolve
    from hbma_ctrl.app.tuning.tune import (
        ROLES,
        TuneSpec,
        apply_params,
        default_params,
        fail_orphans,
        make_space,
        make_storage,
        mean_score,
        open_study,
        parse_seeds,
        write_outputs,
    )

    check_choice("--role", role, ROLES)
    check_range("--trials", trials, 1, 100000)
    check_range("--workers", workers, 1, 256)
    check_range("--seed", seed, 0, 2**31 - 1)
    obj = check_objective(role, objective)
    train = parse_seeds(train_seeds, "--train-seeds")
    test = parse_seeds(test_seeds, "--test-seeds")
    both = sorted(set(train) & set(test))
    if both:
        raise ValueError(f"--test-seeds = '{test_seeds}' shares seeds {both[:5]} with --train-seeds = '{train_seeds}'; "
                         "held-out seeds must never be used in tuning")
    check_range("--duration-s", duration_s, 0.0, 3600.0, lo_open=True, unit="s")
    workers = cap_workers("--workers", workers)
    scenario = resolve(scenario)  # a shipped scenario's name reads the shipped file, as load_scenario does
    scn = load_scenario(scenario)
    data = tomllib.loads(_text(scenario))
    if role not in data:
        raise ValueError(f"{scenario.name}: no [{role}] table to tune (--role {role})")
    if "rig" not in data:
        raise ValueError(f"{scenario.name}: no [rig] table; the train and test seeds are the rig's noise seeds")
    space = make_space(data, role, param_set)
    check_base(data, scenario, duration_s)
    out_dir = out or default_out(f"tune-{scn.name}-{role}")
    study_name = study or f"{scn.name}-{role}"
    out_abs = Path(os.path.abspath(out_dir))
    url = storage or f"sqlite:///{out_abs.parent / (out_abs.name + '.study.db')}"
    resume = _same_study(out_dir, study_name, url)
    check_out(out_dir, overwrite or resume)
    make_storage(url)  # a bad URL or a missing driver: an input error before any work
    n_start = max(3, min(10, trials // 3))
    spec = TuneSpec(scenario=scenario, role=role, objective=obj, space=space, train_seeds=train,
                    duration_s=duration_s, storage=url, study=study_name, seed=seed, n_startup=n_start, data=data)
    con = Console(highlight=False)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    t0 = time.perf_counter()
    with run_dir(out_dir, command="tune", argv=cli_argv(), scenario_path=scenario, overwrite=overwrite or resume) as tmp:
        st = open_study(spec)
        orphans = fail_orphans(st)
        if orphans:
            con.print(f"note: failed trial(s) {orphans} left RUNNING by a process that is gone")
        before = len(st.trials)
        spec.seed = seed + before  # a resumed study must not replay the first run's random samples
        _optimise(spec, trials, workers, con)
        st = open_study(spec, new_ok=False)
        complete = [t for t in st.trials if t.state == optuna.trial.TrialState.COMPLETE]
        defaults = default_params(space)
        con.print(f"scoring default and best settings on held-out seeds {test_seeds} ...")
        d_test = mean_score(apply_params(data, role, defaults), scenario, obj, test, duration_s)
        b_test = (None, [])
        if complete:
            b_test = mean_score(apply_params(data, role, st.best_trial.params), scenario, obj, test, duration_s)
        info = write_outputs(tmp, st, spec, test, d_test, b_test,
                             {"trials_this_run": len(st.trials) - before, "workers": workers,
                              "wall_s": round(time.perf_counter() - t0, 1)})
    _report(con, info, out_dir)


def check_base(data: dict, scenario: Path, duration_s: float | None) -> None:
    """The scenario as a trial runs it (shortened by ``--duration-s``) must be valid: an input error
    now, not a failed trial for every sample later."""
    from hbma_ctrl.app.schema.document import parse_scenario_tables

    if duration_s is None:
        return
    trial = {**data, "scenario": {**data.get("scenario", {}), "duration_s": float(duration_s)}}
    try:
        parse_scenario_tables(trial, scenario)
    except ValueError as exc:
        raise ValueError(f"--duration-s = {duration_s:g}: {exc}") from None


def _same_study(out: Path, study: str, url: str) -> bool:
    """True when ``out`` holds the results of this very study (so rerunning continues it)."""
    try:
        info = json.loads((Path(out) / "tune.json").read_text())
    except (OSError, ValueError):
        return False
    return info.get("study") == study and info.get("storage") == url


def _optimise(spec: TuneSpec, trials: int, workers: int, con: Console) -> None:
    import optuna

    from hbma_ctrl.app.tuning.tune import TuneSpec, open_study, run_worker

    cols = (TextColumn("tune {task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*cols, console=con, transient=False) as bar:
        task = bar.add_task(spec.study, total=trials)
        if workers == 1:
            run_worker(spec, trials, callback=lambda: bar.advance(task))
            return
        st = open_study(spec, new_ok=False)
        start = _finished(st)
        total = trials
        # optuna's SQLite storage can hand one enqueued trial (the defaults, trial 0) to two processes
        # at once (no row lock; the second then fails to tell it): enqueued trials run here, alone,
        # before the workers start
        waiting = len(st.get_trials(deepcopy=False, states=(optuna.trial.TrialState.WAITING,)))
        first = min(waiting, trials)
        if first:
            run_worker(spec, first, callback=lambda: bar.advance(task))
            trials -= first
        if trials == 0:
            return
        # spawn: a forked child would share the parent's database connections
        with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as pool:
            futs = []
            for i, n in enumerate(_shares(trials, workers)):
                w = TuneSpec(**{**spec.__dict__, "seed": spec.seed + 7919 * i})
                futs.append(pool.submit(run_worker, w, n))
            while not all(f.done() for f in futs):
                time.sleep(0.5)
                bar.update(task, completed=min(total, _finished(st) - start))
            for f in futs:
                f.result()  # a worker's error (bad objective key, storage) is this command's error
            bar.update(task, completed=min(total, _finished(st) - start))


def _finished(study: optuna.Study) -> int:
    return sum(t.state.is_finished() for t in study.get_trials(deepcopy=False))


def _report(con: Console, info: dict, out: Path) -> None:
    def f(v):
        return "failed" if v is None else f"{v:.4g}"

    best = "best " + ("(no trial completed)" if info["best_trial"] is None else f"(trial {info['best_trial']})")
    show_table(f"tune {info['study']}: {info['objective']} ({info['n_trials']} trials: {info['n_complete']} complete, "
               f"{info['n_pruned']} pruned, {info['n_failed']} failed)", ("settings", "train", "held-out test"),
               [("default", f(info["default_value_train"]), f(info["default_value_test"])),
                (best, f(info["best_value_train"]), f(info["best_value_test"]))], con, left=1)
    if info["best_params"]:
        con.print("best: " + ", ".join(f"{k} = {v:.4g}" for k, v in info["best_params"].items()))
    con.print(f"wrote {out / 'tuned.toml'}, {out / 'tune.json'}, history.png, importance.png; study in "
              f"{info['storage']}")


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add the ``tune`` command to the top-level CLI (nothing under ``bench``)."""
    app.command("tune")(tune_cmd)
