"""The simulator's commands: ``run FILE``, ``protocol`` (what a bare ``hbma-ctrl`` runs), ``equilibrium``,
``plots``, ``bench sim`` and ``bench protocol``.

Each command imports what it needs when it runs, so that registering them (every ``hbma-ctrl`` start)
loads only typer, rich and a few light modules.
"""

from __future__ import annotations

import json
import math
import time
from collections import Counter
from pathlib import Path
from typing import Annotated, Optional

import typer

from hbma_ctrl.app.cli.args import (ReportDir, assignments, cap_workers, check_choice, check_range, console, fail,
                                    show_table)
from hbma_ctrl.app.cli.constants import CHAMBER_R1_MM, CHAMBER_T0_MM, MEMBRANE_LAW
from hbma_ctrl.app.outputs import OVERWRITE_HELP, cli_argv, default_out, run_dir
from hbma_ctrl.core import units as U

__all__ = ["register", "run_scenario", "run_protocol", "equilibrium_values"]


def run_scenario(scn, out: Path) -> dict:
    """:func:`hbma_ctrl.app.scenes.runner.run_scenario`: runs a loaded scenario into ``out``, returns its metrics.

    Imported on the call: the runner loads every role (estimators, controllers, robot scenes).
    """
    from hbma_ctrl.app.scenes.runner import run_scenario as impl

    return impl(scn, out)


def run_protocol(*args, **kwargs) -> list[dict]:
    """:func:`hbma_ctrl.app.scenes.protocol.run_protocol` (same arguments): the protocol's summary rows.

    Imported on the call, so that importing the CLI for another command skips the simulator and plots.
    """
    from hbma_ctrl.app.scenes.protocol import run_protocol as impl

    return impl(*args, **kwargs)



def run(
    file: Annotated[Path, typer.Argument(help="scenario TOML file")],
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="output directory (default runs/<name>)")] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
) -> None:
    """Run a scenario file: writes metrics.json, the log CSV(s), plots and manifest.json into --out."""
    from hbma_ctrl.app.scenario import load_scenario
    from hbma_ctrl.app.scenes.runner import refuse_recording

    scn = load_scenario(file)
    refuse_recording(scn)  # before --out: a recording is the daemon's, nothing of it runs here
    out_dir = out or default_out(scn.name)
    t0 = time.perf_counter()
    with run_dir(out_dir, command="run", argv=cli_argv(), scenario_path=file, overwrite=overwrite) as tmp:
        metrics = run_scenario(scn, tmp)
    rows = [(role, k, _fmt(v)) for role, vals in metrics.items() if role != "scenario" and isinstance(vals, dict)
            for k, v in vals.items()]
    con = show_table(f"{scn.name} ({scn.kind}) -> {out_dir}", ("role", "metric", "value"), rows, left=2)
    con.print(f"wrote {out_dir / 'metrics.json'} in {time.perf_counter() - t0:.1f} s")


def _fmt(v, width: int = 60) -> str:
    """Compact cell text; long or nested values point to metrics.json."""
    if isinstance(v, float):
        text = f"{v:.4g}"
    elif isinstance(v, dict):
        text = ", ".join(f"{k}: {_fmt(x)}" for k, x in v.items())
    elif isinstance(v, (list, tuple)):
        if any(isinstance(x, (dict, list, tuple)) for x in v):
            return f"{len(v)} entries (see metrics.json)"
        text = "[" + ", ".join(_fmt(x) for x in v) + "]"
    else:
        text = str(v)
    return text if len(text) <= width else text[: width - 25] + "... (see metrics.json)"


