"""Simulator speed/accuracy benchmark over the 150-trial protocol (docs/concepts/model.md §7) (``hbma-ctrl bench sim``).

For each fixed-step integrator (euler, rk4) x step size x fidelity of the loaded trials
('quasi_static', 'platform'; the 0 g trials always run 'free'), the wall time of the whole
protocol and the NRMSD (paper eq. 16, ``rms(y_hat - y) / (y_max - y_min)``, y the reference)
of height and pressure per trial, against the adaptive implicit reference ('radau', same
fidelity), interpolated on the reference's log times. Trials whose reference is constant (a load
that never lifts: height stays 0) have no height NRMSD and are left out of its mean and max.

The reference is cached in the output directory (``ref_<fidelity>.npz``), keyed by the trials,
the reference settings and a hash of the model sources; it is reused when all of these match.
Wall times exclude the one-off casadi Function construction (a short warm-up run per setting)
and are medians over ``repeat`` runs.

The fidelity axis (docs/concepts/model.md §9): every row is also scored against the exact membrane
(``*_vs_exact_*``: the simulator's 'exact' rung, the platform model with the exact flat contact for
loaded trials, exact free inflation for the 0 g ones) at a fine fixed step (rk4,
:data:`EXACT_REF_DT` s; an adaptive reference through 2-D table lookups costs minutes and its
discretisation error at this step is far below the gaps between rungs). Rows of the 'free' rung run
only the 0 g trials (the cap's free inflation is all it models); rows of the 'exact' rung measure
its own cost and step error. ``pareto.png`` beside bench.json plots wall time against NRMSD vs the
exact membrane, one point per fidelity x integrator x step (:mod:`hbma_ctrl.app.bench.plots`).
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import statistics
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from hbma_ctrl.app.metrics import json_safe, nrmsd
from hbma_ctrl.core import units as U
from hbma_ctrl.core.materials import Material, make_material
from hbma_ctrl.sim.batch import fidelity_for, protocol_trials, simulate_trials
from hbma_ctrl.sim.trial import DEFAULT_DT, InputSchedule, SimSettings, Trial

__all__ = ["BenchRow", "GRID", "QUICK_GRID", "FIDELITY_GRID", "QUICK_FIDELITY_GRID", "EXACT_REF_DT", "TARGET_WALL_S",
           "TARGET_NRMSD", "run_bench", "reference", "exact_reference", "bench_trials"]

#: fixed steps (ms) per loaded fidelity and integrator; the platform model is stiffer (a light
#: platform on a stiff gas spring), so its steps are smaller
GRID = {
    "quasi_static": {"euler": (0.5, 1.0, 2.0), "rk4": (2.0, 5.0, 10.0)},
    "platform": {"euler": (0.05, 0.1, 0.2), "rk4": (0.25, 0.5, 1.0)},
}
QUICK_GRID = {
    "quasi_static": {"euler": (1.0,), "rk4": (5.0,)},
    "platform": {"euler": (0.1,), "rk4": (0.5,)},
}
#: the fidelity axis' extra rungs: the cap's free inflation (0 g trials only) and the exact membrane
FIDELITY_GRID = {
    "free": {"euler": (1.0,), "rk4": (10.0,)},
    "exact": {"euler": (0.1,), "rk4": (0.5, 2.0)},
}
QUICK_FIDELITY_GRID = {"free": {"rk4": (10.0,)}, "exact": {"rk4": (2.0,)}}
#: the exact reference's fixed rk4 step, s (loaded and free trials)
EXACT_REF_DT = 2.5e-4
TARGET_WALL_S = 10.0
TARGET_NRMSD = 0.005
REF_RTOL = 1e-8
LOG_DT = 0.01
#: the sources whose change invalidates a cached reference (paths below the package root)
_MODEL_SOURCES = ("core/physics.py", "models/fidelity.py", "models/fidelity_exact.py", "sim/simulate.py",
                  "sim/trial.py", "core/materials.py", "core/params.py", "models/exact.py", "models/exact_tables.py")


@dataclass
class BenchRow:
    """One setting's result. dt_ms None = the simulator's default steps per fidelity.

    wall_s: median wall time of the whole protocol (s); cpu_s: median CPU time of this process and
    its worker processes (s; unlike the wall time, not inflated by other load on the machine);
    *_nrmsd_mean/max over trials (-);
    default: the setting ``hbma-ctrl protocol`` uses; meets_target: wall <= TARGET_WALL_S, max
    height and pressure NRMSD <= TARGET_NRMSD and no trial diverged.
    *_vs_exact_mean/max: NRMSD (-) against the exact membrane's reference (module docstring; NaN when
    the fidelity axis is off). For the 'free' rung n_trials counts the 0 g trials it runs.
    """

    integrator: str
    fidelity: str
    dt_ms: float | None
    dt_free_ms: float
    dt_loaded_ms: float
    wall_s: float
    cpu_s: float
    wall_runs: list
    n_trials: int
    n_diverged: int
    height_nrmsd_mean: float
    height_nrmsd_max: float
    pressure_nrmsd_mean: float
    pressure_nrmsd_max: float
    default: bool = False
    meets_target: bool = False
    height_nrmsd_vs_exact_mean: float = float("nan")
    height_nrmsd_vs_exact_max: float = float("nan")
    pressure_nrmsd_vs_exact_mean: float = float("nan")
    pressure_nrmsd_vs_exact_max: float = float("nan")


def bench_trials(material: Material, quick: bool) -> list[Trial]:
    """All 150 protocol trials, or a representative subset of 8 for ``--quick``."""
    if quick:
        return protocol_trials(material, loads_g=[0.0, 400.0], speeds_pct=[40.0, 100.0], t0_mm=[3.0],
                               r1_mm=[7.5, 12.5])
    return protocol_trials(material)


def _model_hash() -> str:
    h = hashlib.sha256()
    here = Path(__file__).resolve().parents[2]  # the hbma_ctrl package
    for name in _MODEL_SOURCES:
        h.update((here / name).read_bytes())
    return h.hexdigest()[:16]


def _ref_key(trials: list[Trial], fidelity: str) -> str:
    spec = [repr(t) for t in trials] + [fidelity, str(REF_RTOL), str(LOG_DT), _model_hash()]
    for p in {str(t.pneumatics.csv_path) for t in trials}:
        spec.append(hashlib.sha256(Path(p).read_bytes()).hexdigest())
    return hashlib.sha256("\n".join(spec).encode()).hexdigest()[:20]


def _cached_reference(trials: list[Trial], path: Path, key_tag: str, s: SimSettings, fidelity: str,
                      workers: int, progress: bool, label: str) -> dict[str, dict[str, np.ndarray]]:
    """(t, h, p) per trial name from ``s`` at ``fidelity``, cached at ``path`` (npz keyed by the trials
    and ``key_tag``: a changed trial set or setting recomputes it); RuntimeError when a trial diverges."""
    key = _ref_key(trials, key_tag)
    if path.is_file():
        with np.load(path, allow_pickle=False) as z:
            if str(z["key"]) == key:
                return {n: {"t": z[f"{n}/t"], "h": z[f"{n}/h"], "p": z[f"{n}/p"]} for n in z["names"]}
    t0 = time.perf_counter()
    logs = simulate_trials(trials, s, fidelity, workers, progress, label=label)
    wall = time.perf_counter() - t0
    bad = [log.name for log in logs if log.status == "diverged"]
    if bad:
        raise RuntimeError(f"{label} diverged for {bad}: no benchmark against it")
    ref = {log.name: {"t": log["t"], "h": log["h"], "p": log["p"]} for log in logs}
    arrays = {"key": np.array(key), "names": np.array(list(ref)), "wall_s": np.array(wall),
              **{f"{n}/{k}": v for n, d in ref.items() for k, v in d.items()}}
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **arrays)
    return ref


def reference(trials: list[Trial], fidelity: str, out_dir: Path, workers: int = 1,
              progress: bool = False) -> dict[str, dict[str, np.ndarray]]:
    """Radau reference (t, h, p per trial name), cached in out_dir/ref_<fidelity>.npz."""
    s = SimSettings(integrator="radau", log_dt=LOG_DT, rtol=REF_RTOL, atol=1e-8)
    return _cached_reference(trials, out_dir / f"ref_{fidelity}.npz", fidelity, s, fidelity, workers, progress,
                             f"reference radau ({fidelity})")


def exact_reference(trials: list[Trial], out_dir: Path, workers: int = 1,
                    progress: bool = False) -> dict[str, dict[str, np.ndarray]]:
    """The exact membrane's reference (t, h, p per trial name): rk4 at :data:`EXACT_REF_DT`, cached in
    out_dir/ref_exact.npz like :func:`reference`."""
    s = SimSettings(integrator="rk4", dt=EXACT_REF_DT, log_dt=LOG_DT)
    return _cached_reference(trials, out_dir / "ref_exact.npz", f"exact rk4 {EXACT_REF_DT!r}", s, "exact", workers,
                             progress, "reference rk4 (exact)")


def _cpu() -> float:
    """CPU seconds of this process plus its finished children (the worker processes)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def _warm_up(trials: list[Trial], settings: SimSettings, fidelity: str) -> None:
    """Build the casadi step Functions once (a short run of one trial per fidelity group)."""

    seen = {}
    for tr in trials:
        seen.setdefault(fidelity_for(tr, fidelity), tr)
    short = [Trial(tr.actuator, tr.pneumatics, tr.platform, InputSchedule(((0.0, 1.0, 1.0, 0.0),)), 0.05, tr.name)
             for tr in seen.values()]
    simulate_trials(short, settings, fidelity)


