"""Parameter sets (SI units): actuator geometry and gas, pneumatics, platform.

Defaults are the paper's Table I (README Model §6) and the fig. 7 rig where a value is needed. Every dataclass
validates itself and names the field and its allowed range when a value is out of it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

from hbma_ctrl.core.materials import Material, NeoHookean
from hbma_ctrl.core.settings import Settings, check_range, setting

__all__ = ["Actuator", "Valve", "Pneumatics", "Platform", "check_range", "DATA_DIR"]

DATA_DIR = Path(__file__).parent / "data"


@dataclass(frozen=True)
class Actuator(Settings):
    """One HBMA: membrane, clamp and gas (SI; each field's unit, range and one-line doc are in its
    declaration). Defaults: the fig. 7 rig's clamp, Table I's dead volume and neo-Hookean material."""

    WHERE = "actuator"

    r1: float = setting(12.5e-3, lo=0.5e-3, hi=0.1, lo_open=True, unit="m", user="mm", doc="retaining-disk inner radius")
    t0: float = setting(3e-3, lo=0.05e-3, hi=20e-3, lo_open=True, unit="m", user="mm", doc="initial membrane thickness")
    V0: float = setting(3e-6, lo=1e-9, hi=1e-3, unit="m^3", user="cm^3", doc="dead volume in pipe and chamber")
    material: Material = field(default_factory=NeoHookean)  # strain-energy model with its parameters
    R: float = setting(287.058, lo=1.0, hi=1e4, unit="J/(kg K)", doc="specific gas constant (dry air)")
    T: float = setting(293.15, lo=200.0, hi=400.0, unit="K", doc="gas temperature (isothermal)")
    p_env: float = setting(100.0e3, lo=10e3, hi=200e3, unit="Pa", doc="ambient absolute pressure")

    def check_rules(self) -> None:
        self.material.validate()

    def with_(self, **kw) -> "Actuator":
        """A copy with some fields replaced (validated)."""
        return replace(self, **kw).validate()


@dataclass(frozen=True)
class Valve:
    """A solenoid valve as an ISO 6358 orifice.

    C : sonic conductance, m^3/(s Pa) (1e-10 m^3/(s Pa) = 0.01 l/(s bar)).
    b : critical pressure ratio (-).
    laminar_ratio : pressure ratio above which the flow is blended to a laminar (linear) law, so the
        flow is Lipschitz near zero pressure drop (ISO 6358-3 uses a similar low-drop region).
    """

    C: float = 2.0e-10
    b: float = 0.3
    laminar_ratio: float = 0.995

    def validate(self, where: str = "valve") -> "Valve":
        check_range(where, "C", self.C, 0.0, 1e-7, "m^3/(s Pa)")
        check_range(where, "b", self.b, 0.0, 0.99)
        check_range(where, "laminar_ratio", self.laminar_ratio, 0.9, 0.99999)
        if self.laminar_ratio <= self.b:
            raise ValueError(f"{where}.laminar_ratio must exceed b ({self.b})")
        return self


@dataclass(frozen=True)
class Pneumatics:
    """Compressor map and valves.

    compressor_csv : table of (speed 0-1, gauge pressure Pa, mass flow kg/s); None = the shipped
        default ``data/compressor_default.csv`` (an assumption, see that file's header).
    flow_scale : multiplies the compressor map (1.0 nominal; a rig with a weaker pump: 0.9).
    inlet, outlet : valves. The inlet duty scales the pump flow (its pressure drop is neglected at
        these flows); the outlet vents the chamber to ambient.
    """

    compressor_csv: str | None = None
    flow_scale: float = 1.0
    inlet: Valve = field(default_factory=lambda: Valve(C=1.0e-9))
    outlet: Valve = field(default_factory=Valve)

    def validate(self) -> "Pneumatics":
        check_range("pneumatics", "flow_scale", self.flow_scale, 0.0, 10.0)
        self.inlet.validate("pneumatics.inlet")
        self.outlet.validate("pneumatics.outlet")
        if self.compressor_csv is not None and not Path(self.compressor_csv).is_file():
            raise ValueError(f"pneumatics.compressor_csv: no such file '{self.compressor_csv}'")
        return self

    @property
    def csv_path(self) -> Path:
        return Path(self.compressor_csv) if self.compressor_csv else DATA_DIR / "compressor_default.csv"


@dataclass(frozen=True)
class Platform:
    """The guided platform that carries a dead load (README Model §7).

    load : load mass, kg (0 = no platform: free inflation).
    own_mass : platform's own moving mass, kg (added to the load in the dynamic model).
    damping : viscous damping of the prismatic guide, N s/m (dynamic model only).
    g : gravity, m/s^2.
    """

    load: float = 0.0
    own_mass: float = 0.0
    damping: float = 20.0
    g: float = 9.80665

    def validate(self) -> "Platform":
        check_range("platform", "load", self.load, 0.0, 50.0, "kg")
        check_range("platform", "own_mass", self.own_mass, 0.0, 50.0, "kg")
        check_range("platform", "damping", self.damping, 0.0, 1e5, "N s/m")
        check_range("platform", "g", self.g, 0.0, 100.0, "m/s^2")
        return self

    @property
    def weight(self) -> float:
        """Force the membrane must carry to hold the platform, N."""
        return (self.load + self.own_mass) * self.g

    @property
    def mass(self) -> float:
        return self.load + self.own_mass
