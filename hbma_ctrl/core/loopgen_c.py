"""The C side of a closed loop (:class:`hbma_ctrl.core.loopgen.LoopSpec`): sources, build, run, comparison.

:func:`write_c` writes one ``casadi.CodeGenerator`` source and header with every Function
(``with_header``, ``main`` off), ``loop_data.h`` (the initial signals and the streams) and
``closed_loop.c`` from the template ``c/closed_loop.c.in``: the loop with nothing but the generated
code and libc/libm, writing ``trajectory.csv`` and ``times.json``. :func:`build_c` and :func:`run_c`
build and run it; :func:`compare` measures it against the Python path
(:func:`hbma_ctrl.core.loopgen.run_python`); :func:`bench` builds, runs and times both paths. The
application builds the spec of a scenario (``hbma-ctrl codegen``).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import casadi as ca
import numpy as np

from hbma_ctrl.core.loopgen import LIBRARY, LOG, STEPS_NAME, LoopSpec, PythonRun, dense_function, run_python

__all__ = ["write_c", "c_array", "stage_guard", "build_c", "run_c", "read_c", "compare", "find_compiler", "CFLAGS", "OPT_FLAGS", "CRun",
           "time_summary", "build_line", "solver_flags", "bench"]

#: compiler flags of the C loop: no fast-math, so it rounds as the Python path's Functions do (at any
#: level: the per-step Functions' -O3 of hbma_ctrl.core.codegen.HOT_OPT gives the same bits); -O1 for
#: half the build time of -O2 (``codegen --opt`` picks another)
CFLAGS = ("-O1", "-std=c99")


def stage_guard(st, k: str, flag) -> tuple[str, str | None]:
    """How a tick runs one stage ``st`` of a loop spec, in C: the prefix of its block (the condition
    ``every`` and ``gate`` set, the repeat loop ``repeat`` and ``stop_on`` ask for) and the line that
    ends the repeats (None without ``stop_on``). ``k`` is the tick counter's C expression, ``flag(name)``
    a signal's first element's."""
    conds = [f"{k} % {st.every} == 0"] if st.every > 1 else []
    if st.gate is not None:
        conds.append(f"{flag(st.gate)} {'==' if st.gate_off else '!='} 0")
    cond = f"if ({' && '.join(conds)}) " if conds else ""
    loop = f"for (int rep = 0; rep < {st.repeat}; ++rep) " if st.repeat > 1 or st.stop_on else ""
    stop = f"if ({flag(st.stop_on)} != 0) break;" if st.stop_on is not None else None
    return cond + loop, stop


def c_array(values) -> str:
    """A C initialiser of ``values`` (flattened) that round-trips every double, NaN and infinities
    included; ``{0.0}`` for none (C has no empty initialiser)."""
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
    funs = [dense_function(f) for f in spec.functions()]
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
        data.append(f"static double {sig_c[k]}[{max(v.size, 1)}] = {c_array(v)};")
    for k, a in spec.streams.items():
        data.append(f"static const double stream_{_cname(k)}[{max(a.size, 1)}] = {c_array(a)};")
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
        prefix, stop = stage_guard(st, "k", lambda name: f"{sig_c[name]}[0]")
        body += [stop] if stop else []
        tick.append(f"    {prefix}{{  /* {st.name} */\n      " + "\n      ".join(body) + "\n    }")
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
