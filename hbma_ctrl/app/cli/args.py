"""Option helpers shared by the CLI modules: whole-number lists and the worker count.

Kept apart from :mod:`hbma_ctrl.app.cli.main` because the command modules it registers need them too.
"""

from __future__ import annotations

import math
import os

import typer

__all__ = ["cap_workers", "whole_numbers"]


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
