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

import copy
from collections import deque
from dataclasses import dataclass

import casadi as ca
import numpy as np

from hbma_ctrl.core.codegen import FastFunction
from hbma_ctrl.core.loopgen import Part, Stage
from hbma_ctrl.runtime.safety_step import EVENTS, SupervisorSettings, state_parts, state_size, supervisor_function

__all__ = ["SupervisorSettings", "SupervisorEvent", "Supervisor"]

#: target heights at or below this (m) count as "zero": the robot's vent rule
ZERO_TARGET = 5e-5


@dataclass(frozen=True)
class SupervisorEvent:
    """One intervention: time t (s), chamber index, cause ('shifted_plan', 'safe_command', 'vent',
    'guard') and a detail (why the controller failed, the pressure in Pa at a guard)."""

    t: float
    chamber: int
    cause: str
    detail: str = ""


class Supervisor:
    """The safety policy of the module docstring, for ``n`` chambers, no I/O. Each step is one call of
    :func:`~hbma_ctrl.runtime.safety_step.supervisor_function` (the Function the generated loops
    run); the instance keeps its state between steps, the counts and the event log.

    ``lost`` and ``burst`` are the latches of rules 6 and 7, ``released`` the chambers released this
    step, (n,) bool each; the latches are read back into the state at the next step (a caller may
    clear them)."""

    def __init__(self, settings: SupervisorSettings | None = None, n: int = 1):
        if not isinstance(n, int) or n < 1:
            raise ValueError(f"supervisor.n = {n!r} must be an integer >= 1")
        self.settings = (settings or SupervisorSettings()).validate()
        self.n = n
        self._fns: dict = {}
        self._built_for: SupervisorSettings | None = None
        self.reset()

    def reset(self) -> None:
        """Forget the plan, the streaks, the latches, the counts and the log."""
        #: the Function's state for plans of ``_shape`` = (columns, rows); None before the first step
        self._state: np.ndarray | None = None
        self._shape: tuple = (0, 1)
        self._venting = np.zeros(self.n, dtype=bool)
        self.lost = np.zeros(self.n, dtype=bool)
        self.released = np.zeros(self.n, dtype=bool)
        self.burst = np.zeros(self.n, dtype=bool)
        self.counts: dict = dict.fromkeys(EVENTS, 0)
        self.failure_causes: dict = {}
        self.failed_steps = 0
        self.events: deque = deque(maxlen=self.settings.event_log_size)
        #: events logged since the reset (the log keeps the newest event_log_size of them)
        self.logged = 0

    def _function(self, c: int, H: int) -> tuple[FastFunction, dict]:
        """The policy's Function for c columns and H-row plans on buffers, with its state's parts; built
        again when the settings changed (replaced, or a field set) since the last build."""
        if self._built_for != self.settings:
            self._fns.clear()
            self._built_for = copy.copy(self.settings)
        if (c, H) not in self._fns:
            self._fns[(c, H)] = (FastFunction(_policy(self._built_for, self.n, c, H), compile=False),
                                 state_parts(self.n, c, H))
        return self._fns[(c, H)]

    def prepare(self, c: int, H: int) -> None:
        """Build the Function for c columns and H-row plans before the first step (0.2 s for 18
        chambers: start-up work, not a first tick's)."""
        self._function(c, H)
        if self._state is None:
            self._state_for(c, H)

    def state(self, c: int, H: int) -> np.ndarray:
        """The state in :func:`~hbma_ctrl.runtime.safety_step.supervisor_function`'s layout for c columns
        and H-row plans, the latches as they are now (a copy). A stored plan of another shape is
        refused with a ValueError."""
        stored = self._state is not None and self._state[state_parts(self.n, *self._shape)["has_plan"]][0]
        if stored and (c, H) != self._shape:
            raise ValueError(f"Supervisor.state: the stored plan is {self._shape[1]} rows of {self._shape[0]} columns, "
                             f"not {H} of {c}")
        st = self._state_for(c, H).copy()
        parts = state_parts(self.n, c, H)
        st[parts["lost"]], st[parts["burst"]] = self.lost, self.burst
        return st

    def _state_for(self, c: int, H: int) -> np.ndarray:
        """The state for c columns and H-row plans (a stored plan of another shape dropped)."""
        if self._state is None or (c, H) != self._shape:
            n = self.n
            st = np.zeros(state_size(n, c, H))
            if self._state is not None:
                new, old = state_parts(n, c, H), state_parts(n, *self._shape)
                for key in ("plan_t", "streak", "age"):
                    st[new[key]] = self._state[old[key]]
            self._state, self._shape = st, (c, H)
        return self._state

    def _log(self, t: float, chambers, cause: str, detail) -> None:
        """Log ``cause`` for each chamber where ``chambers`` is True, ``detail(i)`` its text."""
        for i in np.nonzero(chambers)[0]:
            self.events.append(SupervisorEvent(float(t), int(i), cause, detail(i)))
            self.logged += 1

    def apply(self, t: float, command, pressure, ok=True, plan=None, target=None,
              cause: str = "controller_failed", stretch=None, lost=None, burst=None) -> np.ndarray:
        """The command to send at time t (s), same shape as ``command``.

        command : proposed command, (n, c) or (c,) for one chamber, values nominally in [0, 1].
        pressure : the guarded gauge pressure per chamber, Pa (estimate or reading, see settings).
        ok : bool or (n,) bool: whether the controller produced this command normally.
        plan : where ok, the controller's plan (H, n, c) or (H, c), row 0 = this command; where not
            ok, a late plan for the next failure, or None. A plan of another shape than the stored
            one replaces it.
        target : target heights per chamber, m, for the vent rule; None = no targets.
        cause : why the controller failed (logged and counted in ``failure_causes``).
        stretch : estimated membrane stretch per chamber (-; NaN = unknown: not guarded) for the
            stretch guard; None = not guarded this step.
        lost : (n,) bool, chambers whose estimate has left its model's range this step (rule 6).
        burst : (n,) bool, chambers the burst test has flagged (rule 7; latched here until reset).
        """
        n = self.n
        cmd = np.asarray(command, dtype=float)
        c = cmd.size // n
        H = self._shape[1] if plan is None else len(plan)
        state = self._state_for(c, H)
        f, parts = self._function(c, H)
        # the inputs written into the Function's buffers (a scalar broadcast to every chamber)
        inp = f.inp
        inp[0][0] = t
        inp[1][:] = cmd.reshape(n * c)
        inp[2][:] = pressure
        inp[3][:] = np.asarray(ok, dtype=bool)
        if plan is not None:
            inp[4][:] = np.asarray(plan, dtype=float).reshape(H * n * c)
        inp[5][0] = plan is not None
        inp[6][:] = np.nan if target is None else target
        inp[7][:] = np.nan if stretch is None else stretch
        inp[8][:] = False if lost is None else np.asarray(lost, dtype=bool)
        inp[9][:] = False if burst is None else np.asarray(burst, dtype=bool)
        inp[10][:] = state
        inp[10][parts["lost"]], inp[10][parts["burst"]] = self.lost, self.burst
        out, st_next, released, ev, failed = f.eval()
        self._state = st_next.copy()
        ev = ev.reshape(len(EVENTS), n) > 0.5
        if failed[0]:
            self.failed_steps += 1
            self.failure_causes[cause] = self.failure_causes.get(cause, 0) + n - int(inp[3].sum())
        new_lost, new_burst = (inp[8] != 0) & ~self.lost, (inp[9] != 0) & ~self.burst
        self.released = released > 0.5
        if ev.any() or self._venting.any():
            self._count_and_log(t, ev, cause, inp[2], inp[7], new_lost, new_burst)
        self.lost, self.burst = st_next[parts["lost"]] > 0.5, st_next[parts["burst"]] > 0.5
        res = out.reshape(n, c).copy()
        return res[0] if cmd.ndim == 1 else res

    def stages(self, c: int, H: int, wiring: dict, every: int = 1, name: str = "supervisor") -> Part:
        """The policy in a generated loop (:mod:`hbma_ctrl.core.loopgen`): its Function for c columns and
        H-row plans, every ``every`` ticks, reading the signals ``wiring`` names for its inputs (by the
        Function's input names; an input left out reads as none: no target or stretch (NaN), no lost
        estimate or burst (0)) and writing ``wiring["command_out"]``; its state (``<name>_state``)
        starts as :meth:`state`. The event log and counts stay in Python."""
        fun = supervisor_function(self.settings, self.n, c, H, name)
        neutral = {"target": np.nan, "stretch": np.nan, "lost": 0.0, "burst": 0.0}
        signals = {f"{name}_state": self.state(c, H)}
        inputs = []
        for key in fun.name_in():
            if key == "state":
                inputs.append(f"{name}_state")
            elif key in wiring:
                inputs.append(wiring[key])
            else:
                inputs.append(f"{name}_{key}")
                signals[inputs[-1]] = np.full(self.n, neutral[key])
        outputs = [wiring["command_out"], f"{name}_state", None, None, None]
        return Part([Stage(fun, inputs, outputs, every=every)], signals)

    def _count_and_log(self, t: float, ev: np.ndarray, cause: str, p: np.ndarray, lam: np.ndarray,
                       new_lost: np.ndarray, new_burst: np.ndarray) -> None:
        """Add a step's events (:data:`EVENTS` rows by chamber) to the counts and the log: fallbacks by
        chamber, then vents as they start, guards (pressure p, Pa), stretch guards (stretch lam),
        lost estimates as they start and their releases, bursts as they start."""
        for key, row in zip(EVENTS, ev):
            self.counts[key] += int(row.sum())
        shifted, safe, vent, guard, over = ev[:5]
        for i in np.nonzero(shifted | safe)[0]:
            self._log(t, np.arange(self.n) == i, "shifted_plan" if shifted[i] else "safe_command", lambda _: cause)
        self._log(t, vent & ~self._venting, "vent", lambda i: "zero target")
        self._venting = vent
        self._log(t, guard, "guard", lambda i: f"p={p[i]:.0f} Pa")
        self._log(t, over, "stretch_guard", lambda i: f"stretch={lam[i]:.2f}")
        self._log(t, new_lost, "lost_estimate", lambda i: "the estimate left its model: venting")
        self._log(t, self.released, "lost_estimate_released", lambda i: f"p={p[i]:.0f} Pa")
        self._log(t, new_burst, "burst", lambda i: "losing gas faster than its valves let it: venting until a reset")


#: the policy's Functions built in this process, by the settings' repr and the shapes
_POLICIES: dict = {}


def _policy(settings: SupervisorSettings, n: int, c: int, H: int) -> ca.Function:
    """:func:`supervisor_function`, built once per process for equal settings and shapes."""
    key = (repr(settings), n, c, H)
    if key not in _POLICIES:
        _POLICIES[key] = supervisor_function(settings, n, c, H)
    return _POLICIES[key]
