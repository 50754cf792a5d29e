"""What a driver uses of a system, the chamber's and the robot's alike (SI).

The lockstep driver (:func:`hbma_ctrl.system.run.run_lockstep`) and the rig daemon's real-time loop
drive a :class:`System`: one ``tick`` per sample period, the events and faults it found since the
last call, its status rows (targets, estimates, layer poses) and setpoints. :class:`SystemBase` gives
the members a system may do without their neutral values.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

__all__ = ["System", "SystemBase"]


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


class SystemBase:
    """Neutral values of the :class:`System` members a system may do without: no calibration, no
    faults of its own, no burst test, no timing or report of its parts."""

    warming: bool = False

    def take_events(self) -> list[tuple[str, str]]:
        """No events."""
        return []

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
