"""Tune a scenario's estimator or controller settings with optuna; score them on held-out seeds.

The study: TPE sampler (seeded), MedianPruner on the running mean of the objective over the train
seeds (one intermediate value per seed), the search space from the role table's declared bounds
(:func:`hbma_ctrl.app.schema.space.search_space`, in the user's units), the default settings as
trial 0 of a new study. A trial whose run fails or diverges is a failed trial, never a crash.

Storage: an optuna RDB URL (``sqlite:///file.db``, PostgreSQL, MySQL) or ``journal:PATH`` (a
:class:`optuna.storages.journal.JournalFileBackend` file, e.g. on a shared disk). Several
processes or machines may work one study; a RUNNING trial left by a dead process of this host is
failed when a study is opened again (:func:`fail_orphans`).

Outputs (:func:`write_outputs`): ``tuned.toml`` (the scenario with the best settings and a header
saying where they came from), ``tune.json`` (:data:`TUNE_KEYS` and more), ``history.png``,
``importance.png`` (with >= 2 completed trials).
"""

from __future__ import annotations

import copy
import datetime as dt
import hashlib
import itertools
import json
import math
import os
import socket
import tempfile
import tomllib
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import optuna
import tomli_w

from hbma_ctrl.app.outputs import pid_alive
from hbma_ctrl.app.scenes.runner import RunFailed, run_scenario
from hbma_ctrl.app.scenario import _text
from hbma_ctrl.app.schema.controller import ControllerTable
from hbma_ctrl.app.schema.document import parse_scenario_tables
from hbma_ctrl.app.schema.estimator import EstimatorTable
from hbma_ctrl.app.schema.space import search_space

__all__ = [
    "CONTROLLER_PENALTY",
    "DEFAULT_OBJECTIVE",
    "DEFAULT_PARAMS",
    "OBJECTIVES",
    "ROLES",
    "TUNE_KEYS",
    "Dim",
    "RunDiverged",
    "TuneSpec",
    "apply_params",
    "default_params",
    "fail_orphans",
    "make_space",
    "make_storage",
    "mean_score",
    "objective_value",
    "open_study",
    "parse_seeds",
    "run_worker",
    "score",
    "write_outputs",
]

#: the roles a study can tune -> the scenario table holding their settings
ROLES = {"controller": ControllerTable, "estimator": EstimatorTable}

#: metrics.json keys an objective may name (all minimised), per role
OBJECTIVES = {
    "controller": ("height_rmse_mm", "height_est_rmse_mm", "height_rmse_estimate_mm", "max_pressure_kpa",
                   "solve_ms_median", "solve_ms_p99", "fallbacks", "guard_activations"),
    "estimator": ("height_nrmsd", "pressure_nrmsd", "height_rmse_mm", "force_rmse_n", "height_nrmsd_max",
                  "force_steady_rel_err_mean", "force_steady_rel_err_max"),
}

#: objective of each role without --objective
DEFAULT_OBJECTIVE = {"controller": "controller.height_rmse_mm", "estimator": "estimator.height_nrmsd"}

#: the default controller objective's penalty, mm added to height_rmse_mm: per fallback step, per
#: pressure-guard activation (the limit was reached) and once if the pressure limit was exceeded
CONTROLLER_PENALTY = {"fallbacks": 0.01, "guard_activations": 0.01, "limit_exceeded": 10.0}

#: the parameters tuned without --param-set (the settings that shape the behaviour, not the limits)
DEFAULT_PARAMS = {
    "controller:mpc": ("w_terminal", "w_rate[0]", "w_rate[2]", "c_input[0]", "c_input[2]"),
    "controller:pid": ("kp", "ki", "kd"),
    "controller:bang_bang": ("band_kpa",),
    "controller:lqi": ("q_height", "q_integral", "r_command"),
    "estimator": ("model_rel_std", "flow_rel_std", "flow_factor_std", "modulus_std", "load_std_n"),
}

#: a default parameter is searched within [default / WINDOW, default * WINDOW] (inside its bounds):
#: the declared bounds (often 0 to 1e9) are far wider than any useful setting
WINDOW = 20.0

