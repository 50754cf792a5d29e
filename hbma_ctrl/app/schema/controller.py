"""The [controller] table: which controller, its settings, the height targets and load steps.

Bounds are those of ``MPCSettings.validate``, ``PIDSettings.validate``,
``BangBangSettings.validate`` and ``ReferenceProfile.validate``, restated in the user's units
(kPa, mm, ms, g). Keys the user does not write are not passed on, so every SI default stays the
settings class's own.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

from pydantic import model_validator

from hbma_ctrl.controllers.baselines import BangBangSettings, PIDSettings
from hbma_ctrl.controllers.mpc_settings import MPCSettings
from hbma_ctrl.app.schema.fields import (
    LOAD_STEPS_SHAPE,
    LoadSteps,
    RuleError,
    Table,
    as_is,
    choice,
    elem,
    flag,
    integer,
    load_steps_si,
    num,
    shaped,
)
from hbma_ctrl.system.sections import ControllerSection, ReferenceProfile
from hbma_ctrl.core import units as U
from hbma_ctrl.models.defaults import DEFAULT_MEMBRANE, DEFAULT_VALVE_MIN_ON
from hbma_ctrl.runtime.calibrate import CalibrationSettings

__all__ = ["ControllerTable", "TargetRow"]

#: a gain per mm is 1000 times the gain per m: the mm -> m length factor inverted
per_mm_to_per_m = U.to_mm

_W = elem(0.0, 1e6, "-", "weight")
_T = elem(0.0, None, "s", "time")
_VEC = "[speed, inlet, outlet]"


class TargetRow(NamedTuple):
    """One target point: from t_s on (or ramping to it), the height h_mm."""

    t_s: elem(0.0, 1e5, "s", "time of the point")
    h_mm: elem(0.0, 200.0, "mm", "target height")


class ControllerTable(Table):
    """[controller] in the user's units; :meth:`to_section` gives the SI ControllerSection."""

    kind: Literal["mpc", "pid", "bang_bang"] = choice("mpc", "which controller runs")
    variant: Literal["rti_osqp", "rti_c_osqp", "rti_fn_osqp", "rti_fn_hpipm", "rti_fn_qrqp", "ipopt", "fatrop"] = choice(
        "rti_c_osqp", "MPC: RTI + OSQP, its QP data as generated C (fast; rti_osqp: the same QP built in numpy, slower), the RTI step as one casadi Function with its QP solved by "
        "OSQP / HPIPM / qrqp (rti_fn_*), or IPOPT / fatrop (accurate)")
    horizon: int = integer(20, 2, 200, "MPC horizon N", "steps")
    sample_ms: float = num(20.0, 0.0, 1000.0, "ms", "controller period (a multiple of the rig's)",
                           lo_open=True)
    p_max_kpa: float = num(35.0, 0.0, 1000.0, "kPa", "gauge pressure limit", lo_open=True)
    p_margin_kpa: float = num(1.0, 0.0, 1000.0, "kPa", "MPC: predicted pressure kept this far below "
                              "p_max_kpa (at most p_max_kpa)")
    guard_margin_kpa: float | None = num(None, 0.0, 1000.0, "kPa", "pressure guard margin, at most "
                                         "p_max_kpa; default MPC 0.5, PID and bang-bang 1")
    lam_max: float = num(1.5, 1.0, 5.0, "-", "MPC: stretch limit", lo_open=True)
    h_max_mm: float = num(20.0, 0.0, 200.0, "mm", "MPC: height bound", lo_open=True)
    integrator: Literal["rk4", "euler"] = choice("rk4", "MPC discretisation")
    substeps: int = integer(1, 1, 20, "MPC integrator steps per interval", "steps")
    w_height: float = num(1.0, 0.0, 1e9, "1/mm^2", "MPC weight on the height error per stage")
    w_terminal: float = num(5.0, 0.0, 1e9, "1/mm^2", "MPC weight on the final height error")
    w_rate: tuple[_W, _W, _W] = shaped((0.02, 0.002, 0.02), "MPC weights on input changes (-)", _VEC)
    w_input: tuple[_W, _W, _W] = shaped((0.002, 0.0, 0.002), "MPC quadratic input weights (-)", _VEC)
    c_input: tuple[_W, _W, _W] = shaped((0.02, 0.01, 0.02), "MPC linear input costs (-)", _VEC)
    budget_ms: float = num(15.0, 0.0, 10000.0, "ms", "MPC wall-clock budget per step (acts with enforce_budget; "
                           "the rig daemon always enforces it)", lo_open=True)
    enforce_budget: bool = flag(False, "MPC: in a simulation, make a step slower than budget_ms an overrun (the "
                                       "supervisor's fallback), as in the rig daemon; off, results do not "
                                       "depend on the machine's load")
    codegen: bool = flag(True, "MPC: compile the RTI linearisation to C")
    membrane: Literal["cap", "exact"] = choice(DEFAULT_MEMBRANE, "MPC prediction model's membrane law: cap "
                                               "(spherical cap) or exact (exact membrane tables)")
    integral_gain_per_s: float = num(2.0, 0.0, 100.0, "1/s", "MPC integral action on the height error near "
                                     "the target (0 = none)")
    fail_window_s: tuple[_T, _T] | None = shaped(None, "MPC solves in this window fail (drill), s",
                                                 "[t_start_s, t_end_s]")
    kp: float = num(1.0, 0.0, 1e4, "1/mm", "PID proportional gain")
    ki: float = num(0.2, 0.0, 1e4, "1/(mm s)", "PID integral gain")
    kd: float = num(0.02, 0.0, 1e4, "s/mm", "PID derivative gain")
    band_kpa: float = num(0.5, 0.0, 100.0, "kPa", "bang-bang hysteresis half-band")
    targets_mm: list[TargetRow] = shaped(..., "target heights from t_s on", "[[t_s, h_mm], ...]", min_length=1)
    interpolation: Literal["step", "linear"] = choice("step", "hold each target or ramp between them")
    sine_amplitude_mm: float = num(0.0, 0.0, 100.0, "mm", "sinusoid added to the targets")
    sine_period_s: float = num(1.0, 0.0, 1e4, "s", "sinusoid period", lo_open=True)
    sine_start_s: float = num(0.0, 0.0, 1e5, "s", "sinusoid start")
    load_steps_g: LoadSteps = shaped(None, "rig load from t_s on", LOAD_STEPS_SHAPE, default_factory=list)
    settle_band_mm: float = num(0.3, 0.0, 50.0, "mm", "settling band of the step metrics", lo_open=True)
    preview: bool | None = flag(None, "give the MPC the future targets; default: for ramps and sines")
    calibrate: bool = flag(True, "before the loop closes, learn the pump-flow, modulus and dead-volume "
                                 "factors from a pump pulse (to at most half of p_max_kpa, 17 kPa) and a vent")
    valve_min_on_ms: float = num(U.to_ms(DEFAULT_VALVE_MIN_ON), 0.0, 100.0, "ms",
                                 "the valves' minimum opening (datasheet): shorter duties "
                                 "are sent as pulses of this length often enough to pass them on average")
    calibration_std_floor: float = num(CalibrationSettings.handover_std_floor, 0.0, 1.0, "-", "smallest sigma of each factor the calibration hands "
                                       "the estimator (its fit's own assumes the model is the chamber)")

    @model_validator(mode="after")
    def _cross(self) -> ControllerTable:
        given = self.model_fields_set
        pmax = self.p_max_kpa
        margins = [("p_margin_kpa", self.p_margin_kpa, "p_margin_kpa" not in given, "the MPC default")]
        if self.guard_margin_kpa is not None:
            margins.append(("guard_margin_kpa", self.guard_margin_kpa, False, ""))
        else:  # every controller's settings are validated, whichever runs: both defaults are checked
            margins += [("guard_margin_kpa", 0.5, True, "the MPC default"),
                        ("guard_margin_kpa", 1.0, True, "the PID and bang-bang default")]
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

    def _given(self, key: str) -> bool:
        return key in self.model_fields_set and getattr(self, key) is not None

    def to_section(self) -> ControllerSection:
        """The SI section: MPCSettings, PIDSettings, BangBangSettings, ReferenceProfile, load steps (kg)."""
        mpc: dict = {}
        pid: dict = {}
        bb: dict = {}
        groups = {"mpc": (mpc,), "pid": (pid,), "bb": (bb,), "all": (mpc, pid, bb)}
        for key, (group, name, conv) in _SI.items():
            if self._given(key):
                v = getattr(self, key)
                for d in groups[group]:
                    d[name] = conv(v)
        ref: dict = {}
        for key, name, conv in (("interpolation", "interpolation", str),
                                ("sine_amplitude_mm", "sine_amplitude", U.mm),
                                ("sine_period_s", "sine_period", float), ("sine_start_s", "sine_start", float)):
            if self._given(key):
                ref[name] = conv(getattr(self, key))
        sec: dict = {}
        if self._given("settle_band_mm"):
            sec["settle_band"] = U.mm(self.settle_band_mm)
        if self._given("valve_min_on_ms"):
            sec["valve_min_on"] = U.ms(self.valve_min_on_ms)
        if self._given("calibration_std_floor"):
            sec["calibration_std_floor"] = float(self.calibration_std_floor)
        try:
            reference = ReferenceProfile(points=tuple((r.t_s, U.mm(r.h_mm)) for r in self.targets_mm),
                                         **ref).validate()
            return ControllerSection(kind=self.kind, mpc=MPCSettings(**mpc).validate(),
                                     pid=PIDSettings(**pid).validate(), bang_bang=BangBangSettings(**bb).validate(),
                                     reference=reference, load_steps=tuple(sorted(load_steps_si(self.load_steps_g))),
                                     preview=self.preview, calibrate=self.calibrate, **sec)
        except ValueError as exc:  # a bound the table could not state (kept as a last guard)
            raise ValueError(f"[controller] {exc}") from None


