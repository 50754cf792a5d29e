"""The reference page of scenario keys, read from the table models (and so from the settings'
declarations they are built from): per table, every key with its type, unit, allowed range,
default and one-line doc, as Markdown. ``hbma-ctrl scenarios keys`` prints it;
``docs/reference/scenario-keys.md`` is its committed copy (a test keeps the two equal).
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any, Literal, get_args, get_origin

from pydantic import BaseModel
from pydantic.fields import FieldInfo

from hbma_ctrl.app.schema.document import ScenarioFile
from hbma_ctrl.app.schema.errors import bounds_of, range_text, unwrap_type

__all__ = ["PAGE", "TABLES", "markdown", "table_markdown"]

#: the page's path in the repository
PAGE = Path("docs") / "reference" / "scenario-keys.md"


def _tables() -> dict[str, type[BaseModel]]:
    return {name: unwrap_type(fi.annotation)[0] for name, fi in ScenarioFile.model_fields.items()}


#: table name -> its model, in the scenario file's order
TABLES = _tables()

_HEAD = """# Scenario keys

Every key of every table of a scenario file, in the user's units. Generated from the table models
(`hbma_ctrl.app.schema.reference`; `hbma-ctrl scenarios keys` prints it): do not edit by hand.
A key not written takes its default; "none" is "not given" (the owner's default applies).
"""


#: the reference's name of a scalar key's type
_SCALARS = {bool: "true/false", int: "integer", float: "number", str: "text"}


def _type(tp: Any) -> str:
    tp = unwrap_type(tp)[0]
    if get_origin(tp) is Literal:
        return "choice: " + ", ".join(str(a) for a in get_args(tp))
    if tp in _SCALARS:
        return _SCALARS[tp]
    origin = get_origin(tp)
    if origin is tuple:
        return f"{len(get_args(tp))} numbers"
    if origin is list or tp is list:
        return "list"
    if origin is dict or tp is dict:
        return "table"
    return getattr(tp, "__name__", str(tp))


def _element_infos(tp: Any) -> list[FieldInfo]:
    """The FieldInfos of a vector's or list's entries (their bounds and unit)."""
    tp = unwrap_type(tp)[0]
    if get_origin(tp) in (tuple, list):
        args = [a for a in get_args(tp) if a is not Ellipsis]
        if args and all(a == args[0] for a in args):
            return unwrap_type(args[0])[1]
    return []


def _default(fi: FieldInfo) -> str:
    if fi.is_required():
        return "required"
    v = fi.get_default(call_default_factory=True)
    if v is None:
        return "none"
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, (str, int)):
        return str(v)
    return json.dumps(v if not isinstance(v, tuple) else list(v))


_SUFFIX = re.compile(r" \((?:[^()]*, integer|true/false|text|choice)\)$")


def _doc(model: type[BaseModel], key: str, fi: FieldInfo, unit: str) -> str:
    spec = getattr(model, "settings_keys", {}).get(key)
    if spec is not None:
        return spec[2].doc
    desc = _SUFFIX.sub("", fi.description or "")
    return desc[:-len(f" ({unit})")] if unit and desc.endswith(f" ({unit})") else desc


def _intro(model: type[BaseModel]) -> str:
    """The model docstring's first paragraph on one line, its Sphinx roles as code."""
    first = " ".join((model.__doc__ or "").strip().split("\n\n")[0].split())
    return re.sub(r":\w+:`~?([^`]*)`", r"`\1`", first)


def _cell(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def key_rows(model: type[BaseModel]) -> list[tuple[str, str, str, str, str, str]]:
    """(key, type, unit, range, default, doc) of every key of ``model``, in its order."""
    rows = []
    old = {new: name for name, new in getattr(model, "renamed", {}).items()}
    for key, fi in model.model_fields.items():
        infos = [fi, *unwrap_type(fi.annotation)[1]]
        lo, hi, lo_open, hi_open, unit = bounds_of(infos + _element_infos(fi.annotation))
        rng = "" if lo is None and hi is None else range_text(lo, hi, lo_open, hi_open, "")
        doc = _doc(model, key, fi, unit) + (f" (old name {old[key]}, still read)" if key in old else "")
        rows.append((key, _type(fi.annotation), "" if unit in ("", "-") else unit, rng, _default(fi), doc))
    return rows


def table_markdown(name: str) -> str:
    """One table's section: a heading and a row per key. ValueError naming the tables for an unknown ``name``."""
    if name not in TABLES:
        raise ValueError(f"{name!r} is not a scenario table; allowed: {', '.join(TABLES)}")
    lines = [f"## [{name}]", "", _intro(TABLES[name]), "",
             "| key | type | unit | range | default | doc |", "|---|---|---|---|---|---|"]
    lines += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in key_rows(TABLES[name])]
    return "\n".join(lines) + "\n"


def markdown(table: str | None = None) -> str:
    """The page (every table), or one table's section."""
    if table is not None:
        return table_markdown(table)
    return _HEAD + "".join("\n" + table_markdown(name) for name in TABLES)