def protocol(
    material: Annotated[str, typer.Option(help="nh | mr | yeoh | gent | ogden")] = "nh",
    out: Annotated[Path, typer.Option("--out", "-o", help="output directory")] = Path("runs/protocol"),
    workers: Annotated[int, typer.Option(help="worker processes (each simulates a chunk of trials)")] = 1,
    integrator: Annotated[str, typer.Option(help="euler | rk4 | radau (reference, slow)")] = "rk4",
    dt_ms: Annotated[Optional[float], typer.Option("--dt-ms", help="fixed step, ms (default per fidelity)")] = None,
    fidelity: Annotated[str, typer.Option(help="auto | quasi_static | platform (0 g trials: free)")] = "auto",
    t_inflate_s: Annotated[float, typer.Option("--t-inflate-s", help="inflation time, s")] = 3.0,
    duration_s: Annotated[float, typer.Option("--duration-s", help="trial duration, s")] = 6.0,
    no_plots: Annotated[bool, typer.Option("--no-plots", help="skip fig6/fig7/fig9")] = False,
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
) -> None:
    """Simulate the 150-trial characterisation protocol (docs/concepts/model.md §7): DIR/summary.csv, DIR/trials/*.csv, fig6/7/9 PNGs."""
    from hbma_ctrl.core.materials import MATERIALS
    from hbma_ctrl.sim.batch import FIDELITY_CHOICES
    from hbma_ctrl.sim.trial import INTEGRATORS, MAX_STEPS

    check_choice("--material", material, MATERIALS)
    check_choice("--integrator", integrator, INTEGRATORS)
    check_choice("--fidelity", fidelity, [f for f in FIDELITY_CHOICES if f != "free"])
    workers = cap_workers("--workers", workers)
    check_range("--duration-s", duration_s, 0.0, 3600.0, lo_open=True, unit="s")
    check_range("--dt-ms", dt_ms, U.to_ms(duration_s) / MAX_STEPS, 100.0, unit="ms",
                note=f"at most {MAX_STEPS:,} steps over --duration-s")
    check_range("--t-inflate-s", t_inflate_s, 0.0, duration_s, lo_open=True, unit="s", hi_open=True,
                note="below --duration-s")
    t0 = time.perf_counter()
    with run_dir(out, command="protocol", argv=cli_argv(), overwrite=overwrite) as tmp:
        rows = run_protocol(material, tmp, integrator, None if dt_ms is None else U.ms(dt_ms), fidelity, workers,
                            t_inflate_s=t_inflate_s, duration_s=duration_s, plots=not no_plots, progress=True)
        counts = Counter(r["status"] for r in rows)
        failed = [r["failed_because"][0] for r in rows if r["status"] == "failed"]
        if failed:  # kept as a failed run, as `run` keeps a protocol scenario's (the runner loads every role)
            from hbma_ctrl.app.scenes.runner import check_physics

            check_physics(counts, failed, "summary.csv status")
    wall = time.perf_counter() - t0
    con = show_table(f"protocol ({material}, {integrator}, fidelity {fidelity})",
                     ("trials", "status", "max height (mm)", "max pressure (kPa)", "wall (s)"),
                     [(str(len(rows)), ", ".join(f"{k} {v}" for k, v in counts.items()),
                       f"{max(r['max_height_mm'] for r in rows):.2f}",
                       f"{max(r['max_pressure_kpa'] for r in rows):.2f}", f"{wall:.1f}")])
    con.print(f"wrote {out / 'summary.csv'}, {out / 'trials'}/*.csv" + ("" if no_plots else ", fig6/fig7/fig9.png"))


