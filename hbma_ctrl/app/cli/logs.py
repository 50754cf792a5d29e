"""``hbma-ctrl report RUN_DIR`` (the figures of a run), ``hbma-ctrl export RUN_DIR`` (its log as tables)
and ``hbma-ctrl bench log`` (what the MCAP log costs the daemon's loop).

Registered by :mod:`hbma_ctrl.app.cli.main` through :func:`register`.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Annotated, Optional

import typer

from hbma_ctrl.app.cli.args import ReportDir, check_choice, check_range, finish_bench
from hbma_ctrl.app.outputs import OVERWRITE_HELP, WRITTEN_LIST, cli_argv

__all__ = ["register", "report", "export", "bench_log"]


def _out_dir(out: Path) -> Path:
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: not a directory")
    return out


def _written_aside(out: Path, explicit: bool, command: str, make) -> list[Path]:
    """Run ``make(folder)`` (it writes files into ``folder``, returns them) in a temporary folder beside
    ``out``, then move its files into ``out``. A file already in ``out`` that an earlier ``command``
    did not write there (:data:`WRITTEN_LIST`) is a user's own: with an explicit ``--out`` it is
    never replaced (ValueError naming ``--out``, nothing moved); ``RUN_DIR/<default>`` is the
    command's own folder."""
    _out_dir(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    listed = out / WRITTEN_LIST
    known = set(listed.read_text(errors="replace").splitlines()) if listed.is_file() else set()
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        made = make(tmp)
        names = [f.relative_to(tmp).as_posix() for f in made]
        if explicit:
            clash = [n for n in names if (out / n).exists() and n not in known]
            if clash:
                more = f" and {len(clash) - 1} more" if len(clash) > 1 else ""
                raise ValueError(f"--out {out}: holds '{clash[0]}'{more}, which {command} did not write; it would be "
                                 "replaced: choose a new or empty folder")
        out.mkdir(parents=True, exist_ok=True)
        for n in names:
            (out / n).parent.mkdir(parents=True, exist_ok=True)
            os.replace(tmp / n, out / n)
        listed.write_text("".join(f"{n}\n" for n in sorted(known | set(names))))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return [out / n for n in names]


def report(
    run_dir: Annotated[Path, typer.Argument(help="a run's results directory (hbma-ctrl run or hbma-ctrl daemon)")],
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="folder for the figures (default "
                                                                    "RUN_DIR/figures)")] = None,
) -> None:
    """Draw the figures of a run from its log (log.mcap, else its CSVs): heights, pressures, commands,
    estimator errors, faults and events, the robot's pose; each as PNG and PDF."""
    from hbma_ctrl.app.report.figures import report as make

    files = _written_aside(out or run_dir / "figures", out is not None, "report", lambda folder: make(run_dir, folder))
    for f in files:
        typer.echo(str(f))


def export(
    run_dir: Annotated[Path, typer.Argument(help="a run's results directory holding log.mcap")],
    fmt: Annotated[str, typer.Option("--format", help="csv | parquet (parquet needs pyarrow installed)")] = "csv",
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="folder for the tables (default "
                                                                    "RUN_DIR/export)")] = None,
) -> None:
    """Export a run's log.mcap as one table per topic (readings, estimates, targets, commands, ...)."""
    from hbma_ctrl.app.logs.export import FORMATS, export_log

    check_choice("--format", fmt, FORMATS)
    log = run_dir / "log.mcap"
    if not log.is_file():
        raise FileNotFoundError(f"RUN_DIR {run_dir}: no log.mcap")
    for f in _written_aside(out or run_dir / "export", out is not None, "export",
                            lambda folder: export_log(log, folder, fmt)):
        typer.echo(str(f))


def bench_log(
    config: Annotated[Path, typer.Argument(help="daemon configuration (CONFIG.toml)")]
    = Path("scenarios/daemon_chamber.toml"),
    duration_s: Annotated[float, typer.Option("--duration-s", help="rig time of each run, s (> 0)")] = 20.0,
    speed: Annotated[float, typer.Option("--speed", help="rig seconds per wall second")] = 1.0,
    repeats: Annotated[int, typer.Option("--repeats", help="runs with the log and as many without")] = 2,
    out: Annotated[Path, typer.Option("--out", "-o", help="results directory")] = Path("runs/bench_log"),
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
    report: ReportDir = None,
) -> None:
    """The daemon on the simulated rig with and without log.mcap, alternating: deadline misses and step
    p99 side by side, and the log's messages against the periods (log.json)."""
    from hbma_ctrl.app.bench.log import run_log_bench
    from hbma_ctrl.app.bench.report import open_report
    from hbma_ctrl.app.cli.daemon import _check_bench

    check_range("--repeats", repeats, 1, 100)
    _check_bench(config, {"--duration-s": duration_s, "--speed": speed})
    rep = open_report(report, "log", cli_argv())  # --report checked before the run
    res = run_log_bench(config, out, duration_s, speed, repeats, overwrite=overwrite, argv=cli_argv(),
                        echo=lambda s: print(s, file=sys.stderr, flush=True))
    for name, r in res["runs"].items():
        logged = (f"; {min(r['messages'].values())}/{r['periods_logged']} periods logged, {r['dropped']} dropped, "
                  f"hand-off median {r['handoff_us_median']:.0f} us, p99 {r['handoff_us_p99']:.0f} us (CPU "
                  f"{r['handoff_cpu_us_median']:.0f}, {r['handoff_cpu_us_p99']:.0f} us)" if r["mcap"] else "")
        typer.echo(f"{name}: {r['steps']} steps, {r['deadline_misses']} deadline misses, step median "
                   f"{r['step_ms_median'] or float('nan'):.3f} ms, p99 {r['step_ms_p99'] or float('nan'):.3f} ms{logged}")
    from hbma_ctrl.app.bench.pages import log_page

    finish_bench("log", res["verdicts"], out / "log.json", rep, lambda: log_page(res))


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``report`` and ``export`` to the top-level app and ``log`` to ``bench``."""
    app.command("report")(report)
    app.command("export")(export)
    bench_app.command("log")(bench_log)