#: a key named without a range whose declared low end is open at 0 is sampled from this share of its
#: top, or from its value when that is lower
OPEN_FLOOR = 1e-9

#: the keys tune.json always holds
TUNE_KEYS = ("objective", "n_trials", "best_params", "best_value_train", "default_value_test", "best_value_test")


@dataclass(frozen=True)
class Dim:
    """One searched parameter: table key ``name`` (``w_rate[0]`` for a vector element), range
    [lo, hi] in the key's unit, ``kind`` "float" or "int", ``log`` sampling, ``default`` value."""

    name: str
    lo: float
    hi: float
    unit: str
    kind: str
    log: bool
    default: float


@dataclass
class TuneSpec:
    """What one worker needs: ``scenario`` path, ``role``, ``objective`` ("role.key"), ``space``
    (list of :class:`Dim`), ``train_seeds`` (rig seeds), ``duration_s`` override (None: the file's),
    ``storage`` URL, ``study`` name, ``seed`` of the sampler, ``n_startup`` random trials, ``data``
    the scenario's TOML data (read from ``scenario`` when empty)."""

    scenario: Path
    role: str
    objective: str
    space: list[Dim]
    train_seeds: list[int]
    duration_s: float | None
    storage: str
    study: str
    seed: int = 0
    n_startup: int = 6
    data: dict = field(default_factory=dict)


#: the most seeds --train-seeds or --test-seeds may name
MAX_SEEDS = 1000


def parse_seeds(text: str, flag: str) -> list[int]:
    """'0-9' or '0,3,5' or '0-4,8' -> sorted distinct seeds; ValueError naming the flag."""
    out: set[int] = set()
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        bounds = part.split("-")
        try:
            nums = [int(b) for b in bounds]
        except ValueError:
            nums = []
        if len(nums) not in (1, 2) or any(n < 0 for n in nums) or (len(nums) == 2 and nums[1] < nums[0]):
            raise ValueError(f"{flag} = '{text}': '{part}' is not a seed or a range A-B of seeds "
                             "(whole numbers >= 0, A <= B)")
        # a range wider than the cap is refused before it is built ('0-99999999' is 1e8 ints); ranges that
        # overlap count their common seeds once ('0-999,0-5' is 1000 seeds)
        if nums[-1] - nums[0] + 1 > MAX_SEEDS or len(out.union(range(nums[0], nums[-1] + 1))) > MAX_SEEDS:
            raise ValueError(f"{flag} = '{text}': more than {MAX_SEEDS} seeds; at most {MAX_SEEDS}")
        out.update(range(nums[0], nums[-1] + 1))
    if not out:
        raise ValueError(f"{flag} = '{text}': expected seeds like 0-9 or 0,3,5")
    return sorted(out)


def _field_default(table: type, name: str) -> Any:
    base, idx = _split(name)
    v = table.model_fields[base].get_default(call_default_factory=True)
    return v[idx] if idx is not None and v is not None else v


def _split(name: str) -> tuple[str, int | None]:
    if name.endswith("]") and "[" in name:
        base, idx = name[:-1].split("[", 1)
        return base, int(idx)
    return name, None


def _current(data: dict, role: str, name: str) -> Any:
    base, idx = _split(name)
    raw = data.get(role, {}).get(base)
    if raw is None:
        return _field_default(ROLES[role], name)
    return raw[idx] if idx is not None else raw


