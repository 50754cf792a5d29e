"""The ``sim`` rig backend: a :class:`~hbma_ctrl.system.rigio.RigIO` on the mismatched rig models (SI).

:class:`SimRig` runs in lockstep: each :meth:`SimRig.write` holds the command for exactly one
``sample_period`` and advances the simulated rig by that period, so rig time is ``k * sample_period``
after k writes, exact and deterministic (same settings and seed -> same readings). :meth:`SimRig.read`
returns the rig's measurement at the current rig time, stamped with that time and a sequence number
(one new sample per period; a second read in the same period repeats the packet with ``fresh``
False, as a real rig's last packet would).

Real-time pacing is NOT done here: the daemon's loop paces the periods (and its ``--speed`` scales
them); a SimRig runs as fast as it is called.

Two constructors: :meth:`SimRig.chamber` (one chamber, :class:`hbma_ctrl.sim.rig.Rig`, with optional
load steps as the closed-loop scene has them) and :meth:`SimRig.robot` (every chamber of a robot,
:class:`hbma_ctrl.robot.rig.RobotRig`, with the robot scene's tip load).
"""

from __future__ import annotations

import numpy as np

from hbma_ctrl.system.rigio import Readings, check_u, safe_u
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.robot.rig import RobotRig, RobotRigSettings
from hbma_ctrl.sim.rig import Rig, RigSettings

__all__ = ["SimRig"]


class SimRig:
    """A simulated rig behind the RigIO interface, in lockstep (see module doc).

    Attributes: ``n`` chambers, ``sample_period`` s, ``sensor_range`` Pa (where readings saturate: the
    monitor's ``sensor_range``), ``t`` rig time (s), ``seq`` the number of the
    newest sample, ``held`` the command (3, n) in force, ``rig`` the wrapped rig model.
    Use :meth:`chamber` or :meth:`robot` to build one.
    """

    #: its reads and writes simulate the plant: time no real rig's I/O would take (the daemon's loop
    #: does not count it against the controller's deadline)
    simulated = True

    def __init__(self, rig: Rig | RobotRig, load_steps=()):
        self.rig = rig
        self._chamber = isinstance(rig, Rig)
        self.n: int = 1 if self._chamber else rig.n
        self.sample_period: float = float(rig.settings.sample_period if self._chamber else rig.s.sample_period)
        self.sensor_range: float = float(rig.settings.sensor_range if self._chamber else rig.sensor_range)
        # the chamber's scheduled loads ((t s, kg), ...), put on once rig time reaches them
        self._loads = sorted((float(t), float(m)) for t, m in load_steps)
        self._loads_due()
        self.t = 0.0
        self.seq = 0
        self.held = safe_u(self.n)
        self.closed = False
        self._packet: Readings | None = None

    # --- constructors ---------------------------------------------------------------------------
    @classmethod
    def chamber(cls, actuator: Actuator, pneumatics: Pneumatics, platform: Platform,
                rig_settings: RigSettings | None = None, load_steps=()) -> "SimRig":
        """One chamber on the mismatched single-chamber rig (nominal actuator, pneumatics and platform;
        the rig applies its own mismatch). ``load_steps``: ((t s, load kg), ...) put on when rig time
        reaches t (as the closed-loop scene's ``load_steps_g``)."""
        return cls(Rig(actuator, pneumatics, platform, rig_settings or RigSettings()), load_steps)

    @classmethod
    def robot(cls, settings, rig_settings: RobotRigSettings | None = None,
              pneumatics: Pneumatics | None = None, tip_load=()) -> "SimRig":
        """Every chamber (3 per layer) of the robot ``settings`` (a :class:`hbma_ctrl.system.sections.RobotSettings`:
        design, topology and sensor range) on the mismatched robot rig; ``tip_load``: rows
        (t s, fx, fy, fz N) as the robot scenes give them."""
        pn = (pneumatics or Pneumatics()).validate()
        rp = settings.pneumatics
        rig = RobotRig(settings.design, pn, rp.sensor_range, rp.topology,
                       (rig_settings or RobotRigSettings()).validate(), tip_load)
        return cls(rig)

    def _loads_due(self) -> None:
        while self._loads and self._loads[0][0] <= self.rig.t + 1e-9:
            self.rig.set_load(self._loads.pop(0)[1])

    # --- RigIO ------------------------------------------------------------------------------------
    def read(self) -> Readings:
        """The rig's measurement (Pa, (n,), NaN on a dropout) at rig time ``t``; one new sample per period."""
        if self.closed:
            raise RuntimeError("SimRig.read after close()")
        if self._packet is None:
            p = np.atleast_1d(np.asarray(self.rig.measure(), dtype=float))
            self._packet = Readings(t=self.t, p=p, seq=self.seq, fresh=np.ones(self.n, dtype=bool))
            return self._packet
        pk = self._packet
        return Readings(t=pk.t, p=pk.p.copy(), seq=pk.seq, fresh=np.zeros(self.n, dtype=bool))

    def write(self, u: np.ndarray) -> None:
        """Hold ``u`` (3, n) for one sample period and advance the rig by it (ValueError on a bad command).
        A diverged plant raises RuntimeError (a simulation failure, not a rig fault)."""
        if self.closed:
            raise RuntimeError("SimRig.write after close()")
        u = check_u(u, self.n)
        self.held = u.copy()
        self.rig.apply(u[:, 0] if self._chamber else u)
        self._loads_due()
        self.seq += 1
        self.t = self.seq * self.sample_period  # exact: no accumulated rounding
        self._packet = None

    def safe(self) -> None:
        """Hold the safe command from now (it acts on the rig from the next period; lockstep: no advance)."""
        self.held = safe_u(self.n)

    def close(self) -> None:
        """End the simulation (reads and writes after it raise)."""
        self.safe()
        self.closed = True

    # --- tests and logs -----------------------------------------------------------------------------
    def truth(self) -> dict:
        """The rig's true state now (the wrapped rig's ``truth()``, with ``t`` s)."""
        return {**self.rig.truth(), "t": self.rig.t}

    def set_load(self, mass_kg: float) -> None:
        """Single chamber only: put a load of ``mass_kg`` kg on now (0 takes it off)."""
        if not self._chamber:
            raise ValueError("SimRig.set_load: only a single-chamber rig carries a platform load")
        self.rig.set_load(mass_kg)
