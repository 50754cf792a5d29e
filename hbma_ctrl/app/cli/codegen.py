"""CLI hook of the code generation: ``hbma-ctrl codegen CONFIG --out DIR`` and ``hbma-ctrl bench codegen``.

``codegen --library`` writes the chamber's (or the robot's) tick as a C library instead and, for a Cortex-M ``--target``,
runs it on QEMU (:mod:`hbma_ctrl.app.codegen.library`). ``codegen`` writes the C sources and header of the scenario's step Functions (plant, EKF, RTI NMPC and
the small glue Functions), ``loop_data.h``, ``closed_loop.c``, a Makefile and README.txt
(:mod:`hbma_ctrl.core.loopgen`, :mod:`hbma_ctrl.app.codegen.chamber`); ``--check`` also builds it with the
system compiler, runs it and compares its trajectory with the Python path's (check.json).
``bench codegen`` times both paths in one run (bench_codegen.json).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console

# the code generator, its scenes and the RTI step (casadi) are imported by the commands when they
# run; the flags their options show come from the light cli_constants
from hbma_ctrl.app.cli.args import ReportDir, check_choice, check_range, show_table
from hbma_ctrl.app.cli.constants import DEFAULT_OPT, OPT_FLAGS
from hbma_ctrl.app.outputs import OVERWRITE_HELP, cli_argv, run_dir

__all__ = ["register"]

#: longest loop a generated program runs, s
DURATION_MAX_S = 3600.0
#: --library's build targets and precisions (hbma_ctrl.app.codegen.library.TARGETS, PRECISIONS)
LIBRARY_TARGETS = ("host", "cortex-m7", "cortex-m4f")
LIBRARY_PRECISIONS = ("double", "single")


def _spec(config: Path, duration_s: float | None, estimator: str, qp_solver: str | None):
    """(the loop's spec, the scenario) of ``config``; ValueError naming the flag or the file otherwise."""
    from hbma_ctrl.controllers.rti_step import QP_SOLVERS
    from hbma_ctrl.app.codegen.chamber import ESTIMATORS, scenario_loop
    from hbma_ctrl.app.scenario import load_scenario

    check_range("--duration-s", duration_s, 0.0, DURATION_MAX_S, lo_open=True, unit="s")
    check_choice("--estimator", estimator, ESTIMATORS)
    if qp_solver is not None:
        check_choice("--qp-solver", qp_solver, QP_SOLVERS)
    scn = load_scenario(config)
    try:
        if scn.role("robot") is not None:
            spec = _robot_spec(scn, duration_s, estimator, qp_solver)
        else:
            spec = scenario_loop(scn, duration_s, estimator, qp_solver)
    except ValueError as exc:
        raise ValueError(f"{config.name}: {exc}") from None
    return spec, scn


def _robot_spec(scn, duration_s: float | None, estimator: str, qp_solver: str | None):
    """The robot scenario's loop (:func:`hbma_ctrl.app.codegen.robot.robot_loop`): its EKF bank and
    OSQP only; ValueError naming the flag otherwise."""
    from hbma_ctrl.app.codegen.robot import robot_loop

    if estimator != "ekf":
        raise ValueError(f"--estimator = '{estimator}': a robot scenario's generated loop runs its EKF bank "
                         "(allowed: ekf)")
    if qp_solver not in (None, "osqp"):
        raise ValueError(f"--qp-solver = '{qp_solver}': the robot NMPC's generated step solves with OSQP "
                         "(allowed: osqp)")
    return robot_loop(scn, duration_s)


def _compiler() -> str:
    from hbma_ctrl.core.loopgen_c import find_compiler

    cc = find_compiler()
    if cc is None:
        raise ValueError("no C compiler (cc, gcc or clang) on PATH: needed to build the generated loop")
    return cc


def _write_run_metrics(scn, spec, out: Path, qp_solver: str | None) -> dict:
    """metrics.json of the C loop's run in ``out`` (its trajectory.csv): the scene's controller object and
    the estimate's errors (:func:`hbma_ctrl.app.codegen.chamber.loop_run_metrics`); returned too."""
    from hbma_ctrl.core.loopgen_c import read_c
    from hbma_ctrl.app.codegen.chamber import loop_run_metrics
    from hbma_ctrl.app.metrics import write_metrics

    if scn.role("robot") is not None:
        from hbma_ctrl.app.codegen.robot import loop_run_metrics as robot_metrics

        m = robot_metrics(scn, spec, read_c(out).trajectory)
    else:
        m = loop_run_metrics(scn, spec, read_c(out).trajectory, qp_solver)
    write_metrics(m, out / "metrics.json")
    return m


def codegen(
    config: Annotated[Path, typer.Argument(help="scenario TOML with [controller] kind = 'mpc' (RTI), or a "
                                              "closed-loop [robot] with controller = 'mpc'")],
    out: Annotated[Path, typer.Option("--out", "-o", help="output directory for the C sources")],
    duration_s: Annotated[Optional[float], typer.Option("--duration-s", help="loop duration, s (default: the scenario's)")] = None,
    estimator: Annotated[str, typer.Option(help="ekf (the scenario's filter) | truth (the rig's state, no filter)")] = "ekf",
    qp_solver: Annotated[Optional[str], typer.Option("--qp-solver", help="the RTI step's QP solver: osqp | "
                                                     "hpipm | daqp (linked from the casadi package) | qrqp "
                                                     "(self-contained C); default: the variant's, else osqp. "
                                                     "--library: osqp (sparse QP) | daqp (condensed dense QP, "
                                                     "its C sources in the library; a chamber's, double)")] = None,
    check: Annotated[bool, typer.Option("--check", help="also build, run and compare with the Python path (check.json)")] = False,
    opt: Annotated[str, typer.Option(help=f"optimisation flag of the --check build: {', '.join(OPT_FLAGS)}")] = DEFAULT_OPT,
    library: Annotated[bool, typer.Option("--library", help="write the chamber's (or robot's) estimator + controller + "
                                          "supervisor tick as a self-contained C library (hbma.h: fixed "
                                          "memory, no malloc, OSQP's embedded sources included) instead of "
                                          "the closed loop")] = False,
    target: Annotated[str, typer.Option(help="--library: build for host | cortex-m7 | cortex-m4f; a "
                                        "cortex-* target also runs on qemu-system-arm on the scenario's "
                                        "recorded pressures beside the host build (embedded.json)")] = "host",
    precision: Annotated[str, typer.Option(help="--library: double | single (floating-point type of "
                                           "the library; single is also compared with double; a robot's library: double)")] = "double",
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
) -> None:
    """Write C sources, one header and a C closed-loop program (no Python at run time) for a scenario, or
    (--library) its chamber's or robot's tick as a C library for a microcontroller."""
    from hbma_ctrl.core.loopgen_c import bench, write_c

    check_choice("--opt", opt, OPT_FLAGS)
    if library:
        _library(config, out, duration_s, estimator, qp_solver, check, target, precision, overwrite)
        return
    check_choice("--target", target, LIBRARY_TARGETS)
    if target != "host" or precision != "double":
        raise ValueError("--target and --precision apply to --library only")
    spec, scn = _spec(config, duration_s, estimator, qp_solver)
    cc = _compiler() if check else None
    con = Console(highlight=False)
    with run_dir(out, command="codegen", argv=cli_argv(), scenario_path=config, overwrite=overwrite) as tmp:
        if check:
            res = bench(spec, tmp, opt=opt, cc=cc)
            (tmp / "check.json").write_text(json.dumps(res, indent=2) + "\n")
            _write_run_metrics(scn, spec, tmp, qp_solver)
        else:
            write_c(spec, tmp)
    con.print(f"wrote {out}: hbma_steps.c/.h, loop_data.h, closed_loop.c, Makefile, README.txt "
              f"({spec.n_ticks} ticks of {spec.dt * 1e3:g} ms)")
    con.print(f"build: cd {out} && make   then ./closed_loop   (or the line in README.txt)")
    if "left out" in spec.meta:
        con.print(f"note: left out of the generated loop: {spec.meta['left out']}", markup=False)
    if check:
        con.print(f"C vs Python path: largest absolute difference {res['max_abs_diff_si_all']:.3g} (SI); "
                  f"see {out / 'check.json'}")

def _library(config: Path, out: Path, duration_s: float | None, estimator: str, qp_solver: str | None,
             check: bool, target: str, precision: str, overwrite: bool) -> None:
    """``codegen --library``: the library (:func:`hbma_ctrl.app.codegen.library.generate`); ValueError
    naming the option otherwise."""
    from hbma_ctrl.app.scenario import load_scenario

    check_choice("--target", target, LIBRARY_TARGETS)
    check_choice("--precision", precision, LIBRARY_PRECISIONS)
    check_range("--duration-s", duration_s, 0.0, DURATION_MAX_S, lo_open=True, unit="s")
    if estimator != "ekf":
        raise ValueError(f"--estimator = '{estimator}': the library runs the scenario's EKF (allowed with "
                         "--library: ekf)")
    if check:
        raise ValueError("--check compares the closed loop with Python; with --library a cortex-* --target "
                         "compares the board with the host build")
    from hbma_ctrl.app.codegen.library import check_precision, check_qp_solver, generate

    qp_solver = qp_solver or "osqp"
    check_qp_solver(qp_solver, precision)
    scn = load_scenario(config)
    try:
        check_precision("robot" if scn.role("robot") is not None else "chamber", precision)
    except ValueError as exc:
        raise ValueError(f"{config.name}: {exc}") from None
    con = Console(highlight=False)
    with run_dir(out, command="codegen", argv=cli_argv(), scenario_path=config, overwrite=overwrite) as tmp:
        try:
            rep = generate(scn, tmp, target, precision, duration_s, log=lambda m: con.print(m, markup=False),
                           qp_solver=qp_solver)
        except ValueError as exc:
            raise ValueError(f"{config.name}: {exc}") from None
    con.print(f"wrote {out}: hbma.h, hbma.c, hbma_steps.c/.h, {qp_solver}/, hbma_run.c, board/, Makefile, "
              "CMakeLists.txt, README.txt")
    if rep:
        con.print(f"{rep['target']} ({rep['qemu_machine']}) vs host over {rep['ticks']} ticks: largest "
                  f"|command difference| {rep['max_abs_diff']:.3g}; instructions per tick median "
                  f"{rep['instructions_per_tick_median']:.0f}, max {rep['instructions_per_tick_max']:.0f}; "
                  f"flash {rep['flash_bytes']} B, RAM {rep['ram_bytes']} B; see {out / 'embedded.json'}")
        if "recorded_commands_max_abs_diff" in rep:
            con.print(f"host vs the scenario's own run: largest |command difference| "
                      f"{rep['recorded_commands_max_abs_diff']:.3g} ({rep['recorded_ticks_diff_above_1e-3']} ticks above "
                      f"1e-3), largest |height estimate difference| "
                      f"{rep['recorded_height_estimate_max_abs_diff_m'] * 1e3:.3g} mm")
        if "max_abs_diff_vs_double" in rep:
            con.print(f"single vs double precision (host): largest |command difference| "
                      f"{rep['max_abs_diff_vs_double']:.3g}, median {rep['abs_diff_vs_double_median']:.3g}")


def bench_codegen(
    config: Annotated[Path, typer.Argument(help="scenario TOML (default scenarios/track_height.toml)")] = Path(
        "scenarios/track_height.toml"),
    out: Annotated[Path, typer.Option("--out", "-o", help="output dir (the C sources and bench_codegen.json)")] = Path(
        "runs/bench_codegen"),
    duration_s: Annotated[Optional[float], typer.Option("--duration-s", help="loop duration, s (default: the scenario's)")] = None,
    estimator: Annotated[str, typer.Option(help="ekf | truth")] = "ekf",
    qp_solver: Annotated[Optional[str], typer.Option("--qp-solver", help="the RTI step's QP solver: osqp | "
                                                     "hpipm | daqp (linked from the casadi package) | qrqp "
                                                     "(self-contained C); default: the variant's, else osqp")] = None,
    opt: Annotated[str, typer.Option(help=f"optimisation flag of the C build: {', '.join(OPT_FLAGS)}")] = DEFAULT_OPT,
    python_vm: Annotated[bool, typer.Option("--python-vm", help="also run the Python path on casadi's virtual "
                                            "machine (uncompiled Functions; slow)")] = False,
    scene: Annotated[bool, typer.Option("--scene/--no-scene", help="also run the scene's own closed loop (EKF and "
                                        "NMPC classes, no calibration) and compare its step times and trajectory")]
    = True,
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
    report: ReportDir = None,
) -> None:
    """Step times of the generated C loop beside the Python path's (median, p99, ratios), one run."""
    from hbma_ctrl.core.loopgen_c import bench, read_c
    from hbma_ctrl.app.codegen.chamber import scene_reference

    check_choice("--opt", opt, OPT_FLAGS)
    spec, scn = _spec(config, duration_s, estimator, qp_solver)
    cc = _compiler()
    from hbma_ctrl.app.bench.report import open_report

    rep = open_report(report, "codegen", cli_argv())  # --report checked before the run
    con = Console(highlight=False, width=150)
    with run_dir(out, command="bench codegen", argv=cli_argv(), scenario_path=config, overwrite=overwrite) as tmp:
        res = bench(spec, tmp, opt=opt, cc=cc, python_vm=python_vm)
        c_metrics = _write_run_metrics(scn, spec, tmp, qp_solver)
        if scene and scn.role("robot") is not None:
            from hbma_ctrl.app.codegen.robot import scene_reference as robot_scene

            res["scene"] = robot_scene(scn, spec, read_c(tmp).trajectory)
        elif scene and estimator == "ekf":
            res["scene"] = scene_reference(scn, spec, read_c(tmp).trajectory, qp_solver)
            res["scene"]["c_height_rmse_mm"] = c_metrics["controller"]["height_rmse_mm"]
            res["scene"]["c_steps_settled"] = c_metrics["controller"]["steps_settled"]
        (tmp / "bench_codegen.json").write_text(json.dumps(res, indent=2) + "\n")
    cols = ["function", "calls", "C median", "C p99", "Python median", "Python p99", "ratio median", "ratio p99"]
    if python_vm:
        cols += ["VM median", "VM p99"]
    rows = []
    for name, r in list(res["functions"].items()) + [("tick (sum)", res["tick"])]:
        c, p = r["c"], r["python"]
        ratio = [f"{v:.1f}x" if v else "-" for v in (r["ratio_median"], r["ratio_p99"])]
        row = [name, str(c["calls"]), f"{c['median_us']:.2f}", f"{c['p99_us']:.2f}",
               f"{p['median_us']:.2f}", f"{p['p99_us']:.2f}", *ratio]
        if python_vm:
            vm = r["python_vm"]
            row += [f"{vm['median_us']:.2f}" if vm["calls"] else "-", f"{vm['p99_us']:.2f}" if vm["calls"] else "-"]
        rows.append(row)
    show_table(f"bench codegen: {spec.name}, {spec.n_ticks} ticks of {spec.dt * 1e3:g} ms, C {opt} vs Python path "
               f"({res['python_path']}); us per call", cols, rows, con)
    if python_vm:
        con.print(f"largest |C - VM path| over the trajectory: {res['vm_max_abs_diff_si_all']:.3g} (SI)")
    con.print(f"largest |C - Python| over the trajectory: {res['max_abs_diff_si_all']:.3g} (SI); "
              f"build {res['wall_s']['build']:.1f} s, C run {res['wall_s']['c_run']:.2f} s, "
              f"Python run {res['wall_s']['python_run']:.1f} s")
    sc = res.get("scene")
    if sc and "nmpc" in sc:
        e, c = sc["ekf_step"], sc["controller_step"]
        con.print(f"scene's own loop (NMPC {sc['nmpc']}): EKF bank {e['median_us']:.1f} / {e['p99_us']:.1f} us, "
                  f"the rest of the tick {c['median_us']:.0f} / {c['p99_us']:.0f} us (median / p99); largest "
                  f"|C - scene| {sc['max_abs_diff_si_all']:.3g} (SI); chamber height RMSE "
                  f"{sc['c_chamber_height_rmse_mm']:.3f} mm (C) vs {sc['chamber_height_rmse_mm']:.3f} mm (scene)")
    elif sc:
        e, c = sc["ekf_step"], sc["controller_step"]
        con.print(f"scene's own loop ({sc['variant']}): EKF step {e['median_us']:.1f} / {e['p99_us']:.1f} us, "
                  f"controller step {c['median_us']:.0f} / {c['p99_us']:.0f} us (median / p99); largest "
                  f"|C - scene| {sc['max_abs_diff_si_all']:.3g} (SI)")
    con.print(f"wrote {out / 'bench_codegen.json'}")
    if rep:
        from hbma_ctrl.app.bench.pages import codegen_page

        con.print(f"wrote {rep.write(codegen_page(res, spec.name, opt))}")


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``codegen`` to the app and ``codegen`` to the bench sub-app (called by :mod:`hbma_ctrl.app.cli.main`)."""
    app.command("codegen")(codegen)
    bench_app.command("codegen")(bench_codegen)