def _score(logs, ref) -> dict:
    hs, ps = [], []
    for log in logs:
        r = ref[log.name]
        for key, acc in (("h", hs), ("p", ps)):
            y_hat = np.interp(r["t"], log["t"], log[key])
            acc.append(nrmsd(y_hat, r[key]))
    hs, ps = np.array(hs), np.array(ps)

    def agg(a, f):
        a = a[np.isfinite(a)] if np.isfinite(a).any() else a
        return float(f(a)) if a.size else float("nan")

    return {"height_nrmsd_mean": agg(hs, np.mean), "height_nrmsd_max": agg(hs, np.max),
            "pressure_nrmsd_mean": agg(ps, np.mean), "pressure_nrmsd_max": agg(ps, np.max)}


def _settings_list(grid: dict) -> list[tuple[str, str, float | None]]:
    """(fidelity, integrator, dt_ms or None) rows; the default (rk4, None) first per fidelity.

    An explicit row identical to the default one (same steps for free and loaded trials) is
    dropped, and the default row takes its place.
    """
    out = []
    for fid, per in grid.items():
        d_free, d_load = U.to_ms(DEFAULT_DT[("rk4", "free")]), U.to_ms(DEFAULT_DT[("rk4", fid)])
        out.append((fid, "rk4", None))
        for integ, dts in per.items():
            for dt in dts:
                if integ == "rk4" and np.isclose(dt, d_free) and np.isclose(dt, d_load):
                    continue
                out.append((fid, integ, dt))
    return out


