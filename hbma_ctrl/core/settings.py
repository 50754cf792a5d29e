"""Settings declared once: a settings dataclass's field carries its bounds, unit, scenario key and doc.

A field declared with :func:`setting` holds a :class:`Spec` in its metadata. :class:`Settings`'
``validate`` checks every declared field (bounds, choices, integers, flags, vector lengths) with one
ValueError naming ``where.field`` and the allowed range in SI; a class adds its few rules across
fields in ``check_rules``. The scenario schema (:func:`hbma_ctrl.app.schema.fields.settings_table`) builds its keys,
in the user's units, from the same declarations.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import MISSING, dataclass, field, fields
from typing import Any, ClassVar, Self

from hbma_ctrl.core import units as U
from hbma_ctrl.core.validation import did_you_mean

__all__ = ["Settings", "Spec", "check_fields", "check_range", "setting", "specs"]


def _bound(x: float | None, inf: str) -> str:
    return inf if x is None else str(x)


def check_range(where: str, name: str, value: float, lo: float | None, hi: float | None, unit: str = "",
                lo_open: bool = False, hi_open: bool = False) -> None:
    """Raise ValueError naming ``where.name`` when ``value`` is not a finite number in [lo, hi] (ends
    open on request; None: unbounded)."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if ok:
        ok = (lo is None or (value > lo if lo_open else value >= lo)) and \
             (hi is None or (value < hi if hi_open else value <= hi))
    if not ok:
        left = "(" if lo_open or lo is None else "["
        right = ")" if hi_open or hi is None else "]"
        raise ValueError(f"{where}.{name} = {value!r} is out of range {left}{_bound(lo, '-inf')}, "
                         f"{_bound(hi, 'inf')}{right} {'' if unit == '-' else unit}".rstrip())


def _user_round(x: float) -> float:
    # a bound or default in the user's unit as a person writes it (1e-3 m -> 1 mm, not 1.0000000000000002)
    return float(f"{x:.12g}")


@dataclass(frozen=True)
class Spec:
    """One setting: what it is and which values it takes (SI), and its scenario key and unit.

    kind : 'number', 'integer', 'flag', 'choice', 'vector' (``size`` numbers, each in [lo, hi]) or 'text'.
    optional : None is allowed (the owner's meaning of "not given").
    user : the scenario key's unit when it is not the SI one (a name of :data:`hbma_ctrl.core.units.USER_UNITS`).
    key : the scenario key; default the field's name with the user unit's suffix (``p_max`` -> ``p_max_kpa``).
    parts : the names of a vector's entries, in order (quoted by the scenario's errors).
    """

    doc: str
    kind: str = "number"
    unit: str = "-"
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple[str, ...] = ()
    size: int = 0
    optional: bool = False
    user: str | None = None
    key: str | None = None
    parts: tuple[str, ...] = ()

    def key_for(self, name: str) -> str:
        """The scenario key of field ``name``."""
        if self.key is not None:
            return self.key
        suffix = U.USER_UNITS[self.user][2] if self.user else ""
        return f"{name}_{suffix}" if suffix else name

    @property
    def user_unit(self) -> str:
        return self.user or self.unit

    def _conv(self, to_si: bool) -> Callable[[float], float]:
        if not self.user:
            return float
        return U.USER_UNITS[self.user][0 if to_si else 1]

    def to_si(self, value: Any) -> Any:
        """A value in the user's unit -> SI (numbers and vectors; anything else as it is)."""
        if value is None or self.kind not in ("number", "vector"):
            return value
        conv = self._conv(True)
        return tuple(conv(x) for x in value) if self.kind == "vector" else conv(value)

    def to_user(self, value: Any) -> Any:
        """An SI value -> the user's unit (rounded to 12 digits)."""
        if value is None or self.kind not in ("number", "vector"):
            return value
        conv = self._conv(False)
        if self.kind == "vector":
            return tuple(_user_round(conv(x)) for x in value)
        return _user_round(conv(value))

    def user_bounds(self) -> tuple[float | None, float | None]:
        """(lo, hi) in the user's unit (of each entry, for a vector)."""
        if self.kind == "integer":
            return self.lo, self.hi
        conv = self._conv(False)
        return tuple(None if x is None else _user_round(conv(x)) for x in (self.lo, self.hi))

    def check(self, where: str, name: str, value: Any) -> None:
        """ValueError naming ``where.name`` and what it takes when ``value`` is not allowed (SI)."""
        if value is None and self.optional:
            return
        head = f"{where}.{name} = {value!r}"
        if self.kind == "flag":
            if not isinstance(value, bool):
                raise ValueError(f"{head} must be true or false")
        elif self.kind == "choice":
            if value not in self.choices:
                hint = did_you_mean(str(value), self.choices)
                raise ValueError(f"{head}{hint}: allowed {', '.join(self.choices)}")
        elif self.kind == "integer":
            ok = isinstance(value, int) and not isinstance(value, bool)
            if not ok or (self.lo is not None and value < self.lo) or (self.hi is not None and value > self.hi):
                rng = f"in [{self.lo}, {self.hi}]" if self.hi is not None else f">= {self.lo}"
                raise ValueError(f"{head} must be an integer {rng}")
        elif self.kind == "vector":
            v = tuple(value) if isinstance(value, (tuple, list)) else ()
            if len(v) != self.size:
                what = f" ({', '.join(self.parts)})" if self.parts else ""
                raise ValueError(f"{head} must have {self.size} entries{what}")
            for i, x in enumerate(v):
                check_range(where, f"{name}[{i}]", x, self.lo, self.hi, self.unit, self.lo_open, self.hi_open)
        elif self.kind == "number":
            check_range(where, name, value, self.lo, self.hi, self.unit, self.lo_open, self.hi_open)


