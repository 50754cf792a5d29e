"""Python's garbage collector in a real-time loop: frozen start-up objects, and every pause timed.

A full (generation-2) collection walks every container object the process holds: the daemon's robot
process holds about 165 000 after start-up (casadi, numpy, pydantic, FastAPI), and one full
collection of them took 32-42 ms of CPU on a 2-core machine (``gc.collect(2)`` after the runner's
first ticks), three to four periods at 100 Hz, in whichever thread allocated last. :func:`gc.freeze`
(objects alive at freeze time move to a permanent generation that collections skip) is called once
the daemon is built, so a full collection then walks only what was allocated since (0.0 ms right
after the freeze; the longest pause of any collection in an hour's robot soak was 0.7 ms). Objects
are still freed by reference counting; only reference cycles made before the freeze wait until
:meth:`GcWatch.close` unfreezes them. (The soak's rare slow ticks were not the collector's: none
had a collection during it.)

:class:`GcWatch` also times every collection (``gc.callbacks``) so a slow tick's event can say how
much of it was the collector's, and the run's stats report the collections and the longest pause.
"""

from __future__ import annotations

import contextlib
import gc
import time

__all__ = ["GcWatch"]


class GcWatch:
    """Freeze the objects alive now (``freeze=True``) and time every collection until :meth:`close`.

    ``total_s`` (s) and ``count`` grow with every collection in any thread; ``max_s`` (s) is the longest
    pause and ``by_generation`` counts collections by generation. :meth:`mark` / :meth:`since` give the
    pauses between two points (the loop marks before each tick)."""

    def __init__(self, freeze: bool = True):
        self.count = 0
        self.total_s = 0.0
        self.max_s = 0.0
        self.by_generation = [0, 0, 0]
        self._t0: float | None = None
        self.frozen = False
        if freeze:
            # what is garbage now is collected once, outside any period, before the rest is frozen
            gc.collect()
            gc.freeze()
            self.frozen = True
        gc.callbacks.append(self._callback)
        self._open = True

    def _callback(self, phase: str, info: dict) -> None:
        if phase == "start":
            self._t0 = time.perf_counter()
            return
        if self._t0 is None:
            return
        d = time.perf_counter() - self._t0
        self._t0 = None
        self.count += 1
        self.total_s += d
        self.max_s = max(self.max_s, d)
        g = int(info.get("generation", 0))
        if 0 <= g < 3:
            self.by_generation[g] += 1

    def mark(self) -> tuple[int, float]:
        """(collections, total pause s) so far, for :meth:`since`."""
        return self.count, self.total_s

    def since(self, mark: tuple[int, float]) -> tuple[int, float]:
        """Collections and their total pause (s) since ``mark``."""
        return self.count - mark[0], self.total_s - mark[1]

    def stats(self) -> dict:
        """For daemon_stats.json: ``gc_collections`` (by generation 0, 1, 2), ``gc_pause_ms_max``,
        ``gc_pause_ms_total``, ``gc_frozen`` (whether start-up objects were frozen)."""
        return {"gc_collections": list(self.by_generation), "gc_pause_ms_max": self.max_s * 1e3,
                "gc_pause_ms_total": self.total_s * 1e3, "gc_frozen": self.frozen}

    def close(self) -> None:
        """Stop timing and unfreeze (idempotent): a process that goes on (a test suite) collects the
        start-up objects again."""
        if not self._open:
            return
        self._open = False
        with contextlib.suppress(ValueError):
            gc.callbacks.remove(self._callback)
        if self.frozen:
            gc.unfreeze()
