"""Field builders shared by every table model: numbers with bounds and units, integers, flags, and
the keys built from a settings class's declarations (:func:`settings_table`).

Every field carries its unit twice: in the description (for people) and in ``json_schema_extra``
(``unit``, for the error formatter and :func:`hbma_ctrl.app.schema.search_space`). Scalars are
strict (a string or a bool is never a number; an int field refuses 2.0); containers stay lax so
TOML arrays validate into tuples.
"""

from __future__ import annotations

import dataclasses
import sys
from typing import Annotated, Any, ClassVar, Literal, NamedTuple, Optional

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, create_model

from hbma_ctrl.core import units as U
from hbma_ctrl.core.settings import Spec, specs

__all__ = [
    "as_is",
    "check_rows",
    "LOAD_STEPS_SHAPE",
    "LoadStepRow",
    "LoadSteps",
    "RuleError",
    "Table",
    "choice",
    "elem",
    "elem_of",
    "flag",
    "integer",
    "load_steps_si",
    "num",
    "renamed_keys",
    "settings_table",
    "shaped",
    "subtable",
    "text",
]


def as_is(v):
    """The conversion of a value that is already in SI (counts, choices, flags, unitless factors)."""
    return v


class Table(BaseModel):
    """Base of every scenario table: unknown keys and non-finite numbers are errors.

    ``settings_keys`` maps the keys built by :func:`settings_table` to (settings class, SI field, Spec).
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, validate_default=False)
    settings_keys: ClassVar[dict[str, tuple[type, str, Spec]]] = {}

    def si(self, owner: type) -> dict[str, Any]:
        """{SI field: SI value} of ``owner``'s keys the user wrote (and not as none)."""
        return {name: spec.to_si(getattr(self, key)) for key, (cls, name, spec) in self.settings_keys.items()
                if cls is owner and key in self.model_fields_set and getattr(self, key) is not None}


#: (file, table, old key) already reported in this process: a file read again (tune's trials) says it once
_REPORTED: set[tuple[str, str, str]] = set()


def renamed_keys(table: str, raw: Any, renamed: dict[str, str], path: Any = None) -> Any:
    """``raw`` (a table as read) with each old key of ``renamed`` {old: current} under its current name
    and a one-line notice on stderr naming both and the file; RuleError when both names are given."""
    if not isinstance(raw, dict) or not renamed.keys() & raw.keys():
        return raw
    out = dict(raw)
    for old, new in renamed.items():
        if old not in out:
            continue
        if new in out:
            raise RuleError(f"{old} and {new} are one key ({old} is its old name): keep {new} only", table)
        out[new] = out.pop(old)
        if (str(path), table, old) not in _REPORTED:
            _REPORTED.add((str(path), table, old))
            where = f"{path}: " if path else ""
            print(f"{where}[{table}] {old} is deprecated: write {new}", file=sys.stderr)
    return out


class RuleError(ValueError):
    """A broken cross-field rule, raised inside a model validator.

    ``text`` follows ``[table] `` in the final message and names the keys as written; ``table``
    (e.g. "inputs") overrides the table the error's location gives (the root validator has none).
    """

    def __init__(self, text: str, table: str | None = None):
        super().__init__(text)
        self.text = text
        self.table = table


def _bounds(lo: float | None, hi: float | None, lo_open: bool, hi_open: bool) -> dict:
    kw: dict = {}
    if lo is not None:
        kw["gt" if lo_open else "ge"] = lo
    if hi is not None:
        kw["lt" if hi_open else "le"] = hi
    return kw


def num(default: Any, lo: float | None, hi: float | None, unit: str, what: str, *,
        lo_open: bool = False, hi_open: bool = False) -> Any:
    """A finite number field in the user's unit, bounded [lo, hi] (open ends on request)."""
    return Field(default, strict=True, allow_inf_nan=False, description=f"{what} ({unit})",
                 json_schema_extra={"unit": unit}, **_bounds(lo, hi, lo_open, hi_open))


def integer(default: Any, lo: int | None, hi: int | None, what: str, unit: str = "-") -> Any:
    """A strict integer field (2.0 and true are refused), bounded [lo, hi]."""
    return Field(default, strict=True, description=f"{what} ({unit}, integer)",
                 json_schema_extra={"unit": unit}, **_bounds(lo, hi, False, False))


def flag(default: Any, what: str) -> Any:
    """A strict true/false field."""
    return Field(default, strict=True, description=f"{what} (true/false)")


def text(default: Any, what: str) -> Any:
    """A strict string field."""
    return Field(default, strict=True, description=f"{what} (text)")


def choice(default: Any, what: str) -> Any:
    """A choice field (the annotation is a Literal: only the listed strings match)."""
    return Field(default, description=f"{what} (choice)")


def subtable(default_factory: Any, what: str, shape: str) -> Any:
    """A TOML sub-table given as a dict (``[robot.targets]``): errors name ``[table.key]``."""
    return Field(default_factory=default_factory, description=f"{what}: {shape}",
                 json_schema_extra={"subtable": True, "shape": shape})


