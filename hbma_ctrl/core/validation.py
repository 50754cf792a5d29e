"""Helpers for the package's input errors: every bad name gets the closest valid one."""

from __future__ import annotations

import difflib
from collections.abc import Iterable

__all__ = ["did_you_mean"]


def did_you_mean(word: str, options: Iterable[str], cutoff: float = 0.6) -> str:
    """" (did you mean 'x'?)" for the option closest to ``word``, or "" when none is close."""
    close = difflib.get_close_matches(str(word), list(options), n=1, cutoff=cutoff)
    return f" (did you mean '{close[0]}'?)" if close else ""