def make_space(data: dict, role: str, names: list[str] | None = None) -> list[Dim]:
    """The searched parameters of ``role`` (``names``, else the role's default set) with their ranges.

    A name may carry its own range, ``NAME=LO:HI`` (inside the declared bounds); a default name
    without one is searched within WINDOW x its current value; log sampling for lo > 0 and
    hi / lo > 100 (more than two decades). ValueError naming the bad name and listing the valid ones.
    """
    table = ROLES[role]
    space = search_space(table)
    kind = data.get(role, {}).get("kind", "mpc")
    defaults = DEFAULT_PARAMS.get(f"{role}:{kind}", DEFAULT_PARAMS.get(role, ()))
    window = names is None
    dims = []
    for item in (list(defaults) if names is None else names):
        name, _, rng = item.partition("=")
        name = name.strip()
        if name not in space:
            raise ValueError(f"--param-set: '{name}' is not a numeric [{role}] key with two bounds; allowed: "
                             f"{', '.join(space)}")
        lo, hi, unit, k = space[name]
        given = _current(data, role, name)
        # a key defaulting to None (e.g. a margin chosen per controller): search its bounds
        d = lo if given is None else given
        if rng:
            try:
                a, b = (float(x) for x in rng.split(":"))
            except ValueError:
                raise ValueError(f"--param-set {item}: expected NAME=LO:HI in {unit}") from None
            if not (math.isfinite(a) and math.isfinite(b) and lo <= a < b <= hi):
                raise ValueError(f"--param-set {item}: range must satisfy {lo:g} <= LO < HI <= {hi:g} {unit}")
            lo, hi = a, b
        elif window and d > 0:
            lo, hi = max(lo, d / WINDOW), min(hi, d * WINDOW)
        elif 0 < lo < hi * OPEN_FLOOR:
            # an open end at 0 is the smallest value inside (search_space), hundreds of decades below any
            # useful setting: sampled from there, nearly every trial would be; the value itself is kept
            lo = hi * OPEN_FLOOR if given is None else max(lo, min(hi * OPEN_FLOOR, given))
        if k == "int":
            lo, hi = math.ceil(lo), math.floor(hi)
        log = lo > 0 and hi / lo > 100.0
        dims.append(Dim(name, float(lo), float(hi), unit, k, log, float(min(max(d, lo), hi))))
    if len({d.name for d in dims}) != len(dims):
        raise ValueError("--param-set: a parameter is named twice")
    return dims


def default_params(space: list[Dim]) -> dict[str, float]:
    """{name: the scenario's own value} of the searched parameters (trial 0 of a new study)."""
    return {d.name: (int(d.default) if d.kind == "int" else d.default) for d in space}


def apply_params(data: dict, role: str, params: dict[str, float]) -> dict:
    """A copy of the scenario data with ``params`` written into the role table (user units)."""
    out = copy.deepcopy(data)
    tab = out.setdefault(role, {})
    for name, v in params.items():
        base, idx = _split(name)
        if idx is None:
            tab[base] = v
        else:
            vec = list(tab.get(base) or _field_default(ROLES[role], base))
            vec[idx] = v
            tab[base] = vec
    return out


def objective_value(metrics: dict, objective: str) -> float:
    """The objective of one run: ``metrics[role][key]``, plus :data:`CONTROLLER_PENALTY` for the default.

    ValueError when the key is missing (the scenario does not produce it).
    """
    role, key = objective.split(".", 1)
    vals = metrics.get(role) or {}
    if key not in vals:
        have = [k for k, v in vals.items() if isinstance(v, (int, float)) and not isinstance(v, bool)]
        raise ValueError(f"--objective {objective}: this scenario's metrics.json has no such key; it has "
                         f"{', '.join(f'{role}.{k}' for k in have)}")
    v = float(vals[key])
    if objective == DEFAULT_OBJECTIVE["controller"]:
        pen = CONTROLLER_PENALTY
        v += pen["fallbacks"] * float(vals.get("fallbacks", 0)) + pen["guard_activations"] * float(
            vals.get("guard_activations", 0))
        if vals.get("pressure_limit_respected") is False:
            v += pen["limit_exceeded"]
    return v


class RunDiverged(RuntimeError):
    """A run failed, diverged or gave a non-finite objective: the trial fails, the study goes on."""


