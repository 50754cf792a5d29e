"""The hybrid soft-rigid continuum robot as data: layers, chamber placement, pneumatics (SI).

Layers of three HBMA each are stacked along z; every chamber is inflated on its own and its
membrane centre is glued to the layer above.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from hbma_ctrl.core import units as U
from hbma_ctrl.core.materials import make_material
from hbma_ctrl.core.params import Actuator, check_range
from hbma_ctrl.core.validation import did_you_mean
from hbma_ctrl.models.bank import TOPOLOGIES

LETTERS = "ABCDEFGHIJKLMNOPQRSTUVWXYZ"
OUTLETS = ("per_chamber",)

#: the paper's Table II: (HBMA inflated, angle deg, length mm, extension %)
TABLE2_PAPER = ((0, 2.3, 9.6, 0.0), (1, 28.9, 18.0, 88.0), (2, 28.5, 23.0, 140.0), (3, 1.3, 26.7, 179.0))


def _robot_chamber() -> Actuator:
    return Actuator(r1=4.5e-3, t0=2e-3, V0=3e-6, material=make_material("nh"))


# ---------------------------------------------------------------------------------------------
# the robot as data
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RobotDesign:
    """A stack of HBMA layers (SI). Defaults: the paper's robot (README Model §8, Fig. 1: 9 HBMA).

    Fields
    ------
    n_layers : number of chamber layers N (bodies 0..N; body N is the top part), 1-26.
    placement_radius : chamber centres' distance from the axis, m (15.4 mm: the 8.75-22 mm annulus
        of a 17.5/44 mm layer holds an r1 = 4.5 mm disk with margin).
    chamber_angles : the three chambers' angles about the axis, rad (0, 120, 240 deg); the same in
        every layer (chambers of consecutive layers aligned).
    layer_thickness : body thickness with the flat membrane, m (9 mm).
    outer_diameter, inner_diameter : layer annulus, m (44, 17.5 mm; the tubing passes inside).
    layer_mass : mass of one layer body, kg (17.6 g).
    end_mass : mass of the top body N, kg; None = a layer's mass.
    chamber : the HBMA of every chamber (r1 4.5 mm, t0 2 mm, V0 3 cm^3 assumed as Table I, NH).
    max_stretch : largest equi-biaxial membrane stretch allowed (-), an assumed safe limit below
        rupture (Ecoflex 00-30); it sets the far-branch reach (see :func:`~hbma_ctrl.robot.reach.chamber_reach`).
    g : gravity, m/s^2 (acts along -z of the world; the base is level).
    """

    n_layers: int = 3
    placement_radius: float = 15.4e-3
    chamber_angles: tuple = (0.0, 2 * math.pi / 3, 4 * math.pi / 3)
    layer_thickness: float = 9e-3
    outer_diameter: float = 44e-3
    inner_diameter: float = 17.5e-3
    layer_mass: float = 17.6e-3
    end_mass: float | None = None
    chamber: Actuator = field(default_factory=_robot_chamber)
    max_stretch: float = 4.0
    g: float = U.G_STD

    def validate(self) -> "RobotDesign":
        """Check every field; ValueError names the field and its range."""
        if not isinstance(self.n_layers, int) or isinstance(self.n_layers, bool) or not 1 <= self.n_layers <= 26:
            raise ValueError(f"robot.n_layers = {self.n_layers!r} must be an integer in [1, 26]")
        check_range("robot", "layer_thickness", self.layer_thickness, 1e-3, 0.1, "m")
        check_range("robot", "inner_diameter", self.inner_diameter, 0.0, 0.5, "m")
        check_range("robot", "outer_diameter", self.outer_diameter, self.inner_diameter, 0.5, "m",
                    lo_open=True)
        check_range("robot", "layer_mass", self.layer_mass, 0.0, 10.0, "kg")
        if self.end_mass is not None:
            check_range("robot", "end_mass", self.end_mass, 0.0, 10.0, "kg")
        check_range("robot", "g", self.g, 0.0, 100.0, "m/s^2")
        self.chamber.validate()
        r1 = self.chamber.r1
        lo, hi = self.inner_diameter / 2 + r1, self.outer_diameter / 2 - r1
        check_range("robot", "placement_radius", self.placement_radius, lo, hi, "m "
                    f"(the chamber disk r1 = {U.to_mm(r1):g} mm must fit the layer annulus)")
        if len(self.chamber_angles) != 3:
            raise ValueError(f"robot.chamber_angles must hold 3 angles, got {len(self.chamber_angles)}")
        for i, a in enumerate(self.chamber_angles):
            check_range("robot", f"chamber_angles[{i}]", a, -2 * math.pi, 2 * math.pi, "rad")
        # the support triangle must contain the axis well (else the 3x3 statics is ill posed) and
        # the chambers must not overlap
        xy = self.chamber_xy()
        for i in range(3):
            for j in range(i + 1, 3):
                if np.linalg.norm(xy[i] - xy[j]) < 2 * r1:
                    raise ValueError(f"robot.chamber_angles: chambers {i + 1} and {j + 1} overlap "
                                     f"(centres {U.to_mm(np.linalg.norm(xy[i] - xy[j])):.1f} mm apart, "
                                     f"need >= 2 r1 = {U.to_mm(2 * r1):g} mm)")
        gaps = np.diff(np.sort(np.mod(np.asarray(self.chamber_angles), 2 * math.pi)))
        gaps = np.append(gaps, 2 * math.pi - gaps.sum())
        if gaps.max() >= math.pi - 1e-6:
            raise ValueError("robot.chamber_angles: the three chambers must not lie in one half-plane "
                             "(the layer would tip over; every gap between angles must be < 180 deg)")
        check_range("robot", "max_stretch", self.max_stretch, 1.05, min(20.0, self.chamber.material.lam_max()))
        return self

    # derived data --------------------------------------------------------------------------
    def chamber_xy(self) -> np.ndarray:
        """Chamber centres in a layer frame, (3, 2) m."""
        a = np.asarray(self.chamber_angles, dtype=float)
        return self.placement_radius * np.column_stack([np.cos(a), np.sin(a)])

    @property
    def body_masses(self) -> np.ndarray:
        """Masses of the moving bodies 1..N, kg."""
        m = np.full(self.n_layers, self.layer_mass)
        m[-1] = self.layer_mass if self.end_mass is None else self.end_mass
        return m

    @property
    def names(self) -> list[str]:
        return chamber_names(self.n_layers)

    def with_(self, **kw) -> "RobotDesign":
        """A validated copy with some fields replaced."""
        return replace(self, **kw).validate()


def chamber_names(n_layers: int) -> list[str]:
    """Chamber names layer-major, as in Fig. 10: A1, A2, A3, B1, ..."""
    return [f"{LETTERS[k]}{i + 1}" for k in range(n_layers) for i in range(3)]


@dataclass(frozen=True)
class RobotPneumatics:
    """How the chambers are supplied (the robot's rig and its controllers' model take the topology).

    topology : 'per_chamber' (one compressor per chamber) or 'shared' (one compressor feeding every
        chamber through its own inlet valve; the open-loop scene then runs the pump at the highest
        speed any open inlet asks for and splits its flow equally among the open inlets).
    outlets : 'per_chamber' (each chamber vents through its own outlet valve; the only layout built).
    sensor_range : pressure at which each chamber's sensor saturates, Pa (50 kPa).
    pressure_limit : largest chamber pressure allowed, Pa (45 kPa); must not exceed the sensor range.
    """

    topology: str = "per_chamber"
    outlets: str = "per_chamber"
    sensor_range: float = 50e3
    pressure_limit: float = 45e3

    def validate(self) -> "RobotPneumatics":
        for name, allowed in (("topology", TOPOLOGIES), ("outlets", OUTLETS)):
            v = getattr(self, name)
            if v not in allowed:
                hint = did_you_mean(str(v), allowed)
                raise ValueError(f"robot.{name} = '{v}'{hint}; allowed: {', '.join(allowed)}")
        check_range("robot", "sensor_range", self.sensor_range, 1e3, 1e6, "Pa")
        check_range("robot", "pressure_limit", self.pressure_limit, 1e3, self.sensor_range, "Pa "
                    "(at most the sensor range)")
        return self

    def n_compressors(self, n_chambers: int) -> int:
        return n_chambers if self.topology == "per_chamber" else 1
