"""``hbma-ctrl fit DATA.csv``: fit a membrane material to static equilibrium data.

Registered by :mod:`hbma_ctrl.app.cli` through :func:`register`. Edge units (mm, kPa, g) here; the
fit (:mod:`hbma_ctrl.app.fit`) works in SI. Writes ``fit.json``, ``params.toml`` and
``residuals.png`` into ``--out`` through :func:`hbma_ctrl.app.outputs.run_dir`. Bad input raises
ValueError, which the top-level CLI prints as one ``error: ...`` line with exit code 2.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.table import Table

from hbma_ctrl.app.fit import check_options, fit_static, parse_data, write_fit
from hbma_ctrl.app.outputs import OVERWRITE_HELP, check_out, cli_argv, run_dir
from hbma_ctrl.core import units as U

__all__ = ["register", "fit_cmd", "parse_fix"]


def parse_fix(items: list[str]) -> dict[str, float]:
    """``--fix NAME=VALUE`` items -> {name: value (SI)}; ValueError naming the bad item."""
    out: dict[str, float] = {}
    for item in items:
        if "=" not in item:
            raise ValueError(f"--fix '{item}': expected NAME=VALUE (SI), e.g. C2=0 or Jm=60")
        name, val = (x.strip() for x in item.split("=", 1))
        try:
            v = float(val)
        except ValueError:
            raise ValueError(f"--fix {name}: '{val}' is not a number") from None
        if not math.isfinite(v):
            raise ValueError(f"--fix {name}: '{val}' is not a finite number")
        out[name] = v
    return out


def _range(name: str, value: float, lo: float, hi: float, unit: str) -> None:
    if not (math.isfinite(value) and lo < value <= hi):
        raise ValueError(f"{name} = {value:g} is out of range ({lo:g}, {hi:g}] {unit}")


def fit_cmd(
    data: Annotated[Path, typer.Argument(help="CSV: h_mm, p_kpa and, with a load, F_n or load_g")],
    material: Annotated[str, typer.Option(help="nh | mr | yeoh | gent | ogden")] = "nh",
    r1_mm: Annotated[float, typer.Option("--r1-mm", help="clamp radius r1, mm")] = 12.5,
    t0_mm: Annotated[float, typer.Option("--t0-mm", help="membrane thickness t0, mm")] = 3.0,
    contact: Annotated[Optional[str], typer.Option(
        help="free (h2 = 0) | flat (load on a plate); default: flat with a force column, else free")] = None,
    fidelity: Annotated[str, typer.Option(help="cap (the spherical cap of README Model §1-§3)")] = "cap",
    fix: Annotated[Optional[list[str]], typer.Option("--fix", help="hold a parameter NAME=VALUE (SI), repeatable")]
    = None,
    out: Annotated[Path, typer.Option("--out", "-o", help="directory for fit.json, params.toml, residuals.png")]
    = Path("runs/fit"),
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
) -> None:
    """Fit material parameters to static equilibrium data (pressure vs height, optional loads)."""
    _range("--r1-mm", r1_mm, 0.5, 100.0, "mm")
    _range("--t0-mm", t0_mm, 0.05, 20.0, "mm")
    check_options(material.lower(), contact, fidelity)
    fixed = parse_fix(fix or [])
    check_out(out, overwrite)  # before the fit: a bad --out costs nothing
    if not data.is_file():
        raise FileNotFoundError(f"data file {data} not found")
    pts = parse_data(data.read_bytes())
    res = fit_static(pts, material.lower(), U.mm(r1_mm), U.mm(t0_mm), contact=contact, fix=fixed,
                     fidelity=fidelity)
    with run_dir(out, command="fit", argv=cli_argv(), overwrite=overwrite) as tmp:
        write_fit(res, tmp)
    con = Console(highlight=False)
    tab = Table(title=f"fit {res.material}: {res.n_points} points, {res.contact} contact, "
                      f"NRMSD {res.nrmsd:.4f}")
    for c in ("parameter", "value (SI)", "95 % interval"):
        tab.add_column(c, justify="right")
    for k, v in res.params.items():
        lo, hi = res.ci95[k]
        ci = "fixed" if k in res.fixed else (f"[{lo:.4g}, {hi:.4g}]" if lo is not None else "n/a (no dof)")
        tab.add_row(k, f"{v:.5g}", ci)
    con.print(tab)
    for s in res.unidentifiable:
        con.print(f"note: {s}")
    con.print(f"wrote {out / 'fit.json'}, {out / 'params.toml'}, {out / 'residuals.png'}")


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add the ``fit`` command to the top-level CLI (nothing under ``bench``)."""
    app.command("fit")(fit_cmd)
