"""A closed loop described once, as data: the spec the generated C loop and its Python path share.

A closed loop is a :class:`LoopSpec`: named signals (flat float vectors, SI), per-tick data streams
(sensor noise, targets), and the stages called every tick in order, each a casadi Function reading
and writing signals (a stage with ``every`` = P runs when k % P == 0). Both paths log the same
columns (:class:`LogColumn`: a signal's entry times a unit factor, edge units).

:func:`run_python` runs the spec in Python (each stage's Function called through preallocated
buffers, :class:`hbma_ctrl.core.codegen.FastFunction`, either loaded from the shared library built
from the same object code as the C program, or on casadi's virtual machine): the *Python path*.
:mod:`hbma_ctrl.core.loopgen_c` writes, builds, runs and compares the C loop.

Why the Python path loads the generated library rather than the virtual machine: casadi's VM and the
generated C of a Function need not agree (measured with the qrqp QP solver in the RTI step: its
generated C reports a failed cold-start iteration where the VM's does not, and the loop parts from the
first tick; with OSQP the two agree on track_height), so the comparison runs the same object code and
tests the loop itself (stages, order, signals, data), which must agree exactly. ``bench --python-vm``
measures the VM path beside it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from hbma_ctrl.core.codegen import FastFunction

__all__ = ["Stage", "LogColumn", "LoopSpec", "Part", "run_python", "PythonRun", "dense_function", "STEPS_NAME",
           "LIBRARY", "LOG"]

#: base name of the generated step sources (``hbma_steps.c`` and ``hbma_steps.h``)
STEPS_NAME = "hbma_steps"
#: the generated steps as a shared library (built beside the program by :func:`hbma_ctrl.core.loopgen_c.build_c`)
LIBRARY = f"lib{STEPS_NAME}.so"
#: the mark a stage list uses for "write the log row here"
LOG = "log"


@dataclass
class Stage:
    """One call per tick (or every ``every`` ticks) of a casadi Function.

    Fields
    ----------
    fun : the Function (dense inputs and outputs; its name is its C symbol).
    inputs : for each Function input, the signal it reads.
    outputs : for each Function output, the signal it writes (None: not kept).
    every : the stage runs at ticks k with k % every == 0 (>= 1).
    gate : a signal whose first entry switches the stage: it runs only while that entry is not 0
        (None: always).
    gate_off : run while the gate's entry IS 0 instead.
    repeat : calls per run, each reading the signals the previous one wrote (iterations).
    stop_on : a signal that ends the repetitions early when its first entry is not 0 after a call
        (a solver's failure status); None: all ``repeat`` calls.
    fails_to : an output signal whose first entry is set to NaN before every call, so that a call that
        fails (a solver inside returns non-zero before the Function writes that output) reads as failed,
        as the Python roles read it (``hbma_ctrl.controllers.rti_step._RtiFunction``); None: none.
    """

    fun: ca.Function
    inputs: list
    outputs: list
    every: int = 1
    gate: str | None = None
    gate_off: bool = False
    repeat: int = 1
    stop_on: str | None = None
    fails_to: str | None = None

    def runs(self, k: int, sig: dict) -> bool:
        """Whether the stage runs at tick k with these signal values."""
        if k % self.every:
            return False
        if self.gate is None:
            return True
        return (sig[self.gate][0] == 0.0) if self.gate_off else (sig[self.gate][0] != 0.0)

    @property
    def name(self) -> str:
        """The Function's name (its C symbol)."""
        return self.fun.name()


@dataclass
class LogColumn:
    """One column of the trajectory: ``signal[index] * scale`` under ``name`` (edge units in the name).

    Fields
    ------
    name : column header, e.g. 'h_true_mm'.
    signal : the signal it reads.
    index : the entry of the signal.
    scale : factor from SI to the column's unit (1e3 for m -> mm).
    """

    name: str
    signal: str
    index: int = 0
    scale: float = 1.0


@dataclass
class Part:
    """What one role adds to a loop: its stages in call order, the initial values of the signals it
    keeps (SI), its per-tick streams (signal -> (n_ticks, size) array), its log columns and a line
    for the loop's ``meta`` (name -> text)."""

    stages: list
    signals: dict
    streams: dict = field(default_factory=dict)
    log: list = field(default_factory=list)
    meta: dict = field(default_factory=dict)

    def add(self, other: "Part") -> "Part":
        """This part followed by ``other`` (its stages after these; its signals, streams and meta over these)."""
        return Part(self.stages + other.stages, {**self.signals, **other.signals}, {**self.streams, **other.streams},
                    self.log + other.log, {**self.meta, **other.meta})


@dataclass
class LoopSpec:
    """A closed loop as signals, streams and stages (see the module docstring).

    Fields
    ------
    name : the loop's name (the scenario's).
    dt : tick period, s.
    n_ticks : ticks to run.
    signals : initial value of every signal (flat float arrays, SI).
    streams : per-tick data, signal name -> (n_ticks, size) array copied into that signal at the start
        of tick k.
    stages : the stages in call order, with the string :data:`LOG` where the log row is written
        (default: after the last stage).
    log : the trajectory's columns; column 't_s' (k * dt) comes first by itself.
    meta : what the loop is made of (name -> text), written to README.txt and the bench's JSON.
    """

    name: str
    dt: float
    n_ticks: int
    signals: dict
    streams: dict
    stages: list
    log: list
    meta: dict = field(default_factory=dict)

    def functions(self) -> list:
        """The distinct stage Functions, in call order."""
        seen, out = set(), []
        for st in self.stages:
            if isinstance(st, Stage) and st.name not in seen:
                seen.add(st.name)
                out.append(st.fun)
        return out

    def validate(self) -> "LoopSpec":
        """Check that every stage's signals exist with the Function's sizes; ValueError naming the stage."""
        sig = {k: np.asarray(v, dtype=float).ravel() for k, v in self.signals.items()}
        self.signals = sig
        for k, v in self.streams.items():
            a = np.asarray(v, dtype=float).reshape(self.n_ticks, -1)
            if k not in sig or a.shape[1] != sig[k].size:
                raise ValueError(f"stream '{k}': needs a signal of {a.shape[1]} entries")
            self.streams[k] = a
        names = set()
        for st in self.stages:
            if st == LOG:
                continue
            f = st.fun
            if st.name in names and any(o is not None for o in st.outputs):
                pass
            names.add(st.name)
            if len(st.inputs) != f.n_in() or len(st.outputs) != f.n_out():
                raise ValueError(f"stage {st.name}: {f.n_in()} inputs / {f.n_out()} outputs, wired "
                                 f"{len(st.inputs)} / {len(st.outputs)}")
            for i, s in enumerate(st.inputs):
                if s not in sig or sig[s].size != f.nnz_in(i) or not f.sparsity_in(i).is_dense():
                    raise ValueError(f"stage {st.name}: input {f.name_in(i)} ({f.nnz_in(i)} dense entries) "
                                     f"has no signal '{s}' of that size")
            for i, s in enumerate(st.outputs):
                if s is not None and (s not in sig or sig[s].size != f.numel_out(i)):
                    raise ValueError(f"stage {st.name}: output {f.name_out(i)} ({f.numel_out(i)} entries) "
                                     f"has no signal '{s}' of that size")
            if not (isinstance(st.every, int) and st.every >= 1):
                raise ValueError(f"stage {st.name}: every = {st.every!r} must be an integer >= 1")
            if not (isinstance(st.repeat, int) and st.repeat >= 1):
                raise ValueError(f"stage {st.name}: repeat = {st.repeat!r} must be an integer >= 1")
            for what, name in (("gate", st.gate), ("stop_on", st.stop_on)):
                if name is not None and name not in sig:
                    raise ValueError(f"stage {st.name}: {what} signal '{name}' does not exist")
            if st.fails_to is not None and st.fails_to not in st.outputs:
                raise ValueError(f"stage {st.name}: fails_to signal '{st.fails_to}' is not one of its outputs")
        for c in self.log:
            if c.signal not in sig or not 0 <= c.index < sig[c.signal].size:
                raise ValueError(f"log column {c.name}: no entry {c.index} of signal '{c.signal}'")
        return self

    def stage_list(self) -> list:
        """The stages with the log mark placed (at the end when the list has none)."""
        return list(self.stages) if LOG in self.stages else list(self.stages) + [LOG]

    def header(self) -> list:
        """The trajectory's column names."""
        return ["t_s"] + [c.name for c in self.log]


def dense_function(fun: ca.Function) -> ca.Function:
    """The Function with dense outputs (a sparse output is densified); itself when all are dense."""
    if all(fun.sparsity_out(i).is_dense() for i in range(fun.n_out())):
        return fun
    args = [ca.MX.sym(fun.name_in(i), fun.sparsity_in(i)) for i in range(fun.n_in())]
    outs = [ca.densify(o) for o in fun.call(args)]
    return ca.Function(fun.name(), args, outs, fun.name_in(), fun.name_out())


@dataclass
class PythonRun:
    """The Python path's trajectory (rows x columns, the spec's header), call times per Function (s)
    and per tick (the sum of its calls, s)."""

    trajectory: np.ndarray
    times: dict
    tick: np.ndarray


def run_python(spec: LoopSpec, library: Path | str | None = None) -> PythonRun:
    """Run the loop with each stage's Function called from Python through buffers.

    ``library`` None: casadi's virtual machine evaluates each Function as built; a path: the
    Functions are loaded (``casadi.external``) from that shared library of the generated sources
    (:func:`hbma_ctrl.core.loopgen_c.build_c` writes ``libhbma_steps.so`` beside the program), the very code the C loop runs.
    """
    spec.validate()
    sig = {k: v.copy() for k, v in spec.signals.items()}
    fast = {}
    for f in spec.functions():
        fun = dense_function(f) if library is None else ca.external(f.name(), str(library))
        fast[f.name()] = FastFunction(fun, compile=False)
    stages = spec.stage_list()
    times = {name: [] for name in fast}
    tick = np.zeros(spec.n_ticks)
    rows = np.full((spec.n_ticks, 1 + len(spec.log)), np.nan)
    for k in range(spec.n_ticks):
        for name, a in spec.streams.items():
            sig[name][:] = a[k]
        for st in stages:
            if st == LOG:
                rows[k, 0] = k * spec.dt
                for j, c in enumerate(spec.log):
                    rows[k, 1 + j] = sig[c.signal][c.index] * c.scale
                continue
            if not st.runs(k, sig):
                continue
            ff = fast[st.name]
            i_fail = None if st.fails_to is None else st.outputs.index(st.fails_to)
            for _ in range(st.repeat):
                if i_fail is not None:
                    ff.out[i_fail][0] = np.nan  # a failed call leaves it unwritten
                args = [sig[s] for s in st.inputs]
                t0 = time.perf_counter()
                out = ff(*args)
                dt = time.perf_counter() - t0
                times[st.name].append(dt)
                tick[k] += dt
                for s, o in zip(st.outputs, out):
                    if s is not None:
                        sig[s][:] = o
                if st.stop_on is not None and sig[st.stop_on][0] != 0.0:
                    break
    return PythonRun(rows, {k: np.asarray(v) for k, v in times.items()}, tick)