def setting(default: Any = MISSING, *, doc: str, unit: str = "-", lo: float | None = None,
            hi: float | None = None, lo_open: bool = False, hi_open: bool = False,
            choices: tuple[str, ...] = (), integer: bool = False, text: bool = False,
            optional: bool = False, user: str | None = None, key: str | None = None,
            parts: tuple[str, ...] = (), repr: bool = True) -> Any:
    """A dataclass field with its :class:`Spec` (SI default, bounds and unit; ``user``/``key``: the
    scenario key's unit and name). The kind follows from the arguments and the default: a bool is a
    flag, a tuple a vector of its length, ``choices`` a choice, ``integer`` an integer, ``text`` a string;
    a None default is optional."""
    if choices:
        kind = "choice"
    elif integer:
        kind = "integer"
    elif text:
        kind = "text"
    elif isinstance(default, bool):
        kind = "flag"
    elif isinstance(default, tuple) or parts:
        kind = "vector"
    else:
        kind = "number"
    size = len(parts) if parts else (len(default) if isinstance(default, tuple) else 0)
    spec = Spec(doc=doc, kind=kind, unit=unit, lo=lo, hi=hi, lo_open=lo_open, hi_open=hi_open,
                choices=tuple(choices), size=size, optional=optional or default is None, user=user, key=key,
                parts=tuple(parts))
    return field(default=default, repr=repr, metadata={"setting": spec})


def specs(cls: Any) -> dict[str, Spec]:
    """{field name: Spec} of a settings dataclass (or instance), in field order."""
    return _specs(cls if isinstance(cls, type) else type(cls))


@functools.cache
def _specs(cls: type) -> dict[str, Spec]:
    return {f.name: f.metadata["setting"] for f in fields(cls) if "setting" in f.metadata}


def check_fields(obj: Any, where: str) -> None:
    """Check every declared field of ``obj`` (:meth:`Spec.check`), in field order."""
    for name, spec in specs(obj).items():
        spec.check(where, name, getattr(obj, name))


class Settings:
    """Base of a settings dataclass whose fields are declared with :func:`setting`.

    ``WHERE`` names the settings in errors (``mpc.p_max = ...``).
    """

    WHERE: ClassVar[str] = ""

    def validate(self) -> Self:
        """Check every field, then the rules across fields; ValueError naming the field otherwise."""
        check_fields(self, self.WHERE)
        self.check_rules()
        return self

    def check_rules(self) -> None:
        """The rules across fields (none by default)."""

    def within(self, name: str, lo: float | None = None, hi: float | None = None) -> None:
        """Check field ``name`` against its declared range with ``lo`` or ``hi`` (another field's value)
        in place of the declared end (open or closed as declared)."""
        s = specs(self)[name]
        check_range(self.WHERE, name, getattr(self, name), s.lo if lo is None else lo, s.hi if hi is None else hi,
                    s.unit, s.lo_open, s.hi_open)
