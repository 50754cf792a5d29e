"""``hbma-ctrl fit DATA.csv``: fit the model to static equilibrium data or to a recorded run.

A file with a ``t_s`` column is a recorded run (:mod:`hbma_ctrl.app.tuning.fit_dynamic`: modulus, dead
volume, compressor-map scale and outlet conductance); otherwise static equilibrium points
(:mod:`hbma_ctrl.app.tuning.fit`: the material parameters).

Registered by :mod:`hbma_ctrl.app.cli.main` through :func:`register`. Edge units (mm, kPa, g) here; the
fit (:mod:`hbma_ctrl.app.tuning.fit`) works in SI. Writes ``fit.json``, ``params.toml`` and
``residuals.png`` into ``--out`` through :func:`hbma_ctrl.app.outputs.run_dir`, and with
``--write-scenario FILE`` the fitted values into a scenario file
(:func:`hbma_ctrl.app.tuning.fit_output.write_scenario`). A recorded run's fit shows its progress and
the time left on stderr: a bar on a terminal, else a line every 10 s. Bad input raises
ValueError, which the top-level CLI prints as one ``error: ...`` line with exit code 2.
"""

from __future__ import annotations

import hashlib
import json
import sys
import time
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console

# the fits (scipy.optimize, scipy.stats, matplotlib, the models) are imported by the command when it runs
from hbma_ctrl.app.cli.args import ReportDir, assignments, cap_workers, check_range, show_table
from hbma_ctrl.app.cli.constants import CHAMBER_R1_MM, CHAMBER_T0_MM, MAX_REPLAY_S
from hbma_ctrl.app.outputs import OVERWRITE_HELP, check_out, cli_argv, run_dir
from hbma_ctrl.core import units as U
from hbma_ctrl.models.actuation import DELAY_MAX
from hbma_ctrl.models.defaults import DEFAULT_SENSOR_DELAY, DEFAULT_VALVE_DELAY

__all__ = ["register", "fit_cmd"]


