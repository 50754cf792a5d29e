"""What the daemon reads of its host: its memory, the host's steal time, a thread's resource usage."""

from __future__ import annotations

import os
import resource

__all__ = ["rss_mb", "steal_ms", "thread_usage"]


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
