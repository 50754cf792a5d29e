"""Helpers for the package's input errors: every bad name gets the closest valid one."""

from __future__ import annotations

import difflib
import math
from collections.abc import Iterable

import numpy as np

__all__ = ["did_you_mean", "finite_or_nan", "floats_or_nan"]


def did_you_mean(word: str, options: Iterable[str], cutoff: float = 0.6) -> str:
    """" (did you mean 'x'?)" for the option closest to ``word``, or "" when none is close."""
    close = difflib.get_close_matches(str(word), list(options), n=1, cutoff=cutoff)
    return f" (did you mean '{close[0]}'?)" if close else ""


def finite_or_nan(value) -> float:
    """``value`` as a float when it is a finite real number, else NaN: a string, bytes or a bool (which
    ``float`` would accept) is not a number here, so a live stream's "12000" or True is refused."""
    if isinstance(value, (str, bytes, bool)) or type(value).__name__ == "bool_":
        return math.nan
    try:
        f = float(value)
    except (TypeError, ValueError):
        return math.nan
    return f if math.isfinite(f) else math.nan


def floats_or_nan(values, n: int) -> np.ndarray:
    """``values`` as an (n,) float array; the entries that are not numbers become NaN (a list of
    readings with a None or a word in it keeps its other readings)."""
    try:
        return np.asarray(values, dtype=float).reshape(n)
    except (TypeError, ValueError):
        out = np.full(n, np.nan)
        for i, v in enumerate(np.ravel(np.asarray(values, dtype=object))):
            try:
                out[i] = float(v)
            except (TypeError, ValueError):
                pass
        return out
