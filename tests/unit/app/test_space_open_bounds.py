"""An open end of a setting's range becomes the nearest value inside it in the tuning search space:
the space keeps out the end and keeps in every valid default, however small."""

from __future__ import annotations

import math
import sys

from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st
from pydantic import Field, create_model
from pydantic.fields import FieldInfo

from hbma_ctrl.app.schema.space import TINY, search_space

FINITE = st.floats(min_value=-1e300, max_value=1e300, allow_nan=False, allow_subnormal=False)


def _space_of(lo: float, hi: float, lo_open: bool, hi_open: bool, tp: type = float) -> tuple:
    bounds = {"gt" if lo_open else "ge": lo, "lt" if hi_open else "le": hi}
    model = create_model("T", x=(tp, Field(tp(hi), json_schema_extra={"unit": "ms"}, **bounds)))
    return search_space(model)["x"], model


def _fast_space_of(lo: float, hi: float, lo_open: bool, hi_open: bool) -> tuple:
    """search_space of a one-field table, without building a pydantic model (the property's many cases)."""
    bounds = {"gt" if lo_open else "ge": lo, "lt" if hi_open else "le": hi}
    fi = FieldInfo.from_annotated_attribute(float, Field(hi, json_schema_extra={"unit": "ms"}, **bounds))
    return search_space(type("T", (), {"model_fields": {"x": fi}}))["x"]


@st.composite
def open_range_and_default(draw):
    """(lo, hi, lo_open, hi_open, default): at least one end open, often 0, the default strictly inside
    and of reasonable size (0 or at least TINY: a value whose SI conversion stays a normal number)."""
    a, b = draw(st.one_of(st.tuples(st.just(0.0), FINITE), st.tuples(FINITE, st.just(0.0)), st.tuples(FINITE, FINITE)))
    assume(a != b)
    lo, hi = min(a, b), max(a, b)
    lo_open, hi_open = draw(st.sampled_from([(True, False), (False, True), (True, True)]))
    assume(not (lo_open and hi_open) or math.nextafter(lo, hi) < hi)  # a float between two open ends
    d = draw(st.floats(min_value=lo, max_value=hi, exclude_min=lo_open, exclude_max=hi_open))
    assume(d == 0 or abs(d) >= TINY)
    return lo, hi, lo_open, hi_open, d


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(open_range_and_default())
@example((1.4217e-295, 5.16e-285, True, False, 4.57e-285))  # an open end nearer 0 than TINY
@example((-1e-300, 1e-300, True, True, 0.0))
@example((0.0, 1e9, True, False, 0.01))
def test_the_space_of_an_open_range_holds_every_default_inside_and_never_the_open_end(case):
    lo, hi, lo_open, hi_open, d = case
    s_lo, s_hi, unit, kind = _fast_space_of(lo, hi, lo_open, hi_open)
    assert (unit, kind) == ("ms", "float")
    assert s_lo <= d <= s_hi
    assert (s_lo > lo) if lo_open else (s_lo == lo)  # so both ends of the space are valid values
    assert (s_hi < hi) if hi_open else (s_hi == hi)


def test_an_open_end_at_zero_is_tiny_yet_stays_positive_and_normal_in_si():
    (s_lo, s_hi, _, _), model = _space_of(0.0, 1e9, True, False)
    assert (s_lo, s_hi) == (TINY, 1e9)
    for v in (s_lo, s_hi):  # both ends of the space are values the setting accepts
        model.model_validate({"x": v})
    assert s_lo <= 0.01 and s_lo * 1e-3 >= sys.float_info.min  # a default of 0.01; ms to s stays normal
    assert TINY * 2.0**-53 >= sys.float_info.min
    (s_lo, s_hi, _, _), _ = _space_of(-5.0, 0.0, False, True)
    assert (s_lo, s_hi) == (-5.0, -TINY)
    (s_lo, _, _, _), _ = _space_of(1.0, 5.0, True, False)
    assert s_lo == math.nextafter(1.0, 2.0)


def test_an_integer_range_moves_an_open_end_by_one():
    (s_lo, s_hi, _, kind), _ = _space_of(0, 10, True, True, int)
    assert (s_lo, s_hi, kind) == (1, 9, "int")


def test_a_small_valid_value_is_neither_clipped_nor_refused_by_the_tuning_space():
    """q_integral is declared (0, 1e6]: a scenario's 1e-4 is trial 0's value and may bound a range; named
    without a range, it is sampled from 1e-9 of the top, or from the value when that is lower."""
    from hbma_ctrl.app.tuning.tune import make_space

    data = {"controller": {"kind": "lqi", "targets_mm": [[0, 2]], "q_integral": 1e-4}}
    (w,) = make_space(data, "controller", ["q_integral"])
    assert (w.lo, w.hi, w.default, w.log) == (1e-4, 1e6, 1e-4, True)
    (r,) = make_space(data, "controller", ["q_integral=1e-6:1e-3"])
    assert (r.lo, r.hi, r.default) == (1e-6, 1e-3, 1e-4)
    (n,) = make_space({"controller": {"kind": "lqi", "targets_mm": [[0, 2]]}}, "controller", ["q_integral"])
    assert (n.lo, n.hi, n.default) == (1e6 * 1e-9, 1e6, 2.0)
    dims = {x.name: x for x in make_space(data, "controller")}  # the default set: around the value
    assert dims["q_integral"].lo < 1e-4 == dims["q_integral"].default < dims["q_integral"].hi
