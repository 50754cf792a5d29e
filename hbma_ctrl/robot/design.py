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
from hbma_ctrl.core.params import Actuator
from hbma_ctrl.core.settings import Settings, check_range, setting
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
class RobotDesign(Settings):
    """A stack of HBMA layers (SI; each field's unit, range and one-line doc are in its declaration).
    Defaults: the paper's robot (docs/concepts/model.md §8, Fig. 1: 9 HBMA).

    Bodies 0..N; body N is the top part. placement_radius 15.4 mm: the 8.75-22 mm annulus of a 17.5/44 mm
    layer holds an r1 = 4.5 mm disk with margin. The chamber angles are the same in every layer
    (chambers of consecutive layers aligned). chamber : the HBMA of every chamber (r1 4.5 mm, t0 2 mm,
    V0 3 cm^3 assumed as Table I, NH). max_stretch is an assumed safe limit below rupture (Ecoflex
    00-30); it sets the far-branch reach (see :func:`~hbma_ctrl.robot.reach.chamber_reach`). Gravity
    acts along -z of the world; the base is level.
    """

    WHERE = "robot"

    n_layers: int = setting(3, integer=True, lo=1, hi=26, unit="layers", key="layers", doc="number of chamber layers")
    placement_radius: float = setting(15.4e-3, lo=1e-3, hi=0.5, unit="m", user="mm",
                                      doc="chamber centres' distance from the axis (the disk must fit the annulus)")
    chamber_angles: tuple = setting((0.0, 2 * math.pi / 3, 4 * math.pi / 3), lo=-2 * math.pi, hi=2 * math.pi,
                                    unit="rad", user="deg", parts=("deg", "deg", "deg"), doc="the chambers' angles")
    layer_thickness: float = setting(9e-3, lo=1e-3, hi=0.1, unit="m", user="mm",
                                     doc="layer body thickness with the flat membrane")
    outer_diameter: float = setting(44e-3, lo=1e-3, hi=0.5, unit="m", user="mm",
                                    doc="layer outer diameter (above inner_diameter_mm)")
    inner_diameter: float = setting(17.5e-3, lo=0.0, hi=0.5, unit="m", user="mm",
                                    doc="layer inner diameter (the tubing passes inside)")
    layer_mass: float = setting(17.6e-3, lo=0.0, hi=10.0, unit="kg", user="g", doc="mass of one layer body")
    end_mass: float | None = setting(None, lo=0.0, hi=10.0, unit="kg", user="g",
                                     doc="mass of the top body; default a layer's")
    chamber: Actuator = field(default_factory=_robot_chamber)
    max_stretch: float = setting(4.0, lo=1.05, hi=20.0,
                                 doc="largest membrane stretch (at most the material's limit)")
    g: float = setting(U.G_STD, lo=0.0, hi=100.0, unit="m/s^2", doc="gravity")

    def check_rules(self) -> None:
        check_range("robot", "outer_diameter", self.outer_diameter, self.inner_diameter, 0.5, "m", lo_open=True)
        self.chamber.validate()
        r1 = self.chamber.r1
        lo, hi = self.inner_diameter / 2 + r1, self.outer_diameter / 2 - r1
        check_range("robot", "placement_radius", self.placement_radius, lo, hi, "m "
                    f"(the chamber disk r1 = {U.to_mm(r1):g} mm must fit the layer annulus)")
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
        self.within("max_stretch", hi=min(20.0, self.chamber.material.lam_max()))

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
class RobotPneumatics(Settings):
    """How the chambers are supplied (the robot's rig and its controllers' model take the topology).

    topology 'shared': one compressor feeds every chamber through its own inlet valve; the open-loop
    scene then runs the pump at the highest speed any open inlet asks for and splits its flow equally
    among the open inlets. outlets 'per_chamber' is the only layout built.
    """

    WHERE = "robot"

    topology: str = setting("per_chamber", choices=TOPOLOGIES, doc="one compressor per chamber or shared")
    outlets: str = setting("per_chamber", choices=OUTLETS, doc="outlet valve layout")
    sensor_range: float = setting(50e3, lo=1e3, hi=1e6, unit="Pa", user="kPa",
                                  doc="chamber sensors' saturation pressure")
    pressure_limit: float = setting(45e3, lo=1e3, hi=1e6, unit="Pa", user="kPa",
                                    doc="largest chamber pressure, at most sensor_range_kpa; default min(45, sensor_range_kpa)")

    def check_rules(self) -> None:
        self.within("pressure_limit", hi=self.sensor_range)


def shared_supply(duties: np.ndarray) -> np.ndarray:
    """Inlet duties (0-1, the chambers along the last axis) of one shared pump as its flow splits among
    them: each duty over their sum where the sum is above 1 (the manifold)."""
    total = duties.sum(axis=-1, keepdims=True)
    return np.where(total > 1.0, duties / np.maximum(total, 1e-12), duties)
