"""One chamber's loop a rig daemon embeds: reading -> estimator -> controller -> supervisor -> command (SI).

``ChamberLoop.tick(t, reading_pa)`` is everything one sample does; no I/O. The estimator runs at
every tick, the controller and the supervisor every ``every`` ticks (the command holds between).
Without ``every``, the loop takes it from the controller's ``settings.sample_period`` and the spacing
of its first two ticks (:func:`whole_multiple`: a ValueError naming both when it is not one).
The controller's wall and thread-CPU time per step go into bounded :class:`StepStats`; its failures
(``step_status`` not ok, or an exception) go to the :class:`Supervisor`, which replays the last
good plan (``controller.plan``), then sends the safe command; the command finally sent is handed
back to the controller (``controller.applied``).

The estimator and the controller are the contracts :class:`hbma_ctrl.core.interfaces.Estimator` and
:class:`hbma_ctrl.core.interfaces.Controller`: a role that lacks a member is a TypeError naming it
when the loop is built (their base classes have the defaults of the optional ones).

References from a live stream are checked: a target that is not a finite number (NaN, inf, a string)
is a ValueError naming ``reference`` -- at :meth:`ChamberLoop.set_reference` for a constant, at the
tick for a function's value -- never a command computed from it. A non-finite or backwards ``t``
is the estimator's ValueError.
"""

from __future__ import annotations

import math
import time
from typing import Callable

from hbma_ctrl.core import units as U
from hbma_ctrl.core.interfaces import (
    SAFE_COMMAND,
    Command,
    Controller,
    ControllerSettings,
    Estimate,
    Estimator,
    Reference,
    SolveStatus,
    StepStatus,
    check_role,
)
from hbma_ctrl.core.validation import finite_or_nan
from hbma_ctrl.runtime.pwm import MinOnTime
from hbma_ctrl.runtime.safety import Supervisor, SupervisorSettings
from hbma_ctrl.runtime.stats import StepStats

__all__ = ["ChamberLoop", "chamber_supervisor", "check_height", "whole_multiple"]


def check_height(value, key: str = "reference") -> float:
    """A target height (m) as a float; ValueError naming ``key`` when it is not a finite number."""
    h = finite_or_nan(value)
    if math.isnan(h):
        raise ValueError(f"{key} = {value!r}: a target height must be a finite number (m)")
    return h


def whole_multiple(period: float, tick: float, period_key: str, tick_key: str) -> int:
    """How many ticks of ``tick`` s make one ``period`` s (>= 1); ValueError naming both keys (in ms)
    when ``period`` is not a whole multiple of ``tick``."""
    ratio = period / tick if tick > 0 else math.nan
    every = int(round(ratio)) if math.isfinite(ratio) else 0
    if every < 1 or abs(ratio - every) > 1e-6:
        raise ValueError(f"{period_key} = {U.to_ms(period):g} ms must be a whole multiple of {tick_key} = "
                         f"{U.to_ms(tick):g} ms")
    return every


def chamber_supervisor(controller_settings: ControllerSettings, **overrides) -> Supervisor:
    """The single-chamber supervisor for a controller's settings (its p_max, guard_margin and
    fallback_plan_steps; the outlet opens within half the guard margin of p_max). ``overrides`` set
    other :class:`SupervisorSettings` fields. TypeError when the settings lack a member of
    :class:`~hbma_ctrl.core.interfaces.ControllerSettings`."""
    s = controller_settings
    check_role(s, ControllerSettings, "chamber_supervisor: controller settings")
    kw = dict(p_max=float(s.p_max), guard_margin=float(s.guard_margin), vent_margin=0.5 * float(s.guard_margin),
              fallback_plan_steps=int(s.fallback_plan_steps))
    kw.update(overrides)
    return Supervisor(SupervisorSettings(**kw), n=1)


def _failure_cause(status: StepStatus) -> str:
    """The supervisor's cause for a step that did not solve."""
    return "overrun" if status.kind is SolveStatus.OVERRUN else "solver_failed"