def equilibrium_values(material: str, r1_mm: float, t0_mm: float, h1_mm: float, h2_mm: float,
                       params: dict | None = None, V0_cm3: float = 3.0, fidelity: str = "cap",
                       contact: str = "flat", disk_radius_mm: float = 2.0,
                       p_kpa: float | None = None) -> dict:
    """Equilibrium of one shape (edge units in and out): pressure, force, load, stretch, volume.

    ``fidelity`` 'cap' (spherical cap, docs/concepts/model.md) or 'exact' (:mod:`hbma_ctrl.models.exact`: the
    centre height h = h1 - h2 held by a flat plate or a bonded disk of radius ``disk_radius_mm`` at
    gauge pressure ``p_kpa``; free inflation when h2 = 0 with a flat contact).
    """
    import numpy as np

    from hbma_ctrl.app.plots import equilibrium_grid
    from hbma_ctrl.core.materials import MATERIALS, make_material

    check_range("--r1-mm", r1_mm, 0.5, 100.0, lo_open=True, unit="mm")
    check_range("--t0-mm", t0_mm, 0.05, 20.0, lo_open=True, unit="mm")
    check_range("--V0-cm3", V0_cm3, 0.001, 1000.0, unit="cm^3")
    check_range("--h1-mm", h1_mm, 0.0, 20 * r1_mm, unit="mm")
    if not (math.isfinite(h2_mm) and 0.0 <= h2_mm <= h1_mm):
        raise ValueError(f"--h2-mm = {h2_mm:g} is out of range [0, h1-mm = {h1_mm:g}] mm (need 0 <= h2 <= h1)")
    check_choice("--material", material, MATERIALS)
    try:
        mat = make_material(material, **(params or {}))
    except ValueError as exc:  # the parameters are the only thing left that can be wrong: say so
        raise ValueError(f"--param {', '.join(params or {})}: {exc}") from None
    check_choice("--fidelity", fidelity, ["cap", "exact"])
    if fidelity == "exact":
        return _exact_equilibrium_values(mat, r1_mm, t0_mm, h1_mm, h2_mm, V0_cm3, contact, disk_radius_mm, p_kpa)
    if contact != "flat" or p_kpa is not None:
        raise ValueError("--contact/--p-kpa need --fidelity exact (the cap's contact is the flat plate, "
                         "its pressure follows from h1 and h2)")
    res = {k: float(v[0]) for k, v in equilibrium_grid(mat, U.mm(r1_mm), U.mm(t0_mm), np.array([U.mm(h1_mm)]),
                                                         np.array([U.mm(h2_mm)]), U.cm3(V0_cm3)).items()}
    if res["lam"] >= mat.lam_max():
        raise ValueError(f"--h1-mm/--h2-mm: stretch {res['lam']:.3f} is beyond the {mat.name} locking stretch "
                         f"{mat.lam_max():.3f}")
    return _equilibrium_row(mat, r1_mm, t0_mm, V0_cm3, h1_mm, h2_mm, {}, res["p"], res["F"], res["lam"], res["V"],
                            math.sqrt(max(res["a2"], 0.0)))


def _equilibrium_row(mat, r1_mm: float, t0_mm: float, V0_cm3: float, h1_mm: float, h2_mm: float, extra: dict,
                     p: float, F: float, stretch: float, V: float, contact_radius: float) -> dict:
    """What ``equilibrium --json`` prints, in edge units, from the SI pressure, force, volume, contact radius."""
    return {
        "material": mat.name,
        "params_si": {k: (list(v) if isinstance(v, tuple) else v) for k, v in mat.as_dict().items()},
        "r1_mm": r1_mm, "t0_mm": t0_mm, "V0_cm3": V0_cm3, "h1_mm": h1_mm, "h2_mm": h2_mm,
        "h_mm": h1_mm - h2_mm,
        **extra,
        "pressure_kpa": U.to_kpa(p),
        "force_n": F,
        "load_g": U.to_grams(F / U.G_STD),
        "stretch": stretch,
        "volume_cm3": U.to_cm3(V),
        "contact_radius_mm": U.to_mm(contact_radius),
    }


# the exact module names its arguments as it knows them; the CLI names the flags the user wrote
_EXACT_ARG_FLAGS = (("h = ", "--h1-mm/--h2-mm: h = "), ("p = ", "--p-kpa: p = "), ("c = ", "--disk-radius-mm: c = "))


