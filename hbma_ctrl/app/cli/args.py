"""Option checks and output helpers shared by the CLI's command modules: a flag's choice and range
(one ValueError naming the flag as the user wrote it), number lists, the worker count, the
one-line failure, the console tables print to and the tables themselves.
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.table import Table

from hbma_ctrl.core.validation import did_you_mean

__all__ = ["assignments", "cap_workers", "numbers", "whole_numbers", "check_choice", "check_range", "console", "fail", "finish_bench",
           "show_table", "ReportDir"]

#: every bench's ``--report DIR`` (:mod:`hbma_ctrl.app.bench.report`); off by default
ReportDir = Annotated[Optional[Path], typer.Option(
    "--report", metavar="DIR", help="also write the results page DIR/<bench>.md (what is measured, the command, "
                                    "the machine, tables, Pareto figure) and update DIR/index.md")]


def numbers(text: str, flag: str) -> list[float]:
    """Comma-separated finite numbers (';' also separates); ValueError naming the flag and the text."""
    try:
        vals = [float(x) for x in text.replace(";", ",").split(",") if x.strip()]
    except ValueError:
        vals = []
    if not vals or not all(math.isfinite(v) for v in vals):
        raise ValueError(f"{flag} = '{text}' must be finite comma-separated numbers")
    return vals


def assignments(items: list[str], flag: str, example: str, one: bool = False) -> dict[str, float | tuple]:
    """``NAME=VALUE`` items (SI) -> {name: value}: one number as a float, comma-separated numbers as a
    tuple (refused when ``one``); ValueError naming the flag and the item otherwise."""
    out: dict[str, float | tuple] = {}
    for item in items:
        name, sep, val = (x.strip() for x in item.partition("="))
        if not sep:
            raise ValueError(f"{flag} '{item}': expected NAME=VALUE (SI), e.g. {example}")
        nums = numbers(val, f"{flag} {name}")
        if one and len(nums) > 1:
            raise ValueError(f"{flag} {name}: '{val}' must be one number")
        out[name] = nums[0] if len(nums) == 1 else tuple(nums)
    return out


def whole_numbers(text: str, flag: str, lo: int, hi: int) -> list[int]:
    """Comma-separated whole numbers in [lo, hi]; '2.5' is refused, never truncated to 2."""
    vals = []
    for item in (x.strip() for x in text.replace(";", ",").split(",")):
        if not item:
            continue
        try:
            v = float(item)
        except ValueError:
            v = float("nan")
        if not (math.isfinite(v) and v.is_integer() and lo <= v <= hi):
            raise ValueError(f"{flag} = '{text}': '{item}' is not a whole number in [{lo}, {hi}]")
        vals.append(int(v))
    if not vals:
        raise ValueError(f"{flag} = '{text}': expected comma-separated whole numbers in [{lo}, {hi}]")
    return vals


def cap_workers(flag: str, workers: int, most: int = 256) -> int:
    """``workers`` checked in [1, ``most``] (:func:`check_range`), then capped at the machine's core
    count with a one-line note on stderr (not an error).

    More processes than cores only share the cores and each costs a model build: never faster.
    """
    check_range(flag, workers, 1, most)
    cores = os.cpu_count() or 1
    if workers > cores:
        typer.echo(f"note: {flag} = {workers} is above this machine's {cores} cores; using {cores}", err=True)
        return cores
    return workers


def check_choice(flag: str, value: str, allowed) -> str:
    """A flag's value among ``allowed``; ValueError naming the flag, the closest choice and all choices."""
    if value not in allowed:
        hint = did_you_mean(value, list(allowed))
        raise ValueError(f"{flag} = '{value}'{hint}; allowed: {', '.join(allowed)}")
    return value


def _g(x: float) -> str:
    # an integer as written (2147483647, not 2.14748e+09), a float in its shortest form
    return str(x) if isinstance(x, int) else f"{x:g}"


def check_range(flag: str, value: float | None, lo: float, hi: float, lo_open: bool = False, unit: str = "",
                hi_open: bool = False, note: str = ""):
    """A flag's number in [lo, hi] (``lo_open``: (lo, ...; ``hi_open``: ..., hi)) in the user's ``unit``;
    None passes through. ValueError naming the flag and the range (and ``note``, what the range is)
    otherwise (NaN and inf included)."""
    if value is None:
        return None
    ok = math.isfinite(value) and (value > lo if lo_open else value >= lo) and (value < hi if hi_open else value <= hi)
    if not ok:
        left, right = "(" if lo_open else "[", ")" if hi_open else "]"
        why = f" ({note})" if note else ""
        raise ValueError(f"{flag} = {_g(value)} is out of range {left}{_g(lo)}, {_g(hi)}{right} {unit}".rstrip() + why)
    return value


def fail(message: str, code: int = 2):
    """Print ``error: <message>`` as one line on stderr and exit with ``code``."""
    text = " ".join(str(message).split())  # one line
    typer.echo(f"error: {text}", err=True)
    sys.exit(code)


def console(min_width: int = 0) -> Console:
    """The console tables print to; piped to a file it is at least ``min_width`` wide (no squeezed tables)."""
    con = Console(highlight=False)
    if not con.is_terminal and con.width < min_width:
        con = Console(highlight=False, width=min_width)
    return con


def show_table(title: str, columns: Sequence[str], rows: Iterable[Sequence[str]], con: Console | None = None,
               justify: str = "right", left: int = 0, no_wrap: bool = False, **table_kw) -> Console:
    """Print a table of ``columns`` and ``rows`` (cell texts) on ``con`` (default :func:`console`) and
    return the console; the first ``left`` columns are left-justified, the others ``justify``-ed."""
    table = Table(title=title, **table_kw)
    for i, c in enumerate(columns):
        table.add_column(c, justify="left" if i < left else justify, no_wrap=no_wrap)
    for r in rows:
        table.add_row(*r)
    con = con or console()
    con.print(table)
    return con


def finish_bench(name: str, verdicts: dict, written: Path, rep, page) -> None:
    """End a bench with verdicts: one line naming the failed ones (or "passed") and the results file
    ``written``, the results page ``page()`` when ``--report`` opened ``rep``, exit 1 when one failed."""
    failed = [k for k, ok in verdicts.items() if not ok]
    typer.echo(f"{name}: {'passed' if not failed else 'FAILED ' + ', '.join(failed)}; wrote {written}")
    if rep:
        typer.echo(f"wrote {rep.write(page())}")
    if failed:
        raise typer.Exit(1)
