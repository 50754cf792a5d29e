"""CLI hook of the estimators: ``hbma-ctrl bench ekf`` and ``hbma-ctrl observability``.

Registered by :mod:`hbma_ctrl.app.cli.main` through ``register(app, bench_app)``.
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Optional

import numpy as np
import typer
from rich.console import Console

# the filters (filterpy, scipy.stats), python-control and the rig are imported by the commands
# when they run
from hbma_ctrl.app.cli.args import ReportDir, check_range, numbers, show_table, whole_numbers
from hbma_ctrl.app.endsignals import raise_if_signalled
from hbma_ctrl.app.outputs import OVERWRITE_HELP, cli_argv, run_dir
from hbma_ctrl.core import units as U

__all__ = ["register", "bench_ekf", "parse_axes", "BENCH_SUBSTEPS", "BENCH_MEMBRANES", "BENCH_HORIZONS",
           "MHE_SUMMARY_N", "DOMPC_STEPS"]

#: the bench's default protocol subset (edge units): both filters see the same rig runs
BENCH_GRID = {"loads_g": [0.0, 400.0, 800.0], "speeds_pct": [40.0, 100.0], "t0_mm": [3.0], "r1_mm": [7.5, 12.5]}


#: the moving-horizon estimator's windows a bench runs by default (samples); the summary's is MHE_SUMMARY_N
BENCH_HORIZONS = (10, 20, 40)
MHE_SUMMARY_N = 20
#: steps of do-mpc's MHE timed in a bench (its IPOPT solve per step is slow): the first trial's first
#: DOMPC_STEPS samples after the window fills, and the MHE's own steps on the same samples
DOMPC_STEPS = 150

#: the estimator's cost/accuracy axes a bench runs by default: integrator sub-steps and membrane laws
BENCH_SUBSTEPS = (1, 2, 4)
BENCH_MEMBRANES = ("exact", "cap")


def parse_axes(substeps: str, membranes: str) -> tuple[tuple[int, ...], tuple[str, ...]]:
    """``--substeps`` (comma-separated integers 1-50) and ``--membranes`` (cap, exact) of ``bench ekf``;
    ValueError naming the flag and the allowed values."""
    ns = tuple(whole_numbers(substeps, "--substeps", 1, 50))
    ms = tuple(m.strip() for m in membranes.split(",") if m.strip())
    bad = [m for m in ms if m not in BENCH_MEMBRANES]
    if bad:
        raise ValueError(f"--membranes: '{bad[0]}' is unknown; allowed {', '.join(BENCH_MEMBRANES)}")
    return ns, ms


def bench_ekf(grid: dict, filters: Sequence[str] | None = None, seed: int = 0,
              substeps: Sequence[int] = (1,), membranes: Sequence[str] = (), horizons: Sequence[int] = (),
              seeds: int = 1, dompc: bool = True, load_prior: str = "unknown") -> dict:
    """Run the filters on the same rig runs (serially, so timings are not shared with workers).

    ``filters``: filter kinds to run, default every one of
    :data:`hbma_ctrl.app.scenes.evaluate.BENCH_FILTERS`, at the default settings (their keys are the kinds).
    ``substeps`` and ``membranes`` add the cost/accuracy axes for the EKF and the UKF: a row
    ``"ekf nsub=2"`` per sub-step count other than the default's, a row ``"ekf cap"`` per membrane law
    other than the default's (the truth is the default rig either way).

    Returns {"settings": ..., "filters": {kind: {accuracy and timing}}, "ratios": {...}}; timings
    are wall time per predict+update of one chamber on this machine (median, p90, max,
    microseconds). ``ratios``: each other filter's median step time over the EKF's, measured in
    this run (``filterpy``: filterpy's ExtendedKalmanFilter on the same casadi model;
    ``ekf_reference``: the EKF's reference path of separate calls).
    """
    from hbma_ctrl.estimators.common import FilterSettings
    from hbma_ctrl.app.scenes.evaluate import BENCH_FILTERS, _open_loop, aggregate, make_filter, run_and_score
    from hbma_ctrl.core.params import Platform
    from hbma_ctrl.sim.batch import protocol_trials
    from hbma_ctrl.sim.rig import RigSettings, simulate_rig

    from hbma_ctrl.estimators.mhe import MHESettings

    filters = BENCH_FILTERS if filters is None else filters
    trials = protocol_trials("nh", platform=Platform(own_mass=0.02), **grid)
    rig = RigSettings(seed=seed)
    fs = FilterSettings(sample_period=rig.sample_period, sensor_range=rig.sensor_range, noise_std=rig.noise_std,
                        load_prior=load_prior)
    recs, ol_one = [], _open_loop(trials, rig.sample_period)
    for sd in range(seed, seed + max(int(seeds), 1)):
        recs += simulate_rig(trials, replace(rig, seed=sd))
    ol = ol_one * max(int(seeds), 1)
    runs = trials * max(int(seeds), 1)
    rows = {kind: fs for kind in filters}
    for n in horizons:
        rows[f"mhe N={int(n)}"] = MHESettings(**{f: getattr(fs, f) for f in fs.__dataclass_fields__},
                                              horizon=int(n)).validate()
        if int(n) == MHE_SUMMARY_N:
            # every node linearised afresh at every step (the summary's row re-linearises its newest two)
            rows[f"mhe N={int(n)} all"] = replace(rows[f"mhe N={int(n)}"], relinearise=0).validate()
    if horizons:
        rows["dlqe"] = fs
    for kind in [k for k in ("ekf", "ukf") if k in filters]:
        for n in substeps:
            if n != fs.nsub:
                rows[f"{kind} nsub={n}"] = replace(fs, nsub=int(n)).validate()
        for m in membranes:
            if m != fs.membrane:
                rows[f"{kind} {m}"] = replace(fs, membrane=m).validate()
    out = {"settings": {"grid": grid, "n_trials": len(trials), "seeds": list(range(seed, seed + max(int(seeds), 1))),
                        "load_prior": load_prior, "rig": "default RigSettings (exact membrane, "
                        "5 ms valve delay, 2 ms minimum opening, pump tilt 0.2, 3 ms sensor lag; modulus x1.15, "
                        "flow x0.9, V0 x1.2, 0.2 kPa noise, 35 kPa range, 10 ms)",
                        "filter": {"membrane": fs.membrane, "valve_delay_ms": U.to_ms(fs.valve_delay),
                                   "sensor_delay_ms": U.to_ms(fs.sensor_delay)}}, "filters": {}}
    for name, rfs in rows.items():
        kind = name.split(" ")[0]
        make_filter(kind, trials[0], rfs)  # compile/load outside the timing
        results, steps = [], []
        t0 = time.perf_counter()
        for tr, rec, h_ol in zip(runs, recs, ol):
            raise_if_signalled()  # a signal caught inside a solver (the MHE's reference, do-mpc's)
            r = run_and_score(kind, tr, rec, rfs, h_ol)
            results.append(r)
            steps.append(r.step_s[1:])
        wall = time.perf_counter() - t0
        st = U.to_us(np.concatenate(steps))
        agg = aggregate(results)
        agg.update({"step_us_median": float(np.median(st)), "step_us_p90": float(np.percentile(st, 90)),
                    "step_us_p99": float(np.percentile(st, 99)), "step_us_max": float(st.max()), "steps": int(st.size),
                    "wall_s": wall})
        if kind == "mhe":
            # the MHE's own steps (the EKF gives the first N of each run, and any fallback)
            own = np.concatenate([r.step_s[1:][r.own[1:]] for r in results])
            own = U.to_us(own)
            agg.update({"horizon": rfs.horizon, "mhe_step_us_median": float(np.median(own)),
                        "mhe_step_us_p99": float(np.percentile(own, 99)),
                        "fallbacks": int(sum(r.counts.get("fallbacks", 0) for r in results))})
        agg.update({"nsub": rfs.nsub, "membrane": rfs.membrane})
        out["filters"][name] = agg
    f = out["filters"]
    if "ekf" in f:
        out["ratios"] = {f"{k}_over_ekf_step_median": f[k]["step_us_median"] / f["ekf"]["step_us_median"]
                         for k in f if k != "ekf"}
    key = f"mhe N={MHE_SUMMARY_N}"
    summary: dict = {}
    if key in f:
        summary.update(mhe_step_us_median=f[key]["mhe_step_us_median"], mhe_step_us_p99=f[key]["mhe_step_us_p99"])
        if dompc:
            from hbma_ctrl.core.extras import dompc_available
            from hbma_ctrl.estimators.dompc_mhe import compare_dompc

            ok, why = dompc_available()
            if ok:
                cmp = compare_dompc(runs[0], recs[0], rows[key], DOMPC_STEPS)
                summary.update(cmp)
            else:
                summary["dompc"] = why
    out["summary"] = summary
    return out


def bench_ekf_cmd(
    loads_g: Annotated[str, typer.Option(help="comma-separated loads, g")] = "0,400,800",
    speeds_pct: Annotated[str, typer.Option(help="comma-separated compressor speeds, %")] = "40,100",
    t0_mm: Annotated[str, typer.Option(help="comma-separated membrane thicknesses, mm")] = "3",
    r1_mm: Annotated[str, typer.Option(help="comma-separated retaining radii, mm")] = "7.5,12.5",
    seed: Annotated[int, typer.Option(help="rig noise seed")] = 0,
    substeps: Annotated[str, typer.Option(help="comma-separated integrator sub-steps per sample (1-50): "
                                               "EKF and UKF rows for each")] = ",".join(map(str, BENCH_SUBSTEPS)),
    membranes: Annotated[str, typer.Option(help="comma-separated membrane laws of the filters' model (cap, "
                                                "exact): EKF and UKF rows for each")] = ",".join(BENCH_MEMBRANES),
    horizons: Annotated[str, typer.Option(help="comma-separated MHE windows, samples (2-200): an MHE row for each, "
                                               "and the dlqe row; empty: none")] = ",".join(map(str, BENCH_HORIZONS)),
    seeds: Annotated[int, typer.Option(help="rig noise seeds from --seed on, every row on the same runs")] = 1,
    load_prior: Annotated[str, typer.Option(help="the filters' load prior: unknown | nominal")] = "unknown",
    dompc: Annotated[bool, typer.Option(help="time do-mpc's MHE on the same problem when it is installed")] = True,
    out: Annotated[Path, typer.Option("--out", "-o", help="output dir for bench_ekf.json")] = Path("runs/bench_ekf"),
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
    report: ReportDir = None,
) -> None:
    """EKF (compiled step and reference path), filterpy's EKF on the same model, the UKF, the MHE at
    several windows and a steady-state Kalman gain on the same rig runs: us per step (median), ratios
    to the EKF, accuracy; do-mpc's MHE side by side."""

    grid = {"loads_g": numbers(loads_g, "--loads-g"), "speeds_pct": numbers(speeds_pct, "--speeds-pct"),
            "t0_mm": numbers(t0_mm, "--t0-mm"), "r1_mm": numbers(r1_mm, "--r1-mm")}
    check_range("--seed", seed, 0, 2**31)
    ns, ms = parse_axes(substeps, membranes)
    hs = tuple(whole_numbers(horizons, "--horizons", 2, 200)) if horizons.strip() else ()
    check_range("--seeds", seeds, 1, 100)
    if load_prior not in ("unknown", "nominal"):
        raise typer.BadParameter(f"--load-prior: '{load_prior}' is unknown; allowed unknown, nominal")
    from hbma_ctrl.app.bench.report import open_report

    rep = open_report(report, "ekf", cli_argv())  # --report checked before the run
    with run_dir(out, command="bench ekf", argv=cli_argv(), overwrite=overwrite) as tmp:
        res = bench_ekf(grid, seed=seed, substeps=ns, membranes=ms, horizons=hs, seeds=seeds, dompc=dompc,
                        load_prior=load_prior)
        (tmp / "bench_ekf.json").write_text(json.dumps(res, indent=1))
    cols = [("us median", "step_us_median", "{:.0f}"), ("us p90", "step_us_p90", "{:.0f}"),
            ("us p99", "step_us_p99", "{:.0f}"), ("viol", "constraint_violations", "{:d}"),
            ("lift-off", "height_nrmsd_liftoff", "{:.3f}"), ("touch-down", "height_nrmsd_touchdown", "{:.3f}"),
            ("height NRMSD", "height_nrmsd", "{:.3f}"), ("worst", "height_nrmsd_max", "{:.3f}"),
            ("open loop", "height_nrmsd_open_loop", "{:.3f}"), ("F rmse N", "force_rmse_n", "{:.3f}"),
            ("F steady err", "force_steady_rel_err_mean", "{:.3f}"), ("NEES", "nees_mean", "{:.2f}"),
            ("NIS", "nis_mean", "{:.2f}")]
    con = show_table(f"bench ekf: {res['settings']['n_trials']} rig trials (the default rig); us = wall time per "
                     "chamber-step on this machine", ["filter", *(c[0] for c in cols)],
                     [(kind, *[(c[2].format(a[c[1]]) if a.get(c[1]) is not None else "-") for c in cols])
                      for kind, a in res["filters"].items()], Console(highlight=False, width=150), left=1)
    for k, v in res.get("ratios", {}).items():
        con.print(f"{k.replace('_over_ekf_step_median', '')} / ekf median step time: {v:.1f}x")
    for k, v in res.get("summary", {}).items():
        # markup off: a summary's text holds brackets of its own (pip install 'hbma-ctrl[bench]')
        con.print(f"{k}: {v:.4g}" if isinstance(v, float) else f"{k}: {v}", markup=False)
    con.print(f"wrote {out / 'bench_ekf.json'}")
    if rep:
        from hbma_ctrl.app.bench.pages import ekf_page

        con.print(f"wrote {rep.write(ekf_page(res, bench_ekf.__doc__, bench_ekf_cmd.__doc__))}")

def observability_cmd(
    out: Annotated[Path, typer.Option("--out", "-o", help="output dir for observability.json")] = Path("runs/observability"),
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
    r1_mm: Annotated[Optional[float], typer.Option(help="retaining radius, mm (default 12.5)")] = None,
    t0_mm: Annotated[Optional[float], typer.Option(help="membrane thickness, mm (default 3)")] = None,
) -> None:
    """Rank/condition of the linearised observability matrix along free, contact and resting runs."""
    from hbma_ctrl.estimators.observability import OBS_SCALE, WINDOW_S, run
    from hbma_ctrl.core.params import Actuator

    check_range("--r1-mm", r1_mm, 0.5, 100.0, lo_open=True, unit="mm")
    check_range("--t0-mm", t0_mm, 0.05, 20.0, lo_open=True, unit="mm")
    act = Actuator().with_(**{k: U.mm(v) for k, v in (("r1", r1_mm), ("t0", t0_mm)) if v is not None})
    with run_dir(out, command="observability", argv=cli_argv(), overwrite=overwrite) as tmp:
        summ = run(tmp, act)
    con = show_table(f"observability of x = \\[m, W, b, k, c] from pressure alone (r1 {U.to_mm(act.r1):g} mm, "
                     f"t0 {U.to_mm(act.t0):g} mm); window = up to {WINDOW_S:g} s in one regime, "
                     f"resolution {OBS_SCALE.tolist()}",
                     ("trajectory", "regime", "samples", "obsv rank (med/min/max)", "cond (med)",
                      "window rank (med/min/max)"),
                     [(r["trajectory"], r["regime"], str(r["samples"]),
                       f"{r['rank_median']:g}/{r['rank_min']}/{r['rank_max']}",
                       f"{r['cond_median']:.2g}" if r["cond_median"] is not None else "inf",
                       f"{r['window_rank_median']:g}/{r['window_rank_min']}/{r['window_rank_max']}") for r in summ],
                     Console(highlight=False, width=150), left=1)
    con.print(f"wrote {out / 'observability.json'}")


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``bench ekf`` and ``observability`` (called by :mod:`hbma_ctrl.app.cli.main`)."""
    bench_app.command("ekf")(bench_ekf_cmd)
    app.command("observability")(observability_cmd)
