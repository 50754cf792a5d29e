"""The [controller] table: which controller, its settings, the height targets and load steps.

The keys are the declarations of :class:`~hbma_ctrl.controllers.mpc_settings.MPCSettings`,
``PIDSettings``, ``BangBangSettings``, ``LQISettings``, ``ReferenceProfile`` and ``ControllerSection`` in the user's
units (kPa, mm, ms, g); ``sample_ms``, ``p_max_kpa`` and ``guard_margin_kpa`` go to all four
controllers. Keys the user does not write are not passed on, so every SI default stays the settings
class's own.
"""

from __future__ import annotations

from typing import NamedTuple

from pydantic import model_validator

from hbma_ctrl.controllers.baselines import BangBangSettings, PIDSettings
from hbma_ctrl.controllers.lqi import LQISettings
from hbma_ctrl.controllers.mpc_settings import MPCSettings
from hbma_ctrl.app.schema.fields import (
    LOAD_STEPS_SHAPE,
    LoadSteps,
    RuleError,
    elem_of,
    flag,
    load_steps_si,
    settings_table,
    shaped,
)
from hbma_ctrl.system.sections import TARGET_HEIGHT, TARGET_TIME, ControllerSection, ReferenceProfile
from hbma_ctrl.core import units as U

__all__ = ["ControllerTable", "TargetRow"]

#: the keys every controller takes (MPCSettings' declarations, the same in PID, bang-bang and LQI)
_SHARED = ("sample_period", "p_max", "guard_margin")

_KEYS = settings_table(
    "ControllerKeys",
    (ControllerSection, ("kind",)),
    (MPCSettings, ("variant", "horizon", *_SHARED, "p_margin", "lam_max", "h_max", "integrator", "substeps",
                   "w_height", "w_terminal", "w_rate", "w_input", "c_input", "budget", "enforce_budget", "codegen",
                   "membrane", "integral_gain", "fail_window")),
    (PIDSettings, ("kp", "ki", "kd")),
    (BangBangSettings, ("band",)),
    (LQISettings, ("q_height", "q_integral", "r_command")),
    (ReferenceProfile, ("interpolation", "sine_amplitude", "sine_period", "sine_start")),
    (ControllerSection, ("settle_band", "calibrate", "valve_min_on", "calibration_std_floor")),
    defaults={"guard_margin": None})  # each controller's own


class TargetRow(NamedTuple):
    """One target point: from t_s on (or ramping to it), the height h_mm."""

    t_s: elem_of(TARGET_TIME)
    h_mm: elem_of(TARGET_HEIGHT)


class ControllerTable(_KEYS):
    """[controller] in the user's units; :meth:`to_section` gives the SI ControllerSection."""

    targets_mm: list[TargetRow] = shaped(..., "target heights from t_s on", "[[t_s, h_mm], ...]", min_length=1)
    load_steps_g: LoadSteps = shaped(None, "rig load from t_s on", LOAD_STEPS_SHAPE, default_factory=list)
    preview: bool | None = flag(None, "give the MPC the future targets; default: for ramps and sines")

    @model_validator(mode="after")
    def _cross(self) -> ControllerTable:
        given = self.model_fields_set
        pmax = self.p_max_kpa
        margins = [("p_margin_kpa", self.p_margin_kpa, "p_margin_kpa" not in given, "the MPC default")]
        if self.guard_margin_kpa is not None:
            margins.append(("guard_margin_kpa", self.guard_margin_kpa, False, ""))
        else:  # every controller's settings are validated, whichever runs: both defaults are checked
            margins += [("guard_margin_kpa", U.to_kpa(MPCSettings.guard_margin), True, "the MPC default"),
                        ("guard_margin_kpa", U.to_kpa(PIDSettings.guard_margin), True, "the PID, bang-bang and LQI default")]
        for key, v, default, which in margins:
            if v > pmax:
                note = f" ({which})" if default else ""
                raise RuleError(f"{key} = {v!r}{note} is out of range [0, {pmax:g}] kPa (at most p_max_kpa)")
        if self.fail_window_s is not None and self.fail_window_s[0] > self.fail_window_s[1]:
            raise RuleError(f"fail_window_s = {list(self.fail_window_s)!r} must be [t_start_s, t_end_s] "
                            "with t_start_s <= t_end_s")
        ts = [r.t_s for r in self.targets_mm]
        for i, (a, b) in enumerate(zip(ts, ts[1:])):
            if b < a:
                raise RuleError(f"targets_mm[{i + 1}].t_s = {b:g} must not be before the previous "
                                f"point's {a:g} s (times must be non-decreasing)")
        return self

    def to_section(self) -> ControllerSection:
        """The SI section: MPCSettings, PIDSettings, BangBangSettings, LQISettings, ReferenceProfile, load steps (kg)."""
        mpc = self.si(MPCSettings)
        shared = {k: v for k, v in mpc.items() if k in _SHARED}
        reference = ReferenceProfile(points=tuple((r.t_s, U.mm(r.h_mm)) for r in self.targets_mm),
                                     **self.si(ReferenceProfile)).validate()
        return ControllerSection(mpc=MPCSettings(**mpc).validate(),
                                 pid=PIDSettings(**self.si(PIDSettings), **shared).validate(),
                                 bang_bang=BangBangSettings(**self.si(BangBangSettings), **shared).validate(),
                                 lqi=LQISettings(**self.si(LQISettings), **shared).validate(),
                                 reference=reference, load_steps=tuple(sorted(load_steps_si(self.load_steps_g))),
                                 preview=self.preview, **self.si(ControllerSection)).validate()
