"""The [robot] table and its sub-tables [robot.inputs] [robot.targets] [robot.material_params].

The keys are the declarations of :class:`~hbma_ctrl.robot.design.RobotDesign`, its chamber's
:class:`~hbma_ctrl.core.params.Actuator`, ``RobotPneumatics``, ``RobotPlantSettings`` and
``RobotSettings``, in the table's units (mm, g, kPa, ms, deg, N). Rules that need the whole
design (the chamber disk in the layer annulus, chamber names, reachable targets) run after the
fields, once, while the SI settings are built.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Annotated, Any, ClassVar, NamedTuple

import numpy as np
from pydantic import Field, PrivateAttr, ValidationInfo, model_validator

from hbma_ctrl.app.schema.base import MaterialName, build_material
from hbma_ctrl.app.schema.errors import hint
from hbma_ctrl.app.schema.fields import (
    RuleError,
    check_rows,
    choice,
    elem,
    elem_of,
    renamed_keys,
    settings_table,
    shaped,
    subtable,
)
from hbma_ctrl.system.sections import POSE_BEND, POSE_HEIGHT, RobotSettings
from hbma_ctrl.core import units as U
from hbma_ctrl.core.params import Actuator
from hbma_ctrl.core.settings import specs
from hbma_ctrl.robot.design import LETTERS, RobotDesign, RobotPneumatics
from hbma_ctrl.robot.kinematics import inverse_kinematics
from hbma_ctrl.robot.plant import RobotPlantSettings
from hbma_ctrl.robot.rig import H_TARGET_MAX

__all__ = ["RobotInputRow", "RobotTable", "RobotTargetRow", "TipLoadRow", "pose_si"]

_BASE = RobotDesign()
_CH = _BASE.chamber


def pose_si(height_mm: float, bend_deg: float, direction_deg: float) -> tuple[float, float, float]:
    """(height m, bend rad >= 0, direction rad in (-pi, pi]) of a pose target in mm and deg: a negative
    bend is the opposite direction's."""
    th = math.radians(bend_deg)
    ps = math.radians(direction_deg) + (math.pi if th < 0 else 0.0)
    return U.mm(height_mm), abs(th), math.atan2(math.sin(ps), math.cos(ps))


class RobotInputRow(NamedTuple):
    """One row of a chamber's schedule in [robot.inputs]."""

    t_s: elem(0.0, 1e6, "s", "switch time")
    speed_pct: elem(0.0, 100.0, "%", "compressor speed")
    inlet_duty: elem(0.0, 1.0, "-", "inlet valve duty")
    outlet_duty: elem(0.0, 1.0, "-", "outlet valve duty")


class RobotTargetRow(NamedTuple):
    """One pose target of a layer in [robot.targets]; a negative bend is the opposite direction."""

    t_s: elem(0.0, 1e5, "s", "time of the target")
    height_mm: elem_of(POSE_HEIGHT)
    bend_deg: elem_of(POSE_BEND)
    direction_deg: elem(None, None, "deg", "bend direction")


class TipLoadRow(NamedTuple):
    """One row of tip_load_n: the tip force from t_s on."""

    t_s: elem(0.0, None, "s", "time the force starts")
    fx: elem(-20.0, 20.0, "N", "tip force x")
    fy: elem(-20.0, 20.0, "N", "tip force y")
    fz: elem(-20.0, 20.0, "N", "tip force z")


_INPUT_SHAPE = "{chamber = [[t_s, speed_pct, inlet_duty, outlet_duty], ...]}"
_TARGET_SHAPE = "{all|A|B|... = [[t_s, height_mm, bend_deg, direction_deg], ...]}"

