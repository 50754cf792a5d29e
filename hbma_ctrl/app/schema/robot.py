"""The [robot] table and its sub-tables [robot.inputs] [robot.targets] [robot.material_params].

Bounds are those of ``RobotDesign.validate``,
``RobotPneumatics.validate``, ``RobotSettings.validate`` and the robot closed loop,
in the table's units (mm, g, kPa, ms, deg, N). Rules that need the whole
design (the chamber disk in the layer annulus, chamber names, reachable targets) run after the
fields, once, while the SI settings are built.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Annotated, Any, Literal, NamedTuple

import numpy as np
from pydantic import Field, PrivateAttr, model_validator

from hbma_ctrl.app.schema.base import MaterialName, build_material, check_rows
from hbma_ctrl.app.schema.errors import closest
from hbma_ctrl.app.schema.fields import (
    RuleError,
    Table,
    choice,
    elem,
    flag,
    integer,
    num,
    shaped,
    subtable,
)
from hbma_ctrl.system.sections import RobotSettings
from hbma_ctrl.core import units as U
from hbma_ctrl.models.defaults import DEFAULT_VALVE_DELAY, DEFAULT_VALVE_MIN_ON, ROBOT_SENSOR_DELAY
from hbma_ctrl.robot.design import LETTERS, RobotDesign, RobotPneumatics
from hbma_ctrl.robot.kinematics import inverse_kinematics
from hbma_ctrl.robot.rig import H_TARGET_MAX
from hbma_ctrl.runtime.burst import BurstTestSettings

__all__ = ["RobotInputRow", "RobotTable", "RobotTargetRow", "TipLoadRow"]

_BASE = RobotDesign()
_CH = _BASE.chamber


class RobotInputRow(NamedTuple):
    """One row of a chamber's schedule in [robot.inputs]."""

    t_s: elem(0.0, 1e6, "s", "switch time")
    speed_pct: elem(0.0, 100.0, "%", "compressor speed")
    inlet_duty: elem(0.0, 1.0, "-", "inlet valve duty")
    outlet_duty: elem(0.0, 1.0, "-", "outlet valve duty")


class RobotTargetRow(NamedTuple):
    """One pose target of a layer in [robot.targets]; a negative bend is the opposite direction."""

    t_s: elem(0.0, 1e5, "s", "time of the target")
    height_mm: elem(0.0, U.to_mm(H_TARGET_MAX), "mm", "centre height")
    bend_deg: elem(-60.0, 60.0, "deg", "bend angle")
    direction_deg: elem(None, None, "deg", "bend direction")


class TipLoadRow(NamedTuple):
    """One row of tip_load_n: the tip force from t_s on."""

    t_s: elem(0.0, None, "s", "time the force starts")
    fx: elem(-20.0, 20.0, "N", "tip force x")
    fy: elem(-20.0, 20.0, "N", "tip force y")
    fz: elem(-20.0, 20.0, "N", "tip force z")


_F = elem(None, None, "N", "force")
_M = elem(None, None, "N m", "moment")
_ANGLE = elem(-360.0, 360.0, "deg", "chamber angle")
_INPUT_SHAPE = "{chamber = [[t_s, speed_pct, inlet_duty, outlet_duty], ...]}"
_TARGET_SHAPE = "{all|A|B|... = [[t_s, height_mm, bend_deg, direction_deg], ...]}"


