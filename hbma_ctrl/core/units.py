"""Unit conversions at the edges of the package, in one place.

Everything inside hbma_ctrl works in SI (m, Pa, N, kg, s, m^3). Users, scenario files, the CLI and
plots speak mm, kPa, g, cm^3 and percent; they convert here and nowhere else.
"""

from __future__ import annotations

import math

__all__ = [
    "G_STD",
    "mm",
    "to_mm",
    "kpa",
    "to_kpa",
    "grams",
    "to_grams",
    "cm3",
    "to_cm3",
    "pct",
    "to_pct",
    "ms",
    "to_ms",
    "to_us",
    "to_mg",
    "megabytes",
    "to_megabytes",
    "lpm_to_kgs",
    "deg",
    "to_deg",
    "USER_UNITS",
]

G_STD = 9.80665  # standard gravity, m/s^2
RHO_AIR_NORMAL = 1.204  # air density at 20 degC, 101.325 kPa (ANR reference), kg/m^3


def mm(x):
    """Millimetres -> metres."""
    return x * 1e-3


def to_mm(x):
    """Metres -> millimetres."""
    return x * 1e3


def kpa(x):
    """Kilopascal -> pascal."""
    return x * 1e3


def to_kpa(x):
    """Pascal -> kilopascal."""
    return x * 1e-3


def grams(x):
    """Grams -> kilograms."""
    return x * 1e-3


def to_grams(x):
    """Kilograms -> grams."""
    return x * 1e3


def cm3(x):
    """Cubic centimetres -> cubic metres."""
    return x * 1e-6


def to_cm3(x):
    """Cubic metres -> cubic centimetres."""
    return x * 1e6


def pct(x):
    """Percent -> fraction (0-100 -> 0-1)."""
    return x * 1e-2


def to_pct(x):
    """Fraction -> percent."""
    return x * 1e2


def ms(x):
    """Milliseconds -> seconds."""
    return x * 1e-3


def to_ms(x):
    """Seconds -> milliseconds."""
    return x * 1e3


def to_us(x):
    """Seconds -> microseconds."""
    return x * 1e6


def to_mg(x):
    """Kilograms (or kg/s) -> milligrams (or mg/s)."""
    return x * 1e6


def megabytes(x):
    """Megabytes -> bytes."""
    return x * 1e6


def to_megabytes(x):
    """Bytes -> megabytes."""
    return x * 1e-6


def lpm_to_kgs(x):
    """Normal litres per minute (ANR) -> mass flow in kg/s."""
    return x * 1e-3 / 60.0 * RHO_AIR_NORMAL


def deg(x):
    """Degrees -> radians."""
    return math.radians(x)


def to_deg(x):
    """Radians -> degrees."""
    return math.degrees(x)


#: a scenario key's unit -> (to SI, from SI, the key's suffix after its SI field's name); a gain per
#: mm is 1000 times the gain per m, so those convert with the mm -> m factor inverted
USER_UNITS = {
    "mm": (mm, to_mm, "mm"),
    "mm/s": (mm, to_mm, "mm_s"),
    "deg": (deg, to_deg, "deg"),
    "kPa": (kpa, to_kpa, "kpa"),
    "ms": (ms, to_ms, "ms"),
    "g": (grams, to_grams, "g"),
    "cm^3": (cm3, to_cm3, "cm3"),
    "%": (pct, to_pct, "pct"),
    "1/mm": (to_mm, mm, ""),
    "1/(mm s)": (to_mm, mm, ""),
    "s/mm": (to_mm, mm, ""),
    "MB": (megabytes, to_megabytes, "mb"),
}
