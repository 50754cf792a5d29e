"""Code generation of a closed loop: casadi step Functions -> C sources, a header and a C main program.

A closed loop is described once, as a :class:`LoopSpec`: named signals (flat float vectors, SI),
per-tick data streams (sensor noise, targets), and the stages called every tick in order, each a
casadi Function reading and writing signals (a stage with ``every`` = P runs when k % P == 0). The
same spec runs

- in Python (:func:`run_python`: each stage's Function called through preallocated buffers,
  :class:`hbma_ctrl.core.codegen.FastFunction`, either loaded from the shared library built from the
  same object code as the C program, or on casadi's virtual machine): the *Python path*;
- as C (:func:`write_c`): one ``casadi.CodeGenerator`` source and header with every Function
  (``with_header``, ``main`` off), ``loop_data.h`` (the initial signals and the streams) and
  ``closed_loop.c`` from the template ``c/closed_loop.c.in``: the loop with nothing but
  the generated code and libc/libm, writing ``trajectory.csv`` and ``times.json``.

Both log the same columns (:class:`LogColumn`: a signal's entry times a unit factor, edge units), so
:func:`compare` measures the C loop against the Python path.
The application builds the spec of a scenario (``hbma-ctrl codegen``); :func:`bench` builds, runs and
times both paths.

Why the Python path loads the generated library rather than the virtual machine: casadi's VM and the
generated C of a Function need not agree (measured with the qrqp QP solver in the RTI step: its
generated C reports a failed cold-start iteration where the VM's does not, and the loop parts from the
first tick; with OSQP the two agree on track_height), so the comparison runs the same object code and
tests the loop itself (stages, order, signals, data), which must agree exactly. ``bench --python-vm``
measures the VM path beside it.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import casadi as ca
import numpy as np

from hbma_ctrl.core.codegen import FastFunction

__all__ = ["Stage", "LogColumn", "LoopSpec", "Part", "run_python", "write_c", "build_c", "run_c", "read_c", "compare",
           "find_compiler", "CFLAGS", "OPT_FLAGS", "STEPS_NAME", "PythonRun", "CRun", "time_summary", "build_line", "LIBRARY", "solver_flags",
           "bench"]

#: base name of the generated step sources (``hbma_steps.c`` and ``hbma_steps.h``)
STEPS_NAME = "hbma_steps"
#: the generated steps as a shared library (built beside the program by :func:`build_c`)
LIBRARY = f"lib{STEPS_NAME}.so"
#: compiler flags of the C loop: no fast-math, so it rounds as the Python path's Functions do (at any
#: level: the per-step Functions' -O3 of hbma_ctrl.core.codegen.HOT_OPT gives the same bits); -O1 for
#: half the build time of -O2 (``codegen --opt`` picks another)
CFLAGS = ("-O1", "-std=c99")
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


def _dense(fun: ca.Function) -> ca.Function:
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
    (:func:`build_c` writes ``libhbma_steps.so`` beside the program), the very code the C loop runs.
    """
    spec.validate()
    sig = {k: v.copy() for k, v in spec.signals.items()}
    fast = {}
    for f in spec.functions():
        fun = _dense(f) if library is None else ca.external(f.name(), str(library))
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


def _c_array(values) -> str:
    vals = np.asarray(values, dtype=float).ravel()
    if vals.size == 0:
        return "{0.0}"
    parts = []
    for v in vals:
        if np.isnan(v):
            parts.append("NAN")
        elif np.isinf(v):
            parts.append("INFINITY" if v > 0 else "-INFINITY")
        else:
            parts.append(repr(float(v)))  # repr round-trips a double exactly
    lines = [", ".join(parts[i:i + 6]) for i in range(0, len(parts), 6)]
    return "{\n  " + ",\n  ".join(lines) + "\n}"


def _cname(name: str) -> str:
    out = "".join(ch if ch.isalnum() else "_" for ch in name)
    return out if out and not out[0].isdigit() else "s_" + out


def _template() -> str:
    return resources.files("hbma_ctrl.core").joinpath("c/closed_loop.c.in").read_text()