class RobotTable(Table):
    """[robot] in the user's units; :meth:`to_settings` gives the SI RobotSettings (targets inside)."""

    mode: Literal["open_loop", "closed_loop"] = choice("open_loop", "inputs by schedule or targets per layer")
    layers: int = integer(_BASE.n_layers, 1, 26, "number of chamber layers", "layers")
    placement_radius_mm: float = num(U.to_mm(_BASE.placement_radius), 1.0, 500.0, "mm",
                                     "chamber centres' distance from the axis (the disk must fit the annulus)")
    chamber_angles_deg: tuple[_ANGLE, _ANGLE, _ANGLE] = shaped((0.0, 120.0, 240.0), "the chambers' angles (deg)",
                                                              "[deg, deg, deg]")
    layer_thickness_mm: float = num(U.to_mm(_BASE.layer_thickness), 1.0, 100.0, "mm", "layer body thickness")
    outer_diameter_mm: float = num(U.to_mm(_BASE.outer_diameter), 1.0, 500.0, "mm",
                                   "layer outer diameter (above inner_diameter_mm)")
    inner_diameter_mm: float = num(U.to_mm(_BASE.inner_diameter), 0.0, 500.0, "mm", "layer inner diameter")
    layer_mass_g: float = num(U.to_grams(_BASE.layer_mass), 0.0, 10000.0, "g", "mass of one layer body")
    end_mass_g: float | None = num(None, 0.0, 10000.0, "g", "mass of the top body; default a layer's")
    r1_mm: float = num(U.to_mm(_CH.r1), 0.5, 100.0, "mm", "chamber disk radius", lo_open=True)
    t0_mm: float = num(U.to_mm(_CH.t0), 0.05, 20.0, "mm", "chamber membrane thickness", lo_open=True)
    V0_cm3: float = num(U.to_cm3(_CH.V0), 0.001, 1000.0, "cm^3", "chamber dead volume")
    material: MaterialName | None = choice(None, "chamber material; default nh")
    material_params: dict[str, Any] = subtable(dict, "material parameters (SI)", "{name = value, ...}")
    max_stretch: float = num(_BASE.max_stretch, 1.05, 20.0, "-", "largest membrane stretch (at most the "
                             "material's limit)")
    topology: Literal["per_chamber", "shared"] = choice("per_chamber", "one compressor per chamber or shared")
    outlets: Literal["per_chamber"] = choice("per_chamber", "outlet valve layout")
    sensor_range_kpa: float = num(50.0, 1.0, 1000.0, "kPa", "chamber sensors' saturation pressure")
    pressure_limit_kpa: float | None = num(None, 1.0, 1000.0, "kPa", "largest chamber pressure, at most "
                                           "sensor_range_kpa; default min(45, sensor_range_kpa)")
    tip_force_n: tuple[_F, _F, _F] = shaped((0.0, 0.0, 0.0), "force on the tip, world frame (N)", "[fx, fy, fz]")
    tip_moment_nm: tuple[_M, _M, _M] = shaped((0.0, 0.0, 0.0), "moment on the tip (N m)", "[mx, my, mz]")
    sync_ms: float = num(10.0, 0.1, 1000.0, "ms", "load-sharing and interlock update period")
    snapshots: int = integer(8, 1, 50, "robot shapes in the shape plot", "shapes")
    inputs: dict[str, Annotated[list[RobotInputRow], Field(min_length=1)]] = subtable(
        dict, "per-chamber schedules", _INPUT_SHAPE)
    controller: Literal["mpc", "pressure_pid"] = choice("mpc", "closed loop: NMPC or the pressure PID")
    targets: dict[str, Annotated[list[RobotTargetRow], Field(min_length=1)]] = subtable(
        dict, "pose targets per layer", _TARGET_SHAPE)
    tip_load_n: list[TipLoadRow] = shaped(None, "tip force from t_s on (N)", "[[t_s, fx, fy, fz], ...]",
                                          default_factory=list)
    compare_baseline: bool = flag(True, "also run the other controller")
    settle_s: float = num(2.0, 0.0, 1e4, "s", "RMSEs skip this long after a target change")
    mpc_horizon: int = integer(15, 1, 100, "NMPC stages", "stages")
    mpc_dt_ms: float = num(20.0, 1.0, 1000.0, "ms", "NMPC prediction step")
    mpc_budget: float = num(0.0, 0.0, 1.0, "-", "NMPC wall-time budget per step as a fraction of the control "
                            "period; an overrun is a failed step (0 = none; the daemon uses 0.8 then); "
                            "in a scene it acts with mpc_enforce_budget")
    mpc_enforce_budget: bool = flag(False, "in a scene, make an NMPC step slower than mpc_budget a failed step, "
                                           "as in the rig daemon; off, results do not depend on the machine's load")
    mpc_w_slack: float | None = num(None, 0.0, 1e6, "1/kPa", "NMPC cost per kPa over its pressure limit "
                                    "(default: 0.001 in a scene, 100 in the daemon: the limit first)")
    target_rate_mm_s: float | None = num(None, 0.0, 1000.0, "mm/s", "fastest a chamber's target height moves "
                                         "after a new target (0 = steps; default: steps in a scene, 3 in the daemon)")
    # the models' valve and sensor timing (hbma_ctrl.models.defaults), as the robot rig's default structure asks
    valve_min_on_ms: float = num(U.to_ms(DEFAULT_VALVE_MIN_ON), 0.0, 100.0, "ms", "the valves' shortest opening: "
                                 "smaller duties are realised on average over the periods (0 = duties sent as decided)")
    valve_delay_ms: float = num(U.to_ms(DEFAULT_VALVE_DELAY), 0.0, 100.0, "ms", "the chambers' filters take the "
                                "valves as acting this long after their command (0 = at once)")
    sensor_delay_ms: float = num(U.to_ms(ROBOT_SENSOR_DELAY), 0.0, 100.0, "ms", "the chambers' filters take the "
                                 "pressure sensors as reading this late (0 = at once)")
    burst_sigma: float = num(BurstTestSettings.threshold, 0.0, 1e4, "sigma", "a chamber whose readings fall "
                             "this far below its filter's prediction, summed over periods, is a burst: vented "
                             "until a reset (0 = no burst test)")

    _settings: Any = PrivateAttr(None)

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
        for key, fld, conv in (("r1_mm", "r1", U.mm), ("t0_mm", "t0", U.mm), ("V0_cm3", "V0", U.cm3)):
            if self._given(key):
                act = replace(act, **{fld: conv(getattr(self, key))})
        kw: dict = {"chamber": act}
        if self._given("layers"):
            kw["n_layers"] = self.layers
        for key, fld, conv in (("placement_radius_mm", "placement_radius", U.mm),
                               ("layer_thickness_mm", "layer_thickness", U.mm),
                               ("outer_diameter_mm", "outer_diameter", U.mm),
                               ("inner_diameter_mm", "inner_diameter", U.mm),
                               ("layer_mass_g", "layer_mass", U.grams), ("end_mass_g", "end_mass", U.grams),
                               ("max_stretch", "max_stretch", float)):
            if self._given(key):
                kw[fld] = conv(getattr(self, key))
        if self._given("chamber_angles_deg"):
            kw["chamber_angles"] = tuple(math.radians(x) for x in self.chamber_angles_deg)
        d0 = replace(_BASE, **kw)
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
            raise RuleError(f"max_stretch = {d0.max_stretch:g} is out of range [1.05, {lam:g}] (at most the "
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
            parsed = []
            for r in rows:
                th = math.radians(r.bend_deg)
                ps = math.radians(r.direction_deg) + (math.pi if th < 0 else 0.0)
                parsed.append((r.t_s, U.mm(r.height_mm), abs(th), math.atan2(math.sin(ps), math.cos(ps))))
            parsed.sort(key=lambda x: x[0])
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
        limit = self.pressure_limit_kpa if self._given("pressure_limit_kpa") else min(45.0, sensor)
        if limit > sensor:
            raise RuleError(f"pressure_limit_kpa = {limit!r} is out of range [1, {sensor:g}] kPa "
                            "(at most sensor_range_kpa)")
        pn = RobotPneumatics(topology=self.topology, outlets=self.outlets, sensor_range=U.kpa(sensor),
                             pressure_limit=U.kpa(limit))
        names = design.names
        inputs = {}
        for name, rows in self.inputs.items():
            if name not in names:
                near = closest(name, names)
                hint = f"; did you mean {near}? chambers: " if near else "; chambers: "
                raise RuleError(f"{name}: no such chamber{hint}{', '.join(names)}", "robot.inputs")
            check_rows(rows, name, "robot.inputs")
            inputs[name] = tuple((r.t_s, U.pct(r.speed_pct), r.inlet_duty, r.outlet_duty) for r in rows)
        closed: dict = {}
        if self._given("controller"):
            closed["controller"] = self.controller
        if "targets" in self.model_fields_set:
            if not self.targets:
                raise RuleError(f"is empty; give {_TARGET_SHAPE}", "robot.targets")
            closed["targets"] = self._targets(design)
        elif self.mode == "closed_loop":
            raise RuleError("mode = 'closed_loop' needs [robot.targets] for closed-loop robot control: "
                            f"{_TARGET_SHAPE} (all, or one per layer)")
        if self._given("tip_load_n"):
            closed["tip_load"] = tuple(tuple(r) for r in self.tip_load_n)
        for key, name, conv in (("compare_baseline", "compare_baseline", bool), ("settle_s", "settle_time", float),
                                ("mpc_horizon", "mpc_horizon", int), ("mpc_dt_ms", "mpc_dt", U.ms),
                                ("mpc_budget", "mpc_budget", float), ("mpc_enforce_budget", "mpc_enforce_budget", bool),
                                ("target_rate_mm_s", "target_rate", U.mm),
                                ("mpc_w_slack", "mpc_w_slack", float), ("valve_min_on_ms", "valve_min_on", U.ms),
                                ("valve_delay_ms", "valve_delay", U.ms), ("sensor_delay_ms", "sensor_delay", U.ms),
                                ("burst_sigma", "burst_sigma", float)):
            if self._given(key):
                closed[name] = conv(getattr(self, key))
        sync = U.ms(self.sync_ms) if self._given("sync_ms") else RobotSettings().sync_period
        try:
            return RobotSettings(design=design, pneumatics=pn, mode=self.mode, inputs=inputs,
                                 tip_force=tuple(self.tip_force_n), tip_moment=tuple(self.tip_moment_nm),
                                 sync_period=sync, snapshots=self.snapshots, **closed).validate()
        except ValueError as exc:  # SI ranges as a last guard
            raise RuleError(str(exc).replace("robot.", "")) from None
