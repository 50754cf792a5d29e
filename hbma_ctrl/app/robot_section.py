"""The scenario's ``[robot]`` section: robot settings parsed from edge units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from hbma_ctrl.core import units as U
from hbma_ctrl.core.materials import Material, make_material
from hbma_ctrl.core.params import check_range
from hbma_ctrl.core.validation import did_you_mean
from hbma_ctrl.robot.design import RobotDesign, RobotPneumatics
from hbma_ctrl.robot.plant import RobotPlantSettings
from hbma_ctrl.robot.targets import parse_targets

SCENE_MODES = ("open_loop", "closed_loop")
CONTROLLERS = ("mpc", "pressure_pid")


@dataclass(frozen=True)
class RobotSettings:
    """The ``[robot]`` scenario table, validated (SI inside; the table uses edge units).

    design : the robot (:class:`RobotDesign`).
    pneumatics : supply topology, sensor range and pressure limit (:class:`RobotPneumatics`).
    mode : 'open_loop' (inputs by schedule) or 'closed_loop' (targets per layer; see below).
    inputs : per-chamber schedules {name: ((t s, speed 0-1, inlet 0-1, outlet 0-1), ...)}; chambers
        not listed keep everything closed. Safety interlocks of the open-loop scene close a chamber's
        inlet while its pressure is at the pressure limit or its stretch at ``design.max_stretch``.
    tip_force : force on the tip, world frame, N; tip_moment : moment on the tip, N m.
    sync_period : how often the load sharing and the interlocks update every chamber's load, s.
    snapshots : number of robot shapes drawn in the shape-over-time plot.

    Closed loop (mode 'closed_loop', see :mod:`controllers.robot_loop`):
    controller : 'mpc' (per-chamber EKF bank + structured NMPC) or 'pressure_pid' (baseline).
    targets : {layer index: ((t s, centre height m, bend rad >= 0, direction rad), ...)}.
    tip_load : ((t s, fx N, fy N, fz N), ...) tip force from each row's time on (a disturbance the
        controller does not know).
    compare_baseline : also run the other controller on the same targets and report it beside.
    settle_time : RMSEs count samples at least this long after a target change, s.
    mpc_horizon, mpc_dt : NMPC stages and prediction step (s).
    """

    design: RobotDesign = field(default_factory=RobotDesign)
    pneumatics: RobotPneumatics = field(default_factory=RobotPneumatics)
    mode: str = "open_loop"
    inputs: dict = field(default_factory=dict)
    tip_force: tuple = (0.0, 0.0, 0.0)
    tip_moment: tuple = (0.0, 0.0, 0.0)
    sync_period: float = 0.01
    snapshots: int = 8
    controller: str = "mpc"
    targets: dict = field(default_factory=dict)
    tip_load: tuple = ()
    compare_baseline: bool = True
    settle_time: float = 2.0
    mpc_horizon: int = 15
    mpc_dt: float = 0.02

    @property
    def plant(self) -> RobotPlantSettings:
        """The part of these settings the robot's plant needs."""
        return RobotPlantSettings(design=self.design, pneumatics=self.pneumatics, inputs=self.inputs,
                                  tip_force=self.tip_force, tip_moment=self.tip_moment,
                                  sync_period=self.sync_period)

    def validate(self) -> "RobotSettings":
        self.plant.validate()
        if self.mode not in SCENE_MODES:
            hint = did_you_mean(str(self.mode), SCENE_MODES)
            raise ValueError(f"robot.mode = '{self.mode}'{hint}; allowed: {', '.join(SCENE_MODES)}")
        if not isinstance(self.snapshots, int) or not 1 <= self.snapshots <= 50:
            raise ValueError(f"robot.snapshots = {self.snapshots!r} must be an integer in [1, 50]")
        if self.controller not in CONTROLLERS:
            hint = did_you_mean(str(self.controller), CONTROLLERS)
            raise ValueError(f"robot.controller = '{self.controller}'{hint}; allowed: {', '.join(CONTROLLERS)}")
        if self.mode == "closed_loop" and not self.targets:
            raise ValueError("robot.mode = 'closed_loop': closed-loop robot control needs robot.targets "
                             "(a table {all = [[t_s, height_mm, bend_deg, direction_deg], ...]} or one per layer)")
        for j, row in enumerate(self.tip_load):
            if len(row) != 4 or not all(math.isfinite(float(v)) for v in row) or row[0] < 0:
                raise ValueError(f"robot.tip_load_n[{j}] must be [t_s >= 0, fx, fy, fz] (finite)")
        check_range("robot", "settle_time", self.settle_time, 0.0, 1e4, "s")
        if not isinstance(self.mpc_horizon, int) or not 1 <= self.mpc_horizon <= 100:
            raise ValueError(f"robot.mpc_horizon = {self.mpc_horizon!r} must be an integer in [1, 100]")
        check_range("robot", "mpc_dt", self.mpc_dt, 1e-3, 1.0, "s")
        return self


