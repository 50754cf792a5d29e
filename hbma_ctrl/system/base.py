"""What a driver uses of a system, the chamber's and the robot's alike (SI).

The lockstep driver (:func:`hbma_ctrl.system.run.run_lockstep`) and the rig daemon's real-time loop
drive a :class:`System`: one ``tick`` per sample period, the events and faults it found since the
last call, its status rows (targets, estimates, layer poses) and setpoints. :class:`SystemBase` is what
the two systems share: their runtime loop's supervisor episodes as events, its statistics, and the
neutral values of the members a system may do without.
"""

from __future__ import annotations

import itertools
from typing import Protocol, runtime_checkable

import numpy as np

__all__ = ["System", "Neutral", "SystemBase", "SupervisorEpisodes"]


@runtime_checkable
class System(Protocol):
    """A chamber or robot system: ``n`` chambers named ``names``, pressure limit ``p_limit`` (Pa)."""

    kind: str
    n: int
    names: tuple
    p_limit: float

    @property
    def warming(self) -> bool:
        """True while a start-up calibration runs (before the loop closes)."""
        ...

    def tick(self, t: float, p: np.ndarray, held: np.ndarray | None = None) -> np.ndarray:
        """One period at time t (s) with the readings p (Pa, (n,)) -> the command u (3, n)."""
        ...

    def take_events(self) -> list[tuple[str, str]]:
        """(kind, cause) events since the last call."""
        ...

    def take_faults(self) -> list[tuple[str, int, str]]:
        """(kind, chamber, cause) faults found since the last call, which a daemon latches."""
        ...

    def burst_peak(self) -> float | None:
        """The burst test's largest sum so far, sigma (None without the test)."""
        ...

    def tick_timing(self) -> tuple[float, float, float] | None:
        """The last tick's (step, estimator, controller) times, s (None when not measured)."""
        ...

    def tick_parts(self) -> dict:
        """The last tick's finer parts (s) and the controller's report, by name ({} when none)."""
        ...

    def controller_report(self) -> dict | None:
        """The controller's report of its last step, a new dict every step, with its ``status``."""
        ...

    def targets(self) -> np.ndarray:
        """This period's target height per chamber, m (NaN = none)."""
        ...

    def effective_targets(self) -> np.ndarray:
        """The target height per chamber the controller works to (the target limited to what it can
        reach), m (NaN = none)."""
        ...

    def estimates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(height m, its std m, pressure Pa) per chamber."""
        ...

    def layers(self) -> list:
        """The estimated pose of every layer ([] for a chamber)."""
        ...

    def check_setpoint(self, request: dict) -> dict:
        """A setpoint request checked and clipped: {"applied", "clipped"} (ValueError when refused)."""
        ...

    def apply_setpoint(self, applied: dict, t: float) -> None:
        """Hold a checked setpoint from now on."""
        ...

    def stats(self) -> dict:
        """The run's statistics (ms, counts)."""
        ...


class SupervisorEpisodes:
    """The runtime supervisor's interventions as daemon events ("supervisor", "<chamber>: <cause>
    (<detail>)"), one per episode: a chamber's cause is passed on when it was not logged in the
    previous tick (the pressure guard and the stretch guard log every step they act; the run log
    would otherwise get one row per chamber and period)."""

    def __init__(self, supervisor, names):
        self.sup = supervisor
        self.names = tuple(names)
        self._seen = supervisor.logged
        self._prev: set = set()

    def take(self) -> list[tuple[str, str]]:
        """The episodes started since the last call (oldest first)."""
        sup = self.sup
        new = min(sup.logged - self._seen, len(sup.events))
        self._seen = sup.logged
        events = list(itertools.islice(reversed(sup.events), new))[::-1] if new > 0 else []
        out, cur = [], set()
        for e in events:
            key = (e.chamber, e.cause)
            if key not in self._prev and key not in cur:
                name = self.names[e.chamber] if 0 <= e.chamber < len(self.names) else str(e.chamber)
                out.append(("supervisor", f"{name}: {e.cause}" + (f" ({e.detail})" if e.detail else "")))
            cur.add(key)
        self._prev = cur
        return out


class Neutral:
    """The neutral values of the :class:`System` members a system may do without: no faults of its
    own, no burst test, no timing or report of its parts."""

    def take_faults(self) -> list[tuple[str, int, str]]:
        """No faults of its own."""
        return []

    def burst_peak(self) -> float | None:
        """No burst test."""
        return None

    def tick_timing(self) -> tuple[float, float, float] | None:
        """Not measured."""
        return None

    def tick_parts(self) -> dict:
        """No parts."""
        return {}

    def controller_report(self) -> dict | None:
        """No report."""
        return None


class SystemBase(Neutral):
    """A system over the runtime loop ``loop`` (its ``supervisor`` and ``stats()``) of the chambers
    ``names`` (pressure limit ``p_limit``, Pa), with the :class:`Neutral` values and no calibration."""

    warming: bool = False

    def __init__(self, loop, names, p_limit: float):
        self.loop = loop
        self.names = tuple(names)
        self.n = len(self.names)
        self.p_limit = float(p_limit)
        self._events: list[tuple[str, str]] = []  # the system's own, before the supervisor's
        self._episodes = SupervisorEpisodes(loop.supervisor, self.names)

    def take_events(self) -> list[tuple[str, str]]:
        """(kind, cause) events since the last call: the system's own (a calibration's start and
        outcome), then the supervisor's interventions (:class:`SupervisorEpisodes`: interlocks, vents,
        a lost estimate, fallbacks)."""
        ev, self._events = self._events, []
        return ev + self._episodes.take()

    def stats(self) -> dict:
        """The runtime loop's statistics (ms, counts)."""
        return self.loop.stats()

    def effective_targets(self) -> np.ndarray:
        """The targets as they are (a controller that reports no reach works to them)."""
        return self.targets()
