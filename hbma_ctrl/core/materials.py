"""Hyperelastic strain energies for an equi-biaxially stretched, incompressible membrane (docs/concepts/model.md §2).

Each material gives its strain energy ``W(lam)`` (J/m^3) and, for the regular pressure formula of
docs/concepts/model.md §3, ``Q(lam) = W'(lam) / (lam - 1)`` written so that it is finite and smooth at ``lam = 1``.
With ``S5 = 1 + lam + ... + lam^5``:

- ``dI1/dlam = 4 lam^-5 (lam - 1) S5`` and ``dI2/dlam = 4 lam^-3 (lam - 1) S5``,

so every invariant-based model factors exactly; Ogden uses ``expm1`` ratios.

Defaults (all Pa): Neo-Hookean and Mooney-Rivlin come from the paper's Table I. Yeoh, Gent and Ogden
are not in the paper; their defaults keep the Table I small-strain shear modulus
``mu0 = E/3 = 43.53 kPa`` (so all five agree for small deflections) and add a moderate strain
stiffening typical of platinum-cure silicones such as Ecoflex 00-30 (Yeoh third-order term, Gent
locking at ``I1 - 3 = Jm = 60``, i.e. an equi-biaxial stretch of about 5.5, a two-term Ogden with a
stiffening ``alpha = 5`` term). They are assumptions, not measurements: replace them with a fit to
your data.
"""

from __future__ import annotations

from functools import lru_cache
from dataclasses import dataclass, fields
from typing import ClassVar

import casadi as ca
import numpy as np

from hbma_ctrl.core.validation import did_you_mean

__all__ = [
    "Material",
    "NeoHookean",
    "MooneyRivlin",
    "Yeoh",
    "Gent",
    "Ogden",
    "MATERIALS",
    "make_material",
]

E_TABLE_I = 130.6e3  # Pa, Table I
#: stretches checked for a positive pressure: past any scene's reach (35 kPa sensors stop NH near 1.6)
LAM_CHECK = 4.0
#: how many entries a list-valued parameter may hold (Yeoh is the classic three-term form)
_LENGTHS: dict[tuple[str, str], tuple[int, int]] = {("yeoh", "C"): (1, 3)}
MU0 = E_TABLE_I / 3.0  # small-strain shear modulus shared by the defaults, Pa


def _invariants(lam):
    i1 = 2 * lam**2 + lam**-4
    i2 = 2 * lam**-2 + lam**4
    return i1, i2


def _s5(lam):
    return 1 + lam + lam**2 + lam**3 + lam**4 + lam**5


@dataclass(frozen=True)
class Material:
    """Base class: a strain energy with named parameters (Pa unless stated)."""

    name: ClassVar[str] = ""
    #: parameters that are not moduli (exponents, locking limits): scaling the stiffness keeps them
    dimensionless: ClassVar[tuple] = ()

    def scaled(self, factor) -> "Material":
        """The same material with every modulus multiplied by ``factor`` (float or casadi symbol).

        The strain energy, and so the pressure at a given shape, scales by ``factor``; exponents and
        locking limits stay. Used for a rig's modulus mismatch and an estimator's modulus factor.
        """
        kw = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name in self.dimensionless:
                kw[f.name] = v
            elif isinstance(v, tuple):
                kw[f.name] = tuple(factor * e for e in v)
            else:
                kw[f.name] = factor * v
        return type(self)(**kw)

    def W(self, lam):  # noqa: N802 - physics notation
        """Strain energy density W(lam) in J/m^3 (casadi or float)."""
        raise NotImplementedError

    def Q(self, lam):  # noqa: N802
        """W'(lam) / (lam - 1) in Pa, regular at lam = 1."""
        raise NotImplementedError

    def dW(self, lam):  # noqa: N802
        """W'(lam) in Pa."""
        return (lam - 1) * self.Q(lam)

    @property
    def modulus_q1(self) -> float:
        """Q(1) = W''(1) in Pa: sets the flat-limit pressure. NH: 4E."""
        return float(ca.DM(self.Q(ca.DM(1.0))))

    def lam_max(self) -> float:
        """Largest admissible equi-biaxial stretch (inf unless the model locks)."""
        return float("inf")

    def validate(self) -> None:
        """Raise ValueError naming the parameter when a value is outside its range."""
        for f in fields(self):
            v = getattr(self, f.name)
            vals = v if isinstance(v, tuple) else (v,)
            for x in vals:
                if not (x == x) or x in (float("inf"), float("-inf")):
                    raise ValueError(f"material {self.name}: {f.name} must be finite, got {v}")
        _check_modulus_and_pressure(self)

    def _check_positive_pressure(self) -> None:
        # p has the sign of W'(lam) = (lam - 1) Q(lam): a Q <= 0 (or inf/nan) anywhere a scene can reach
        # makes the membrane pull the gas in, which no solver can make sense of
        hi = min(LAM_CHECK, 1.0 + 0.999 * (self.lam_max() - 1.0))
        lam = np.linspace(1.0, hi, 301)
        q = np.asarray(ca.DM(self.Q(ca.DM(lam)))).ravel()
        bad = ~np.isfinite(q) | (q <= 0)
        if bad.any():
            dws = (lam - 1.0) * q
            # the first non-finite point, else where the pull is strongest
            i = int(np.argmax(~np.isfinite(q))) if not np.isfinite(q).all() else int(np.argmin(dws))
            dw = dws[i] if i > 0 else q[i]
            params = ", ".join(f"{k} = {_fmt(v)}" for k, v in self.as_dict().items())
            raise ValueError(f"material {self.name} ({params}): dW/dlam = {dw * 1e-3:.4g} kPa at stretch "
                             f"{lam[i]:.3f}; the pressure must be finite and >= 0 for stretch in [1, {hi:g}]")

    def as_dict(self) -> dict:
        """Parameters as plain data."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass(frozen=True)
class NeoHookean(Material):
    """W = (E/6)(I1 - 3). E: equivalent Young's modulus, Pa (Table I: 130.6 kPa)."""

    name: ClassVar[str] = "nh"
    E: float = E_TABLE_I

    def W(self, lam):
        i1, _ = _invariants(lam)
        return self.E / 6 * (i1 - 3)

    def Q(self, lam):
        return (2 * self.E / 3) * lam**-5 * _s5(lam)

    def validate(self) -> None:
        if not self.E > 0:
            raise ValueError(f"material nh: E must be > 0 Pa, got {self.E}")
        super().validate()