def _exact_equilibrium_values(mat, r1_mm: float, t0_mm: float, h1_mm: float, h2_mm: float, V0_cm3: float,
                              contact: str, disk_radius_mm: float, p_kpa: float | None) -> dict:
    """``equilibrium --fidelity exact``: the exact membrane's equilibrium in edge units."""
    from hbma_ctrl.models.exact import equilibrium as exact_equilibrium

    check_choice("--contact", contact, ["flat", "bonded"])
    if contact == "bonded":
        check_range("--disk-radius-mm", disk_radius_mm, 0.0, r1_mm, lo_open=True, unit="mm", hi_open=True,
                    note="inside the retaining radius")
    free = h2_mm == 0 and contact == "flat"
    if free and p_kpa is not None:
        raise ValueError("--p-kpa: free inflation (--h2-mm 0, flat contact) has its pressure set by the height; "
                         "give --h2-mm > 0 or --contact bonded to hold the centre at a pressure")
    if not free and p_kpa is None:
        raise ValueError("--p-kpa is required with a contact (--h2-mm > 0 or --contact bonded): "
                         "the gauge pressure, kPa, in (0, 1000]")
    check_range("--p-kpa", p_kpa, 0.0, 1000.0, lo_open=True, unit="kPa")
    h_mm = h1_mm - h2_mm
    if not h_mm > 0:
        raise ValueError(f"--h1-mm/--h2-mm: h = h1 - h2 = {h_mm:g} mm must be > 0 mm for the exact membrane")
    try:
        res = exact_equilibrium(mat, U.mm(r1_mm), U.mm(t0_mm), U.mm(h_mm), None if free else U.kpa(p_kpa),
                                contact, U.mm(disk_radius_mm), U.cm3(V0_cm3))
    except ValueError as exc:
        msg = str(exc)
        for arg, flag in _EXACT_ARG_FLAGS:
            if msg.startswith(arg):
                msg = flag + msg[len(arg):]
                break
        raise ValueError(msg) from None
    return _equilibrium_row(mat, r1_mm, t0_mm, V0_cm3, h1_mm, h2_mm, {"fidelity": "exact", "contact": contact},
                            res["p"], res["F"], res["stretch"], res["V"], res["contact_radius"])


def equilibrium(
    h1_mm: Annotated[float, typer.Option("--h1-mm", help="virtual cap height h1, mm")],
    h2_mm: Annotated[float, typer.Option("--h2-mm", help="cut height h2 (contact), mm; 0 = free")] = 0.0,
    material: Annotated[str, typer.Option(help="nh | mr | yeoh | gent | ogden")] = "nh",
    r1_mm: Annotated[float, typer.Option("--r1-mm", help="retaining radius r1, mm")] = CHAMBER_R1_MM,
    t0_mm: Annotated[float, typer.Option("--t0-mm", help="membrane thickness t0, mm")] = CHAMBER_T0_MM,
    V0_cm3: Annotated[float, typer.Option("--V0-cm3", help="dead volume, cm^3")] = 3.0,
    param: Annotated[Optional[list[str]], typer.Option("--param", help="material parameter NAME=VALUE (SI), repeatable")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="print one JSON object")] = False,
    fidelity: Annotated[Optional[str], typer.Option(
        help=f"cap | exact; default: {MEMBRANE_LAW} (the roles' and fit's law) where it computes the shape asked "
             "(free inflation, or a contact at --p-kpa), else the cap (a plate at --h2-mm without --p-kpa)")] = None,
    contact: Annotated[str, typer.Option(help="flat | bonded (exact only)")] = "flat",
    disk_radius_mm: Annotated[float, typer.Option("--disk-radius-mm", help="bonded disk radius c, mm")] = 2.0,
    p_kpa: Annotated[Optional[float], typer.Option("--p-kpa", help="gauge pressure, kPa (exact contact)")] = None,
) -> None:
    """Equilibrium pressure, contact force (and load F/g), stretch and volume of one shape (h1, h2).

    ``--fidelity exact``: the exact axisymmetric membrane; h = h1 - h2 is the centre height, free
    inflation for --h2-mm 0 (flat), otherwise a flat plate or a bonded disk at --p-kpa.
    """
    if fidelity is None:
        # the shared default law where it computes the shape asked: the exact law holds a contact at a pressure
        fidelity = MEMBRANE_LAW if (h2_mm == 0 or p_kpa is not None or contact != "flat") else "cap"
    res = equilibrium_values(material, r1_mm, t0_mm, h1_mm, h2_mm, assignments(param or [], "--param", "E=130.6e3 or C=2e4,-200,10"), V0_cm3,
                             fidelity, contact, disk_radius_mm, p_kpa)
    if as_json:
        typer.echo(json.dumps(res))
        return
    labels = (("h_mm", "height h (mm)"), ("pressure_kpa", "pressure (kPa)"), ("force_n", "force (N)"),
              ("load_g", "load F/g (g)"), ("stretch", "stretch lambda"), ("volume_cm3", "volume (cm^3)"),
              ("contact_radius_mm", "contact radius a (mm)"))
    show_table(f"{res['material']}: r1 {r1_mm:g}, t0 {t0_mm:g}, h1 {h1_mm:g}, h2 {h2_mm:g} mm", ("quantity", "value"),
               [(label, f"{res[key]:.4f}") for key, label in labels], left=1, show_header=False)