def elem(lo: float | None, hi: float | None, unit: str, what: str, *, lo_open: bool = False,
         hi_open: bool = False) -> Any:
    """The type of one number inside a row or vector (a tuple element), with bounds and unit."""
    return Annotated[float, num(..., lo, hi, unit, what, lo_open=lo_open, hi_open=hi_open)]


def shaped(default: Any, what: str, shape: str, *, min_length: int | None = None,
           default_factory: Any = None) -> Any:
    """A list or vector field; ``shape`` (e.g. "[[t_s, h_mm], ...]") is quoted by the errors."""
    kw: dict = {"description": f"{what}: {shape}", "json_schema_extra": {"shape": shape}}
    if min_length is not None:
        kw["min_length"] = min_length
    if default_factory is not None:
        return Field(default_factory=default_factory, **kw)
    return Field(default, **kw)


class LoadStepRow(NamedTuple):
    """One load step: from t_s on, the rig carries mass_g."""

    t_s: elem(0.0, 1e5, "s", "time of the step")
    mass_g: elem(0.0, 50000.0, "g", "load mass from then on")


def check_rows(rows: list, key: str, table: str | None = None, what: str = "row", from_zero: bool = True) -> list:
    """``rows`` when their times (first entries, s) increase strictly and, ``from_zero``, start at 0 s;
    RuleError naming the row (``key[i].t_s``) and the previous ``what``'s time otherwise."""
    last = -1.0
    for i, r in enumerate(rows):
        if from_zero and i == 0 and r[0] != 0.0:
            raise RuleError(f"{key}[0].t_s = {r[0]:g} must be 0 (the schedule starts at t = 0 s)", table)
        if r[0] <= last:
            raise RuleError(f"{key}[{i}].t_s = {r[0]:g} must be after the previous {what}'s {last:g} s", table)
        last = r[0]
    return rows


#: [[t_s, mass_g], ...] with strictly increasing times: the one rule for [controller] and [estimator]
LoadSteps = Annotated[list[LoadStepRow], AfterValidator(lambda rows: check_rows(rows, "load_steps_g", what="step",
                                                                                 from_zero=False))]
LOAD_STEPS_SHAPE = "[[t_s, mass_g], ...]"


def load_steps_si(rows: list) -> tuple:
    """((t s, mass kg), ...) from the table's [[t_s, mass_g], ...]."""
    return tuple((r.t_s, U.grams(r.mass_g)) for r in rows)


def elem_of(spec: Spec) -> Any:
    """The type of one number (a row's or vector's entry) a declaration bounds, in the user's unit."""
    lo, hi = spec.user_bounds()
    return elem(lo, hi, spec.user_unit, spec.doc, lo_open=spec.lo_open, hi_open=spec.hi_open)


def key_field(spec: Spec, default: Any) -> tuple[Any, Any]:
    """(annotation, field) of the scenario key a setting declares, in the user's unit, with ``default``."""
    lo, hi = spec.user_bounds()
    unit, doc, ends = spec.user_unit, spec.doc, {"lo_open": spec.lo_open, "hi_open": spec.hi_open}
    if spec.kind == "integer":
        tp, fi = int, integer(default, lo, hi, doc, unit)
    elif spec.kind == "flag":
        tp, fi = bool, flag(default, doc)
    elif spec.kind == "choice":
        tp, fi = Literal[spec.choices], choice(default, doc)
    elif spec.kind == "text":
        tp, fi = str, text(default, doc)
    elif spec.kind == "vector":
        tp = tuple[(elem_of(spec),) * spec.size]
        fi = shaped(default, doc, f"[{', '.join(spec.parts)}]" if spec.parts else f"{spec.size} numbers")
    else:
        tp, fi = float, num(default, lo, hi, unit, doc, **ends)
    return (Optional[tp] if spec.optional or default is None else tp), fi


def settings_table(name: str, *sources: tuple[type, tuple[str, ...]], defaults: dict[str, Any] | None = None,
                   base: type[Table] = Table) -> type[Table]:
    """A table model with one key per named field of each (settings class, field names) source, as
    the field's :class:`~hbma_ctrl.core.settings.Spec` declares it; the default is the settings class's
    in the user's unit, or ``defaults[field]`` (user's unit; None: "not given", the key is optional)."""
    defaults = defaults or {}
    fields: dict[str, Any] = {}
    keys: dict[str, tuple[type, str, Spec]] = {}
    for cls, names in sources:
        declared, si_defaults = specs(cls), {f.name: f.default for f in dataclasses.fields(cls)}
        for n in names:
            spec = declared[n]
            key = spec.key_for(n)
            fields[key] = key_field(spec, defaults[n] if n in defaults else spec.to_user(si_defaults[n]))
            keys[key] = (cls, n, spec)
    model = create_model(name, __base__=base, **fields)
    model.settings_keys = {**base.settings_keys, **keys}
    return model