class ChamberLoop:
    """Estimator, controller and supervisor of one chamber (see module doc).

    Parameters
    ----------
    estimator : an :class:`~hbma_ctrl.core.interfaces.Estimator` (``step(t, reading_pa, command) ->
        Estimate``); None = none, for a caller that hands :meth:`control` the estimate itself.
    controller : a :class:`~hbma_ctrl.core.interfaces.Controller` (``step(t, estimate, reference[,
        preview]) -> Command``, ``stats() -> dict``, ...).
    supervisor : a 1-chamber :class:`Supervisor`; None = :func:`chamber_supervisor` of the
        controller's settings (ValueError when it has none).
    reference : target height (m) at time t (s), or a constant height (m); None = hold (no target).
    every : the controller runs every ``every`` ticks (>= 1); None = its ``settings.sample_period``
        over the spacing of the first two ticks (1 for a controller without a sample period).
    preview_steps : future targets handed to the controller (at ``preview_period`` s apart), 0 = none;
        more than 0 only for a controller that ``accepts_preview`` (ValueError otherwise).
    preview_period : spacing of the preview targets, s.
    stats_capacity : samples kept for the median and p99 of the step times.
    pwm : the valves' minimum on-time shaping (:class:`~hbma_ctrl.runtime.pwm.MinOnTime`), applied
        every tick to the held command (the controller and supervisor see the duties they asked
        for; the estimator the duties sent); None = the command as it is.
    """

    def __init__(self, estimator: Estimator | None, controller: Controller, supervisor: Supervisor | None = None,
                 reference: Callable[[float], float] | None = None, every: int | None = None, preview_steps: int = 0,
                 preview_period: float = 0.0, stats_capacity: int = 4096, pwm: MinOnTime | None = None):
        if every is not None and (not isinstance(every, int) or every < 1):
            raise ValueError(f"ChamberLoop.every = {every!r} must be an integer >= 1")
        if estimator is not None:
            check_role(estimator, Estimator, "ChamberLoop: estimator")
        check_role(controller, Controller, "ChamberLoop: controller")
        if preview_steps and not controller.accepts_preview:
            raise ValueError(f"ChamberLoop: preview_steps = {preview_steps!r} for a controller that does not accept "
                             f"a preview ({type(controller).__name__}.accepts_preview is False)")
        if supervisor is None and controller.settings is None:
            raise ValueError(f"ChamberLoop: {type(controller).__name__}.settings is None: pass the supervisor, or give "
                             "the controller settings with p_max and guard_margin")
        self.estimator = estimator
        self.controller = controller
        self.supervisor = supervisor or chamber_supervisor(controller.settings)
        if self.supervisor.n != 1:
            raise ValueError("ChamberLoop: the supervisor must be for one chamber (n = 1)")
        self.reference = None
        self.set_reference(reference)
        self.every = every
        self.preview_steps = int(preview_steps)
        self.preview_period = float(preview_period)
        self.solve_ms = StepStats(stats_capacity)
        self.solve_cpu_ms = StepStats(stats_capacity)
        self.command = Command(0.0, 0.0, 0.0)  # sent this tick (after the PWM shaping)
        self.wanted = Command(0.0, 0.0, 0.0)  # the supervisor's, held between controller steps
        self.pwm = pwm if pwm is not None and pwm.active else None
        self.estimate: Estimate | None = None
        self.target: float | None = None
        self._k = 0
        self._t_first: float | None = None

    def set_reference(self, reference: Callable[[float], float] | float | None) -> None:
        """Replace the target height from the next tick on: a function (m at time t s), a constant
        height (m) or None (hold). ValueError naming ``reference`` when a constant is not a finite
        number (the old reference then stays)."""
        if reference is None or callable(reference):
            self.reference = reference
            return
        h = check_height(reference)
        self.reference = lambda t: h

    def tick(self, t: float, reading_pa: float, held: Command | None = None) -> Command:
        """One sample at time t (s) with the pressure reading (Pa, NaN = dropout): estimate, then
        (every ``every`` ticks) controller and supervisor. Returns the command to hold until the next tick.
        ``held``: the command the rig reports it held over the period this reading ends (None = the
        last one returned, as in a lockstep simulation); the estimator predicts with it."""
        self.estimate = self.estimator.step(t, reading_pa, self.command if held is None else held)
        self.target = None if self.reference is None else check_height(self.reference(t), f"reference(t={t})")
        if self.every is None:
            self._derive_every(t)
        if self._k % (self.every or 1) == 0:
            preview = None
            if self.preview_steps and self.target is not None:
                preview = [check_height(self.reference(tp), f"reference(t={tp})")
                           for tp in (t + self.preview_period * (j + 1) for j in range(self.preview_steps))]
            self.wanted = self.control(t, self.estimate, Reference(self.target), preview)
        self.command = self.wanted if self.pwm is None else self.pwm.shape(self.wanted)
        self._k += 1
        return self.command

    def _derive_every(self, t: float) -> None:
        """``every`` from the controller's sample period and the spacing of the first two ticks (s)."""
        period = getattr(self.controller.settings, "sample_period", None)
        if period is None:
            self.every = 1
        elif self._t_first is None:
            self._t_first = float(t)
        else:
            self.every = whole_multiple(float(period), float(t) - self._t_first,
                                        f"{type(self.controller).__name__} sample_period",
                                        "the tick period (the time between the first two ticks)")

    def control(self, t: float, estimate: Estimate, reference: Reference, preview=None) -> Command:
        """Controller then supervisor on a given estimate (what ``tick`` does after the estimator)."""
        ctrl = self.controller
        t0, c0 = time.perf_counter(), time.thread_time()
        plan = None
        try:
            cmd = ctrl.step(t, estimate, reference, preview=preview) if preview is not None else \
                ctrl.step(t, estimate, reference)
            status = ctrl.step_status
            ok = status.ok
            plan = ctrl.plan
            cause = "ok" if ok else _failure_cause(status)
        except Exception as exc:  # noqa: BLE001 - a daemon must keep commanding whatever a controller raises
            cmd, ok, cause = SAFE_COMMAND, False, f"exception: {type(exc).__name__}"
        self.solve_ms.add((time.perf_counter() - t0) * 1e3)
        self.solve_cpu_ms.add((time.thread_time() - c0) * 1e3)
        arr = self.supervisor.apply(t, cmd.as_array(), estimate.p, ok=ok, plan=plan, cause=cause,
                                    target=reference.height)
        out = Command(float(arr[0]), float(arr[1]), float(arr[2]))
        ctrl.applied(out)
        return out

    def stats(self) -> dict:
        """The controller's own stats with the runtime's timing (ms), fallbacks and guard counts (same keys
        as the controllers reported before the runtime layer)."""
        sup = self.supervisor
        st = dict(self.controller.stats())
        t, c = self.solve_ms.summary(), self.solve_cpu_ms.summary()
        st.update({"solve_ms_median": t["median"], "solve_ms_p99": t["p99"], "solve_ms_max": t["max"],
                   "steps": t["n"], "guard_activations": int(sup.counts["guard"]),
                   "fallbacks": int(st.get("fallbacks", 0)) + int(sup.failed_steps)})
        if self.controller.reports_failures:
            st.update({"solve_cpu_ms_median": c["median"], "solve_cpu_ms_p99": c["p99"]})
            detail = {"solver_failed": 0, "overrun": 0}
            for cause, k in sup.failure_causes.items():
                detail[cause] = detail.get(cause, 0) + k
            detail.update({"shifted_plan": int(sup.counts["shifted_plan"]),
                           "safe_command": int(sup.counts["safe_command"])})
            st["fallback_detail"] = detail
        return st

    def events(self) -> list:
        """The supervisor's logged interventions (oldest first)."""
        return list(self.supervisor.events)
