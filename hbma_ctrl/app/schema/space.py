"""The numeric fields of a table with their bounds and units: the tuning CLI's search space."""

from __future__ import annotations

import math
from typing import Any, get_args, get_origin

from pydantic import BaseModel

from hbma_ctrl.app.schema.errors import bounds_of, unwrap_type

__all__ = ["search_space"]


def _entry(infos: list, tp: Any, finite_only: bool) -> tuple | None:
    if tp is bool or tp not in (float, int):
        return None
    lo, hi, lo_open, hi_open, unit = bounds_of(infos)
    if finite_only and (lo is None or hi is None):
        return None
    lo = -math.inf if lo is None else lo
    hi = math.inf if hi is None else hi
    kind = "int" if tp is int else "float"
    # an open end moves inside by 1e-9 of the span (not to the next float: 5e-324 ms would
    # underflow to 0 s on conversion), so every value of [lo, hi] is valid
    step = (hi - lo) * 1e-9 if math.isfinite(hi - lo) else 1e-9
    if lo_open and math.isfinite(lo):
        lo = lo + 1 if kind == "int" else lo + step
    if hi_open and math.isfinite(hi):
        hi = hi - 1 if kind == "int" else hi - step
    return (lo, hi, unit, kind)


def search_space(model: type[BaseModel] | BaseModel, finite_only: bool = True) -> dict[str, tuple]:
    """{key: (lo, hi, unit, kind)} for every number of a table, in the user's units.

    kind is "float" or "int"; vectors give one entry per element (``w_rate[0]``). Open bounds are
    moved inside by 1e-9 of the span. ``finite_only`` leaves out keys without two finite bounds
    (seeds, forces), which an optimiser cannot sample.
    """
    cls = model if isinstance(model, type) else type(model)
    out: dict[str, tuple] = {}
    for name, fi in cls.model_fields.items():
        tp, more = unwrap_type(fi.annotation)
        e = _entry([fi] + more, tp, finite_only)
        if e is not None:
            out[name] = e
        elif get_origin(tp) is tuple and Ellipsis not in get_args(tp):
            for i, arg in enumerate(get_args(tp)):
                atp, infos = unwrap_type(arg)
                e = _entry(infos, atp, finite_only)
                if e is not None:
                    out[f"{name}[{i}]"] = e
    return out