_KEYS = settings_table(
    "RobotKeys",
    (RobotSettings, ("mode",)),
    (RobotDesign, ("n_layers", "placement_radius", "chamber_angles", "layer_thickness", "outer_diameter",
                   "inner_diameter", "layer_mass", "end_mass")),
    (Actuator, ("r1", "t0", "V0")),
    (RobotDesign, ("max_stretch",)),
    (RobotPneumatics, ("topology", "outlets", "sensor_range", "pressure_limit")),
    (RobotPlantSettings, ("tip_force", "tip_moment", "sync_period")),
    (RobotSettings, ("snapshots", "controller", "compare_baseline", "settle_time", "mpc_horizon", "mpc_dt",
                     "mpc_budget", "mpc_enforce_budget", "mpc_w_slack", "target_rate", "valve_min_on", "valve_delay",
                     "sensor_delay", "burst_sigma")),
    # the robot's chamber, not a single HBMA's; the pressure limit's default follows the sensor range
    defaults={"r1": U.to_mm(_CH.r1), "t0": U.to_mm(_CH.t0), "V0": U.to_cm3(_CH.V0), "pressure_limit": None})


class RobotTable(_KEYS):
    """[robot] in the user's units; :meth:`to_settings` gives the SI RobotSettings (targets inside)."""

    material: MaterialName | None = choice(None, "chamber material; default nh")
    material_params: dict[str, Any] = subtable(dict, "material parameters (SI)", "{name = value, ...}")
    inputs: dict[str, Annotated[list[RobotInputRow], Field(min_length=1)]] = subtable(
        dict, "per-chamber schedules", _INPUT_SHAPE)
    targets: dict[str, Annotated[list[RobotTargetRow], Field(min_length=1)]] = subtable(
        dict, "pose targets per layer", _TARGET_SHAPE)
    tip_load_n: list[TipLoadRow] = shaped(None, "tip force from t_s on (N)", "[[t_s, fx, fy, fz], ...]",
                                          default_factory=list)

    #: old key -> the name it shares with [controller]; the old one is still read, with a notice
    renamed: ClassVar[dict[str, str]] = {"mpc_horizon": "horizon", "mpc_enforce_budget": "enforce_budget"}

    _settings: Any = PrivateAttr(None)

    @model_validator(mode="before")
    @classmethod
    def _old_names(cls, data: Any, info: ValidationInfo) -> Any:
        return renamed_keys("robot", data, cls.renamed, (info.context or {}).get("path"))

    def _given(self, key: str) -> bool:
        return key in self.model_fields_set and getattr(self, key) is not None

    @model_validator(mode="after")
    def _build(self) -> RobotTable:
        self._settings = self._settings_si()
        return self

    def to_settings(self) -> RobotSettings:
        """The SI robot settings (design, pneumatics, inputs, targets), built once at validation."""
        return self._settings

    # --- the SI objects, with the rules that need the whole design -----------------------------
    def _design(self) -> RobotDesign:
        act = _CH
        if self._given("material") or self._given("material_params"):
            act = replace(act, material=build_material(self.material or "nh", self.material_params,
                                                       "robot.material_params"))
        d0 = replace(_BASE, chamber=replace(act, **self.si(Actuator)), **self.si(RobotDesign))
        act = d0.chamber
        inner, outer = U.to_mm(d0.inner_diameter), U.to_mm(d0.outer_diameter)
        if outer <= inner:
            raise RuleError(f"outer_diameter_mm = {outer:g} is out of range ({inner:g}, 500] mm "
                            "(above inner_diameter_mm)")
        # the annulus rule in the table's units, rounded as the table's numbers are
        lo = round(U.to_mm(d0.inner_diameter / 2 + act.r1), 3)
        hi = round(U.to_mm(d0.outer_diameter / 2 - act.r1), 3)
        pr = U.to_mm(d0.placement_radius)
        if not lo <= pr <= hi:
            raise RuleError(f"placement_radius_mm = {pr:g} is out of range [{lo:g}, {hi:g}] mm (the chamber "
                            f"disk, r1 = {U.to_mm(act.r1):g} mm, must fit the layer annulus)")
        lam = min(20.0, act.material.lam_max())
        if d0.max_stretch > lam:
            lo = specs(RobotDesign)["max_stretch"].lo
            raise RuleError(f"max_stretch = {d0.max_stretch:g} is out of range [{lo:g}, {lam:g}] (at most the "
                            f"material's stretch limit)")
        try:
            return d0.validate()
        except ValueError as exc:  # angles that overlap or tip the layer; SI ranges as a last guard
            raise RuleError(str(exc).replace("actuator.", "").replace("robot.chamber_angles:", "chamber_angles_deg:")
                            .replace("robot.", "")) from None

    def _targets(self, design: RobotDesign) -> dict:
        n = design.n_layers
        letters = list(LETTERS[:n])
        out: dict = {}
        for key, rows in self.targets.items():
            if key != "all" and key not in letters:
                raise RuleError(f"{key}: no such layer; allowed: all, {', '.join(letters)}", "robot.targets")
            parsed = sorted(((r.t_s, *pose_si(r.height_mm, r.bend_deg, r.direction_deg)) for r in rows),
                            key=lambda x: x[0])
            for k in (range(n) if key == "all" else [letters.index(key)]):
                if key == "all" and k in out:
                    continue
                out[k] = tuple(parsed)
        one = design.with_(n_layers=1)
        h_top = U.to_mm(H_TARGET_MAX)
        for k in range(n):
            if k not in out:
                raise RuleError(f"layer {letters[k]} has no rows (give all or {letters[k]})", "robot.targets")
            for t, c, th, ps in out[k]:
                h = inverse_kinematics(one, c, th, ps)[0]
                if h.min() < -5e-5 or h.max() > H_TARGET_MAX + 1e-9:  # 0.05 mm: the table's rounding
                    raise RuleError(f"layer {letters[k]} at t = {t:g} s needs chamber heights "
                                    f"{np.round(U.to_mm(h), 2).tolist()} mm; each must lie in [0, {h_top:g}] mm "
                                    "(raise height_mm or lower bend_deg)", "robot.targets")
        return out

    def _settings_si(self) -> RobotSettings:
        design = self._design()
        sensor = self.sensor_range_kpa
        limit = self.pressure_limit_kpa if self._given("pressure_limit_kpa") else \
            min(U.to_kpa(RobotPneumatics.pressure_limit), sensor)
        if limit > sensor:
            raise RuleError(f"pressure_limit_kpa = {limit!r} is out of range [1, {sensor:g}] kPa "
                            "(at most sensor_range_kpa)")
        pn = RobotPneumatics(topology=self.topology, outlets=self.outlets, sensor_range=U.kpa(sensor),
                             pressure_limit=U.kpa(limit))
        names = design.names
        inputs = {}
        for name, rows in self.inputs.items():
            if name not in names:
                raise RuleError(f"{name}: no such chamber{hint(name, names, 'chambers')}", "robot.inputs")
            check_rows(rows, name, "robot.inputs")
            inputs[name] = tuple((r.t_s, U.pct(r.speed_pct), r.inlet_duty, r.outlet_duty) for r in rows)
        closed: dict = {}
        if "targets" in self.model_fields_set:
            if not self.targets:
                raise RuleError(f"is empty; give {_TARGET_SHAPE}", "robot.targets")
            closed["targets"] = self._targets(design)
        elif self.mode == "closed_loop":
            raise RuleError("mode = 'closed_loop' needs [robot.targets] for closed-loop robot control: "
                            f"{_TARGET_SHAPE} (all, or one per layer)")
        if self._given("tip_load_n"):
            closed["tip_load"] = tuple(tuple(r) for r in self.tip_load_n)
        try:
            return RobotSettings(design=design, pneumatics=pn, inputs=inputs, **self.si(RobotPlantSettings),
                                 **self.si(RobotSettings), **closed).validate()
        except ValueError as exc:  # SI ranges as a last guard
            raise RuleError(str(exc).replace("robot.", "")) from None
