"""What the daemon's loop reads from and writes to a rig, whatever the backend (SI).

A rig has ``n`` chambers. Each period the loop calls :meth:`RigIO.read` once (the newest pressure of
every chamber) and :meth:`RigIO.write` once (the command to hold until the next write). A command is
the plant's input array ``U`` of shape (3, n): row 0 the pump speed, row 1 the inlet (supply) valve
duty, row 2 the outlet valve duty, each in [0, 1], one column per chamber (a shared pump has the
same speed in every column). :func:`safe_u` of a rig is pump off, inlets closed, outlets open.

Backends: ``sim`` (:mod:`hbma_ctrl.system.sim_rig`) steps a mismatched rig model one period per
write; ``serial`` (:mod:`hbma_ctrl.system.serial_link`) speaks the line protocol to firmware.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

__all__ = ["Readings", "RigIO", "RigLinkError", "safe_u", "check_u"]


class RigLinkError(RuntimeError):
    """The link to the rig is lost (no heartbeat, port gone): the daemon goes to the safe state."""


@dataclass(frozen=True)
class Readings:
    """One read of every chamber.

    t : the rig's own time stamp of the readings, s (None when the rig gives none).
    p : gauge pressures, Pa, shape (n,); NaN = no reading for that chamber this period.
    seq : the rig's sequence number of this packet (-1 when the rig gives none).
    fresh : (n,) bool, False where the value is a repeat of an older packet (no new sample).
    held : the command (3, n) the rig reports it held over the period these readings end (a rig
        that reports it: the serial protocol's version 2); None = the last command written (a
        lockstep simulation, where that is exact).
    """

    t: float | None
    p: np.ndarray
    seq: int = -1
    fresh: np.ndarray = field(default_factory=lambda: np.ones(0, dtype=bool))
    held: np.ndarray | None = None


def safe_u(n: int) -> np.ndarray:
    """The safe command for n chambers: pump off, inlets closed, outlets open, (3, n)."""
    u = np.zeros((3, n))
    u[2] = 1.0
    return u


def check_u(u: np.ndarray, n: int) -> np.ndarray:
    """``u`` as a (3, n) float array in [0, 1]; ValueError naming what is wrong otherwise (never clipped)."""
    a = np.asarray(u, dtype=float)
    if a.shape != (3, n):
        raise ValueError(f"rig command has shape {a.shape}, expected (3, {n}) (pump, inlet, outlet per chamber)")
    if not np.all(np.isfinite(a)) or a.min() < 0.0 or a.max() > 1.0:
        raise ValueError("rig command values must be finite and in [0, 1]")
    return a


@runtime_checkable
class RigIO(Protocol):
    """A rig link. ``n`` chambers, ``sample_period`` s between the rig's samples."""

    n: int
    sample_period: float
    #: True when its reads and writes simulate the plant: time no real rig's I/O takes, which the
    #: daemon's loop does not count against the controller's deadline (a link without it is real)
    simulated: bool

    def read(self) -> Readings:
        """The newest readings of every chamber (never blocks longer than one period; raises
        :class:`RigLinkError` when the link is lost)."""
        ...

    def write(self, u: np.ndarray) -> None:
        """Send the command ``u`` (3, n) to hold until the next write."""
        ...

    def safe(self) -> None:
        """Send the safe command (pump off, inlets closed, outlets open); must not raise."""
        ...

    def close(self) -> None:
        """Release the link (after :meth:`safe`)."""
        ...