_SECTION_KEYS = {
    "mode": "open_loop | closed_loop", "layers": "number of chamber layers",
    "placement_radius_mm": "", "chamber_angles_deg": "3 angles", "layer_thickness_mm": "",
    "outer_diameter_mm": "", "inner_diameter_mm": "", "layer_mass_g": "", "end_mass_g": "",
    "r1_mm": "", "t0_mm": "", "V0_cm3": "", "material": "", "material_params": "table (SI)",
    "max_stretch": "", "topology": "", "outlets": "", "sensor_range_kpa": "", "pressure_limit_kpa": "",
    "tip_force_n": "[fx, fy, fz]", "tip_moment_nm": "[mx, my, mz]", "sync_ms": "", "snapshots": "",
    "inputs": "table {chamber: [[t_s, speed_pct, inlet_duty, outlet_duty], ...]}",
    "controller": "mpc | pressure_pid", "targets": "table {all|A|B|..: [[t_s, height_mm, bend_deg, direction_deg]]}",
    "tip_load_n": "[[t_s, fx, fy, fz], ...]", "compare_baseline": "bool", "settle_s": "", "mpc_horizon": "",
    "mpc_dt_ms": "",
}


#: allowed ranges of the numeric keys, in the table's own (edge) units
_EDGE_RANGES = {
    "placement_radius_mm": (1.0, 500.0), "layer_thickness_mm": (1.0, 100.0), "outer_diameter_mm": (1.0, 500.0),
    "inner_diameter_mm": (0.0, 500.0), "layer_mass_g": (0.0, 10000.0), "end_mass_g": (0.0, 10000.0),
    "r1_mm": (0.5, 100.0), "t0_mm": (0.05, 20.0), "V0_cm3": (0.001, 1000.0), "max_stretch": (1.05, 20.0),
    "sensor_range_kpa": (1.0, 1000.0), "pressure_limit_kpa": (1.0, 1000.0), "sync_ms": (0.1, 1000.0),
    "settle_s": (0.0, 1e4), "mpc_dt_ms": (1.0, 1000.0),
}