def score(data: dict, scenario: Path, objective: str, seed: int, duration_s: float | None) -> float:
    """Run the scenario once with rig seed ``seed`` (and ``duration_s``) in a scratch directory;
    the objective value. RunDiverged on a failed run; ValueError on a bad scenario or objective."""
    d = copy.deepcopy(data)
    d.setdefault("rig", {})["seed"] = int(seed)
    if duration_s is not None:
        d.setdefault("scenario", {})["duration_s"] = float(duration_s)
    try:
        scn = parse_scenario_tables(d, scenario)
    except ValueError as exc:  # the base scenario was checked: a sampled combination broke a cross-rule
        raise RunDiverged(str(exc)) from None
    with tempfile.TemporaryDirectory(prefix="hbma-tune-") as tmp:
        try:
            metrics = run_scenario(scn, tmp)
        except RunFailed as exc:
            raise RunDiverged(str(exc)) from None
        except (ArithmeticError, RuntimeError, ValueError, FloatingPointError) as exc:
            # a setting inside its bounds that still breaks a solver or the plant is a bad trial
            raise RunDiverged(f"{type(exc).__name__}: {exc}") from None
    v = objective_value(metrics, objective)
    if not math.isfinite(v):
        raise RunDiverged(f"{objective} = {v}")
    return v


def _is_journal(path: str) -> bool:
    """Whether ``path`` is missing, empty or starts with an optuna journal record (a JSON object with an
    ``op_code``); a folder or another file is not."""
    p = Path(path)
    if not p.exists():
        return True
    if not p.is_file():
        return False
    try:
        with p.open("rb") as fh:
            first = fh.readline(1 << 20)
        return not first.strip() or "op_code" in json.loads(first)
    except (OSError, ValueError, TypeError):
        return False


def make_storage(url: str) -> optuna.storages.BaseStorage:
    """An optuna storage for ``url``: RDB URL (sqlite with a 60 s lock wait) or ``journal:PATH``."""
    if url.startswith("journal:"):
        from optuna.storages.journal import JournalFileBackend

        path = url[len("journal:"):]
        if path.startswith("//"):
            path = path[2:]
        if not path:
            raise ValueError("--storage journal:PATH: the journal file path is missing")
        if not _is_journal(path):  # optuna would append its log to any file: never to a user's own
            raise ValueError(f"--storage {url}: {path} is not an optuna journal (its first line is not one of "
                             "a journal's records); give a new path or a journal's")
        try:
            return optuna.storages.JournalStorage(JournalFileBackend(path))
        except OSError as exc:
            raise ValueError(f"--storage {url}: cannot open {path} ({exc.strerror or exc})") from None
    kw: dict = {}
    if url.startswith("sqlite"):
        kw["connect_args"] = {"timeout": 60}
    try:
        return optuna.storages.RDBStorage(url, engine_kwargs=kw)
    except (ImportError, ModuleNotFoundError) as exc:
        raise ValueError(f"--storage {url}: its database driver is not installed ({exc})") from None
    except Exception as exc:  # sqlalchemy's ArgumentError, OperationalError, ...: one line naming the flag
        text = " ".join(str(exc).split())[:200]
        raise ValueError(f"--storage {url}: cannot open ({type(exc).__name__}: {text})") from None


def _study_attrs(spec: TuneSpec) -> dict:
    return {"role": spec.role, "objective": spec.objective, "params": [d.name for d in spec.space],
            "train_seeds": spec.train_seeds, "duration_s": spec.duration_s}


def open_study(spec: TuneSpec, new_ok: bool = True) -> optuna.Study:
    """Create or load the study; a loaded one must tune the same role, objective, parameters and seeds.

    A new study gets the default settings as its first trial; ValueError on a mismatching study.
    """
    storage = make_storage(spec.storage)
    names = [s.study_name for s in optuna.study.get_all_study_summaries(storage, include_best_trial=False)]
    sampler = optuna.samplers.TPESampler(seed=spec.seed, n_startup_trials=spec.n_startup)
    pruner = optuna.pruners.MedianPruner(n_startup_trials=3, n_warmup_steps=0)
    if spec.study in names:
        study = optuna.load_study(study_name=spec.study, storage=storage, sampler=sampler, pruner=pruner)
        attrs = {k: study.user_attrs.get(k) for k in _study_attrs(spec)}
        want = json.loads(json.dumps(_study_attrs(spec)))
        diff = [k for k in want if attrs[k] != want[k]]
        if diff:
            raise ValueError(f"--study {spec.study}: the study in {spec.storage} was made with other settings ("
                             + "; ".join(f"{k}: {attrs[k]} there, {want[k]} now" for k in diff)
                             + "); choose another --study or the same settings")
        return study
    if not new_ok:
        raise ValueError(f"--study {spec.study}: not found in {spec.storage}")
    try:
        study = optuna.create_study(study_name=spec.study, storage=storage, sampler=sampler, pruner=pruner,
                                    direction="minimize")
    except optuna.exceptions.DuplicatedStudyError:  # another process created it meanwhile
        return open_study(spec, new_ok=False)
    for k, v in _study_attrs(spec).items():
        study.set_user_attr(k, v)
    study.enqueue_trial(default_params(spec.space), user_attrs={"default": True})
    return study


