"""Ending signals (Ctrl-C, SIGTERM, SIGHUP) that end every command alike.

The first one is raised in the main thread as :class:`Terminated` (a KeyboardInterrupt), so the
command's clean-up runs (a results directory kept aside and marked, its lock released); the signal is
kept (:func:`pending_signal`) for when that exception is lost in C code on its way up. A second one
ends the process at once: every open run (:data:`open_runs`, registered by
:func:`hbma_ctrl.app.outputs.run_dir`) is parked as cut short first, so nothing is left hidden or
locked. A few renames can hold them (:func:`holding_signals`) so that a finished run is never left
half moved.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from collections.abc import Iterator

from hbma_ctrl.core import interrupt

__all__ = ["Terminated", "end_on_signals", "holding_signals", "open_runs", "pending_signal",
           "raise_if_signalled", "signal_name", "signal_number"]


class Terminated(KeyboardInterrupt):
    """An ending signal (SIGINT, SIGTERM, SIGHUP) raised where the program is, so that every one ends it
    as Ctrl-C does (outputs kept aside and marked, lock released); ``signum`` is the signal's number."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


#: the signals that end a command: Ctrl-C, ``kill``, a closed terminal
_ENDING = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

#: the process that asked for :func:`end_on_signals` and the signal it got (None: none yet)
_signalled: dict = {"pid": None, "signum": None}


#: the runs of this process between taking their lock and releasing it, for a second signal to park: each a
#: dict whose ``"cut_short"`` (a callable of the reason, returning where the work went or None) does that
open_runs: list[dict] = []

#: ending signals that came while a finished run was being moved into place, dealt with once it is
_held: dict = {"on": False, "first": None, "again": None}


def _terminate(signum: int, frame) -> None:
    # the first ending signal is raised where the program is, so that its clean-up runs
    if os.getpid() != _signalled["pid"]:  # a forked worker inherited the handler: the default action
        for sig in _ENDING:
            signal.signal(sig, signal.SIG_DFL)
        os.kill(os.getpid(), signum)
        return
    for sig in _ENDING:
        signal.signal(sig, _terminate_again)
    _signalled["signum"] = signum
    if _held["on"]:
        _held["first"] = signum
        return
    raise Terminated(signum)


def _terminate_again(signum: int, frame) -> None:
    # a second signal while the first one's clean-up runs ends the process at once; a third one finds the
    # default action, which ends it even inside C code that holds back the Python handler
    for sig in _ENDING:
        signal.signal(sig, signal.SIG_DFL)
    if os.getpid() != _signalled["pid"]:
        os.kill(os.getpid(), signum)
        return
    if _held["on"]:
        _held["again"] = signum
        return
    _end_at_once(signum)


def _end_at_once(signum: int) -> None:
    """Park every open run as cut short (a rename, its manifest marked), release its lock, exit 128 +
    ``signum`` without the clean-up the first signal started: nothing is left hidden or locked."""
    first = _signalled["signum"]
    why = (f"{signal_name(first) if first is not None else 'an ending signal'}, then "
           f"{signal.Signals(signum).name}: ended at once, its clean-up cut short")
    lines = []
    for run in reversed(list(open_runs)):
        where = run["cut_short"](why)
        lines.append(f"interrupted: partial results in {where} (cut short by a second signal)" if where else
                     "interrupted (cut short by a second signal)")
    with contextlib.suppress(OSError):
        os.write(2, ("\n".join(lines or ["interrupted (cut short by a second signal)"]) + "\n").encode())
    os._exit(128 + signum)


@contextlib.contextmanager
def holding_signals() -> Iterator[None]:
    """Hold the ending signals for a few renames, then act on them: a finished run is never left half
    moved (the old one aside, the new one still hidden). Only the main thread, where handlers run."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _held.update(on=True, first=None, again=None)
    try:
        yield
    finally:
        _held["on"] = False
        if _held["again"] is not None:
            _end_at_once(_held["again"])
        if _held["first"] is not None:
            raise Terminated(_held["first"])


def end_on_signals() -> None:
    """Make SIGINT (Ctrl-C), SIGTERM and SIGHUP (a closed terminal) end the program alike:
    :class:`Terminated` (a KeyboardInterrupt) is raised in the main thread and the signal is kept
    (:func:`pending_signal`); a second signal kills at once; a forked child dies as by default.
    Call from the main thread."""
    _signalled.update(pid=os.getpid(), signum=None)
    interrupt.set_check(raise_if_signalled)  # the loops below the application check between steps
    for sig in _ENDING:
        signal.signal(sig, _terminate)


def pending_signal() -> int | None:
    """The ending signal this process got since :func:`end_on_signals`, also when the exception it
    raised was lost on its way up (in a callback from C code, casadi's, it becomes a RuntimeError),
    else None."""
    return _signalled["signum"] if os.getpid() == _signalled["pid"] else None


def raise_if_signalled() -> None:
    """Raise :class:`Terminated` when an ending signal came and its exception was lost: casadi's solvers
    check for signals inside their C code, and one that arrives there stops that solve only, while the
    Python code around it carries on. A long loop calls this between its steps, so the command ends
    within one step of the signal instead of at its end."""
    signum = pending_signal()
    if signum is not None:
        raise Terminated(signum)


def signal_name(signum: int) -> str:
    """How manifest.json names what ended a run: KeyboardInterrupt for Ctrl-C, else the signal."""
    return "KeyboardInterrupt" if signum == signal.SIGINT else signal.Signals(signum).name


def signal_number(exc: KeyboardInterrupt) -> int:
    """The signal that ended a run: SIGINT for Ctrl-C, else the :class:`Terminated` signal's."""
    return getattr(exc, "signum", int(signal.SIGINT))
