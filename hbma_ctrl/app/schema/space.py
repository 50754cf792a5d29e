"""The numeric fields of a table with their bounds and units: the tuning CLI's search space."""

from __future__ import annotations

import math
import sys
from typing import Any, get_args, get_origin

from pydantic import BaseModel

from hbma_ctrl.app.schema.errors import bounds_of, unwrap_type

__all__ = ["TINY", "inside", "search_space"]


#: where an open end at 0 moves: the smallest positive value a setting may take in a search. A normal
#: float that stays normal through any unit conversion by a factor down to 2**-53 (ms to s is 1e-3),
#: so that no searched value reaches the SI settings as 0 or as a subnormal number
TINY = sys.float_info.min * 2.0**53


def inside(end: float, toward: float) -> float:
    """The value next to the open end ``end`` of a range, on the side of ``toward``: the next float
    (any value strictly inside is at least as far from ``end``), but 0 or :data:`TINY` (toward
    ``toward``) where the next float is smaller in size than TINY and that value is strictly inside."""
    v = math.nextafter(end, toward)
    if abs(v) < TINY:
        w = 0.0 if end < 0 < toward or toward < 0 < end else math.copysign(TINY, toward - end)
        if min(end, toward) < w < max(end, toward):  # strictly inside
            v = w
    return v


def _entry(infos: list, tp: Any, finite_only: bool) -> tuple | None:
    if tp is bool or tp not in (float, int):
        return None
    lo, hi, lo_open, hi_open, unit = bounds_of(infos)
    if finite_only and (lo is None or hi is None):
        return None
    lo = -math.inf if lo is None else lo
    hi = math.inf if hi is None else hi
    kind = "int" if tp is int else "float"
    # an open end moves to the nearest value strictly inside (see inside), so that every value of
    # [lo, hi] is valid and every valid default of reasonable size is in [lo, hi]: a move by a share
    # of the span put (0, 1e6] at 1e-3, above valid settings
    if lo_open and math.isfinite(lo):
        lo = lo + 1 if kind == "int" else inside(lo, hi)
    if hi_open and math.isfinite(hi):
        hi = hi - 1 if kind == "int" else inside(hi, lo)
    return (lo, hi, unit, kind)


def search_space(model: type[BaseModel] | BaseModel, finite_only: bool = True) -> dict[str, tuple]:
    """{key: (lo, hi, unit, kind)} for every number of a table, in the user's units.

    kind is "float" or "int"; vectors give one entry per element (``w_rate[0]``). An open bound is
    moved to the nearest value inside (:func:`inside`: the next float, or :data:`TINY` for 0).
    ``finite_only`` leaves out keys without two finite bounds (seeds, forces), which an optimiser
    cannot sample.
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
