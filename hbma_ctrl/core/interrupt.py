"""The check that long loops make between their steps, so that an ending signal ends them promptly.

casadi's solvers look for signals inside their C code: a Ctrl-C (or SIGTERM) that arrives there stops
that one solve, the Python exception it raised is lost, and the loop around it carries on. The
application registers what to do (:func:`set_check`: raise the signal again); the loops below it call
:func:`check` once per step. With nothing registered (the package used as a library) it does nothing.
"""

from __future__ import annotations

from collections.abc import Callable

__all__ = ["check", "set_check"]

_check: list[Callable[[], None]] = []


def set_check(fn: Callable[[], None] | None) -> None:
    """Register ``fn`` as what :func:`check` calls (None: nothing)."""
    _check[:] = [] if fn is None else [fn]


def check() -> None:
    """Call the registered check (it may raise to end the loop); nothing when none is registered."""
    if _check:
        _check[0]()