def _num(raw: dict, key: str) -> float:
    v = raw[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError(f"robot.{key} = {v!r} must be a number")
    lo, hi = _EDGE_RANGES[key]
    check_range("robot", key, float(v), lo, hi)
    return float(v)


def parse_section(raw: dict) -> RobotSettings:
    """Validate a ``[robot]`` scenario table (edge units in the key names) -> :class:`RobotSettings`.

    Unknown keys get the closest valid name; out-of-range values name the key and its range (in
    the key's units). Keys: mode, layers, placement_radius_mm, chamber_angles_deg,
    layer_thickness_mm, outer_diameter_mm, inner_diameter_mm, layer_mass_g, end_mass_g, r1_mm,
    t0_mm, V0_cm3, material, material_params, max_stretch, topology, outlets, sensor_range_kpa,
    pressure_limit_kpa, tip_force_n, tip_moment_nm, sync_ms, snapshots, inputs (a table of
    per-chamber schedules, rows [t_s, speed_pct, inlet_duty, outlet_duty]); closed loop: controller,
    targets (a table {all|A|B|...: [[t_s, height_mm, bend_deg, direction_deg], ...]}, a negative
    bend is the opposite direction), tip_load_n ([[t_s, fx, fy, fz], ...]), compare_baseline,
    settle_s, mpc_horizon, mpc_dt_ms. Omitted keys take the
    paper's robot (:class:`RobotDesign`) and :class:`RobotPneumatics` defaults.
    """
    if not isinstance(raw, dict):
        raise ValueError("[robot] must be a table")
    for k in raw:
        if k not in _SECTION_KEYS:
            hint = did_you_mean(k, _SECTION_KEYS)
            raise ValueError(f"robot.{k}: unknown key{hint}; allowed: {', '.join(_SECTION_KEYS)}")
    base = RobotDesign()
    act = base.chamber
    if "material" in raw or "material_params" in raw:
        params = raw.get("material_params", {})
        if not isinstance(params, dict):
            raise ValueError("robot.material_params must be a table of SI values")
        mat: Material = make_material(str(raw.get("material", "nh")), **params)
        act = replace(act, material=mat)
    for key, fld, conv in (("r1_mm", "r1", U.mm), ("t0_mm", "t0", U.mm), ("V0_cm3", "V0", U.cm3)):
        if key in raw:
            act = replace(act, **{fld: conv(_num(raw, key))})
    kw: dict = {"chamber": act}
    if "layers" in raw:
        v = raw["layers"]
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 26:
            raise ValueError(f"robot.layers = {v!r} must be an integer in [1, 26]")
        kw["n_layers"] = v
    for key, fld, conv in (("placement_radius_mm", "placement_radius", U.mm),
                           ("layer_thickness_mm", "layer_thickness", U.mm),
                           ("outer_diameter_mm", "outer_diameter", U.mm),
                           ("inner_diameter_mm", "inner_diameter", U.mm),
                           ("layer_mass_g", "layer_mass", U.grams), ("end_mass_g", "end_mass", U.grams),
                           ("max_stretch", "max_stretch", float)):
        if key in raw:
            kw[fld] = conv(_num(raw, key))
    if "chamber_angles_deg" in raw:
        a = raw["chamber_angles_deg"]
        if not isinstance(a, list) or len(a) != 3 or not all(isinstance(x, (int, float)) for x in a):
            raise ValueError(f"robot.chamber_angles_deg must be a list of 3 numbers, got {a!r}")
        kw["chamber_angles"] = tuple(math.radians(x) for x in a)
    # cross-field checks in the table's units, before the SI validation of the design
    d0 = replace(base, **kw)
    lo, hi = round(U.to_mm(d0.inner_diameter / 2 + act.r1), 3), round(U.to_mm(d0.outer_diameter / 2 - act.r1), 3)
    check_range("robot", "placement_radius_mm", U.to_mm(d0.placement_radius), lo, hi,
                f"mm (the chamber disk, r1 = {U.to_mm(act.r1):g} mm, must fit the layer annulus)")
    try:
        design = d0.validate()
    except ValueError as exc:  # name the table's section
        raise ValueError(str(exc).replace("actuator.", "robot.")
                         .replace("robot.chamber_angles:", "robot.chamber_angles_deg:")) from None
    sensor = _num(raw, "sensor_range_kpa") if "sensor_range_kpa" in raw else 50.0
    limit = _num(raw, "pressure_limit_kpa") if "pressure_limit_kpa" in raw else min(45.0, sensor)
    check_range("robot", "pressure_limit_kpa", limit, 1.0, sensor, "kPa (at most sensor_range_kpa)")
    pn = RobotPneumatics(topology=str(raw.get("topology", "per_chamber")), outlets=str(raw.get("outlets", "per_chamber")),
                         sensor_range=U.kpa(sensor), pressure_limit=U.kpa(limit)).validate()
    inputs = {}
    tab = raw.get("inputs", {})
    if not isinstance(tab, dict):
        raise ValueError("robot.inputs must be a table {chamber: [[t_s, speed_pct, inlet, outlet], ...]}")
    for name, rows in tab.items():
        if not isinstance(rows, list) or not all(isinstance(r, list) and len(r) == 4 for r in rows):
            raise ValueError(f"robot.inputs.{name} must be a list of [t_s, speed_pct, inlet_duty, outlet_duty]")
        for i, r in enumerate(rows):
            check_range(f"robot.inputs.{name}[{i}]", "speed_pct", r[1], 0.0, 100.0, "%")
        inputs[name] = tuple((float(r[0]), U.pct(float(r[1])), float(r[2]), float(r[3])) for r in rows)
    vec = {}
    for key in ("tip_force_n", "tip_moment_nm"):
        v = raw.get(key, [0.0, 0.0, 0.0])
        if not isinstance(v, list) or len(v) != 3 or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                             and math.isfinite(x) for x in v):
            raise ValueError(f"robot.{key} must be a list of 3 finite numbers, got {v!r}")
        vec[key] = tuple(float(x) for x in v)
    sync = U.mm(_num(raw, "sync_ms")) if "sync_ms" in raw else 0.01  # ms -> s, same factor as mm -> m
    closed: dict = {}
    if "controller" in raw:
        closed["controller"] = str(raw["controller"])
    if "targets" in raw:

        closed["targets"] = parse_targets(raw["targets"], design)
    if "tip_load_n" in raw:
        rows = raw["tip_load_n"]
        if not isinstance(rows, list) or not all(
                isinstance(r, list) and len(r) == 4 and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                            for v in r) for r in rows):
            raise ValueError("robot.tip_load_n must be a list of [t_s, fx, fy, fz] (numbers, N)")
        for j, r in enumerate(rows):
            for v in r[1:]:
                check_range(f"robot.tip_load_n[{j}]", "force", v, -20.0, 20.0, "N")
        closed["tip_load"] = tuple(tuple(float(v) for v in r) for r in rows)
    if "compare_baseline" in raw:
        if not isinstance(raw["compare_baseline"], bool):
            raise ValueError(f"robot.compare_baseline = {raw['compare_baseline']!r} must be true or false")
        closed["compare_baseline"] = raw["compare_baseline"]
    if "settle_s" in raw:
        closed["settle_time"] = _num(raw, "settle_s")
    if "mpc_horizon" in raw:
        closed["mpc_horizon"] = raw["mpc_horizon"]
    if "mpc_dt_ms" in raw:
        closed["mpc_dt"] = _num(raw, "mpc_dt_ms") * 1e-3
    return RobotSettings(design=design, pneumatics=pn, mode=str(raw.get("mode", "open_loop")), inputs=inputs,
                         tip_force=vec["tip_force_n"], tip_moment=vec["tip_moment_nm"], sync_period=sync,
                         snapshots=raw.get("snapshots", 8), **closed).validate()