def plots(
    out: Annotated[Path, typer.Option("--out", "-o", help="output directory")] = Path("runs/plots"),
    material: Annotated[str, typer.Option(help="material of the fig 7 / fig 9 simulations")] = "nh",
    fidelity: Annotated[str, typer.Option(help="auto | quasi_static | platform")] = "auto",
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
) -> None:
    """Paper figures fig6.png (equilibrium surfaces), fig7.png and fig9.png (simulated) into --out."""
    from hbma_ctrl.app.plots import paper_figures
    from hbma_ctrl.core.materials import MATERIALS
    from hbma_ctrl.sim.batch import FIDELITY_CHOICES

    check_choice("--material", material, MATERIALS)
    check_choice("--fidelity", fidelity, [f for f in FIDELITY_CHOICES if f != "free"])
    with run_dir(out, command="plots", argv=cli_argv(), overwrite=overwrite) as tmp:
        paths = paper_figures(tmp, material, fidelity=fidelity)
    console().print("wrote " + ", ".join(str(out / Path(p).name) for p in paths))


def _role_plots(ekf_json: Path | None, mpc_json: Path | None) -> list:
    """(points, PNG name, axes) of the role benches' results given (read now: a bad file is one error line
    before the long run)."""
    from hbma_ctrl.app.bench import plots as bench_plots

    out = []
    for path, read, name, axes in (
            (ekf_json, bench_plots.estimator_points, "pareto_estimator.png", ("median filter step (us)", "height NRMSD")),
            (mpc_json, bench_plots.controller_points, "pareto_controller.png", ("median solve time (ms)",
                                                                                 "height RMSE (mm)"))):
        if path is not None:
            out.append((read(path), name, axes))
    return out


def _role_benches(out: Path, con) -> list:
    """``bench ekf`` and ``bench mpc`` on their defaults into ``out`` (bench_ekf.json, bench_mpc.json, as
    those commands write them); their Pareto points for :func:`bench_sim`."""
    from hbma_ctrl.app.bench.mpc import run_bench as run_mpc
    from hbma_ctrl.app.bench.mpc import write_bench
    from hbma_ctrl.app.cli.controllers import MPC_VARIANTS
    from hbma_ctrl.app.cli.estimators import BENCH_GRID, BENCH_MEMBRANES, BENCH_SUBSTEPS, bench_ekf

    con.print("  bench ekf (EKF/UKF x sub-steps x membrane law) ...")
    (out / "bench_ekf.json").write_text(json.dumps(bench_ekf(BENCH_GRID, substeps=BENCH_SUBSTEPS,
                                                             membranes=BENCH_MEMBRANES), indent=1))
    con.print("  bench mpc (IPOPT, fatrop, RTI x horizon, baselines, do-mpc) ...")
    write_bench(run_mpc(variants=MPC_VARIANTS,
                        progress=lambda name: con.print(f"    {name} ...")), out)
    return _role_plots(out / "bench_ekf.json", out / "bench_mpc.json")