def fail_orphans(study: optuna.Study) -> list[int]:
    """Fail the RUNNING trials whose process (recorded host and pid) is gone; their numbers.

    A RUNNING trial of another host or of a live process is left alone: another worker owns it.
    """
    storage = study._storage  # optuna's public storage API needs the storage object, not the study
    host = socket.gethostname()
    failed = []
    for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.RUNNING,)):
        pid = t.user_attrs.get("pid")
        if t.user_attrs.get("host") == host and isinstance(pid, int) and not pid_alive(pid):
            storage.set_trial_state_values(t._trial_id, optuna.trial.TrialState.FAIL)
            failed.append(t.number)
    return failed


def _objective(spec: TuneSpec) -> Callable[[optuna.Trial], float]:
    def run(trial: optuna.Trial) -> float:
        trial.set_user_attr("host", socket.gethostname())
        trial.set_user_attr("pid", os.getpid())
        params: dict[str, float] = {}
        for d in spec.space:
            if d.kind == "int":
                params[d.name] = trial.suggest_int(d.name, int(d.lo), int(d.hi), log=d.log)
            else:
                params[d.name] = trial.suggest_float(d.name, d.lo, d.hi, log=d.log)
        data = apply_params(spec.data, spec.role, params)
        vals = []
        for step, seed in enumerate(spec.train_seeds):
            try:
                vals.append(score(data, spec.scenario, spec.objective, seed, spec.duration_s))
            except RunDiverged as exc:
                # optuna marks the trial FAIL (catch=) and goes on; the reason stays with the trial
                trial.set_user_attr("failure", f"seed {seed}: {exc}"[:500])
                raise
            mean = sum(vals) / len(vals)
            trial.report(mean, step)
            if step < len(spec.train_seeds) - 1 and trial.should_prune():
                raise optuna.TrialPruned(f"running mean {mean:.4g} after {step + 1} seeds")
        return sum(vals) / len(vals)

    return run


def run_worker(spec: TuneSpec, n_trials: int, callback: Callable[[], None] | None = None) -> None:
    """Run ``n_trials`` trials of the study in this process (a worker of ``--workers``)."""
    # a failed trial is counted in the report and its reason kept in the trial's user attrs
    optuna.logging.set_verbosity(optuna.logging.ERROR)
    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)
    if not spec.data:
        spec.data = tomllib.loads(_text(spec.scenario))
    study = open_study(spec, new_ok=False)
    cbs = [lambda s, t: callback()] if callback is not None else []
    study.optimize(_objective(spec), n_trials=n_trials, catch=(RunDiverged,), callbacks=cbs,
                   gc_after_trial=False)


def mean_score(data: dict, scenario: Path, objective: str, seeds: list[int], duration_s: float | None
               ) -> tuple[float | None, list]:
    """Mean objective over ``seeds`` and the per-seed values (None where the run failed)."""
    per = []
    for s in seeds:
        try:
            per.append(score(data, scenario, objective, s, duration_s))
        except RunDiverged:
            per.append(None)
    ok = [v for v in per if v is not None]
    return (sum(ok) / len(ok) if ok and len(ok) == len(per) else None), per