@dataclass(frozen=True)
class MooneyRivlin(Material):
    """W = C1 (I1 - 3) + C2 (I2 - 3), Pa (Table I: C1 = 21.8 kPa, C2 = 600 Pa; sign typo fixed)."""

    name: ClassVar[str] = "mr"
    C1: float = 21.8e3
    C2: float = 600.0

    def W(self, lam):
        i1, i2 = _invariants(lam)
        return self.C1 * (i1 - 3) + self.C2 * (i2 - 3)

    def Q(self, lam):
        return 4 * _s5(lam) * (self.C1 * lam**-5 + self.C2 * lam**-3)

    def validate(self) -> None:
        if not (self.C1 > 0 and self.C2 >= 0):
            raise ValueError(f"material mr: need C1 > 0 and C2 >= 0 Pa, got {self.C1}, {self.C2}")
        super().validate()


@dataclass(frozen=True)
class Yeoh(Material):
    """W = sum_i C_i (I1 - 3)^i, C = (C10, C20, C30) in Pa.

    Default: C10 = mu0/2 (Table I small strain), C20 = -C10/100, C30 = C10/2000 (assumed mild
    softening then stiffening, the usual Yeoh shape for silicone; fit your own).
    """

    name: ClassVar[str] = "yeoh"
    C: tuple = (MU0 / 2, -MU0 / 200, MU0 / 4000)

    def W(self, lam):
        i1, _ = _invariants(lam)
        return sum(c * (i1 - 3) ** (i + 1) for i, c in enumerate(self.C))

    def Q(self, lam):
        i1, _ = _invariants(lam)
        dw_di1 = sum((i + 1) * c * (i1 - 3) ** i for i, c in enumerate(self.C))
        return dw_di1 * 4 * lam**-5 * _s5(lam)

    def validate(self) -> None:
        if len(self.C) < 1 or not self.C[0] > 0:
            raise ValueError(f"material yeoh: C[0] (C10) must be > 0 Pa, got {self.C}")
        super().validate()


@dataclass(frozen=True)
class Gent(Material):
    """W = -(mu Jm / 2) ln(1 - (I1 - 3)/Jm). mu: shear modulus, Pa; Jm: locking limit (-)."""

    name: ClassVar[str] = "gent"
    dimensionless: ClassVar[tuple] = ("Jm",)
    mu: float = MU0
    Jm: float = 60.0

    def W(self, lam):
        i1, _ = _invariants(lam)
        return -(self.mu * self.Jm / 2) * ca.log(1 - (i1 - 3) / self.Jm)

    def Q(self, lam):
        i1, _ = _invariants(lam)
        return (self.mu / 2) / (1 - (i1 - 3) / self.Jm) * 4 * lam**-5 * _s5(lam)

    def lam_max(self) -> float:
        # solve 2 lam^2 + lam^-4 - 3 = Jm for the locking stretch (lam > 1 root)
        # scipy.optimize loads in 0.3 s: imported where the one Gent root is needed, not with every material
        from scipy.optimize import brentq

        return float(brentq(lambda x: 2 * x**2 + x**-4 - 3 - self.Jm, 1.0 + 1e-9, np.sqrt(self.Jm) + 2))

    def validate(self) -> None:
        if not (self.mu > 0 and self.Jm > 0):
            raise ValueError(f"material gent: need mu > 0 Pa and Jm > 0, got {self.mu}, {self.Jm}")
        super().validate()


