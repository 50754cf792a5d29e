"""The supervisor's policy as ONE casadi Function (SI): what :meth:`hbma_ctrl.runtime.safety.Supervisor.apply`
evaluates each step, and what a generated loop (C without Python) runs.

:func:`supervisor_function` writes rules 1-7 of :mod:`hbma_ctrl.runtime.safety` for
``n`` chambers with ``c`` command columns and plans of ``H`` rows, its state (the stored plan, the
streaks, the lost and burst latches) passed in and out::

    supervisor(t, command[n c], pressure[n], ok[n], plan[H n c], plan_given, target[n], stretch[n],
               lost[n], burst[n], state[S])
        -> (command_out[n c], state_next[S], released[n], events[7 n], failed)

Arrays are flat: a command row-major by chamber (chamber i's columns at i c .. i c + c - 1), a plan
row-major ``[row][chamber][column]``. ``plan_given`` is 1 when a plan (or a late plan) comes with this
command, as ``plan`` is not None in ``apply``; ``target`` NaN where there is none (no vent),
``stretch`` NaN where unknown (not guarded); ``lost`` and ``burst`` 0 / 1. ``events`` flags per
chamber this step's interventions, row by row in :data:`EVENTS` order (their sums are what the
Supervisor adds to its ``counts``); ``failed`` is 1 on a step with any chamber not ok (its
``failed_steps``). :meth:`~hbma_ctrl.runtime.safety.Supervisor.state` gives a Supervisor's state in
the Function's layout, :func:`state_size` its length S. The event log and its texts stay in Python.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca

from hbma_ctrl.core.codegen import is_finite
from hbma_ctrl.core.interfaces import guard_margin_setting, p_max_setting
from hbma_ctrl.core.settings import Settings, setting

__all__ = ["EVENTS", "SupervisorSettings", "supervisor_function", "state_size", "state_parts"]


@dataclass
class SupervisorSettings(Settings):
    """Settings of :class:`hbma_ctrl.runtime.safety.Supervisor` and its Function (SI; each field's unit, range and one-line doc are in its declaration).

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

#: the per-chamber event rows of the Function's ``events`` output (the Supervisor's counts' keys)
EVENTS = ("shifted_plan", "safe_command", "vent", "guard", "stretch_guard", "lost_estimate", "burst")


#: the per-chamber parts of the Function's state, in its order after the plan and whether there is one
_CHAMBER_PARTS = ("plan_t", "streak", "age", "lost", "burst")


def state_parts(n: int, c: int, H: int) -> dict:
    """Where each part of the Function's state sits (name -> slice): the plan (H n c) and whether there
    is one ("has_plan", 1), then per chamber the plan's time, the streak, the rows replayed, the lost
    and the burst latches (n each)."""
    m = H * n * c
    parts = {"plan": slice(0, m), "has_plan": slice(m, m + 1)}
    for j, key in enumerate(_CHAMBER_PARTS):
        parts[key] = slice(m + 1 + j * n, m + 1 + (j + 1) * n)
    return parts


def state_size(n: int, c: int, H: int) -> int:
    """The length of the Function's state (:func:`state_parts`)."""
    return state_parts(n, c, H)["burst"].stop


def supervisor_function(settings: SupervisorSettings, n: int, c: int, H: int,
                        name: str = "supervisor") -> ca.Function:
    """The policy of :class:`~hbma_ctrl.runtime.safety.Supervisor` with ``settings`` for n chambers,
    c columns, H-row plans (module docstring)."""
    s = settings.validate()
    SX = ca.SX
    t = SX.sym("t")
    cmd_in, p_in, ok_in = SX.sym("command", n * c), SX.sym("pressure", n), SX.sym("ok", n)
    plan_in, given = SX.sym("plan", H * n * c), SX.sym("plan_given")
    target, stretch, lost_in, burst_in = SX.sym("target", n), SX.sym("stretch", n), SX.sym("lost", n), SX.sym("burst", n)
    parts = state_parts(n, c, H)
    st = SX.sym("state", state_size(n, c, H))
    m = H * n * c
    plan0, has0 = st[parts["plan"]], st[parts["has_plan"].start]
    plan_t0, streak0, age0, lost0, burst0 = (st[parts[key]] for key in _CHAMBER_PARTS)

    def per_entry(flags: list):  # per-chamber values -> per plan entry (row-major [row][chamber][column])
        return ca.repmat(ca.vec(ca.repmat(ca.vertcat(*flags).T, c, 1)), H, 1)

    ok = [ok_in[i] != 0 for i in range(n)]
    all_ok, any_good = ok[0], ok[0]
    for i in range(1, n):
        all_ok, any_good = ca.logic_and(all_ok, ok[i]), ca.logic_or(any_good, ok[i])
    giv = given != 0
    # --- 1. fallback. The good chambers' plan is stored first (the whole plan when none is stored)
    store_good = ca.logic_and(giv, any_good)
    had = has0 != 0
    take = [ca.logic_and(store_good, ca.logic_or(ca.logic_not(had), ok[i])) for i in range(n)]
    plan1 = ca.if_else(per_entry(take), plan_in, plan0)
    has1 = ca.logic_or(had, store_good)
    safe = [0.0] * (c - 1) + [s.safe_outlet]
    rows = [age0[i] + 1 if s.plan_period is None else ca.floor((t - plan_t0[i]) / s.plan_period + 1e-6)
            for i in range(n)]
    # each chamber's entries of its plan row: the plan as (n c) x H, one column per row
    sel = ca.repmat(ca.vec(ca.repmat(ca.vertcat(*rows).T, c, 1)), 1, H) == ca.repmat(ca.DM(range(H)).T, n * c, 1)
    picked = ca.sum2(ca.if_else(sel, ca.reshape(plan1, n * c, H), 0))
    cmd, streak, age, plan_t = [], [], [], []
    shifted, safe_ev = [], []
    for i in range(n):
        st_i = ca.if_else(ok[i], 0, streak0[i] + 1)
        row = rows[i]
        can = ca.logic_and(ca.logic_and(has1, st_i <= s.fallback_plan_steps), ca.logic_and(row >= 0, row < H))
        failed = ca.logic_not(ok[i])
        use_plan = ca.logic_and(failed, can)
        use_safe = ca.logic_and(failed, ca.logic_not(can))
        cmd.append([ca.if_else(use_plan, picked[i * c + j], ca.if_else(use_safe, safe[j], cmd_in[i * c + j]))
                    for j in range(c)])
        streak.append(st_i)
        # rows replayed since the plan was stored; a good chamber's plan stored now starts again at 0
        age_i = ca.if_else(use_plan, row, age0[i])
        good_stored = ca.logic_and(store_good, ok[i])
        age.append(ca.if_else(good_stored, 0, age_i))
        plan_t.append(ca.if_else(good_stored, t, plan_t0[i]))
        shifted.append(use_plan)
        safe_ev.append(use_safe)
    # a late plan given with the failure is stored for the failed chambers after their replay (with
    # none stored and no chamber good, that is the whole plan: every chamber failed)
    late = [ca.logic_and(giv, ca.logic_not(ok[i])) for i in range(n)]
    plan2 = ca.if_else(per_entry(late), plan_in, plan1)
    for i in range(n):
        age[i] = ca.if_else(late[i], 0, age[i])
        plan_t[i] = ca.if_else(late[i], t, plan_t[i])
    # every chamber ok: the plan given is kept whole (stored above), or without one none is kept
    plan_out = ca.if_else(ca.logic_and(all_ok, ca.logic_not(giv)), ca.DM.zeros(m), plan2)
    has_out = ca.if_else(all_ok, giv, ca.logic_or(has1, giv))
    # --- 2. clip
    cmd = [[ca.fmin(ca.fmax(v, 0.0), 1.0) for v in row] for row in cmd]
    # --- 3. vent on a zero target
    vent = []
    for i in range(n):
        v_i = SX(0) if s.vent_height is None else ca.logic_and(is_finite(target[i]), target[i] <= s.vent_height)
        vent.append(v_i)
        cmd[i] = [ca.if_else(v_i, safe[j], cmd[i][j]) for j in range(c)]
    # --- 4. pressure guard, 5. stretch guard, 6. lost estimate, 7. burst
    guard, sguard, lost_ev, released, lost_next, burst_next, burst_ev = [], [], [], [], [], [], []
    for i in range(n):
        fin = is_finite(p_in[i])
        p_g = ca.if_else(fin, p_in[i], s.p_max)
        zone = p_g >= s.p_max - s.guard_margin
        if not s.missing_is_limit:
            zone = ca.logic_and(zone, fin)
        unsafe = cmd[i][0] > 0
        if s.vent_margin is not None:
            unsafe = ca.logic_or(unsafe, cmd[i][c - 1] < 1.0)
        act = ca.logic_and(zone, unsafe)
        row = [ca.if_else(act, 0.0, cmd[i][j]) for j in range(c - 1)] + [cmd[i][c - 1]]
        if s.vent_margin is not None:
            row[c - 1] = ca.if_else(ca.logic_and(act, p_g >= s.p_max - s.vent_margin), 1.0, row[c - 1])
        guard.append(act)
        over = SX(0)
        if s.stretch_max is not None:
            over = ca.logic_and(stretch[i] >= s.stretch_max, row[0] > 0)  # (NaN compares false: not guarded)
            row = [ca.if_else(over, 0.0, row[j]) for j in range(c - 1)] + [row[c - 1]]
        sguard.append(over)
        lost_i = ca.logic_or(lost0[i] != 0, lost_in[i] != 0)
        rel = ca.logic_and(ca.logic_and(lost_i, fin), p_g <= s.lost_release)
        row = [ca.if_else(lost_i, safe[j], row[j]) for j in range(c)]
        lost_ev.append(lost_i)
        released.append(rel)
        lost_next.append(ca.logic_and(lost_i, ca.logic_not(rel)))
        b_i = ca.logic_or(burst0[i] != 0, burst_in[i] != 0)
        row = [ca.if_else(b_i, safe[j], row[j]) for j in range(c)]
        burst_next.append(b_i)
        burst_ev.append(b_i)
        cmd[i] = row
    events = [shifted, safe_ev, vent, guard, sguard, lost_ev, burst_ev]
    state_next = ca.vertcat(plan_out, has_out, *plan_t, *streak, *age, *lost_next, *burst_next)
    return ca.Function(name, [t, cmd_in, p_in, ok_in, plan_in, given, target, stretch, lost_in, burst_in, st],
                       [ca.vertcat(*[v for row in cmd for v in row]), state_next, ca.vertcat(*released),
                        ca.vertcat(*[e for ev in events for e in ev]), ca.logic_not(all_ok)],
                       ["t", "command", "pressure", "ok", "plan", "plan_given", "target", "stretch", "lost",
                        "burst", "state"], ["command_out", "state_next", "released", "events", "failed"],
                       {"cse": True})
