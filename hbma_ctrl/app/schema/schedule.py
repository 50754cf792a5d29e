"""The [schedule] table and its [[schedule.step]] tables: an open-loop recording run on the daemon
(kPa, s, %).

The keys are the declarations of :class:`~hbma_ctrl.app.daemon.schedule.Schedule` and
:class:`~hbma_ctrl.app.daemon.schedule.ScheduleStep` in the user's units.
"""

from __future__ import annotations

from pydantic import Field, model_validator

from hbma_ctrl.app.daemon.schedule import Schedule, ScheduleStep
from hbma_ctrl.app.schema.fields import RuleError, settings_table

__all__ = ["ScheduleStepTable", "ScheduleTable"]


class ScheduleStepTable(settings_table("ScheduleStepKeys", (ScheduleStep, (
        "action", "duration", "speed", "inlet", "outlet", "chamber")))):
    """One [[schedule.step]] in the user's units."""

    def to_step(self) -> ScheduleStep:
        """The SI step (its rules checked by the schedule)."""
        return ScheduleStep(**self.si(ScheduleStep))


class ScheduleTable(settings_table("ScheduleKeys", (Schedule, ("repeat", "pump_stop", "p_max")))):
    """[schedule] in the user's units; :meth:`to_schedule` gives the SI Schedule."""

    step: list[ScheduleStepTable] = Field(default_factory=list, description="[[schedule.step]] the steps, in order")

    @model_validator(mode="after")
    def _rules(self) -> ScheduleTable:
        try:
            self.to_schedule()
        except ValueError as exc:
            raise RuleError(str(exc).removeprefix("schedule.").removeprefix("schedule: ")) from None
        return self

    def to_schedule(self) -> Schedule:
        """The SI schedule (ValueError naming the step and key when a rule fails)."""
        return Schedule(**self.si(Schedule), steps=tuple(s.to_step() for s in self.step)).validate()
