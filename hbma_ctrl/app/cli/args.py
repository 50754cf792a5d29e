"""Option checks and output helpers shared by the CLI's command modules: a flag's choice and range
(one ValueError naming the flag as the user wrote it), whole-number lists, the worker count, the
one-line failure and the console tables print to.
"""

from __future__ import annotations

import math
import os
import sys

import typer
from rich.console import Console

from hbma_ctrl.core.validation import did_you_mean

__all__ = ["cap_workers", "whole_numbers", "check_choice", "check_range", "console", "fail"]


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


def cap_workers(flag: str, workers: int) -> int:
    """``workers`` capped at the machine's core count, with a one-line note on stderr (not an error).

    More processes than cores only share the cores and each costs a model build: never faster.
    """
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


def check_range(flag: str, value: float | None, lo: float, hi: float, lo_open: bool = False, unit: str = ""):
    """A flag's number in [lo, hi] (``lo_open``: (lo, hi]) in the user's ``unit``; None passes through.
    ValueError naming the flag and the range otherwise (NaN and inf included)."""
    if value is None:
        return None
    ok = math.isfinite(value) and (value > lo if lo_open else value >= lo) and value <= hi
    if not ok:
        raise ValueError(f"{flag} = {value:g} is out of range {'(' if lo_open else '['}{lo:g}, {hi:g}] {unit}".rstrip())
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
