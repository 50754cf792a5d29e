"""One error formatter: a pydantic ValidationError -> one line naming the table and key as written.

Examples::

    [controller] p_max_kpa = 1000000 is out of range (0, 1000] kPa
    [actuator] r1_mm = 'abc' must be a number in (0.5, 100] mm
    [controler]: unknown table; did you mean [controller]? allowed: scenario, actuator, ...
    [controller] p_max_kpaa: unknown key; did you mean p_max_kpa? allowed: kind, variant, ...

Only the first error is reported: one fix at a time, like the parsers this replaces. The ranges
come from the fields' own bounds and units (never restated here), so a message cannot drift from
the schema.
"""

from __future__ import annotations

import types
import typing
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal, Union, get_args, get_origin

import annotated_types as at
from pydantic import BaseModel, ValidationError
from pydantic.fields import FieldInfo

from hbma_ctrl.app.schema.fields import RuleError
from hbma_ctrl.core.validation import did_you_mean

__all__ = ["HINT_CUTOFF", "bounds_of", "closest", "format_error", "format_one", "hint", "range_text", "unwrap_type"]

#: scenario keys are long, a typo moves them further than difflib's default 0.6 allows
HINT_CUTOFF = 0.5
_PREFIX, _SUFFIX = " (did you mean '", "'?)"


def closest(word: Any, options: typing.Iterable[str]) -> str | None:
    """The option closest to ``word`` (the package's did_you_mean rule, cutoff 0.5), or None."""
    # did_you_mean owns the closeness rule; its sentence is unwrapped so the hint can be reworded
    s = did_you_mean(str(word), options, cutoff=HINT_CUTOFF)
    return s[len(_PREFIX):-len(_SUFFIX)] if s else None


def hint(word: Any, options: list[str], label: str = "allowed", near_as: str = "{}") -> str:
    """"; did you mean <near>? <label>: a, b, ..." (";" alone in front when no option is close); the
    closest option is written as ``near_as`` shows it (e.g. "[{}]" for a table)."""
    near = closest(word, options) if isinstance(word, str) else None
    ask = f"; did you mean {near_as.format(near)}?" if near else ";"
    return f"{ask} {label}: {', '.join(options)}"


def _g(x: float) -> str:
    return f"{x:g}"


def bounds_of(infos: list[FieldInfo]) -> tuple[float | None, float | None, bool, bool, str]:
    """(lo, hi, lo_open, hi_open, unit) from fields' constraints; None = unbounded, unit "-" = none."""
    lo = hi = None
    lo_open = hi_open = False
    unit = ""
    for fi in infos:
        for m in fi.metadata:
            if isinstance(m, at.Ge):
                lo, lo_open = m.ge, False
            elif isinstance(m, at.Gt):
                lo, lo_open = m.gt, True
            elif isinstance(m, at.Le):
                hi, hi_open = m.le, False
            elif isinstance(m, at.Lt):
                hi, hi_open = m.lt, True
        extra = fi.json_schema_extra if isinstance(fi.json_schema_extra, dict) else {}
        unit = str(extra.get("unit", unit))
    return lo, hi, lo_open, hi_open, unit


def range_text(lo: float | None, hi: float | None, lo_open: bool, hi_open: bool, unit: str) -> str:
    """Interval in the user's unit, e.g. "(0, 1000] kPa"; an open end is "-inf" / "inf"."""
    left = "(" if lo_open or lo is None else "["
    right = ")" if hi_open or hi is None else "]"
    a = "-inf" if lo is None else _g(lo)
    b = "inf" if hi is None else _g(hi)
    return f"{left}{a}, {b}{right} {unit}".rstrip()


def unwrap_type(tp: Any) -> tuple[Any, list[FieldInfo]]:
    """Remove Annotated (keeping its FieldInfos) and Optional around a type."""
    infos: list[FieldInfo] = []
    while True:
        if get_origin(tp) is Annotated:
            args = get_args(tp)
            tp = args[0]
            infos += [m for m in args[1:] if isinstance(m, FieldInfo)]
            continue
        if get_origin(tp) in (Union, types.UnionType):
            args = [a for a in get_args(tp) if a is not type(None)]
            if len(args) == 1:
                tp = args[0]
                continue
        return tp, infos


def _is_model(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, BaseModel)


@dataclass
class _Spot:
    """Where an error sits: table path, key path as written, the leaf's type and field infos."""

    tables: list[str] = field(default_factory=list)
    keys: list = field(default_factory=list)
    tp: Any = None
    infos: list = field(default_factory=list)
    model: Any = None  # the model whose keys are allowed where an unknown key was found
    unknown: bool = False
    shape: str = ""
    top: str = ""  # the table's key the error is under (for shape messages)

    @property
    def table(self) -> str:
        return ".".join(self.tables)

    @property
    def key(self) -> str:
        out = ""
        for k in self.keys:
            if isinstance(k, int):
                out += f"[{k}]"
            else:
                out += f".{k}" if out else str(k)
        return out