#: table key -> (settings it goes to: mpc | pid | bb | all, SI field, conversion from the user's unit)
_SI = {
    "variant": ("mpc", "variant", as_is),
    "horizon": ("mpc", "horizon", as_is),
    "sample_ms": ("all", "sample_period", U.ms),
    "p_max_kpa": ("all", "p_max", U.kpa),
    "p_margin_kpa": ("mpc", "p_margin", U.kpa),
    "guard_margin_kpa": ("all", "guard_margin", U.kpa),
    "lam_max": ("mpc", "lam_max", float),
    "h_max_mm": ("mpc", "h_max", U.mm),
    "integrator": ("mpc", "integrator", as_is),
    "substeps": ("mpc", "substeps", as_is),
    "w_height": ("mpc", "w_height", float),
    "w_terminal": ("mpc", "w_terminal", float),
    "w_rate": ("mpc", "w_rate", tuple),
    "w_input": ("mpc", "w_input", tuple),
    "c_input": ("mpc", "c_input", tuple),
    "budget_ms": ("mpc", "budget", U.ms),
    "enforce_budget": ("mpc", "enforce_budget", as_is),
    "codegen": ("mpc", "codegen", as_is),
    "membrane": ("mpc", "membrane", as_is),
    "integral_gain_per_s": ("mpc", "integral_gain", float),
    "fail_window_s": ("mpc", "fail_window", tuple),
    "kp": ("pid", "kp", per_mm_to_per_m),
    "ki": ("pid", "ki", per_mm_to_per_m),
    "kd": ("pid", "kd", per_mm_to_per_m),
    "band_kpa": ("bb", "band", U.kpa),
}