def fit_cmd(
    data: Annotated[Path, typer.Argument(help="CSV: static (h_mm, p_kpa[, F_n|load_g]) or a recorded run (t_s, "
                                              "p_kpa, speed, inlet, outlet[, h_mm, load_g]); or the daemon's run "
                                              "log (run_0001.csv, or its run directory)")],
    material: Annotated[str, typer.Option(help="nh | mr | yeoh | gent | ogden")] = "nh",
    r1_mm: Annotated[float, typer.Option("--r1-mm", help="clamp radius r1, mm")] = CHAMBER_R1_MM,
    t0_mm: Annotated[float, typer.Option("--t0-mm", help="membrane thickness t0, mm")] = CHAMBER_T0_MM,
    contact: Annotated[Optional[str], typer.Option(
        help="free (h2 = 0) | flat (load on a plate) | bonded (a rigid disk glued at the centre, lifting the load: "
             "static points, nh or gent and the exact law; give --disk-radius-mm); default: flat with a force column, "
             "else free")] = None,
    disk_radius_mm: Annotated[Optional[float], typer.Option(
        "--disk-radius-mm", help="--contact bonded: the glued disk's radius c, mm, in (0, --r1-mm)")] = None,
    fidelity: Annotated[Optional[str], typer.Option(
        help="membrane law: exact (the axisymmetric membrane, docs/concepts/model.md §9: the rig's and the roles' default; "
             "on a plate or with --fit-material nh only, free points of any material) | cap (the spherical cap, "
             "Model §1-§3); default: exact where it can fit, else cap")] = None,
    fix: Annotated[Optional[list[str]], typer.Option("--fix", help="hold a parameter NAME=VALUE (SI), repeatable")]
    = None,
    keep_beyond_reach: Annotated[bool, typer.Option(
        "--keep-beyond-reach", help="--contact bonded: keep rows beyond the exact membrane's reach at the fit (their "
                                    "pressure continued past its table; counted in a note) instead of refusing the "
                                    "first")] = False,
    v0_cm3: Annotated[Optional[float], typer.Option(
        "--v0-cm3", help="recorded run: nominal dead volume (the start), cm^3 (default 3)")] = None,
    load_g: Annotated[Optional[float], typer.Option(
        "--load-g", help="recorded run without a load_g column: the load it carried, g (default 0)")] = None,
    sensor_range_kpa: Annotated[Optional[float], typer.Option(
        "--sensor-range-kpa", help="recorded run: readings at this pressure are saturated and left out, kPa "
                                   "(default 35)")] = None,
    fit_material: Annotated[bool, typer.Option(
        "--fit-material", help="recorded run: fit the material's parameters instead of one modulus scale")] = False,
    valve_delay_ms: Annotated[Optional[float], typer.Option(
        "--valve-delay-ms", help="recorded run: the valves act this long after their command, ms (default: the "
                                 f"roles', {DEFAULT_VALVE_DELAY * 1e3:g}; 0 = at once)")] = None,
    sensor_delay_ms: Annotated[Optional[float], typer.Option(
        "--sensor-delay-ms", help="recorded run: the sensor reads the chamber this long late, ms (default: the "
                                  f"roles', {DEFAULT_SENSOR_DELAY * 1e3:g})")] = None,
    no_height: Annotated[bool, typer.Option(
        "--no-height", help="recorded run: fit the pressure only, even with a height column")] = False,
    chamber: Annotated[Optional[str], typer.Option(
        "--chamber", help="the daemon's run log: the chamber to fit, by name (default: its only one)")] = None,
    max_replay_s: Annotated[float, typer.Option(
        "--max-replay-s", help="recorded run: the longest run replayed, s of rig time (the fit's time grows "
                               "with it)")] = MAX_REPLAY_S,
    write_scenario: Annotated[Optional[Path], typer.Option(
        "--write-scenario", help="put the fitted values into this scenario file (each key replaced, the file's "
                                 "comments not kept; created with the fitted tables alone when missing)")] = None,
    out: Annotated[Path, typer.Option("--out", "-o", help="directory for fit.json, params.toml, residuals.png")]
    = Path("runs/fit"),
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
) -> None:
    """Fit the model to static equilibrium points (material) or a recorded run (material scale, dead
    volume, pump and outlet)."""
    from hbma_ctrl.app.tuning.fit import check_disk_radius, check_options, fit_static, parse_data, resolve_fidelity
    from hbma_ctrl.app.tuning.fit_output import write_fit, write_scenario as put_in_scenario
    from hbma_ctrl.app.tuning.fit_dynamic import fit_dynamic, is_dynamic, parse_run, write_dynamic_fit

    check_range("--r1-mm", r1_mm, 0.5, 100.0, lo_open=True, unit="mm")
    check_range("--t0-mm", t0_mm, 0.05, 20.0, lo_open=True, unit="mm")
    check_range("--v0-cm3", v0_cm3, 0.001, 1000.0, lo_open=True, unit="cm^3")
    check_range("--sensor-range-kpa", sensor_range_kpa, 1.0, 1000.0, lo_open=True, unit="kPa")
    check_range("--load-g", load_g, 0.0, 50000.0, unit="g")
    check_range("--valve-delay-ms", valve_delay_ms, 0.0, U.to_ms(DELAY_MAX), unit="ms")
    check_range("--sensor-delay-ms", sensor_delay_ms, 0.0, U.to_ms(DELAY_MAX), unit="ms")
    check_range("--max-replay-s", max_replay_s, 0.0, 1e6, lo_open=True, unit="s")
    if write_scenario is not None and write_scenario.is_dir():
        raise ValueError(f"--write-scenario {write_scenario}: is a folder; give a scenario file (.toml)")
    check_options(material.lower(), contact, fidelity)
    disk_radius = None if disk_radius_mm is None else U.mm(disk_radius_mm)
    check_disk_radius(contact, disk_radius, U.mm(r1_mm))
    if keep_beyond_reach and contact != "bonded":
        raise ValueError("--keep-beyond-reach: only with --contact bonded")
    if contact == "bonded" and write_scenario is not None:
        raise ValueError("--write-scenario: a scenario's chamber has no glued disk (its roles model free inflation "
                         "or a loose plate), so a bonded fit has no place there; the fitted modulus is in params.toml "
                         "([actuator.material_params]) for a scenario whose chamber is made of this membrane")
    fixed = assignments(fix or [], "--fix", "C2=0 or Jm=60", one=True)
    check_out(out, overwrite)  # before the fit: a bad --out costs nothing
    raw, data = _read_data(data)
    source = f"{data.resolve()}, sha256 {hashlib.sha256(raw).hexdigest()[:16]}"
    if is_dynamic(raw):
        fidelity, law_note = resolve_fidelity(fidelity, material.lower(), needs_tables=fit_material)
        run = parse_run(raw, None if load_g is None else U.grams(load_g), chamber=chamber)
        with _progress() as bar:
            dres = fit_dynamic(run, material.lower(), U.mm(r1_mm), U.mm(t0_mm),
                               V0=U.cm3(3.0 if v0_cm3 is None else v0_cm3), fix=fixed, fit_material=fit_material,
                               sensor_range=U.kpa(35.0 if sensor_range_kpa is None else sensor_range_kpa),
                               use_height=not no_height, fidelity=fidelity, contact=contact, source=source,
                               valve_delay=DEFAULT_VALVE_DELAY if valve_delay_ms is None else U.ms(valve_delay_ms),
                               sensor_delay=DEFAULT_SENSOR_DELAY if sensor_delay_ms is None else U.ms(sensor_delay_ms),
                               max_replay=max_replay_s, progress=bar)
        with run_dir(out, command="fit", argv=cli_argv(), overwrite=overwrite) as tmp:
            write_dynamic_fit(dres, tmp)
        notes = put_in_scenario(write_scenario, dres, fidelity, source) if write_scenario is not None else []
        hn = f", height NRMSD {dres.nrmsd_h:.4f}" if dres.nrmsd_h is not None else ""
        _print(f"fit {dres.material} to a run: {dres.n_points} points, {dres.fidelity} model, "
               f"pressure NRMSD {dres.nrmsd:.4f}{hn}", dres.params, dres.ci95, dres.fixed,
               dres.notes() + ([law_note] if law_note else []) + notes, out, write_scenario)
        return
    for flag, given in (("--load-g", load_g is not None), ("--fit-material", fit_material), ("--no-height", no_height),
                        ("--v0-cm3", v0_cm3 is not None), ("--sensor-range-kpa", sensor_range_kpa is not None),
                        ("--valve-delay-ms", valve_delay_ms is not None), ("--chamber", chamber is not None),
                        ("--sensor-delay-ms", sensor_delay_ms is not None)):
        if given:
            raise ValueError(f"{flag}: only for a recorded run (a t_s column); {data.name} holds static points")
    pts = parse_data(raw)
    # a bonded fit has its own tables per material (fit_bonded), not the exact law's one shape
    on_plate = contact == "flat" or (contact is None and pts.F is not None)
    fidelity, law_note = resolve_fidelity(fidelity, material.lower(), needs_tables=on_plate)
    res = fit_static(pts, material.lower(), U.mm(r1_mm), U.mm(t0_mm), contact=contact, fix=fixed,
                     fidelity=fidelity, disk_radius=disk_radius, keep_beyond=keep_beyond_reach)
    res.source = source
    with run_dir(out, command="fit", argv=cli_argv(), overwrite=overwrite) as tmp:
        write_fit(res, tmp)
    notes = put_in_scenario(write_scenario, res, fidelity, source) if write_scenario is not None else []
    disk = "" if res.disk_radius is None else f" (disk {U.to_mm(res.disk_radius):g} mm)"
    _print(f"fit {res.material}: {res.n_points} points, {res.contact} contact{disk}, {res.fidelity} law, "
           f"NRMSD {res.nrmsd:.4f}", res.params, res.ci95, res.fixed,
           res.unidentifiable + res.notes + ([law_note] if law_note else []) + notes, out, write_scenario)