def write_outputs(out: Path, study: optuna.Study, spec: TuneSpec, test_seeds: list[int],
                  default_test: tuple, best_test: tuple, extra: dict) -> dict:
    """tuned.toml, tune.json, history.png and importance.png into ``out``; returns tune.json's content."""
    states = [t.state for t in study.trials]
    complete = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    best = study.best_trial if complete else None
    now = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds").replace("+00:00", "Z")
    info = {
        "objective": spec.objective,
        "n_trials": len(study.trials),
        "best_params": dict(best.params) if best else None,
        "best_value_train": best.value if best else None,
        "default_value_test": default_test[0],
        "best_value_test": best_test[0],
        "n_complete": states.count(optuna.trial.TrialState.COMPLETE),
        "n_pruned": states.count(optuna.trial.TrialState.PRUNED),
        "n_failed": states.count(optuna.trial.TrialState.FAIL),
        "best_trial": best.number if best else None,
        "default_params": default_params(spec.space),
        "default_value_train": next((t.value for t in complete if t.user_attrs.get("default")), None),
        "default_test_per_seed": default_test[1],
        "best_test_per_seed": best_test[1],
        "penalty": CONTROLLER_PENALTY if spec.objective == DEFAULT_OBJECTIVE["controller"] else None,
        "space": [d.__dict__ for d in spec.space],
        "train_seeds": spec.train_seeds,
        "test_seeds": test_seeds,
        "duration_s": spec.duration_s,
        "study": spec.study,
        "storage": spec.storage,
        "scenario": str(spec.scenario),
        "scenario_sha256": hashlib.sha256(spec.scenario.read_bytes()).hexdigest(),
        "finished_utc": now,
        **extra,
    }
    (out / "tune.json").write_text(json.dumps(info, indent=1) + "\n")
    if best is not None:
        data = apply_params(spec.data, spec.role, best.params)
        csv = data.get("pneumatics", {}).get("compressor_csv")
        if isinstance(csv, str) and not Path(csv).is_absolute():  # tuned.toml lives elsewhere: keep the file
            data["pneumatics"]["compressor_csv"] = str((spec.scenario.parent / csv).resolve())
        head = (f"# [{spec.role}] tuned by hbma-ctrl tune on {now}: study '{spec.study}' in {spec.storage},\n"
                f"# trial {best.number} of {len(study.trials)}, objective {spec.objective}, train seeds "
                f"{_ranges(spec.train_seeds)}"
                + (f", runs shortened to {spec.duration_s:g} s" if spec.duration_s is not None else "") + ".\n"
                f"# Source: {spec.scenario} (sha256 {info['scenario_sha256'][:16]}). Held-out seeds "
                f"{_ranges(test_seeds)}: default {_num(default_test[0])}, tuned {_num(best_test[0])}.\n")
        (out / "tuned.toml").write_text(head + tomli_w.dumps(data))
    _plots(out, study)
    return info


def _num(v: float | None) -> str:
    return "failed" if v is None else f"{v:.4g}"


def _ranges(seeds: list[int]) -> str:
    """Sorted distinct seeds as :func:`parse_seeds` reads them: runs of consecutive ones as A-B."""
    # within a run of consecutive seeds, seed - position is constant
    runs = [[s for _, s in g] for _, g in itertools.groupby(enumerate(seeds), lambda p: p[1] - p[0])]
    return ",".join(str(r[0]) if len(r) == 1 else f"{r[0]}-{r[-1]}" for r in runs)


def _plots(out: Path, study: optuna.Study) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from optuna.visualization import matplotlib as vm

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ax = vm.plot_optimization_history(study)
        ax.figure.tight_layout()
        ax.figure.savefig(out / "history.png", dpi=110)
        plt.close(ax.figure)
        n_complete = sum(t.state == optuna.trial.TrialState.COMPLETE for t in study.trials)
        fig, ax = plt.subplots(figsize=(6, 3.5))
        try:
            if n_complete < 2 or len(study.best_trial.params) < 2:
                raise ValueError(f"{n_complete} completed trial(s)")
            plt.close(fig)
            ax = vm.plot_param_importances(study)
            fig = ax.figure
        except (ValueError, RuntimeError) as exc:
            ax.text(0.5, 0.5, f"parameter importance needs >= 2 completed trials\nand >= 2 parameters "
                              f"({exc})", ha="center", va="center")
            ax.set_axis_off()
        fig.tight_layout()
        fig.savefig(out / "importance.png", dpi=110)
        plt.close(fig)
