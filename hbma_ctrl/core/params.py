"""Parameter sets (SI units): actuator geometry and gas, pneumatics, platform.

Defaults are the paper's Table I (docs/concepts/model.md §6) and the fig. 7 rig where a value is needed. Every dataclass
validates itself and names the field and its allowed range when a value is out of it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

from hbma_ctrl.core.materials import Material, NeoHookean
from hbma_ctrl.core.settings import Settings, check_fields, check_range, setting

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
class Valve(Settings):
    """A solenoid valve as an ISO 6358 orifice (each field's unit, range and one-line doc are in its
    declaration; 1e-10 m^3/(s Pa) of conductance = 0.01 l/(s bar)).

    laminar_ratio : the flow is blended to a laminar (linear) law above it, so the flow is Lipschitz
        near zero pressure drop (ISO 6358-3 uses a similar low-drop region).
    """

    WHERE = "valve"

    C: float = setting(2.0e-10, lo=0.0, hi=1e-7, unit="m^3/(s Pa)", doc="sonic conductance")
    b: float = setting(0.3, lo=0.0, hi=0.99, doc="critical pressure ratio")
    laminar_ratio: float = setting(0.995, lo=0.9, hi=0.99999,
                                   doc="pressure ratio above which the flow is laminar (above b)")

    def validate(self, where: str = "valve") -> "Valve":
        """Check every field and the laminar ratio against b, naming ``where`` (the valve's place)."""
        check_fields(self, where)
        if self.laminar_ratio <= self.b:
            raise ValueError(f"{where}.laminar_ratio must exceed b ({self.b})")
        return self


@dataclass(frozen=True)
class Pneumatics(Settings):
    """Compressor map and valves (each setting's unit, range and one-line doc are in its declaration).

    compressor_csv : None = the shipped default ``data/compressor_default.csv`` (an assumption, see
        that file's header).
    inlet, outlet : valves. The inlet duty scales the pump flow (its pressure drop is neglected at
        these flows); the outlet vents the chamber to ambient.
    """

    WHERE = "pneumatics"

    compressor_csv: str | None = setting(None, text=True,
                                         doc="compressor map CSV (speed, Pa, kg/s); default: the shipped one")
    flow_scale: float = setting(1.0, lo=0.0, hi=10.0, doc="multiplies the compressor map")
    inlet: Valve = field(default_factory=lambda: Valve(C=1.0e-9))
    outlet: Valve = field(default_factory=Valve)

    def check_rules(self) -> None:
        self.inlet.validate("pneumatics.inlet")
        self.outlet.validate("pneumatics.outlet")
        if self.compressor_csv is not None and not Path(self.compressor_csv).is_file():
            raise ValueError(f"pneumatics.compressor_csv: no such file '{self.compressor_csv}'")

    @property
    def csv_path(self) -> Path:
        return Path(self.compressor_csv) if self.compressor_csv else DATA_DIR / "compressor_default.csv"


@dataclass(frozen=True)
class Platform(Settings):
    """The guided platform that carries a dead load (docs/concepts/model.md §7; each field's unit, range and
    one-line doc are in its declaration)."""

    WHERE = "platform"

    load: float = setting(0.0, lo=0.0, hi=50.0, unit="kg", user="g", key="mass_g",
                          doc="load mass (0: no platform, free inflation; kind 'single')")
    own_mass: float = setting(0.0, lo=0.0, hi=50.0, unit="kg", user="g",
                              doc="platform's own moving mass (added to the load in the dynamic model)")
    damping: float = setting(20.0, lo=0.0, hi=1e5, unit="N s/m", key="damping_ns_per_m",
                             doc="platform damping (the prismatic guide's; dynamic model only)")
    g: float = setting(9.80665, lo=0.0, hi=100.0, unit="m/s^2", doc="gravity")

    @property
    def weight(self) -> float:
        """Force the membrane must carry to hold the platform, N."""
        return (self.load + self.own_mass) * self.g

    @property
    def mass(self) -> float:
        return self.load + self.own_mass