@dataclass(frozen=True)
class Ogden(Material):
    """W = sum_i (mu_i/alpha_i)(2 lam^alpha_i + lam^(-2 alpha_i) - 3); mu_i Pa, alpha_i (-).

    Small-strain shear modulus = sum(mu_i alpha_i)/2. Default: (alpha 1.3, 5.0) with
    mu_i alpha_i / 2 = (0.97, 0.03) mu0 (assumed: an almost neo-Hookean silicone that stiffens late).
    """

    name: ClassVar[str] = "ogden"
    dimensionless: ClassVar[tuple] = ("alpha",)
    mu: tuple = (2 * 0.97 * MU0 / 1.3, 2 * 0.03 * MU0 / 5.0)
    alpha: tuple = (1.3, 5.0)

    def W(self, lam):
        return sum(
            (m / a) * (2 * lam**a + lam ** (-2 * a) - 3) for m, a in zip(self.mu, self.alpha)
        )

    def Q(self, lam):
        # W' = sum 2 mu_i lam^(-2a-1) (lam^(3a) - 1); divide by (lam - 1) with expm1 ratios so
        # that the quotient tends to 3a at lam = 1 instead of 0/0.
        L = ca.log(lam)
        small = ca.fabs(L) < 1e-6
        out = 0
        for m, a in zip(self.mu, self.alpha):
            safe_l = ca.if_else(small, 1.0, L)
            ratio = ca.if_else(small, 3 * a * (1 + (3 * a - 1) * L / 2), ca.expm1(3 * a * safe_l) / ca.expm1(safe_l))
            out = out + 2 * m * lam ** (-2 * a - 1) * ratio
        return out

    def validate(self) -> None:
        if len(self.mu) != len(self.alpha) or not self.mu:
            raise ValueError("material ogden: mu and alpha must have the same, non-zero length")
        if any(a == 0 for a in self.alpha):
            raise ValueError("material ogden: alpha_i must be non-zero")
        super().validate()


def _fmt(v) -> str:
    return "[" + ", ".join(f"{x:g}" for x in v) + "]" if isinstance(v, tuple) else f"{v:g}"


def _is_number(x) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, (bool, np.bool_))


def _checked(key: str, cls: type[Material], name: str, v) -> float | tuple:
    """One number where the default is one, a list of numbers (of the allowed length) where it is a list."""
    default = next(f.default for f in fields(cls) if f.name == name)
    if isinstance(default, tuple):
        vals = list(v) if isinstance(v, (list, tuple)) else [v]
        lo, hi = _LENGTHS.get((key, name), (1, 64))
        if not all(_is_number(x) for x in vals):
            raise ValueError(f"material {key}: {name} = {v!r} must be a list of numbers (SI)")
        if not lo <= len(vals) <= hi:
            raise ValueError(f"material {key}: {name} has {len(vals)} entries; allowed {lo} to {hi} numbers (SI)")
        return tuple(float(x) for x in vals)
    if isinstance(v, (list, tuple)):
        raise ValueError(f"material {key}: {name} must be one number (SI), got {len(v)} values {list(v)}")
    if not _is_number(v):
        raise ValueError(f"material {key}: {name} = {v!r} must be a number (SI)")
    return float(v)


MATERIALS: dict[str, type[Material]] = {
    cls.name: cls for cls in (NeoHookean, MooneyRivlin, Yeoh, Gent, Ogden)
}


def make_material(name: str, **overrides) -> Material:
    """Build a material by name ('nh', 'mr', 'yeoh', 'gent', 'ogden') with parameter overrides (SI).

    Unknown names or parameters raise ValueError with the closest valid spelling; so do a list where
    one number belongs (or the reverse), a list of the wrong length, and a strain energy whose
    pressure is negative or not finite for a stretch in [1, LAM_CHECK].
    """
    key = name.lower()
    if key not in MATERIALS:
        hint = did_you_mean(key, MATERIALS)
        raise ValueError(f"material: unknown '{name}'{hint}; allowed: {', '.join(MATERIALS)}")
    cls = MATERIALS[key]
    allowed = {f.name for f in fields(cls)}
    for k in overrides:
        if k not in allowed:
            hint = did_you_mean(k, allowed)
            raise ValueError(f"material {key}: unknown parameter '{k}'{hint}; allowed: {sorted(allowed)}")
    clean = {k: _checked(key, cls, k, v) for k, v in overrides.items()}
    mat = cls(**clean)
    mat.validate()
    return mat


@lru_cache(maxsize=256)
def _check_modulus_and_pressure(material: Material) -> None:
    """The casadi part of :meth:`Material.validate` (the modulus and the pressure's sign over the
    stretch range), once per material: a protocol validates the same material 300 times, at 0.5 ms
    each. A failure raises and is not cached."""
    if material.modulus_q1 <= 0:
        raise ValueError(f"material {material.name}: small-strain modulus must be > 0")
    material._check_positive_pressure()