def bench_sim(
    quick: Annotated[bool, typer.Option("--quick", help="8 trials and one step per integrator: a fast check")] = False,
    workers: Annotated[int, typer.Option(help="worker processes for the reference and each run")] = 1,
    out: Annotated[Path, typer.Option("--out", "-o", help="output dir (reference cache, bench.json/csv)")] = Path("runs/bench_sim"),
    repeat: Annotated[int, typer.Option(help="timed runs per setting (median reported)")] = 1,
    material: Annotated[str, typer.Option(help="membrane material")] = "nh",
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP + "; its cached reference is kept")]
    = False,
    fidelity_axis: Annotated[bool, typer.Option("--fidelity-axis/--no-fidelity-axis",
                                                help="also score every row against the exact membrane, run the "
                                                     "free and exact rungs, and write pareto.png")] = True,
    ekf_json: Annotated[Optional[Path], typer.Option("--ekf-json", help="a bench ekf result: also write "
                                                  "pareto_estimator.png (step time vs height NRMSD)")] = None,
    mpc_json: Annotated[Optional[Path], typer.Option("--mpc-json", help="a bench mpc result: also write "
                                                  "pareto_controller.png (solve time vs height RMSE)")] = None,
    roles: Annotated[bool, typer.Option("--roles", help="also run bench ekf (EKF/UKF x sub-steps x membrane "
                                                        "law) and bench mpc (IPOPT/fatrop/RTI x horizon, "
                                                        "baselines, do-mpc when installed) on their defaults into "
                                                        "--out and draw their Pareto plots: every role from one "
                                                        "command (about 15 min)")] = False,
    report: ReportDir = None,
) -> None:
    """Simulator speed/accuracy: integrator x step x fidelity over the protocol vs a Radau reference, and
    (fidelity axis) vs the exact membrane, with a Pareto plot (wall time vs NRMSD) beside bench.json."""
    from hbma_ctrl.app.bench.sim import TARGET_NRMSD, TARGET_WALL_S, run_bench
    from hbma_ctrl.core.materials import MATERIALS

    check_choice("--material", material, MATERIALS)
    workers = cap_workers("--workers", workers)
    check_range("--repeat", repeat, 1, 100)
    from hbma_ctrl.app.bench import plots as bench_plots

    if roles and (ekf_json is not None or mpc_json is not None):
        fail("--roles runs the estimator and controller benches itself: leave out --ekf-json and --mpc-json")
    role_plots = _role_plots(ekf_json, mpc_json)
    from hbma_ctrl.app.bench.report import open_report

    rep = open_report(report, "sim", cli_argv())  # --report checked before the run
    con = console(160)

    def show(row):
        vs = (f"  vs exact h {row.height_nrmsd_vs_exact_mean:.2e} p {row.pressure_nrmsd_vs_exact_mean:.2e} (mean)"
              if fidelity_axis else "")
        con.print(f"  {row.fidelity:12s} {row.integrator:5s} dt {_dt_text(row):>14s}  wall {row.wall_s:7.2f} s  "
                  f"cpu {row.cpu_s:7.2f} s  "
                  f"NRMSD h {row.height_nrmsd_max:.2e} p {row.pressure_nrmsd_max:.2e} (max){vs}")

    # the Radau reference cache (ref_*.npz) is keyed by trials and model sources: safe to carry over
    with run_dir(out, command="bench sim", argv=cli_argv(), overwrite=overwrite, carry=("ref_*.npz",)) as tmp:
        rows = run_bench(tmp, quick=quick, workers=workers, repeat=repeat, material=material, on_row=show,
                         fidelity_axis=fidelity_axis)
        if roles:
            role_plots = _role_benches(tmp, con)
        written = [bench_plots.pareto_png(pts, tmp / name, *axes, title).name for (pts, title), name, axes in role_plots]
        meta = json.loads((tmp / "bench.json").read_text())["meta"]
    cols = ("loaded fidelity", "integrator", "dt (ms)", "wall (s)", "cpu (s)", "diverged", "h NRMSD mean",
            "h NRMSD max", "p NRMSD mean", "p NRMSD max", "target") + (("h vs exact", "p vs exact") if fidelity_axis
                                                                        else ())
    table = [(r.fidelity + (" (0 g)" if r.fidelity == "free" else ""), r.integrator,
              _dt_text(r) + (" *" if r.default else ""), f"{r.wall_s:.2f}", f"{r.cpu_s:.2f}", str(r.n_diverged),
              f"{r.height_nrmsd_mean:.2e}", f"{r.height_nrmsd_max:.2e}", f"{r.pressure_nrmsd_mean:.2e}",
              f"{r.pressure_nrmsd_max:.2e}", "yes" if r.meets_target else "no",
              *((f"{r.height_nrmsd_vs_exact_mean:.2e}", f"{r.pressure_nrmsd_vs_exact_mean:.2e}") if fidelity_axis
                else ())) for r in rows]
    show_table(f"bench sim: {rows[0].n_trials if rows else 0} trials, workers {workers}, median of {repeat}; "
               f"target wall <= {TARGET_WALL_S:g} s, max NRMSD <= {TARGET_NRMSD:g}", cols, table, con, no_wrap=True)
    con.print("* the setting `hbma-ctrl protocol` uses by default (fidelity auto: free for 0 g, quasi_static loaded)")
    if fidelity_axis:
        con.print("vs exact: mean NRMSD against the exact membrane (rk4, fine step); free (0 g): the cap's free "
                  "inflation on the 0 g trials only; exact: its own step error")
    con.print(f"wrote {out / 'bench.json'}, {out / 'bench.csv'}" + (f", {out / 'pareto.png'}" if fidelity_axis else "")
              + "".join(f", {out / n}" for n in written))
    if rep:
        from hbma_ctrl.app.bench.pages import sim_page

        con.print(f"wrote {rep.write(sim_page(rows, meta))}")


