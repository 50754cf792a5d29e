"""One chamber as a system: ``tick(t, p[1], held[3, 1]) -> u[3, 1]``, the start-up calibration, setpoints
and the status a daemon shows (SI).

:class:`ChamberSystem` wraps :class:`hbma_ctrl.runtime.chamber.ChamberLoop` (estimator, controller,
supervisor) and the :class:`hbma_ctrl.runtime.calibrate.StartupCalibration` that runs before it for the
rig's view: the readings of every chamber (Pa, (n,)) in, the plant input ``u`` (3, n) out. Setpoints are
checked on the caller's thread (:meth:`ChamberSystem.check_setpoint`: clipped to what is reachable,
saying what was clipped) and applied between periods (:meth:`ChamberSystem.apply_setpoint`).
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from hbma_ctrl.core import units as U
from hbma_ctrl.core.interfaces import Command
from hbma_ctrl.runtime.calibrate import StartupCalibration
from hbma_ctrl.runtime.chamber import ChamberLoop
from hbma_ctrl.system.roles import calibration_summary

__all__ = ["ChamberSystem", "SupervisorEpisodes"]


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


class ChamberSystem:
    """One chamber under :class:`ChamberLoop` (see module doc). ``h_range``: reachable targets (lo, hi), m.

    ``calibration``: a :class:`StartupCalibration` run first (``[controller] calibrate``), as the
    controller scene runs it: its excitation drives the chamber, its estimator is the loop's, and
    the file's target schedule starts when it ends (a setpoint sent meanwhile holds from then on).
    While it runs, ``warming`` is True: its fit (about a second in the tick that ends it, while the
    chamber vents) does not feed the loop watchdog. ``take_events()`` hands the loop what to log.
    """

    kind = "chamber"

    def __init__(self, loop: ChamberLoop, p_limit: float, h_range: tuple[float, float], names=("C1",),
                 calibration: StartupCalibration | None = None):
        self.loop = loop
        self.n = 1
        self.names = tuple(names)
        self.p_limit = float(p_limit)
        self.h_range = (float(h_range[0]), float(h_range[1]))
        self.calibration = calibration
        self.calibration_summary: dict | None = None
        self._setpoint_during_calibration = False
        self._events: list[tuple[str, str]] = []
        self._t0: float | None = None
        self._episodes = SupervisorEpisodes(loop.supervisor, self.names)

    @property
    def warming(self) -> bool:
        """True while the start-up calibration runs (its ticks do not feed the loop watchdog)."""
        return self.calibration is not None and not self.calibration.done

    def take_events(self) -> list[tuple[str, str]]:
        """(kind, cause) events since the last call (the calibration's start and outcome, the
        supervisor's interventions: :class:`SupervisorEpisodes`)."""
        ev, self._events = self._events, []
        return ev + self._episodes.take()

    def tick(self, t: float, p: np.ndarray, held: np.ndarray | None = None) -> np.ndarray:
        """One period at rig time t (s) with the reading p (Pa, (1,)) -> U (3, 1); ``held`` (3, 1): the
        command the rig reports it held over the period p ends (None: the last one returned)."""
        if self._t0 is None:
            self._t0 = float(t)
            if self.calibration is not None:
                self._events.append(("calibration", "start-up calibration: vent, pump pulse, hold, vent"))
        h = None if held is None else Command(*(float(x) for x in np.asarray(held, dtype=float).reshape(3)))
        if self.warming:
            cmd, done = self.calibration.tick(t, float(p[0]), h)
            if done:
                self._calibrated(t, cmd)
            return cmd.as_array().reshape(3, 1)
        return self.loop.tick(t, float(p[0]), h).as_array().reshape(3, 1)

    def _calibrated(self, t: float, cmd: Command) -> None:
        """The calibration ended at rig time t (s): the loop takes over from its vent command, the
        file's schedule shifted to start now (as the scene's loop starts at 0 when it closes)."""
        cal = self.calibration
        self.calibration_summary = calibration_summary(cal, t - self._t0)
        self.loop.command = cmd
        ref = self.loop.reference
        if ref is not None and not self._setpoint_during_calibration:
            self.loop.set_reference(lambda tt, ref=ref, t1=float(t): ref(tt - t1))
        s = self.calibration_summary
        facts = (f": flow x{s['flow_factor']:.3f}, modulus x{s['modulus_factor']:.3f}, dead volume "
                 f"x{s['dead_volume_factor']:.3f}" if cal.result is not None else "")
        self._events.append(("calibration", f"{cal.status} after {t - self._t0:.2f} s{facts}"))

    def targets(self) -> np.ndarray:
        """This period's target height per chamber, m (NaN = none)."""
        tg = self.loop.target
        return np.array([np.nan if tg is None else tg])

    def estimates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(height m, its std m, pressure Pa) per chamber from the estimator, NaN before the first tick."""
        e = self.loop.estimate
        if e is None:
            return (np.full(1, np.nan),) * 3
        return np.array([e.h]), np.array([float(e.std.get("h", np.nan))]), np.array([e.p])

    def layers(self) -> list:
        """No layers: a single chamber."""
        return []

    def check_setpoint(self, request: dict) -> dict:
        """Heights {0: h m} -> {"applied", "clipped"} (clipped to ``h_range``); ValueError for layers or
        another chamber."""
        if request.get("layers"):
            raise ValueError("layers: this daemon runs one chamber; send heights_mm instead")
        heights = request.get("heights") or {}
        if not heights:
            raise ValueError("no setpoint given: send heights_mm for chamber 0")
        clipped, applied = [], {}
        lo, hi = self.h_range
        for i, h in heights.items():
            if int(i) != 0:
                raise ValueError(f"heights_mm.{i}: chamber index out of range [0, 0] (one chamber)")
            h = float(h)
            if not math.isfinite(h):
                raise ValueError(f"heights_mm.{i}: must be a finite number")
            hc = min(max(h, lo), hi)
            if hc != h:
                clipped.append(f"heights_mm.{i} = {U.to_mm(h):g} clipped to {U.to_mm(hc):g} mm (reachable "
                               f"[{U.to_mm(lo):g}, {U.to_mm(hi):g}] mm)")
            applied[0] = hc
        return {"applied": {"heights": applied}, "clipped": clipped}

    def apply_setpoint(self, applied: dict, t: float) -> None:
        """Hold the applied height from now on (the file's target schedule ends)."""
        h = applied.get("heights", {}).get(0)
        if h is not None:
            self._setpoint_during_calibration = self.warming
            self.loop.set_reference(lambda _t, h=float(h): h)

    def stats(self) -> dict:
        """The controller's and the runtime's statistics (ms, counts), and ``calibration`` (the
        start-up calibration's outcome, edge units, as the controller scene reports it) when it ran."""
        out = self.loop.stats()
        if self.calibration is not None:
            out["calibration"] = self.calibration_summary or {"status": self.calibration.status}
        return out
