"""Command line: ``hbma-ctrl`` (typer). Parses, runs and reports; the work happens in the library.

The application and its error handling; every command lives in one module of this package, which
adds it with ``register(app, bench_app)``: :mod:`hbma_ctrl.app.cli.sim` (``run``, ``protocol`` -- also
what a bare ``hbma-ctrl`` runs --, ``equilibrium``, ``plots``), :mod:`hbma_ctrl.app.cli.estimators`,
:mod:`hbma_ctrl.app.cli.controllers`, :mod:`hbma_ctrl.app.cli.robot`, :mod:`hbma_ctrl.app.cli.fit`,
:mod:`hbma_ctrl.app.cli.tune`, :mod:`hbma_ctrl.app.cli.daemon`, :mod:`hbma_ctrl.app.cli.logs` (``report``,
``export``), :mod:`hbma_ctrl.app.cli.codegen`,
:mod:`hbma_ctrl.app.cli.scenario` (``scenarios``) and :mod:`hbma_ctrl.app.cli.rig`.
A new command is a function in one of them (or a new module in the tuple at the end of this file).

Bad input (ValueError, FileNotFoundError, usage errors) prints one line ``error: ...`` on stderr and
exits with code 2, never a traceback; a run whose trials all diverged does the same with code 1, and
so does any other failure of a run (a RuntimeError: a diverged plant, a solver's error; set
HBMA_CTRL_TRACEBACK=1 for its traceback). Ctrl-C, SIGTERM and SIGHUP print ``interrupted: partial
results in <path>`` and exit with code 128 + the signal's number (130, 143, 129); a second signal
ends at once. Every command writing a results directory goes through
:func:`hbma_ctrl.app.outputs.run_dir` (``--out`` checked before any work, ``--overwrite`` to replace a
run, manifest.json, nothing half-written left at ``--out``).

Start-up: importing this module (and the command modules it registers) loads only typer, rich and a
few light modules; each command imports what it needs when it runs, so that ``protocol`` does not
pay for the daemon, the tuner or the roles. An option default or choice list from a slow module is a
copy in :mod:`hbma_ctrl.app.cli.constants` (tests/test_cli.py checks both).
"""

from __future__ import annotations

import os
import signal
import sys
import threading

import typer
from typer.core import TyperGroup

try:  # typer >= 0.24 vendors click as typer._click; older typer uses click itself
    from typer._click import exceptions as _cx
except ImportError:  # pragma: no cover
    from click import exceptions as _cx

# Only what registering the commands needs is imported here: each command imports its own heavy
# modules (casadi-built models, scipy, matplotlib, the roles, the daemon, optuna, ...) when it runs,
# so that `hbma-ctrl protocol` (the main job) and `--help` do not pay for the others.
from hbma_ctrl.app.cli import codegen, controllers, daemon, estimators, fit, logs, rig, robot, scenario, sim, tune
from hbma_ctrl.app.cli.args import fail
from hbma_ctrl.app.endsignals import end_on_signals, pending_signal, signal_number
from hbma_ctrl.app.outputs import ARGV_KEY

__all__ = ["app", "bench_app"]