def run_bench(out_dir: Path | str = "runs/bench_sim", quick: bool = False, workers: int = 1, repeat: int = 1,
              material: str | Material = "nh", grid: dict | None = None, progress: bool = True,
              on_row=None, fidelity_axis: bool = False, fidelity_grid: dict | None = None) -> list[BenchRow]:
    """Run the benchmark; writes bench.json, bench.csv and (with the fidelity axis) pareto.png into
    out_dir and returns the rows.

    ``on_row(row)`` is called after each setting (e.g. to print progress). ``fidelity_axis`` (off here,
    on in ``hbma-ctrl bench sim``): also
    score every row against the exact membrane and run the 'free' and 'exact' rungs
    (``fidelity_grid``, default :data:`FIDELITY_GRID` or :data:`QUICK_FIDELITY_GRID`).
    """
    if repeat < 1:
        raise ValueError(f"repeat = {repeat} is out of range [1, inf)")
    if workers < 1:
        raise ValueError(f"workers = {workers} is out of range [1, inf)")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    mat = make_material(material) if isinstance(material, str) else material
    trials = bench_trials(mat, quick)
    grid = grid or (QUICK_GRID if quick else GRID)
    fgrid = {}
    if fidelity_axis:
        fgrid = fidelity_grid if fidelity_grid is not None else (QUICK_FIDELITY_GRID if quick else FIDELITY_GRID)
    free_trials = [tr for tr in trials if tr.platform.mass <= 0]
    refs = {}
    t_ref = {}
    for fid in list(grid) + [f for f in fgrid if f != "exact"]:
        t0 = time.perf_counter()
        refs[fid] = reference(free_trials if fid == "free" else trials, fid, out, workers, progress)
        t_ref[fid] = time.perf_counter() - t0
    if fgrid:
        t0 = time.perf_counter()
        refs["exact"] = exact_reference(trials, out, workers, progress)
        t_ref["exact"] = time.perf_counter() - t0
    rows = []
    for fid, integ, dt_ms in _settings_list(grid) + _settings_list(fgrid):
        s = SimSettings(integrator=integ, dt=None if dt_ms is None else U.ms(dt_ms), log_dt=LOG_DT)
        run_trials = free_trials if fid == "free" else trials
        _warm_up(run_trials, s, fid)
        walls, cpus = [], []
        for _ in range(repeat):
            c0, t0 = _cpu(), time.perf_counter()
            logs = simulate_trials(run_trials, s, fid, workers)
            walls.append(time.perf_counter() - t0)
            cpus.append(_cpu() - c0)
        score = _score(logs, refs[fid])
        if "exact" in refs:
            score.update({k.replace("_nrmsd_", "_nrmsd_vs_exact_"): v for k, v in _score(logs, refs["exact"]).items()})
        row = BenchRow(integ, fid, dt_ms, U.to_ms(s.step_for("free")), U.to_ms(s.step_for(fid)), statistics.median(walls),
                       statistics.median(cpus), walls, len(run_trials), sum(log.status == "diverged" for log in logs),
                       **score, default=(integ == "rk4" and dt_ms is None and fid == "quasi_static"))
        row.meets_target = bool(row.wall_s <= TARGET_WALL_S and row.n_diverged == 0
                                and row.height_nrmsd_max <= TARGET_NRMSD and row.pressure_nrmsd_max <= TARGET_NRMSD)
        rows.append(row)
        if on_row:
            on_row(row)
    meta = {"quick": quick, "workers": workers, "repeat": repeat, "material": mat.name, "n_trials": len(trials),
            "reference": {"integrator": "radau", "rtol": REF_RTOL, "log_dt_s": LOG_DT,
                          "wall_s_incl_cache": t_ref},
            "target": {"wall_s": TARGET_WALL_S, "nrmsd_max": TARGET_NRMSD},
            "default_fidelity_auto": "free for 0 g, quasi_static for loaded trials",
            "fidelity_axis": ({"reference": "exact", "integrator": "rk4", "dt_s": EXACT_REF_DT,
                               "rungs": ["free (0 g trials only)"] + list(grid) + ["exact"],
                               "pareto_png": "pareto.png"} if fgrid else None)}
    (out / "bench.json").write_text(json.dumps({"meta": meta, "rows": json_safe([asdict(r) for r in rows])}, indent=2)
                                    + "\n")
    if fgrid and rows:
        from hbma_ctrl.app.bench.plots import sim_pareto_png

        sim_pareto_png(rows, out / "pareto.png", title=f"bench sim: {len(trials)} trials, {mat.name}")
    with open(out / "bench.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=[f.name for f in fields(BenchRow) if f.name != "wall_runs"],
                           extrasaction="ignore")
        w.writeheader()
        w.writerows(asdict(r) for r in rows)
    return rows
