"""What the daemon asks of its host and reads from it: a short scheduler slice, memory, steal time.

A short slice: Linux's scheduler runs a thread soon after it wakes, without privileges (EEVDF's
custom slice).

Linux's fair scheduler (EEVDF, kernel 6.6 on; a per-task slice from 6.12) picks the runnable task with
the earliest virtual deadline, which is its eligible time plus its slice. A task that asks for a short
slice (``sched_setattr`` with ``sched_runtime``, 0.1 to 100 ms) gets an early deadline when it wakes
and preempts a task with a longer one, for the same share of the CPU: its nice value, its weight and
its class are kept. That is what the daemon's loop (asleep most of its period, due at its deadline),
its API link and the API's server want on a host shared with other work: to run when their event comes,
not after another task's slice. No capability is needed, unlike a real-time class (``chrt -f``), which
the daemon keeps when it is started in one (the ask is then not made).

Elsewhere (another OS, an older kernel that ignores the slice of a fair task, a seccomp filter) the ask
does nothing and says so: :func:`ask_short_slice` returns None.
"""

from __future__ import annotations

import ctypes
import os
import platform
import resource
import sys

__all__ = ["SLICE_S", "ask_short_slice", "rss_mb", "steal_ms", "thread_slice_s", "thread_usage"]

#: the slice asked for, s: the kernel's lowest (its range is 0.1 to 100 ms; its default is 0.7 to 3 ms
#: by the number of CPUs)
SLICE_S = 1e-4

# (sched_setattr, sched_getattr) by machine: the C library of Debian 12 has no wrapper for them
_SYSCALLS = {"x86_64": (314, 315), "aarch64": (274, 275), "armv7l": (380, 381), "armv6l": (380, 381),
             "riscv64": (274, 275)}
_FAIR = (0, 3)  # SCHED_OTHER, SCHED_BATCH: the classes whose slice this sets


class _SchedAttr(ctypes.Structure):
    """``struct sched_attr`` (include/uapi/linux/sched/types.h), its version with utilisation clamps."""
    _fields_ = [("size", ctypes.c_uint32), ("sched_policy", ctypes.c_uint32), ("sched_flags", ctypes.c_uint64),
                ("sched_nice", ctypes.c_int32), ("sched_priority", ctypes.c_uint32),
                ("sched_runtime", ctypes.c_uint64), ("sched_deadline", ctypes.c_uint64),
                ("sched_period", ctypes.c_uint64), ("sched_util_min", ctypes.c_uint32),
                ("sched_util_max", ctypes.c_uint32)]


def _calls():
    if not sys.platform.startswith("linux"):
        return None
    nums = _SYSCALLS.get(platform.machine())
    if nums is None:
        return None
    try:
        libc = ctypes.CDLL(None, use_errno=True)
    except OSError:
        return None
    return libc, nums


def _get(libc, nr: int) -> _SchedAttr | None:
    attr = _SchedAttr()
    attr.size = ctypes.sizeof(_SchedAttr)
    if libc.syscall(nr, 0, ctypes.byref(attr), ctypes.sizeof(_SchedAttr), 0) != 0:
        return None
    return attr


def thread_slice_s() -> float | None:
    """The calling thread's slice under the fair scheduler, s; None where it has none or it cannot be read
    (another OS, a real-time class)."""
    calls = _calls()
    if calls is None:
        return None
    libc, (_, get_nr) = calls
    attr = _get(libc, get_nr)
    if attr is None or attr.sched_policy not in _FAIR or attr.sched_runtime == 0:
        return None
    return attr.sched_runtime * 1e-9


def ask_short_slice(slice_s: float = SLICE_S) -> float | None:
    """Ask for a slice of ``slice_s`` (s) for the calling thread (module doc), keeping its class and
    nice value; the slice the kernel then reports, s, or None when the ask was not made or not taken
    (another OS or machine, a real-time or idle class, a kernel that ignores it)."""
    calls = _calls()
    if calls is None:
        return None
    libc, (set_nr, get_nr) = calls
    attr = _get(libc, get_nr)
    if attr is None or attr.sched_policy not in _FAIR:
        return None
    attr.size = ctypes.sizeof(_SchedAttr)
    attr.sched_flags = 0
    attr.sched_runtime = int(round(slice_s * 1e9))
    if libc.syscall(set_nr, 0, ctypes.byref(attr), 0) != 0:
        return None
    got = thread_slice_s()
    # a kernel before per-task slices takes the call and keeps its own slice: not what was asked
    return got if got is not None and abs(got - slice_s) <= 1e-6 else None


def rss_mb() -> float:
    """Resident set size of this process, MB (/proc/self/statm; the peak from getrusage elsewhere)."""
    try:
        with open("/proc/self/statm") as fh:
            pages = int(fh.read().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 1e6
    except (OSError, ValueError, IndexError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3


def steal_ms() -> float | None:
    """The host's steal time summed over this machine's CPUs, ms (/proc/stat; None where there is none)."""
    try:
        with open("/proc/stat") as fh:
            f = fh.readline().split()
        return float(f[8]) * 1e3 / os.sysconf("SC_CLK_TCK") if f and f[0] == "cpu" and len(f) > 8 else None
    except (OSError, ValueError, IndexError):
        return None


def thread_usage():
    """This thread's resource usage (getrusage RUSAGE_THREAD: user and system time, page faults,
    preemptions), None where the platform has none."""
    try:
        return resource.getrusage(resource.RUSAGE_THREAD)
    except (AttributeError, OSError, ValueError):
        return None