def _locate(root: type[BaseModel], loc: tuple, table: str | None) -> _Spot:
    s = _Spot(tp=root, model=root, tables=table.split(".") if table else [])
    for el in loc:
        tp, more = unwrap_type(s.tp)
        s.infos += more
        if _is_model(tp):
            s.model = tp
            fi = tp.model_fields.get(el) if isinstance(el, str) else None
            if fi is None:
                s.keys.append(el)
                s.unknown, s.tp, s.infos = True, None, []
                return s
            sub, _ = unwrap_type(fi.annotation)
            extra = fi.json_schema_extra if isinstance(fi.json_schema_extra, dict) else {}
            if not s.keys and (_is_model(sub) or extra.get("subtable")):
                s.tables.append(el)
            else:
                s.keys.append(el)
                if not s.top or len(s.keys) == 1:
                    s.top = el
            s.shape = str(extra.get("shape", s.shape if len(s.keys) > 1 else ""))
            s.tp, s.infos = fi.annotation, [fi]
        elif isinstance(tp, type) and issubclass(tp, tuple) and hasattr(tp, "_fields"):  # NamedTuple row
            name = tp._fields[el] if isinstance(el, int) and el < len(tp._fields) else el
            s.keys.append(str(name))
            hints = typing.get_type_hints(tp, include_extras=True)
            s.tp, s.infos = hints.get(str(name)), []
        elif get_origin(tp) in (list, tuple, dict):
            args = get_args(tp)
            s.keys.append(el)
            if get_origin(tp) is dict:
                s.tp = args[1] if len(args) == 2 else Any
                if not s.top:
                    s.top = str(el)
            elif get_origin(tp) is tuple and not (len(args) == 2 and args[1] is Ellipsis):
                s.tp = args[el] if isinstance(el, int) and el < len(args) else Any
            else:
                s.tp = args[0] if args else Any
            s.infos = []
        else:
            s.keys.append(el)
            s.tp, s.infos = Any, []
    tp, more = unwrap_type(s.tp)
    s.tp, s.infos = tp, s.infos + more
    return s


#: a pydantic error type -> what the value must be (with the field's range when it has one)
_MUST = {"finite_number": "a finite number", "float_type": "a number", "float_parsing": "a number",
         "int_type": "an integer", "int_parsing": "an integer", "int_from_float": "an integer",
         "bool_type": "true or false", "bool_parsing": "true or false", "string_type": "a string"}


def format_error(exc: ValidationError, root: type[BaseModel], table: str | None = None) -> str:
    """The first error of ``exc`` (raised validating ``root``) as one line starting with ``[table]``.

    ``table``: the name of ``root`` when it is one table (e.g. "controller"); None when ``root`` is
    the whole file, whose keys are the tables.
    """
    errs = exc.errors(include_url=False)
    if not errs:
        return f"[{table or 'scenario'}] invalid"
    if errs[0]["type"] == "missing":
        # a required key missing beside an unknown one is almost surely that key misspelt: name the
        # key as the user wrote it (with the closest valid name), not the one they did not write
        unknown = [e for e in errs if e["type"] == "extra_forbidden"]
        if unknown:
            return format_one(unknown[0], root, table)
    return format_one(errs[0], root, table)


def format_one(err: dict, root: type[BaseModel], table: str | None = None) -> str:
    """One pydantic error dict as one line (see the module docstring)."""
    kind, loc, value = err["type"], tuple(err["loc"]), err.get("input")
    file_root = table is None
    s = _locate(root, loc, table)
    if kind in ("value_error", "assertion_error"):
        e = (err.get("ctx") or {}).get("error")
        if isinstance(e, RuleError):
            return f"[{e.table or s.table or 'scenario'}] {e.text}"
        text = str(e) if e is not None else err["msg"]
        return f"[{s.table or 'scenario'}] {s.key + ': ' if s.key else ''}{text}"
    if kind == "extra_forbidden" and s.unknown:
        allowed = list(s.model.model_fields) if s.model is not None else []
        word = s.keys[-1]
        if file_root and not s.tables and len(s.keys) == 1 and s.model is root:
            return f"[{word}]: unknown table{hint(word, allowed, near_as='[{}]')}"
        return f"[{s.table}] {s.key}: unknown key{hint(word, allowed)}"
    head = f"[{s.table or (s.keys[0] if s.keys else 'scenario')}]"
    if not s.keys or (file_root and not s.tables and len(s.keys) == 1 and s.model is root):
        # a whole table has the wrong type (e.g. ``controller = 5``)
        return f"{head} must be a table, got {type(value).__name__}"
    key = s.key
    lo, hi, lo_open, hi_open, unit = bounds_of(s.infos)
    unit = "" if unit == "-" else unit
    rng = range_text(lo, hi, lo_open, hi_open, unit)
    bounded = lo is not None or hi is not None
    if kind in ("greater_than", "greater_than_equal", "less_than", "less_than_equal") or \
            (kind == "finite_number" and bounded):
        return f"{head} {key} = {value!r} is out of range {rng}"
    if kind in _MUST:  # strings are not parsed: '1e2' in TOML is a typo
        return f"{head} {key} = {value!r} must be {_MUST[kind]}" + (f" in {rng}" if bounded else "")
    if kind == "literal_error":
        opts = [str(o) for o in get_args(s.tp)] if get_origin(s.tp) is Literal else []
        return f"{head} {key} = {value!r} is not allowed" + hint(value, opts, near_as="'{}'")
    if kind == "missing":
        if len(s.keys) == 1:
            return f"{head} {key} is required" + (f": {s.shape}" if s.shape else "")
        return f"{head} {key} is missing" + (f"; {s.top} must be {s.shape}" if s.shape else "")
    if s.shape:
        where = key.rsplit(".", 1)[0] if kind == "missing_argument" else key
        return f"{head} {where} = {value!r} has the wrong shape; {s.top} must be {s.shape}"
    return f"{head} {key} = {value!r}: {err['msg']}"
