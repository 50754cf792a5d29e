"""Low-overhead evaluation of casadi Functions: compiled once (cached on disk), called via buffers.

A Python call of a casadi Function costs tens of microseconds of argument conversion, and the
virtual machine evaluates a large SX graph slowly. For the 100 us per step budget of the estimators
this module

1. generates C code for the Function, compiles it with the system C compiler (``cc``/``gcc``,
   ``-O1`` by default, :data:`HOT_OPT` for the per-step Functions) into a shared library cached
   under ``$HBMA_CTRL_CACHE`` (default
   ``~/.cache/hbma-ctrl``), keyed by the SHA-1 of the generated source, so each model is compiled
   once per machine (a few seconds) and reused by every process, and
2. evaluates it through :meth:`casadi.Function.buffer` with preallocated numpy arrays.

Without a compiler (or with ``compile=False``) the Function runs on casadi's virtual machine,
still through buffers; results are identical up to rounding.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

import casadi as ca
import numpy as np

__all__ = ["FastFunction", "compiled", "casadi_lib_flags", "cache_dir", "has_compiler", "HOT_OPT", "HOT_FLAGS", "OPT_ENV", "NATIVE_FLAGS", "cpu_signature", "is_nan", "is_finite"]

#: the optimisation level and flags of the Functions called every step whose compilation is short
#: (the EKF step and its reference path's parts, the UKF's propagation, the robot's EKF bank, the
#: chamber RTI's QP data). Their code is long straight-line arithmetic that -O3 schedules better, and
#: -fno-semantic-interposition lets it inline the generated subfunctions (global symbols, which
#: position-independent code otherwise calls through the symbol table). Measured on recorded inputs,
#: every output bit-identical: the exact EKF step's call 21.6 -> 13.3 us median (-O3 alone 15.9), the
#: RTI's QP data 80 -> 70 us (-O3 alone no faster), for 4-6 s of compilation once per machine instead
#: of 0.1-3 s. Not the fast-math flags: results must not depend on the compiler's choices. The
#: robot's QP data (229 -> 185 us for 9 chambers) keeps -O1: its compilation grows with the chambers
#: (12.6 s for 9)
HOT_OPT = "-O3"
HOT_FLAGS = ("-fno-semantic-interposition",)
#: an environment variable that, set, replaces every build's optimisation flag (e.g. ``-O0``: a build in
#: seconds instead of a minute, for checks of what generated code computes rather than how fast)
OPT_ENV = "HBMA_CTRL_CC_OPT"
#: code for this machine's processor (its vector units and fused multiply-adds), for the fatrop solver
#: only: its generated NLP functions are most of a solve, 6.6 -> 5.1 ms per step at N = 20 (``bench
#: mpc``, both in one run). Not for the per-step Functions above: their outputs are compared bit for bit
#: with other builds, and this changes the last bit (the exact EKF step's outputs differ on recorded
#: inputs, enough to take another branch in 483 of 7200 steps, even without the fused operations).
#: A library built with it is keyed by the processor too (:func:`cpu_signature`): a cache shared by
#: machines never hands one an instruction it lacks
NATIVE_FLAGS = ("-march=native",)

_MEMO: dict = {}


def is_nan(v):
    """1 where the casadi expression v is NaN (it compares false both ways; casadi simplifies
    ``v != v`` to false, so the test is written with two comparisons)."""
    return ca.logic_not(ca.logic_or(v <= 0, v > 0))


def is_finite(v):
    """1 where the casadi expression v is a finite number (neither NaN nor +-inf)."""
    return ca.logic_and(v > -ca.inf, v < ca.inf)


def cache_dir() -> Path:
    """Directory of compiled model libraries."""
    return Path(os.environ.get("HBMA_CTRL_CACHE", Path.home() / ".cache" / "hbma-ctrl"))


def cpu_signature() -> str:
    """The processor's model and instruction-set extensions (``/proc/cpuinfo``; elsewhere the platform's
    machine and processor strings): what a ``-march=native`` library is valid for."""
    import platform

    try:
        fields = {}
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if not line.strip() and fields:
                    break  # the first processor's block is enough (the file repeats it per core)
                key, _, val = line.partition(":")
                key = key.strip()
                if key in ("model name", "flags", "Features", "CPU implementer", "CPU part") and key not in fields:
                    fields[key] = val.strip()
        if fields:
            return "|".join(f"{k}={fields[k]}" for k in sorted(fields))
    except OSError:
        pass
    return f"{platform.machine()}|{platform.processor()}"


def _compiler() -> str | None:
    for cc in ("cc", "gcc", "clang"):
        if shutil.which(cc):
            return cc
    return None


def has_compiler() -> bool:
    """Is there a system C compiler (cc, gcc or clang) for :func:`compiled`?"""
    return _compiler() is not None


def casadi_lib_flags(libs: Sequence[str]) -> list[str]:
    """Compiler and linker flags for generated C that calls solver libraries shipped inside the casadi
    package (``libs``: e.g. ``["-losqp"]``): its headers, the libraries and their run-time path. No
    libraries: no flags."""
    if not libs:
        return []
    root = Path(ca.__file__).parent
    return [f"-I{root / 'include'}", f"-L{root}", *libs, f"-Wl,-rpath,{root}"]


def compiled(fun: ca.Function, opt: str = "-O1", flags: Sequence[str] = (),
             on_failure: str = "fallback", notice: str | None = None) -> ca.Function | None:
    """The Function compiled to a shared library (cached by source and flags), or itself without a compiler.

    ``opt`` is the optimisation flag (:data:`OPT_ENV` in the environment replaces it); no level enables
    fast-math, so results do not depend on it.
    ``flags``: more compiler and linker flags (e.g. a QP solver's headers and library); a build that
    fails with any of :data:`HOT_FLAGS` or :data:`NATIVE_FLAGS` among them is tried again without them.
    ``on_failure``: 'fallback' returns ``fun`` when there is no compiler or the build fails, 'none'
    returns None then. ``notice``: a line written to stderr when the library is not cached and the
    build starts (for builds that take a minute: the user sees why nothing happens).
    """
    cc = _compiler()
    if cc is None:
        return fun if on_failure == "fallback" else None
    opt = os.environ.get(OPT_ENV) or opt
    name = fun.name()
    flags = list(flags)
    with tempfile.TemporaryDirectory() as tmp:
        cg = ca.CodeGenerator(f"{name}.c", {"with_header": False})
        cg.add(fun)
        src_path = Path(tmp) / f"{name}.c"
        cg.generate(tmp + os.sep)  # a directory prefix: the process's working directory is never changed
        src = src_path.read_bytes()
        tag = " ".join([opt, *flags])
        if any(f in NATIVE_FLAGS for f in flags):
            tag += " " + cpu_signature()
        key = hashlib.sha1(src + tag.encode()).hexdigest()[:16]
        if key in _MEMO:
            return _MEMO[key]
        d = cache_dir()
        d.mkdir(parents=True, exist_ok=True)
        lib = d / f"{name}_{key}.so"
        if not lib.exists():
            if notice:
                print(notice, file=sys.stderr, flush=True)
            out = Path(tmp) / "out.so"
            res = subprocess.run([cc, opt, "-fPIC", "-shared", str(src_path), "-o", str(out), *flags, "-lm"],
                                 capture_output=True, text=True)
            if res.returncode != 0:
                hot = [f for f in flags if f in HOT_FLAGS or f in NATIVE_FLAGS]
                if hot:  # a compiler that does not know a per-step flag still builds the Function without it
                    return compiled(fun, opt, [f for f in flags if f not in hot], on_failure, notice)
                return fun if on_failure == "fallback" else None
            fd, part = tempfile.mkstemp(dir=d, suffix=".so.part")
            os.close(fd)
            shutil.copyfile(out, part)
            os.replace(part, lib)  # atomic: parallel workers never see half a library
    ext = ca.external(name, str(lib))
    _MEMO[key] = ext
    return ext


class FastFunction:
    """Call a casadi Function with numpy inputs through preallocated buffers.

    ``compile``: run it as C compiled at ``opt`` with ``flags`` (:func:`compiled`). ``f(*args)`` copies each
    argument into its input buffer (dense, column-major), evaluates, and
    returns the list of output arrays (reused between calls: copy what you keep). Outputs are
    returned flat (nonzeros); :meth:`dense` reshapes one to its matrix shape.
    """

    def __init__(self, fun: ca.Function, compile: bool = True, opt: str = "-O1", flags: Sequence[str] = ()):
        self.fun = compiled(fun, opt, flags) if compile else fun
        f = self.fun
        self._sp_out = [f.sparsity_out(i) for i in range(f.n_out())]
        for i in range(f.n_in()):
            if not f.sparsity_in(i).is_dense():
                raise ValueError(f"{f.name()}: input {i} must be dense")
        self.inp = [np.zeros(f.nnz_in(i)) for i in range(f.n_in())]
        self.out = [np.zeros(f.nnz_out(i)) for i in range(f.n_out())]
        self._buf, self._eval = f.buffer()
        for i, a in enumerate(self.inp):
            self._buf.set_arg(i, memoryview(a))
        for i, a in enumerate(self.out):
            self._buf.set_res(i, memoryview(a))
        self._dense_idx = []
        for sp in self._sp_out:
            r, c = sp.get_triplet()
            self._dense_idx.append((np.asarray(r, dtype=int), np.asarray(c, dtype=int), sp.shape))

    def __call__(self, *args) -> list:
        """Evaluate; an argument given as None keeps the value of the previous call (constants)."""
        for dst, a in zip(self.inp, args):
            if a is None:
                continue
            if isinstance(a, float):
                dst[0] = a
            elif isinstance(a, np.ndarray) and a.ndim == 1:
                dst[:] = a
            else:
                dst[:] = np.ravel(a, order="F")
        self._eval()
        return self.out

    def eval(self) -> list:
        """Evaluate on the input buffers ``inp`` as they are (written in place by the caller); returns
        the output buffers ``out``."""
        self._eval()
        return self.out

    def dense(self, i: int) -> np.ndarray:
        """Output i of the last call as a dense matrix (a copy)."""
        r, c, shape = self._dense_idx[i]
        M = np.zeros(shape)
        M[r, c] = self.out[i]
        return M