def write_c(spec: LoopSpec, out_dir: Path | str) -> list:
    """Write the generated step sources, ``loop_data.h``, ``closed_loop.c``, a ``Makefile`` and
    ``README.txt`` into ``out_dir``; returns the written paths."""
    spec.validate()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    funs = [_dense(f) for f in spec.functions()]
    cg = ca.CodeGenerator(f"{STEPS_NAME}.c", {"with_header": True, "main": False})
    for f in funs:
        cg.add(f)
    cg.generate(str(out) + os.sep)
    stages = spec.stage_list()
    sig_c = {k: "sig_" + _cname(k) for k in spec.signals}

    data = [f"/* Data of the closed loop \"{spec.name}\" (SI): initial signals and per-tick streams. */",
            "#ifndef LOOP_DATA_H", "#define LOOP_DATA_H", "#include <math.h>",
            f"#define N_TICKS {int(spec.n_ticks)}L", f"#define DT {float(spec.dt)!r}",
            f"#define LOG_HEADER \"{','.join(spec.header())}\""]
    for k, v in spec.signals.items():
        data.append(f"static double {sig_c[k]}[{max(v.size, 1)}] = {_c_array(v)};")
    for k, a in spec.streams.items():
        data.append(f"static const double stream_{_cname(k)}[{max(a.size, 1)}] = {_c_array(a)};")
    data.append("#endif")
    (out / "loop_data.h").write_text("\n".join(data) + "\n")

    code, init, tick, times, free = [], [], [], [], []
    calls = {f.name(): 1 for f in funs}  # most calls each Function can get: sizes its time buffer
    for st in stages:
        if st != LOG:
            calls[st.name] += -(-spec.n_ticks // st.every) * st.repeat
    for f in funs:
        n = _cname(f.name())
        code.append(f"static work_t wk_{n};")
        code.append(f"static double* tm_{n};  /* call times, s */\nstatic long ntm_{n};\n"
                    f"static long nrc_{n};  /* calls that returned non-zero (a solver's failure flag) */")
        for i in range(f.n_out()):
            code.append(f"static double out_{n}_{i}[{max(f.nnz_out(i), 1)}];")
        init.append(f"""  {{
    casadi_int sz_arg, sz_res, sz_iw, sz_w;
    {f.name()}_work(&sz_arg, &sz_res, &sz_iw, &sz_w);
    wk_{n}.arg = (const casadi_real**)xmalloc(sizeof(casadi_real*) * (size_t)sz_arg);
    wk_{n}.res = (casadi_real**)xmalloc(sizeof(casadi_real*) * (size_t)sz_res);
    wk_{n}.iw = (casadi_int*)xmalloc(sizeof(casadi_int) * (size_t)sz_iw);
    wk_{n}.w = (casadi_real*)xmalloc(sizeof(casadi_real) * (size_t)sz_w);
    {f.name()}_incref();
    wk_{n}.mem = {f.name()}_checkout();
    tm_{n} = (double*)xmalloc(sizeof(double) * (size_t){calls[f.name()]});
    ntm_{n} = 0;
  }}""")
        free.append(f"  {f.name()}_release(wk_{n}.mem);\n  {f.name()}_decref();\n"
                    f"  free(wk_{n}.arg); free(wk_{n}.res); free(wk_{n}.iw); free(wk_{n}.w); free(tm_{n});")
        sep = '""' if f is funs[0] else '","'
        fmt = (r'"%s\n    \"' + f.name() + r'\": {\"calls\": %ld, \"median_us\": %.6g, \"p99_us\": %.6g, '
               r'\"max_us\": %.6g, \"nonzero_returns\": %ld}"')
        times.append(f"""  qsort(tm_{n}, (size_t)ntm_{n}, sizeof(double), cmp_double);
  fprintf(js, {fmt},
          {sep}, ntm_{n}, 1e6 * percentile(tm_{n}, ntm_{n}, 0.5),
          1e6 * percentile(tm_{n}, ntm_{n}, 0.99), ntm_{n} ? 1e6 * tm_{n}[ntm_{n} - 1] : 0.0, nrc_{n});""")
    for k, a in spec.streams.items():
        m = a.shape[1]
        tick.append(f"    memcpy({sig_c[k]}, stream_{_cname(k)} + k * {m}, sizeof(double) * {m});")
    for st in stages:
        if st == LOG:
            fields = ["t"] + [f"{sig_c[c.signal]}[{c.index}] * {float(c.scale)!r}" for c in spec.log]
            tick.append(f"    fprintf(csv, \"{','.join(['%.17g'] * len(fields))}\\n\", {', '.join(fields)});")
            continue
        f = st.fun
        n = _cname(st.name)
        body = [f"wk_{n}.arg[{i}] = {sig_c[s]};" for i, s in enumerate(st.inputs)]
        body += [f"wk_{n}.res[{i}] = out_{n}_{i};" for i in range(f.n_out())]
        if st.fails_to is not None:
            body.append(f"out_{n}_{st.outputs.index(st.fails_to)}[0] = NAN;  /* a failed call leaves it unwritten */")
        body += ["double t0 = now_s();",
                 f"int rc = {f.name()}(wk_{n}.arg, wk_{n}.res, wk_{n}.iw, wk_{n}.w, wk_{n}.mem);",
                 f"tm_{n}[ntm_{n}] = now_s() - t0;",
                 f"tick_s += tm_{n}[ntm_{n}++];",
                 f"if (rc) ++nrc_{n};"]
        body += [f"memcpy({sig_c[s]}, out_{n}_{i}, sizeof(double) * {f.numel_out(i)});"
                 for i, s in enumerate(st.outputs) if s is not None]
        if st.stop_on is not None:
            body.append(f"if ({sig_c[st.stop_on]}[0] != 0.0) break;")
        conds = [f"k % {st.every} == 0"] if st.every > 1 else []
        if st.gate is not None:
            conds.append(f"{sig_c[st.gate]}[0] {'==' if st.gate_off else '!='} 0.0")
        cond = f"if ({' && '.join(conds)}) " if conds else ""
        loop = f"for (int rep = 0; rep < {st.repeat}; ++rep) " if st.repeat > 1 or st.stop_on else ""
        tick.append(f"    {cond}{loop}{{  /* {st.name} */\n      " + "\n      ".join(body) + "\n    }")
    src = (_template().replace("@NAME@", spec.name).replace("@HEADER@", f"{STEPS_NAME}.h")
           .replace("@STAGE_CODE@", "\n".join(code)).replace("@STAGE_INIT@", "\n".join(init))
           .replace("@TICK@", "\n".join(tick)).replace("@TIMES@", "\n".join(times))
           .replace("@STAGE_FREE@", "\n".join(free)))
    (out / "closed_loop.c").write_text(src)
    line = build_line(source=(out / f"{STEPS_NAME}.c").read_text())
    cf, lf = solver_flags((out / f"{STEPS_NAME}.c").read_text())
    (out / "Makefile").write_text(
        "# Build the closed loop (no Python needed): make && ./closed_loop\n"
        f"CC ?= cc\nCFLAGS ?= {' '.join(CFLAGS)}\nSOLVER_CFLAGS = {' '.join(cf)}\nSOLVER_LIBS = {' '.join(lf)}\n\n"
        f"closed_loop: closed_loop.c {STEPS_NAME}.c {STEPS_NAME}.h loop_data.h\n"
        f"\t$(CC) $(CFLAGS) $(SOLVER_CFLAGS) -o $@ closed_loop.c {STEPS_NAME}.c $(SOLVER_LIBS) -lm\n\n"
        "run: closed_loop\n\t./closed_loop .\n\n.PHONY: run\n")
    stage_text = "\n".join(
        f"  {st.name:14s} every {st.every} tick(s)"
        + (f" while {st.gate} {'== 0' if st.gate_off else '!= 0'}" if st.gate else "")
        + (f", up to {st.repeat} calls" if st.repeat > 1 else "")
        + (f" (stop when {st.stop_on} != 0)" if st.stop_on else "")
        + f": ({', '.join(st.inputs)}) -> ({', '.join(s or '-' for s in st.outputs)})"
        if st != LOG else "  (trajectory row)" for st in stages)
    (out / "README.txt").write_text(
        f"Closed loop \"{spec.name}\" generated by hbma-ctrl codegen: {spec.n_ticks} ticks of "
        f"{spec.dt * 1e3:g} ms.\n\n"
        "Build and run (a C99 compiler and libm"
        + (", and the QP solver's shared library shipped in the casadi package" if "-l" in line.replace("-lm", "")
           else "") + f"; no Python):\n  {line}\n  ./closed_loop [OUT_DIR]\n"
        "or: make run\n\n"
        f"Files: {STEPS_NAME}.c / {STEPS_NAME}.h (the casadi-generated step Functions), loop_data.h (initial "
        "signals and per-tick data), closed_loop.c (the loop).\n"
        "Outputs: trajectory.csv (one row per tick, edge units in the column names, %.17g), times.json (per "
        "Function: calls, median/p99/max wall time of one call, us, and calls that returned non-zero; per tick: "
        "the sum of its calls; clock_gettime MONOTONIC).\n\n"
        f"Stages per tick, in order (signals SI):\n{stage_text}\n"
        + "".join(f"\n{k}: {v}" for k, v in spec.meta.items()) + "\n")
    return [out / f"{STEPS_NAME}.c", out / f"{STEPS_NAME}.h", out / "loop_data.h", out / "closed_loop.c",
            out / "Makefile", out / "README.txt"]


#: header of a QP solver the generated source includes -> the libraries it links (shipped with casadi)
_SOLVER_LIBS = {"hpipm_d_ocp_qp.h": ("hpipm", "blasfeo"), "osqp/osqp.h": ("osqp",), "daqp/api.h": ("daqp",)}


def solver_flags(source: str) -> tuple[list, list]:
    """(compile flags, link flags) for the QP solvers the generated ``source`` includes: their headers
    and shared libraries ship inside the casadi package (qrqp needs none: self-contained C)."""
    libs = [lib for header, names in _SOLVER_LIBS.items() if f"#include <{header}>" in source for lib in names]
    if not libs:
        return [], []
    root = Path(ca.__file__).parent
    return [f"-I{root / 'include'}"], [f"-L{root}", *(f"-l{lib}" for lib in libs), f"-Wl,-rpath,{root}"]


def build_line(cc: str = "cc", opt: str = CFLAGS[0], source: str = "") -> str:
    """The command that builds the loop in its directory (``opt``: the optimisation flag; ``source``: the
    generated steps, for the QP solvers' flags)."""
    cf, lf = solver_flags(source)
    return " ".join([cc, opt, *CFLAGS[1:], *cf, "-o closed_loop closed_loop.c", f"{STEPS_NAME}.c", *lf, "-lm"])


def find_compiler() -> str | None:
    """The system C compiler (cc, gcc or clang on PATH), or None."""
    for cc in ("cc", "gcc", "clang"):
        path = shutil.which(cc)
        if path:
            return path
    return None


#: optimisation flags a build may use (none enables fast-math: the rounding stays the Python path's)
OPT_FLAGS = ("-O0", "-O1", "-O2", "-O3")


def build_c(out_dir: Path | str, cc: str | None = None, opt: str = CFLAGS[0]) -> Path:
    """Compile the loop in ``out_dir`` with the system compiler and ``opt`` (one of :data:`OPT_FLAGS`):
    the program ``closed_loop`` and the shared library :data:`LIBRARY` of the same object code.
    RuntimeError with the compiler's message on failure."""
    if opt not in OPT_FLAGS:
        raise ValueError(f"--opt = '{opt}'; allowed: {', '.join(OPT_FLAGS)}")
    cc = cc or find_compiler()
    if cc is None:
        raise RuntimeError("no C compiler (cc, gcc or clang) on PATH")
    out = Path(out_dir)
    cf, lf = solver_flags((out / f"{STEPS_NAME}.c").read_text())
    flags = [opt, *CFLAGS[1:]]
    # one object file serves the program and the shared library the Python path loads
    for cmd in ([cc, *flags, *cf, "-fPIC", "-c", f"{STEPS_NAME}.c", "-o", f"{STEPS_NAME}.o"],
                [cc, "-shared", f"{STEPS_NAME}.o", "-o", LIBRARY, *lf, "-lm"],
                [cc, *flags, "-o", "closed_loop", "closed_loop.c", f"{STEPS_NAME}.o", *lf, "-lm"]):
        res = subprocess.run(cmd, cwd=out, capture_output=True, text=True)
        if res.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed: {res.stderr.strip()[:2000]}")
    return out / "closed_loop"


@dataclass
class CRun:
    """The C loop's trajectory (rows x columns), header and times.json content."""

    trajectory: np.ndarray
    header: list
    times: dict


def run_c(out_dir: Path | str, timeout: float = 600.0) -> CRun:
    """Run the built loop in ``out_dir``; read trajectory.csv and times.json."""
    out = Path(out_dir)
    res = subprocess.run([str(out / "closed_loop"), str(out)], capture_output=True, text=True, timeout=timeout)
    if res.returncode != 0:
        raise RuntimeError(f"closed_loop exited {res.returncode}: {res.stderr.strip()[:2000]}")
    return read_c(out)


def read_c(out_dir: Path | str) -> CRun:
    """The outputs of the loop run last in ``out_dir`` (trajectory.csv and times.json), without running it."""
    out = Path(out_dir)
    with (out / "trajectory.csv").open() as fh:
        header = fh.readline().strip().split(",")
    traj = np.loadtxt(out / "trajectory.csv", delimiter=",", skiprows=1, ndmin=2)
    return CRun(traj, header, json.loads((out / "times.json").read_text()))


def compare(spec: LoopSpec, py: PythonRun, c: CRun) -> dict:
    """Largest absolute difference per column between the two trajectories, in SI (column / scale)."""
    if c.trajectory.shape != py.trajectory.shape:
        raise ValueError(f"trajectories differ in shape: C {c.trajectory.shape}, Python {py.trajectory.shape}")
    scales = [1.0] + [c_.scale for c_ in spec.log]
    out = {}
    for j, name in enumerate(spec.header()):
        a, b = py.trajectory[:, j] / scales[j], c.trajectory[:, j] / scales[j]
        same_nan = np.isnan(a) & np.isnan(b)
        d = np.where(same_nan, 0.0, np.abs(a - b))
        out[name] = float(np.max(d)) if d.size else 0.0
    return out


def time_summary(samples_s) -> dict:
    """calls, median_us, p99_us, max_us of call times given in s (numpy's linear percentiles)."""
    a = np.asarray(samples_s, dtype=float)
    if a.size == 0:
        return {"calls": 0, "median_us": None, "p99_us": None, "max_us": None}
    return {"calls": int(a.size), "median_us": float(np.median(a) * 1e6),
            "p99_us": float(np.percentile(a, 99) * 1e6), "max_us": float(a.max() * 1e6)}


def bench(spec: LoopSpec, out_dir: Path | str, opt: str = CFLAGS[0], cc: str | None = None,
          python_vm: bool = False) -> dict:
    """Generate, build and run the C loop in ``out_dir``, run the Python path, and compare them in one run.

    The Python path calls the same compiled Functions (the generated library, through buffers);
    ``python_vm`` adds a run on casadi's virtual machine (the Functions as built, uncompiled).
    Returns the JSON-ready result: per Function (and per tick, ``tick``: the sum of a tick's calls) the
    C and Python call times (calls, median, p99, max, us) and the ratios Python / C of the medians and
    p99s; the largest absolute difference of the trajectories per column (SI) and overall; the wall
    times of each part (s).
    """
    out = Path(out_dir)
    wall = {}
    t0 = time.perf_counter()
    write_c(spec, out)
    wall["generate"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    build_c(out, cc, opt)
    wall["build"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    c = run_c(out)
    wall["c_run"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    py = run_python(spec, out / LIBRARY)
    wall["python_run"] = time.perf_counter() - t0
    diff = compare(spec, py, c)
    vm = None
    if python_vm:
        t0 = time.perf_counter()
        vm = run_python(spec)
        wall["python_vm_run"] = time.perf_counter() - t0
    funs = {}
    for name, ct in c.times["functions"].items():
        row = {"c": ct, "python": time_summary(py.times.get(name, []))}
        if vm is not None:
            row["python_vm"] = time_summary(vm.times.get(name, []))
        for q in ("median_us", "p99_us"):
            a, b = row["python"].get(q), ct.get(q)
            row[f"ratio_{q[:-3]}"] = (a / b) if a and b else None
        funs[name] = row
    tick = {"c": c.times["tick"], "python": time_summary(py.tick)}
    if vm is not None:
        tick["python_vm"] = time_summary(vm.tick)
    for q in ("median_us", "p99_us"):
        a, b = tick["python"].get(q), tick["c"].get(q)
        tick[f"ratio_{q[:-3]}"] = (a / b) if a and b else None
    res = {"loop": spec.name, "ticks": spec.n_ticks, "tick_s": spec.dt, "opt": opt, "tick": tick,
           "python_path": "the generated library through casadi.external and buffers (FastFunction)",
           "functions": funs, "max_abs_diff_si": diff, "max_abs_diff_si_all": max(diff.values()) if diff else 0.0,
           "wall_s": wall, "meta": dict(spec.meta)}
    if vm is not None:
        dv = compare(spec, vm, c)
        res["vm_max_abs_diff_si"] = dv
        res["vm_max_abs_diff_si_all"] = max(dv.values()) if dv else 0.0
    return res