class _Interrupted(Exception):
    """Ctrl-C (SIGTERM, SIGHUP) seen inside a command; not a KeyboardInterrupt, so typer does not
    swallow it as exit 130."""

    def __init__(self, partial, signum: int):
        super().__init__(str(partial))
        self.partial = partial
        self.signum = signum


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
            raise _Interrupted(getattr(exc, "partial", None), signal_number(exc)) from None
        except Exception as exc:
            if pending_signal() is None:
                raise
            # the signal's KeyboardInterrupt hit code that turned it into another error (casadi does)
            raise _Interrupted(getattr(exc, "partial", None), pending_signal()) from None

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        # SIGINT, SIGTERM and SIGHUP end a command alike; the handlers are put back on return, so a
        # process that runs the CLI as a function keeps its own
        main_thread = threading.current_thread() is threading.main_thread()
        old = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)} if main_thread else {}
        if main_thread:
            end_on_signals()
        try:
            return self._main(args, prog_name, complete_var, standalone_mode, **extra)
        finally:
            for sig, handler in old.items():
                signal.signal(sig, handler)

    def _main(self, args, prog_name, complete_var, standalone_mode, **extra):
        try:
            rv = super().main(args=args, prog_name=prog_name, complete_var=complete_var,
                              standalone_mode=False, **extra)
            if pending_signal() is not None:  # its exception was lost on its way up
                raise _Interrupted(None, pending_signal())
        except _cx.NoArgsIsHelpError:  # a group called bare: its help was printed, nothing failed
            sys.exit(0)
        except _cx.ClickException as exc:  # usage errors (exit code 2) and other CLI errors
            fail(exc.format_message(), exc.exit_code)
        except typer.Abort:
            fail("aborted", 1)
        except _Interrupted as exc:
            typer.echo(f"interrupted: partial results in {exc.partial}" if exc.partial else "interrupted", err=True)
            sys.exit(128 + exc.signum)
        except (ValueError, FileNotFoundError) as exc:
            _fail_keeping(exc, str(exc), 2)
        except OSError as exc:  # a path the system refuses (too long, no permission, a directory for a file)
            _fail_keeping(exc, _os_error_line(exc), 2)
        except RuntimeError as exc:
            if _is_run_failed(exc):  # the input was fine; the run failed (every trial diverged)
                _fail_keeping(exc, str(exc), 1)
            # any other failed simulation (a diverged plant, a solver's error): one line, exit 1; the
            # traceback only when asked for (HBMA_CTRL_TRACEBACK=1), for a bug report
            if os.environ.get("HBMA_CTRL_TRACEBACK"):
                raise
            _fail_keeping(exc, f"the run failed: {type(exc).__name__}: {exc}", 1)
        code = rv if isinstance(rv, int) else 0
        if standalone_mode:
            sys.exit(code)
        return rv


def _fail_keeping(exc: BaseException, message: str, code: int):
    """:func:`fail` with ``message``, naming the partial results ``exc`` kept (``partial_results``), if any."""
    partial = getattr(exc, "partial_results", None)
    fail(f"{message}; partial results in {partial}" if partial else message, code)


def _os_error_line(exc: OSError) -> str:
    """One line for an OSError that no command turned into its own message: the path (shortened) and why."""
    name = str(exc.filename) if exc.filename is not None else ""
    if len(name) > 80:
        name = name[:60] + "..." + name[-17:]
    why = exc.strerror or type(exc).__name__
    return f"{name}: {why}" if name else f"{why} ({exc})"


def _is_run_failed(exc: BaseException) -> bool:
    """True for the runner's RunFailed (all trials diverged). Looked up, not imported: the runner pulls
    in every role, and a command that never imported it cannot have raised its error."""
    runner = sys.modules.get("hbma_ctrl.app.scenes.runner")
    return runner is not None and isinstance(exc, runner.RunFailed)


app = typer.Typer(cls=_OneLineErrors, add_completion=False, rich_markup_mode=None, no_args_is_help=False, pretty_exceptions_enable=False,
                  help="Model, observe and control Hyperelastic Ballooning Membrane Actuators (HBMA). "
                       "Without a command: run the 150-trial protocol (docs/concepts/model.md §7) with defaults into ./runs/protocol.")
bench_app = typer.Typer(add_completion=False, rich_markup_mode=None, no_args_is_help=True, help="Benchmarks (speed and accuracy).")
app.add_typer(bench_app, name="bench")


@app.callback(invoke_without_command=True)
def _main(ctx: typer.Context) -> None:
    """Without a command: the main job, the default protocol into ./runs/protocol."""
    if ctx.invoked_subcommand is None:
        sim.protocol()


# every command module registers its commands the same way; the order is --help's
for _module in (sim, estimators, controllers, robot, fit, tune, daemon, logs, codegen, scenario, rig):
    _module.register(app, bench_app)