def _read_data(data: Path) -> tuple[bytes, Path]:
    """The data file's bytes and the file read: a daemon's run directory reads its run log, every part
    (header once); FileNotFoundError naming DATA otherwise."""
    if data.is_dir():
        from hbma_ctrl.app.daemon.runlog import read_run_log

        try:
            header, rows = read_run_log(data)
        except FileNotFoundError:
            raise FileNotFoundError(f"data {data}: is a folder without a daemon run log (run_*.csv); give a "
                                    "CSV file") from None
        lines = [",".join(header)] + [",".join(r) for r in rows]
        return ("\n".join(lines) + "\n").encode(), data / "run_0001.csv"
    if not data.is_file():
        raise FileNotFoundError(f"data file {data} not found")
    return data.read_bytes(), data


class _progress:
    """The fit's replays and the time left, on stderr: a progress bar when it is a terminal, else (a log
    file, a batch job) one line every :attr:`PLAIN_EVERY_S` seconds; called as ``bar(done, total)``."""

    #: seconds between two plain progress lines
    PLAIN_EVERY_S = 10.0
    #: the clock of the plain lines (s); replaceable in tests
    clock = staticmethod(time.monotonic)

    def __enter__(self):
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

        self.plain = not sys.stderr.isatty()
        self.bar = Progress(TextColumn("fit: replays (at most)"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                            TimeElapsedColumn(), TextColumn("left at most"), TimeRemainingColumn(),
                            console=Console(stderr=True), transient=True, disable=self.plain)
        self.bar.start()
        self.task = self.bar.add_task("fit", total=None)
        self.t0 = self.last = self.clock()
        return self

    def __call__(self, done: int, total: int) -> None:
        self.bar.update(self.task, completed=done, total=total)
        now = self.clock()
        if self.plain and 0 < done < total and now - self.last >= self.PLAIN_EVERY_S:
            self.last = now
            spent = now - self.t0
            print(f"fit: {done}/{total} replays (at most), {spent:.0f} s, at most {spent / done * (total - done):.0f} s "
                  "left", file=sys.stderr, flush=True)

    def __exit__(self, *exc) -> None:
        self.bar.stop()


def _print(title: str, params: dict, ci95: dict, fixed: dict, notes: list, out: Path,
           scenario: Path | None = None) -> None:
    rows = [(k, f"{v:.5g}", "fixed" if k in fixed else (f"[{ci95[k][0]:.4g}, {ci95[k][1]:.4g}]"
                                                          if ci95[k][0] is not None else "n/a (no dof)"))
            for k, v in params.items()]
    con = show_table(title, ("parameter", "value (SI)", "95 % interval"), rows, Console(highlight=False))
    for s in notes:
        con.print(f"note: {s}", markup=False)
    con.print(f"wrote {out / 'fit.json'}, {out / 'params.toml'}, {out / 'residuals.png'}"
              + (f", {scenario}" if scenario is not None else ""))


def bench_fit_cmd(
    seeds: Annotated[int, typer.Option(help="rig noise seeds of the recorded runs, 0..seeds-1 (1-100)")] = 8,
    workers: Annotated[int, typer.Option(help="parallel processes (1-64)")] = 2,
    out: Annotated[Path, typer.Option("--out", "-o", help="output dir for bench_fit.json")] = Path("runs/bench_fit"),
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
    report: ReportDir = None,
) -> None:
    """The fit's membrane law against truths it is not: the exact solver's static points and pump /
    hold / vent runs of the cap, exact and default rigs, each fitted with the cap's and the exact law."""
    from hbma_ctrl.app.bench.fit import run_rows, static_rows, summarize_runs, write_fit_bench

    check_range("--seeds", seeds, 1, 100)
    workers = cap_workers("--workers", workers, 64)
    from hbma_ctrl.app.bench.report import open_report

    rep = open_report(report, "fit", cli_argv())  # --report checked before the run
    con = Console(highlight=False, width=140)
    with run_dir(out, command="bench fit", argv=cli_argv(), overwrite=overwrite) as tmp:
        static = static_rows(progress=lambda r: con.print(f"  static {r['case']}, {r['law']} law: worst miss "
                                                          f"{100 * r['worst_rel_miss']:.2g} % ({r['wall_s']:.0f} s)"))
        runs = run_rows(list(range(seeds)), workers=workers,
                        progress=lambda rows: con.print(f"  {rows[0]['rig']} rig, seed {rows[0]['seed']}: " + ", ".join(
                            f"{r['law']} {r['params']['modulus_scale']:.4f}" for r in rows)))
        written = write_fit_bench(static, runs, tmp, seeds)
        doc = json.loads(written.read_text())
    cells = {(r["case"], r["law"]): f"{100 * r['worst_rel_miss']:.3g} %, {r['nrmsd']:.2g}"
             + (", undetermined" if r["unidentifiable"] else "") for r in static}
    show_table("static points of the exact solver: the largest miss of a parameter (found / truth - 1), NRMSD, "
               "undetermined", ("data", "cap law", "exact law"),
               [(case, cells[case, "cap"], cells[case, "exact"]) for case in dict.fromkeys(r["case"] for r in static)],
               con)
    show_table(f"pump / hold / vent runs, {seeds} rig noise seeds (truth: modulus x1.15, pump x0.9, dead volume "
               "x1.2): the range over the seeds",
               ("rig / law", "modulus_scale", "V0 (cm^3)", "flow_scale", "C_out (1e-10)", "NRMSD", "structured"),
               [(key, *(f"{v[k][0]:.4f}-{v[k][1]:.4f}" for k in ("modulus_scale", "V0_cm3", "flow_scale", "C_out_1e10",
                                                                   "nrmsd")), f"{v['structured']}/{v['runs']}")
                for key, v in summarize_runs(runs).items()], con)
    con.print(f"wrote {out / written.name}")
    if rep:
        from hbma_ctrl.app.bench.pages import fit_page

        con.print(f"wrote {rep.write(fit_page(doc))}")


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add the ``fit`` command to the top-level CLI and ``bench fit`` under ``bench``."""
    app.command("fit")(fit_cmd)
    bench_app.command("fit")(bench_fit_cmd)
