"""One safety supervisor for the single chamber and the robot: fallback, vent, pressure guard (SI).

Every command a controller proposes passes :meth:`Supervisor.apply` before it reaches the valves.
Commands are arrays of shape (n, c), one row per chamber (a 1-D array is one chamber); the last
column is the outlet duty, the columns before it are the supply (column 0 the pump: compressor
speed for the single chamber ``[speed, inlet, outlet]``, supply duty for the robot
``[supply, outlet]``). All values are in [0, 1].

The policy, in this order, per chamber:

1. fallback: when the controller failed for a chamber (a solver failure, an overrun, an exception),
   the last good plan is replayed while it lasts (at most ``fallback_plan_steps`` consecutive failed
   steps and while the plan has a row for the elapsed time), then the safe command (supply off,
   outlet at ``safe_outlet``). A late plan handed in with a failure becomes the plan for the next
   failure (its first move is already missed);
2. the command is clipped to [0, 1];
3. vent: a chamber whose target height is at or below ``vent_height`` gets the safe command (a zero
   target means "lower onto the stop": vent, no dithering about ambient pressure);
4. pressure guard: while a chamber's pressure is within ``guard_margin`` of ``p_max`` and its command
   pumps (or, with a ``vent_margin``, does not fully open the outlet), the supply is cut; within
   ``vent_margin`` the outlet is opened fully;
5. stretch guard (with ``stretch_max``): while a chamber's estimated membrane stretch is at or above
   ``stretch_max`` and its command pumps, the supply is cut. Past its limit point a membrane at a
   held pressure keeps growing (a balloon), so the pressure guard alone does not bound it;
6. lost estimate: a chamber whose estimate has left its model's range (``lost``: the membrane may be
   anywhere above what the model covers) gets the safe command from then until its pressure is at
   or below ``lost_release``; on that step it is in ``released`` (its owner restarts the estimate
   from the flat chamber). A far-branch membrane pumped on by a lost estimate grows without bound.
7. burst: a chamber its owner's burst test flagged (``burst``: it loses gas faster than its valves
   let it, :mod:`hbma_ctrl.runtime.burst`) gets the safe command from then on, until :meth:`Supervisor.reset`:
   a burst membrane or a stuck outlet is for a person to look at, and pumping it only feeds the leak.

Every intervention is counted (by cause) and logged as an event (time, chamber, cause, detail) in a
bounded log; vents are logged when they start (a held zero target would flood the log otherwise).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from hbma_ctrl.core.interfaces import guard_margin_setting, p_max_setting
from hbma_ctrl.core.settings import Settings, setting

__all__ = ["SupervisorSettings", "SupervisorEvent", "Supervisor"]

#: target heights at or below this (m) count as "zero": the robot's vent rule
ZERO_TARGET = 5e-5


@dataclass
class SupervisorSettings(Settings):
    """Settings of :class:`Supervisor` (SI; each field's unit, range and one-line doc are in its declaration).

    vent_margin None: the guard only cuts the supply (the robot's interlock) and a closed outlet does
    not trigger it. missing_is_limit: a non-finite pressure counts as at the limit (True: a lost
    estimate) or is skipped (False: a sensor dropout, the last good command stands).
    """

    WHERE = "supervisor"

    p_max: float = p_max_setting()
    guard_margin: float = guard_margin_setting(0.5e3)
    vent_margin: float | None = setting(0.25e3, lo=0.0, hi=1e6, unit="Pa", optional=True,
                                        doc="within this of p_max the guard also opens the outlet fully")
    missing_is_limit: bool = setting(True, doc="a non-finite pressure counts as at the limit")
    vent_height: float | None = setting(None, lo=0.0, hi=0.2, unit="m",
                                        doc="targets at or below this height get the safe command (None: no vent rule)")
    fallback_plan_steps: int = setting(10, integer=True, lo=0,
                                       doc="consecutive failed steps the last good plan may stand in before the safe command")
    plan_period: float | None = setting(None, lo=0.0, hi=10.0, lo_open=True, unit="s",
                                        doc="time between two rows of a controller's plan (None: one row per step)")
    safe_outlet: float = setting(1.0, lo=0.0, hi=1.0, doc="outlet duty of the safe command (1 = vent; 0 = hold the gas)")
    stretch_max: float | None = setting(None, lo=1.0, hi=20.0, lo_open=True,
                                        doc="the stretch guard's limit (equi-biaxial stretch; None: no stretch guard)")
    lost_release: float = setting(1e3, lo=0.0, hi=1e6, unit="Pa",
                                  doc="a chamber vented for a lost estimate is released at or below this pressure")
    event_log_size: int = setting(10000, integer=True, lo=1,
                                  doc="events the log keeps (the oldest drop out; counts keep growing)")

    def check_rules(self) -> None:
        self.within("guard_margin", hi=self.p_max)
        if self.vent_margin is not None:
            self.within("vent_margin", hi=self.p_max)
        self.within("lost_release", hi=self.p_max)


@dataclass(frozen=True)
class SupervisorEvent:
    """One intervention: time t (s), chamber index, cause ('shifted_plan', 'safe_command', 'vent',
    'guard') and a detail (why the controller failed, the pressure in Pa at a guard)."""

    t: float
    chamber: int
    cause: str
    detail: str = ""


class Supervisor:
    """The safety policy of the module docstring, for ``n`` chambers. No I/O; all state on the instance."""

    def __init__(self, settings: SupervisorSettings | None = None, n: int = 1):
        if not isinstance(n, int) or n < 1:
            raise ValueError(f"supervisor.n = {n!r} must be an integer >= 1")
        self.settings = (settings or SupervisorSettings()).validate()
        self.n = n
        self.reset()

    def reset(self) -> None:
        """Forget the plan, the streaks, the counts and the log."""
        self._plan: np.ndarray | None = None  # (H, n, c)
        self._plan_t = np.zeros(self.n)  # time of each chamber's row 0, s
        self._streak = np.zeros(self.n, dtype=int)
        self._age = np.zeros(self.n, dtype=int)  # plan rows replayed since the plan was stored
        self._venting = np.zeros(self.n, dtype=bool)
        #: chambers vented for a lost estimate (until their pressure is down), and those released this step
        self.lost = np.zeros(self.n, dtype=bool)
        self.released = np.zeros(self.n, dtype=bool)
        #: chambers put on the safe command for a burst (rule 7), until the next reset
        self.burst = np.zeros(self.n, dtype=bool)
        self.counts: dict = {"shifted_plan": 0, "safe_command": 0, "vent": 0, "guard": 0, "stretch_guard": 0,
                             "lost_estimate": 0, "burst": 0}
        self.failure_causes: dict = {}
        self.failed_steps = 0
        self.events: deque = deque(maxlen=self.settings.event_log_size)
        #: events logged since the reset (the log keeps the newest event_log_size of them)
        self.logged = 0

    # --- helpers ---------------------------------------------------------------------------------
    def safe_command(self, channels: int) -> np.ndarray:
        """The safe command row: supply off, outlet at ``safe_outlet``."""
        row = np.zeros(channels)
        row[-1] = self.settings.safe_outlet
        return row

    def vent_mask(self, target: np.ndarray | float | None) -> np.ndarray:
        """(n,) bool: chambers the vent rule puts on the safe command for these target heights (m)."""
        vh = self.settings.vent_height
        if target is None or vh is None:
            return np.zeros(self.n, dtype=bool)
        tg = np.broadcast_to(np.asarray(target, dtype=float), (self.n,))
        return np.isfinite(tg) & (tg <= vh)

    def stretch_over(self, stretch) -> np.ndarray:
        """(n,) bool: chambers the stretch guard holds for these estimated stretches (-): at or above
        ``stretch_max`` (rule 5); none without a limit or estimates (NaN compares False: not guarded)."""
        lim = self.settings.stretch_max
        if stretch is None or lim is None:
            return np.zeros(self.n, dtype=bool)
        return np.broadcast_to(np.asarray(stretch, dtype=float), (self.n,)) >= lim

    def _log(self, t: float, i: int, cause: str, detail: str = "") -> None:
        self.events.append(SupervisorEvent(float(t), int(i), cause, detail))
        self.logged += 1

    def _store_plan(self, t: float, plan: np.ndarray, rows: np.ndarray) -> None:
        if self._plan is None or self._plan.shape != plan.shape:
            self._plan = plan.copy()
        else:
            self._plan[:, rows] = plan[:, rows]
        self._plan_t[rows] = t
        self._age[rows] = 0

    def _as_plan(self, plan, shape: tuple) -> np.ndarray | None:
        if plan is None:
            return None
        p = np.asarray(plan, dtype=float)
        return p.reshape(p.shape[0], *shape)

    # --- the policy ------------------------------------------------------------------------------
    def apply(self, t: float, command, pressure, ok=True, plan=None, target=None,
              cause: str = "controller_failed", stretch=None, lost=None, burst=None) -> np.ndarray:
        """The command to send at time t (s), same shape as ``command``.

        command : proposed command, (n, c) or (c,) for one chamber, values nominally in [0, 1].
        pressure : the guarded gauge pressure per chamber, Pa (estimate or reading, see settings).
        ok : bool or (n,) bool: whether the controller produced this command normally.
        plan : where ok, the controller's plan (H, n, c) or (H, c), row 0 = this command; where not
            ok, a late plan for the next failure, or None.
        target : target heights per chamber, m, for the vent rule; None = no targets.
        cause : why the controller failed (logged and counted in ``failure_causes``).
        stretch : estimated membrane stretch per chamber (-; NaN = unknown: not guarded) for the
            stretch guard; None = not guarded this step.
        lost : (n,) bool, chambers whose estimate has left its model's range this step (rule 6).
        burst : (n,) bool, chambers the burst test has flagged (rule 7; latched here until reset).
        """
        s = self.settings
        cmd = np.array(command, dtype=float)
        single = cmd.ndim == 1
        cmd = cmd.reshape(self.n, -1)
        c = cmd.shape[1]
        ok_m = np.broadcast_to(np.asarray(ok, dtype=bool), (self.n,))
        pl = self._as_plan(plan, cmd.shape)
        # 1. fallback
        if ok_m.all():
            self._streak[:] = 0
            if pl is not None:
                self._store_plan(t, pl, np.arange(self.n))
            else:
                self._plan = None
        else:
            self.failed_steps += 1
            good = np.nonzero(ok_m)[0]
            self._streak[good] = 0
            if pl is not None and good.size:
                self._store_plan(t, pl, good)
            for i in np.nonzero(~ok_m)[0]:
                self.failure_causes[cause] = self.failure_causes.get(cause, 0) + 1
                self._streak[i] += 1
                row = None
                if self._plan is not None and self._streak[i] <= s.fallback_plan_steps:
                    # the plan row for now: by elapsed time when the plan's period differs from the step
                    row = (self._age[i] + 1 if s.plan_period is None
                           else int(np.floor((t - self._plan_t[i]) / s.plan_period + 1e-6)))
                if row is not None and 0 <= row < self._plan.shape[0]:
                    self._age[i] = row
                    cmd[i] = self._plan[row, i]
                    self.counts["shifted_plan"] += 1
                    self._log(t, i, "shifted_plan", cause)
                else:
                    cmd[i] = self.safe_command(c)
                    self.counts["safe_command"] += 1
                    self._log(t, i, "safe_command", cause)
            if pl is not None:
                self._store_plan(t, pl, np.nonzero(~ok_m)[0])
        # 2. clip
        cmd = np.clip(cmd, 0.0, 1.0)
        # 3. vent on a zero target
        vent = self.vent_mask(target)
        if vent.any():
            cmd[vent] = self.safe_command(c)
            self.counts["vent"] += int(vent.sum())
            for i in np.nonzero(vent & ~self._venting)[0]:
                self._log(t, i, "vent", "zero target")
        self._venting = vent
        # 4. pressure guard
        p = np.broadcast_to(np.asarray(pressure, dtype=float), (self.n,))
        finite = np.isfinite(p)
        p_g = np.where(finite, p, s.p_max)
        zone = p_g >= s.p_max - s.guard_margin
        if not s.missing_is_limit:
            zone &= finite
        unsafe = cmd[:, 0] > 0
        if s.vent_margin is not None:
            unsafe |= cmd[:, -1] < 1.0
        act = zone & unsafe
        if act.any():
            cmd[act, :-1] = 0.0
            if s.vent_margin is not None:
                cmd[act & (p_g >= s.p_max - s.vent_margin), -1] = 1.0
            self.counts["guard"] += int(act.sum())
            for i in np.nonzero(act)[0]:
                self._log(t, i, "guard", f"p={p[i]:.0f} Pa")
        # 5. stretch guard
        over = self.stretch_over(stretch) & (cmd[:, 0] > 0)
        if over.any():
            cmd[over, :-1] = 0.0
            self.counts["stretch_guard"] += int(over.sum())
            lam = np.broadcast_to(np.asarray(stretch, dtype=float), (self.n,))
            for i in np.nonzero(over)[0]:
                self._log(t, i, "stretch_guard", f"stretch={lam[i]:.2f}")
        # 6. lost estimate: vent until the pressure is down
        new = np.zeros(self.n, dtype=bool) if lost is None else \
            np.broadcast_to(np.asarray(lost, dtype=bool), (self.n,)) & ~self.lost
        for i in np.nonzero(new)[0]:
            self._log(t, i, "lost_estimate", "the estimate left its model: venting")
        self.lost |= new
        # a dropout (NaN) keeps the vent on: only a reading says the pressure is down
        self.released = self.lost & finite & (p_g <= s.lost_release)
        for i in np.nonzero(self.released)[0]:
            self._log(t, i, "lost_estimate_released", f"p={p[i]:.0f} Pa")
        if self.lost.any():
            # the step of the release too: its command came from the lost estimate
            cmd[self.lost] = self.safe_command(c)
            self.counts["lost_estimate"] += int(self.lost.sum())
        self.lost &= ~self.released
        # 7. burst: the safe command until a reset
        new = np.zeros(self.n, dtype=bool) if burst is None else \
            np.broadcast_to(np.asarray(burst, dtype=bool), (self.n,)) & ~self.burst
        for i in np.nonzero(new)[0]:
            self._log(t, i, "burst", "losing gas faster than its valves let it: venting until a reset")
        self.burst |= new
        if self.burst.any():
            cmd[self.burst] = self.safe_command(c)
            self.counts["burst"] += int(self.burst.sum())
        return cmd[0] if single else cmd
