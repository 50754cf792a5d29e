"""CLI hook of the controllers: ``hbma-ctrl bench mpc`` (registered by ``register(app, bench_app)``)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console

# the benches (the controllers, the EKF, the rig) are imported by their commands when they run
from hbma_ctrl.app.cli.args import ReportDir, cap_workers, check_range, show_table, whole_numbers
from hbma_ctrl.app.outputs import OVERWRITE_HELP, cli_argv, run_dir

#: the variants ``bench mpc`` sweeps by default (x its horizons)
MPC_VARIANTS = ("ipopt", "rti_osqp", "rti_c_osqp", "rti_fn_hpipm", "fatrop")

__all__ = ["register"]


def bench_loop(
    seeds: Annotated[int, typer.Option(help="rig noise seeds per case, 0..seeds-1 (1-100)")] = 10,
    cases: Annotated[str, typer.Option(help="comma-separated cases: steps_0g, steps_400g, load_step_200g")]
    = "steps_0g,steps_400g,load_step_200g",
    workers: Annotated[int, typer.Option(help="parallel processes (1-64)")] = 2,
    out: Annotated[Path, typer.Option("--out", "-o", help="output dir for bench_loop.json")] = Path("runs/bench_loop"),
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
    rig: Annotated[str, typer.Option(help="the truth: cap (scalar mismatches) | structured (exact membrane, "
                                          "valve timing, pump shape, sensor lag; the default)")] = "structured",
    membrane: Annotated[Optional[str], typer.Option(help="the EKF's, calibration's and MPC's membrane law: "
                                                         "cap | exact (default: the rig's)")] = None,
    valve_delay_ms: Annotated[Optional[float], typer.Option(help="valve delay the EKF and calibration model, "
                                                                "ms, 0-100 (default 5 on structured, else 0)")] = None,
    sensor_delay_ms: Annotated[Optional[float], typer.Option(help="sensor delay they model, ms, 0-100 "
                                                                 "(default 3 on structured, else 0)")] = None,
    valve_min_on_ms: Annotated[Optional[float], typer.Option(help="valves' minimum opening the loop shapes its "
                                                                 "duties for, ms, 0-100 (default 2 on structured, "
                                                                 "else 0)")] = None,
    calibration_std_floor: Annotated[Optional[float], typer.Option(help="smallest sigma of the calibration's "
                                                                       "factors handed to the EKF, 0-1 "
                                                                       "(default 0.08)")] = None,
    prior: Annotated[Optional[str], typer.Option(help="the EKF's and the calibration's prior on the flow, "
                                                      "modulus and dead-volume factors, b,k,c (a fit's; "
                                                      "default 1,1,1)")] = None,
    prior_std: Annotated[Optional[float], typer.Option(help="its one sigma for each factor (default the "
                                                           "filter's 0.15, 0.15, 0.2)")] = None,
    report: ReportDir = None,
) -> None:
    """Closed loop through the EKF over rig seeds: how often each case (steps at 0 g and 400 g, a 200 g load step) settles."""
    from hbma_ctrl.app.bench.loop import (check_cases, loop_setup, run_loop_bench, summarize_loop,
                                          write_loop_bench)

    check_range("--seeds", seeds, 1, 100)
    workers = cap_workers("--workers", workers, 64)
    con = Console(highlight=False, width=140)
    cs = check_cases([c.strip() for c in cases.split(",") if c.strip()])  # before --out is touched
    setup = loop_setup(rig, membrane, valve_delay_ms, sensor_delay_ms, valve_min_on_ms, calibration_std_floor,
                       prior, prior_std)
    from hbma_ctrl.app.bench.report import open_report

    rep = open_report(report, "loop", cli_argv())  # --report checked before the run
    with run_dir(out, command="bench loop", argv=cli_argv(), overwrite=overwrite) as tmp:
        rows = run_loop_bench(list(range(seeds)), cs, workers,
                              progress=lambda r: con.print(f"  {r['case']} seed {r['seed']}: "
                                                           f"{'ok' if r['passed'] else 'MISS'} "
                                                           f"(final error {r['final_error_mm']:.3f} mm)"),
                              setup=setup)
        written = write_loop_bench(rows, tmp, setup)
    show_table(f"bench loop: {setup['rig']} rig -> EKF -> RTI-OSQP -> rig ({setup['membrane']} models, delays "
               f"{setup['valve_delay_ms']:g} + {setup['sensor_delay_ms']:g} ms), {seeds} noise seeds per case; "
               "pass = true height within 0.3 mm",
               ("case", "passed", "final error median (mm)", "worst (mm)", "max p (kPa)", "limit (kPa)", "fallbacks"),
               [(case, f"{v['passed']}/{v['runs']}", f"{v['final_error_mm_median']:.3f}",
                 f"{v['final_error_mm_max']:.3f}", f"{v['max_pressure_kpa']:.2f}", f"{v['pressure_limit_kpa']:g}",
                 str(v["fallbacks"])) for case, v in summarize_loop(rows).items()], con)
    con.print(f"wrote {out / written.name}")
    if rep:
        from hbma_ctrl.app.bench.pages import loop_page

        con.print(f"wrote {rep.write(loop_page(rows, setup))}")

def bench_mpc(
    scenario: Annotated[Optional[Path], typer.Option(
        "--scenario", "-s", help="scenario TOML with a controller section (default: the track_height "
                                 "setup: 400 g, steps 2 -> 8 -> 5 mm)")] = None,
    horizons: Annotated[str, typer.Option(help="comma-separated horizons")] = "10,20,40",
    variants: Annotated[str, typer.Option(help="comma-separated MPC variants")] = ",".join(MPC_VARIANTS),
    dompc: Annotated[bool, typer.Option("--dompc/--no-dompc",
                                        help="also time do-mpc on the same OCP (N=20; extra 'bench')")] = True,
    baselines: Annotated[bool, typer.Option("--baselines/--no-baselines", help="PID, bang-bang and LQI rows")] = True,
    duration: Annotated[Optional[float], typer.Option(help="simulated seconds (default: the scenario's, 9 s)")] = None,
    budget_ms: Annotated[float, typer.Option(help="MPC step budget in the sweep (acts only with [controller] "
                                                     "enforce_budget = true in the scenario)")] = 1000.0,
    rt_budget_ms: Annotated[float, typer.Option(help="real-time budget for the over_rt column")] = 15.0,
    out: Annotated[Path, typer.Option("--out", "-o", help="output dir for bench_mpc.json")] = Path("runs/bench_mpc"),
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
    ipopt_c: Annotated[bool, typer.Option("--ipopt-c", help="one more row: IPOPT N=20 generated as C as "
                                          "fatrop is (about 80 s to build the first time; needs a C compiler)")] = False,
    report: ReportDir = None,
) -> None:
    """MPC speed/accuracy: IPOPT, fatrop, RTI-OSQP and the one-Function RTI x horizon, baselines and do-mpc, on one closed loop."""
    from hbma_ctrl.app.bench.mpc import run_bench, summarize, write_bench
    from hbma_ctrl.app.scenario import load_scenario
    from hbma_ctrl.controllers.mpc_settings import MPCSettings
    from hbma_ctrl.core.settings import specs

    spec = specs(MPCSettings)["horizon"]
    hs = tuple(whole_numbers(horizons, "--horizons", spec.lo, spec.hi))
    vs = tuple(v.strip() for v in variants.split(",") if v.strip())
    kw = {}
    if scenario is not None:
        scn = load_scenario(scenario)
        if scn.role("controller") is None:
            raise ValueError(f"{scenario}: the bench needs a [controller] section")
        kw = {"actuator": scn.actuator, "pneumatics": scn.pneumatics, "platform": scn.platform,
              "section": scn.role("controller"), "rig_settings": scn.role("rig")}
        duration = duration if duration is not None else scn.duration
    duration = 9.0 if duration is None else duration
    check_range("--duration", duration, 0.0, 600.0, lo_open=True, unit="s")
    if ipopt_c:
        from hbma_ctrl.core.codegen import has_compiler

        if not has_compiler():
            raise ValueError("--ipopt-c: IPOPT generated as C needs a C compiler (cc, gcc or clang); none was found")
    from hbma_ctrl.app.bench.report import open_report

    rep = open_report(report, "mpc", cli_argv())  # --report checked before the run
    con = Console(highlight=False, width=170)
    with run_dir(out, command="bench mpc", argv=cli_argv(), scenario_path=scenario, overwrite=overwrite) as tmp:
        res = run_bench(duration=duration, variants=vs, horizons=hs, baselines=baselines, dompc=dompc,
                        budget_ms=budget_ms, rt_budget_ms=rt_budget_ms, ipopt_c=ipopt_c,
                        progress=lambda name: con.print(f"  running {name} ..."), **kw)
        written = write_bench(res, tmp)
    show_table(f"bench mpc: {res['settings']['load_g']:g} g, {duration:g} s, targets {res['settings']['targets_mm']} "
               "mm; solve = wall ms per step on this machine",
               ("controller", "RMSE h (mm)", "RMSE est (mm)", "max p (kPa)", "solve med", "solve p99", "solve max",
                "cpu med", "cpu p99", "fallbacks", f"over {rt_budget_ms:g} ms", "settled (est)"),
               [(r["controller"], f"{r['height_rmse_mm']:.3f}", f"{r['height_rmse_estimate_mm']:.3f}",
                 f"{r['max_pressure_kpa']:.2f}", f"{r['solve_ms_median']:.3f}", f"{r['solve_ms_p99']:.3f}",
                 f"{r['solve_ms_max']:.3f}",
                 *(f"{v:.3f}" if isinstance(v, float) else "-" for v in (r.get("solve_cpu_ms_median"),
                                                                         r.get("solve_cpu_ms_p99"))),
                 str(r["fallbacks"]), str(r["over_rt"]),
                 f"{r['steps_settled']}/{r['steps_total']} ({r['steps_settled_estimate']})") for r in res["rows"]], con)
    con.print(f"do-mpc: {res['dompc']}")
    for k, v in summarize(res).items():
        con.print(f"  {k}: {v if not isinstance(v, float) else f'{v:.3g}'}")
    con.print(f"wrote {out / written.name}")
    if rep:
        from hbma_ctrl.app.bench.pages import mpc_page

        con.print(f"wrote {rep.write(mpc_page(res))}")


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``bench mpc`` and ``bench loop`` to the bench sub-app (called by :mod:`hbma_ctrl.app.cli.main`)."""
    bench_app.command("loop")(bench_loop)
    bench_app.command("mpc")(bench_mpc)