def bench_protocol(
    repeat: Annotated[int, typer.Option(help="timed runs per row (median reported)")] = 3,
    out: Annotated[Path, typer.Option("--out", "-o", help="output dir (bench.json)")] = Path("runs/bench_protocol"),
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
    report: ReportDir = None,
) -> None:
    """The main job as a user waits for it: `hbma-ctrl protocol` on its defaults in fresh interpreters,
    with and without its figures, the start-up alone and the simulation alone (bench.json)."""
    from hbma_ctrl.app.bench.protocol import TARGET_WALL_S, run_bench_protocol

    from hbma_ctrl.app.bench.report import open_report

    check_range("--repeat", repeat, 1, 100)
    rep = open_report(report, "protocol", cli_argv())  # --report checked before the run
    con = console(120)

    def show(name, row):
        con.print(f"  {name:45s} median {row['median_s']:6.2f} s  (min {row['min_s']:.2f}, max {row['max_s']:.2f})")

    with run_dir(out, command="bench protocol", argv=cli_argv(), overwrite=overwrite) as tmp:
        res = run_bench_protocol(tmp, repeat, on_row=show)
    con.print(f"protocol median {res['rows']['protocol']['median_s']:.2f} s against the target {TARGET_WALL_S:g} s: "
              f"{'met' if res['meets_target'] else 'not met'}; wrote {out / 'bench.json'}")
    if rep:
        from hbma_ctrl.app.bench.pages import protocol_page

        con.print(f"wrote {rep.write(protocol_page(res))}")


def _dt_text(row) -> str:
    if row.dt_ms is None:
        return f"default {row.dt_free_ms:g}/{row.dt_loaded_ms:g}"
    return f"{row.dt_ms:g}"


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``run``, ``protocol``, ``equilibrium`` and ``plots`` to the app, ``sim`` and ``protocol`` to the bench sub-app."""
    app.command("run")(run)
    app.command("protocol")(protocol)
    app.command("equilibrium")(equilibrium)
    app.command("plots")(plots)
    bench_app.command("sim")(bench_sim)
    bench_app.command("protocol")(bench_protocol)
