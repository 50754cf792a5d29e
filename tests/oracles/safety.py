"""The supervisor's policy in numpy, rule by rule: the oracle :class:`hbma_ctrl.runtime.safety.Supervisor`
(which runs :func:`hbma_ctrl.runtime.safety_step.supervisor_function`) is compared with over long random
runs. Rules 1-7 as the module docstring of :mod:`hbma_ctrl.runtime.safety` states them."""

from __future__ import annotations

from collections import deque

import numpy as np

from hbma_ctrl.runtime.safety import SupervisorEvent, SupervisorSettings
from hbma_ctrl.runtime.safety_step import EVENTS


class SupervisorOracle:
    """The safety policy of :mod:`hbma_ctrl.runtime.safety`, for ``n`` chambers, in numpy."""

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
        self.counts: dict = dict.fromkeys(EVENTS, 0)
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


def oracle_state(sup: SupervisorOracle, c: int, H: int) -> np.ndarray:
    """``sup``'s state in :func:`~hbma_ctrl.runtime.safety_step.supervisor_function`'s layout (a stored
    plan must have H rows)."""
    plan, has = np.zeros((H, sup.n, c)), 0.0
    if sup._plan is not None:
        assert sup._plan.shape == (H, sup.n, c), sup._plan.shape
        plan, has = sup._plan, 1.0
    return np.concatenate([plan.ravel(), [has], sup._plan_t, sup._streak, sup._age, sup.lost, sup.burst]).astype(float)
