"""Command line: ``hbma-ctrl`` (typer). Parses, runs and reports; the work happens in the library.

Commands: ``run FILE``, ``protocol`` (also what a bare ``hbma-ctrl`` runs, with defaults),
``equilibrium``, ``plots``, ``bench sim``; the estimator, controller, robot, fit, tune and daemon
commands come from ``register(app, bench_app)`` in :mod:`hbma_ctrl.app.cli.estimators`,
:mod:`hbma_ctrl.app.cli.controllers`, :mod:`hbma_ctrl.app.cli.robot`, :mod:`hbma_ctrl.app.cli.fit`,
:mod:`hbma_ctrl.app.cli.tune` and :mod:`hbma_ctrl.app.cli.daemon`.

Bad input (ValueError, FileNotFoundError, usage errors) prints one line ``error: ...`` on stderr and
exits with code 2, never a traceback; a run whose trials all diverged does the same with code 1, and
so does any other failure of a run (a RuntimeError: a diverged plant, a solver's error; set
HBMA_CTRL_TRACEBACK=1 for its traceback). Ctrl-C prints ``interrupted: partial results in <path>`` and
exits with code 130. Every command writing a results directory goes through
:func:`hbma_ctrl.app.outputs.run_dir` (``--out`` checked before any work, ``--overwrite`` to replace a
run, manifest.json, nothing half-written left at ``--out``).

Start-up: importing this module (and the command modules it registers) loads only typer, rich and a
few light modules; each command imports what it needs when it runs, so that ``protocol`` does not
pay for the daemon, the tuner or the roles. An option default or choice list from a slow module is a
copy in :mod:`hbma_ctrl.app.cli.constants` (tests/test_cli.py checks both).
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.table import Table
from typer.core import TyperGroup

try:  # typer >= 0.24 vendors click as typer._click; older typer uses click itself
    from typer._click import exceptions as _cx
except ImportError:  # pragma: no cover
    from click import exceptions as _cx

# Only what registering the commands needs is imported here: each command imports its own heavy
# modules (casadi-built models, scipy, matplotlib, the roles, the daemon, optuna, ...) when it runs,
# so that `hbma-ctrl protocol` (the main job) and `--help` do not pay for the others.
from hbma_ctrl.app.cli.args import cap_workers
from hbma_ctrl.app.cli.codegen import register as register_codegen
from hbma_ctrl.app.cli.controllers import register as register_controllers
from hbma_ctrl.app.cli.daemon import register as register_daemon
from hbma_ctrl.app.cli.estimators import register as register_estimators
from hbma_ctrl.app.cli.fit import register as register_fit
from hbma_ctrl.app.cli.robot import register as register_robot
from hbma_ctrl.app.cli.tune import register as register_tune
from hbma_ctrl.app.outputs import (
    ARGV_KEY,
    OVERWRITE_HELP,
    cli_argv,
    default_out,
    run_dir,
)
from hbma_ctrl.core import units as U
from hbma_ctrl.core.validation import did_you_mean

__all__ = ["app", "bench_app"]


class _Interrupted(Exception):
    """Ctrl-C seen inside a command; not a KeyboardInterrupt, so typer does not swallow it as exit 130."""

    def __init__(self, partial):
        super().__init__(str(partial))
        self.partial = partial


class _OneLineErrors(TyperGroup):
    """Top-level group: bad input and usage errors become one 'error: ...' line and exit code 2."""

    def make_context(self, info_name, args, parent=None, **extra):
        argv = list(args)  # before parsing consumes them: manifest.json records the command line
        ctx = super().make_context(info_name, args, parent=parent, **extra)
        ctx.meta[ARGV_KEY] = argv
        return ctx

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt as exc:
            raise _Interrupted(getattr(exc, "partial", None)) from None

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        try:
            rv = super().main(args=args, prog_name=prog_name, complete_var=complete_var,
                              standalone_mode=False, **extra)
        except _cx.NoArgsIsHelpError:  # a group called bare: its help was printed, nothing failed
            sys.exit(0)
        except _cx.ClickException as exc:  # usage errors (exit code 2) and other CLI errors
            _fail(exc.format_message(), exc.exit_code)
        except typer.Abort:
            _fail("aborted", 1)
        except _Interrupted as exc:
            typer.echo(f"interrupted: partial results in {exc.partial}" if exc.partial else "interrupted", err=True)
            sys.exit(130)
        except (ValueError, FileNotFoundError) as exc:
            partial = getattr(exc, "partial_results", None)
            _fail(f"{exc}; partial results in {partial}" if partial else str(exc), 2)
        except RuntimeError as exc:
            partial = getattr(exc, "partial_results", None)
            if _is_run_failed(exc):  # the input was fine; the run failed (every trial diverged)
                msg = str(exc)
            elif os.environ.get("HBMA_CTRL_TRACEBACK"):
                # any other failed simulation (a diverged plant, a solver's error): one line, exit 1;
                # the traceback only when asked for (HBMA_CTRL_TRACEBACK=1), for a bug report
                raise
            else:
                msg = f"the run failed: {type(exc).__name__}: {exc}"
            _fail(f"{msg}; partial results in {partial}" if partial else msg, 1)
        code = rv if isinstance(rv, int) else 0
        if standalone_mode:
            sys.exit(code)
        return rv


def _is_run_failed(exc: BaseException) -> bool:
    """True for the runner's RunFailed (all trials diverged). Looked up, not imported: the runner pulls
    in every role, and a command that never imported it cannot have raised its error."""
    runner = sys.modules.get("hbma_ctrl.app.scenes.runner")
    return runner is not None and isinstance(exc, runner.RunFailed)


def _fail(message: str, code: int = 2):
    text = " ".join(str(message).split())  # one line
    typer.echo(f"error: {text}", err=True)
    sys.exit(code)


app = typer.Typer(cls=_OneLineErrors, add_completion=False, no_args_is_help=False, pretty_exceptions_enable=False,
                  help="Model, observe and control Hyperelastic Ballooning Membrane Actuators (HBMA). "
                       "Without a command: run the 150-trial protocol (README Model §7) with defaults into ./runs/protocol.")
bench_app = typer.Typer(add_completion=False, no_args_is_help=True, help="Benchmarks (speed and accuracy).")
app.add_typer(bench_app, name="bench")


def _console(min_width: int = 0) -> Console:
    con = Console(highlight=False)
    if not con.is_terminal and con.width < min_width:  # piped to a log file: do not squeeze tables
        con = Console(highlight=False, width=min_width)
    return con


def _choice(name: str, value: str, allowed) -> str:
    if value not in allowed:
        hint = did_you_mean(value, list(allowed))
        raise ValueError(f"{name} = '{value}'{hint}; allowed: {', '.join(allowed)}")
    return value


def _range(name: str, value: float | None, lo: float, hi: float, lo_open: bool = False, unit: str = ""):
    if value is None:
        return None
    ok = math.isfinite(value) and (value > lo if lo_open else value >= lo) and value <= hi
    if not ok:
        raise ValueError(f"{name} = {value:g} is out of range {'(' if lo_open else '['}{lo:g}, {hi:g}] {unit}".rstrip())
    return value


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


# ---------------------------------------------------------------------------------------------
@app.callback(invoke_without_command=True)
def _main(ctx: typer.Context) -> None:
    """Without a command: the main job, the default protocol into ./runs/protocol."""
    if ctx.invoked_subcommand is None:
        protocol()


@app.command()
def run(
    file: Annotated[Path, typer.Argument(help="scenario TOML file")],
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="output directory (default runs/<name>)")] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
) -> None:
    """Run a scenario file: writes metrics.json, the log CSV(s), plots and manifest.json into --out."""
    from hbma_ctrl.app.scenario import load_scenario

    scn = load_scenario(file)
    out_dir = out or default_out(scn.name)
    t0 = time.perf_counter()
    with run_dir(out_dir, command="run", argv=cli_argv(), scenario_path=file, overwrite=overwrite) as tmp:
        metrics = run_scenario(scn, tmp)
    con = _console()
    table = Table(title=f"{scn.name} ({scn.kind}) -> {out_dir}", show_header=True)
    table.add_column("role")
    table.add_column("metric")
    table.add_column("value", justify="right")
    for role, vals in metrics.items():
        if role == "scenario" or not isinstance(vals, dict):
            continue
        for k, v in vals.items():
            table.add_row(role, k, _fmt(v))
    con.print(table)
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


@app.command()
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
    """Simulate the 150-trial characterisation protocol (README Model §7): DIR/summary.csv, DIR/trials/*.csv, fig6/7/9 PNGs."""
    from hbma_ctrl.core.materials import MATERIALS
    from hbma_ctrl.sim.batch import FIDELITY_CHOICES
    from hbma_ctrl.sim.trial import INTEGRATORS

    _choice("--material", material, MATERIALS)
    _choice("--integrator", integrator, INTEGRATORS)
    _choice("--fidelity", fidelity, [f for f in FIDELITY_CHOICES if f != "free"])
    _range("--workers", workers, 1, 256)
    workers = cap_workers("--workers", workers)
    _range("--dt-ms", dt_ms, 0.0, 100.0, lo_open=True, unit="ms")
    _range("--duration-s", duration_s, 0.0, 3600.0, lo_open=True, unit="s")
    _range("--t-inflate-s", t_inflate_s, 0.0, duration_s, lo_open=True, unit="s")
    if t_inflate_s >= duration_s:
        raise ValueError(f"--t-inflate-s = {t_inflate_s:g} must be below --duration-s = {duration_s:g}")
    con = _console()
    t0 = time.perf_counter()
    with run_dir(out, command="protocol", argv=cli_argv(), overwrite=overwrite) as tmp:
        rows = run_protocol(material, tmp, integrator, None if dt_ms is None else U.ms(dt_ms), fidelity, workers,
                            t_inflate_s=t_inflate_s, duration_s=duration_s, plots=not no_plots, progress=True)
    wall = time.perf_counter() - t0
    counts: dict = {}
    for r in rows:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    table = Table(title=f"protocol ({material}, {integrator}, fidelity {fidelity})")
    for c in ("trials", "status", "max height (mm)", "max pressure (kPa)", "wall (s)"):
        table.add_column(c, justify="right")
    table.add_row(str(len(rows)), ", ".join(f"{k} {v}" for k, v in counts.items()),
                  f"{max(r['max_height_mm'] for r in rows):.2f}", f"{max(r['max_pressure_kpa'] for r in rows):.2f}",
                  f"{wall:.1f}")
    con.print(table)
    con.print(f"wrote {out / 'summary.csv'}, {out / 'trials'}/*.csv" + ("" if no_plots else ", fig6/fig7/fig9.png"))


def _parse_params(items: list[str]) -> dict:
    out = {}
    for item in items:
        if "=" not in item:
            raise ValueError(f"--param '{item}': expected NAME=VALUE (SI), e.g. E=130.6e3 or C=2e4,-200,10")
        name, val = item.split("=", 1)
        try:
            nums = [float(x) for x in val.split(",")]
        except ValueError:
            raise ValueError(f"--param {name}: '{val}' is not a number (or comma-separated numbers)") from None
        out[name.strip()] = nums[0] if len(nums) == 1 else tuple(nums)
    return out


def equilibrium_values(material: str, r1_mm: float, t0_mm: float, h1_mm: float, h2_mm: float,
                       params: dict | None = None, V0_cm3: float = 3.0, fidelity: str = "cap",
                       contact: str = "flat", disk_radius_mm: float = 2.0,
                       p_kpa: float | None = None) -> dict:
    """Equilibrium of one shape (edge units in and out): pressure, force, load, stretch, volume.

    ``fidelity`` 'cap' (spherical cap, README Model) or 'exact' (:mod:`hbma_ctrl.models.exact`: the
    centre height h = h1 - h2 held by a flat plate or a bonded disk of radius ``disk_radius_mm`` at
    gauge pressure ``p_kpa``; free inflation when h2 = 0 with a flat contact).
    """
    import numpy as np

    from hbma_ctrl.app.plots import equilibrium_grid
    from hbma_ctrl.core.materials import MATERIALS, make_material

    _range("--r1-mm", r1_mm, 0.5, 100.0, lo_open=True, unit="mm")
    _range("--t0-mm", t0_mm, 0.05, 20.0, lo_open=True, unit="mm")
    _range("--V0-cm3", V0_cm3, 0.001, 1000.0, unit="cm^3")
    _range("--h1-mm", h1_mm, 0.0, 20 * r1_mm, unit="mm")
    if not (math.isfinite(h2_mm) and 0.0 <= h2_mm <= h1_mm):
        raise ValueError(f"--h2-mm = {h2_mm:g} is out of range [0, h1-mm = {h1_mm:g}] mm (need 0 <= h2 <= h1)")
    _choice("--material", material, MATERIALS)
    try:
        mat = make_material(material, **(params or {}))
    except ValueError as exc:  # the parameters are the only thing left that can be wrong: say so
        raise ValueError(f"--param {', '.join(params or {})}: {exc}") from None
    _choice("--fidelity", fidelity, ["cap", "exact"])
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
    return {
        "material": mat.name,
        "params_si": {k: (list(v) if isinstance(v, tuple) else v) for k, v in mat.as_dict().items()},
        "r1_mm": r1_mm, "t0_mm": t0_mm, "V0_cm3": V0_cm3, "h1_mm": h1_mm, "h2_mm": h2_mm,
        "h_mm": h1_mm - h2_mm,
        "pressure_kpa": U.to_kpa(res["p"]),
        "force_n": res["F"],
        "load_g": U.to_grams(res["F"] / U.G_STD),
        "stretch": res["lam"],
        "volume_cm3": U.to_cm3(res["V"]),
        "contact_radius_mm": U.to_mm(math.sqrt(max(res["a2"], 0.0))),
    }


# the exact module names its arguments as it knows them; the CLI names the flags the user wrote
_EXACT_ARG_FLAGS = (("h = ", "--h1-mm/--h2-mm: h = "), ("p = ", "--p-kpa: p = "), ("c = ", "--disk-radius-mm: c = "))


def _exact_equilibrium_values(mat, r1_mm: float, t0_mm: float, h1_mm: float, h2_mm: float, V0_cm3: float,
                              contact: str, disk_radius_mm: float, p_kpa: float | None) -> dict:
    """``equilibrium --fidelity exact``: the exact membrane's equilibrium in edge units."""
    from hbma_ctrl.models.exact import equilibrium as exact_equilibrium

    _choice("--contact", contact, ["flat", "bonded"])
    if contact == "bonded":
        if not (math.isfinite(disk_radius_mm) and 0.0 < disk_radius_mm < r1_mm):
            raise ValueError(f"--disk-radius-mm = {disk_radius_mm:g} is out of range (0, {r1_mm:g}) mm "
                             "(inside the retaining radius)")
    free = h2_mm == 0 and contact == "flat"
    if free and p_kpa is not None:
        raise ValueError("--p-kpa: free inflation (--h2-mm 0, flat contact) has its pressure set by the height; "
                         "give --h2-mm > 0 or --contact bonded to hold the centre at a pressure")
    if not free and p_kpa is None:
        raise ValueError("--p-kpa is required with a contact (--h2-mm > 0 or --contact bonded): "
                         "the gauge pressure, kPa, in (0, 1000]")
    _range("--p-kpa", p_kpa, 0.0, 1000.0, lo_open=True, unit="kPa")
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
    return {
        "material": mat.name,
        "params_si": {k: (list(v) if isinstance(v, tuple) else v) for k, v in mat.as_dict().items()},
        "r1_mm": r1_mm, "t0_mm": t0_mm, "V0_cm3": V0_cm3, "h1_mm": h1_mm, "h2_mm": h2_mm,
        "h_mm": h_mm,
        "fidelity": "exact", "contact": contact,
        "pressure_kpa": U.to_kpa(res["p"]),
        "force_n": res["F"],
        "load_g": U.to_grams(res["F"] / U.G_STD),
        "stretch": res["stretch"],
        "volume_cm3": U.to_cm3(res["V"]),
        "contact_radius_mm": U.to_mm(res["contact_radius"]),
    }


@app.command()
def equilibrium(
    h1_mm: Annotated[float, typer.Option("--h1-mm", help="virtual cap height h1, mm")],
    h2_mm: Annotated[float, typer.Option("--h2-mm", help="cut height h2 (contact), mm; 0 = free")] = 0.0,
    material: Annotated[str, typer.Option(help="nh | mr | yeoh | gent | ogden")] = "nh",
    r1_mm: Annotated[float, typer.Option("--r1-mm", help="retaining radius r1, mm")] = 7.5,
    t0_mm: Annotated[float, typer.Option("--t0-mm", help="membrane thickness t0, mm")] = 3.0,
    V0_cm3: Annotated[float, typer.Option("--V0-cm3", help="dead volume, cm^3")] = 3.0,
    param: Annotated[Optional[list[str]], typer.Option("--param", help="material parameter NAME=VALUE (SI), repeatable")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="print one JSON object")] = False,
    fidelity: Annotated[str, typer.Option(help="cap | exact")] = "cap",
    contact: Annotated[str, typer.Option(help="flat | bonded (exact only)")] = "flat",
    disk_radius_mm: Annotated[float, typer.Option("--disk-radius-mm", help="bonded disk radius c, mm")] = 2.0,
    p_kpa: Annotated[Optional[float], typer.Option("--p-kpa", help="gauge pressure, kPa (exact contact)")] = None,
) -> None:
    """Equilibrium pressure, contact force (and load F/g), stretch and volume of one shape (h1, h2).

    ``--fidelity exact``: the exact axisymmetric membrane; h = h1 - h2 is the centre height, free
    inflation for --h2-mm 0 (flat), otherwise a flat plate or a bonded disk at --p-kpa.
    """
    res = equilibrium_values(material, r1_mm, t0_mm, h1_mm, h2_mm, _parse_params(param or []), V0_cm3,
                             fidelity, contact, disk_radius_mm, p_kpa)
    if as_json:
        typer.echo(json.dumps(res))
        return
    table = Table(title=f"{res['material']}: r1 {r1_mm:g}, t0 {t0_mm:g}, h1 {h1_mm:g}, h2 {h2_mm:g} mm",
                  show_header=False)
    table.add_column("quantity")
    table.add_column("value", justify="right")
    for key, label in (("h_mm", "height h (mm)"), ("pressure_kpa", "pressure (kPa)"), ("force_n", "force (N)"),
                       ("load_g", "load F/g (g)"), ("stretch", "stretch lambda"), ("volume_cm3", "volume (cm^3)"),
                       ("contact_radius_mm", "contact radius a (mm)")):
        table.add_row(label, f"{res[key]:.4f}")
    _console().print(table)


@app.command()
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

    _choice("--material", material, MATERIALS)
    _choice("--fidelity", fidelity, [f for f in FIDELITY_CHOICES if f != "free"])
    with run_dir(out, command="plots", argv=cli_argv(), overwrite=overwrite) as tmp:
        paths = paper_figures(tmp, material, fidelity=fidelity)
    _console().print("wrote " + ", ".join(str(out / Path(p).name) for p in paths))


def _role_benches(out: Path, con) -> list:
    """``bench ekf`` and ``bench mpc`` on their defaults into ``out`` (bench_ekf.json, bench_mpc.json, as
    those commands write them); their Pareto points for :func:`bench_sim`."""
    import json

    from hbma_ctrl.app.bench import plots as bench_plots
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
    return [(bench_plots.estimator_points(out / "bench_ekf.json"), "pareto_estimator.png",
             ("median filter step (us)", "height NRMSD")),
            (bench_plots.controller_points(out / "bench_mpc.json"), "pareto_controller.png",
             ("median solve time (ms)", "height RMSE (mm)"))]


@bench_app.command("sim")
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
) -> None:
    """Simulator speed/accuracy: integrator x step x fidelity over the protocol vs a Radau reference, and
    (fidelity axis) vs the exact membrane, with a Pareto plot (wall time vs NRMSD) beside bench.json."""
    from hbma_ctrl.app.bench.sim import TARGET_NRMSD, TARGET_WALL_S, run_bench
    from hbma_ctrl.core.materials import MATERIALS

    _choice("--material", material, MATERIALS)
    _range("--workers", workers, 1, 256)
    workers = cap_workers("--workers", workers)
    _range("--repeat", repeat, 1, 100)
    from hbma_ctrl.app.bench import plots as bench_plots

    if roles and (ekf_json is not None or mpc_json is not None):
        _fail("--roles runs the estimator and controller benches itself: leave out --ekf-json and --mpc-json")
    # read before the long run: a bad file is one error line now
    role_plots = []
    for path, read, name, axes in (
            (ekf_json, bench_plots.estimator_points, "pareto_estimator.png", ("median filter step (us)", "height NRMSD")),
            (mpc_json, bench_plots.controller_points, "pareto_controller.png", ("median solve time (ms)",
                                                                                 "height RMSE (mm)"))):
        if path is not None:
            try:
                role_plots.append((read(path), name, axes))
            except ValueError as e:
                _fail(str(e))
    con = _console(160)

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
    table = Table(title=f"bench sim: {rows[0].n_trials if rows else 0} trials, workers {workers}, "
                        f"median of {repeat}; target wall <= {TARGET_WALL_S:g} s, max NRMSD <= {TARGET_NRMSD:g}")
    for c in ("loaded fidelity", "integrator", "dt (ms)", "wall (s)", "cpu (s)", "diverged", "h NRMSD mean", "h NRMSD max",
              "p NRMSD mean", "p NRMSD max", "target") + (("h vs exact", "p vs exact") if fidelity_axis else ()):
        table.add_column(c, justify="right", no_wrap=True)
    for r in rows:
        extra = ((f"{r.height_nrmsd_vs_exact_mean:.2e}", f"{r.pressure_nrmsd_vs_exact_mean:.2e}")
                 if fidelity_axis else ())
        table.add_row(r.fidelity + (" (0 g)" if r.fidelity == "free" else ""), r.integrator,
                      _dt_text(r) + (" *" if r.default else ""), f"{r.wall_s:.2f}",
                      f"{r.cpu_s:.2f}", str(r.n_diverged), f"{r.height_nrmsd_mean:.2e}", f"{r.height_nrmsd_max:.2e}",
                      f"{r.pressure_nrmsd_mean:.2e}", f"{r.pressure_nrmsd_max:.2e}", "yes" if r.meets_target else "no",
                      *extra)
    con.print(table)
    con.print("* the setting `hbma-ctrl protocol` uses by default (fidelity auto: free for 0 g, quasi_static loaded)")
    if fidelity_axis:
        con.print("vs exact: mean NRMSD against the exact membrane (rk4, fine step); free (0 g): the cap's free "
                  "inflation on the 0 g trials only; exact: its own step error")
    con.print(f"wrote {out / 'bench.json'}, {out / 'bench.csv'}" + (f", {out / 'pareto.png'}" if fidelity_axis else "")
              + "".join(f", {out / n}" for n in written))


@bench_app.command("protocol")
def bench_protocol(
    repeat: Annotated[int, typer.Option(help="timed runs per row (median reported)")] = 3,
    out: Annotated[Path, typer.Option("--out", "-o", help="output dir (bench.json)")] = Path("runs/bench_protocol"),
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
) -> None:
    """The main job as a user waits for it: `hbma-ctrl protocol` on its defaults in fresh interpreters,
    with and without its figures, the start-up alone and the simulation alone (bench.json)."""
    from hbma_ctrl.app.bench.protocol import TARGET_WALL_S, run_bench_protocol

    _range("--repeat", repeat, 1, 100)
    con = _console(120)

    def show(name, row):
        con.print(f"  {name:45s} median {row['median_s']:6.2f} s  (min {row['min_s']:.2f}, max {row['max_s']:.2f})")

    with run_dir(out, command="bench protocol", argv=cli_argv(), overwrite=overwrite) as tmp:
        res = run_bench_protocol(tmp, repeat, on_row=show)
    con.print(f"protocol median {res['rows']['protocol']['median_s']:.2f} s against the target {TARGET_WALL_S:g} s: "
              f"{'met' if res['meets_target'] else 'not met'}; wrote {out / 'bench.json'}")


def _dt_text(row) -> str:
    if row.dt_ms is None:
        return f"default {row.dt_free_ms:g}/{row.dt_loaded_ms:g}"
    return f"{row.dt_ms:g}"


for _register in (register_estimators, register_controllers, register_robot, register_fit, register_tune,
                  register_daemon, register_codegen):
    _register(app, bench_app)
