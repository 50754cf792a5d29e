"""The model-based burst test (hbma_ctrl.runtime.burst), the supervisor's burst rule and their settings."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hbma_ctrl.system.sections import RobotSettings
from hbma_ctrl.runtime.burst import BurstTest, BurstTestSettings
from hbma_ctrl.runtime.safety import Supervisor, SupervisorSettings


def _update(t: BurstTest, r) -> np.ndarray:
    """One period of innovations r, no estimate lost: the chambers newly flagged."""
    return t.step(0.0, r, np.zeros(t.n, dtype=bool))


def _lost(t: BurstTest, time: float, new) -> np.ndarray:
    """One period at ``time`` with the estimates of ``new`` lost anew, no innovation: the chambers newly flagged."""
    return t.step(time, np.zeros(t.n), new)


def _periods_to_flag(r: float, n_max: int = 1000, s: BurstTestSettings | None = None) -> int | None:
    """Periods of a constant innovation r (sigma) until one chamber is flagged, None within n_max."""
    t = BurstTest(1, s)
    for k in range(1, n_max + 1):
        if _update(t, [r])[0]:
            return k
    return None


def test_a_steady_fall_of_10_sigma_a_period_is_flagged_on_the_tenth_period():
    # each period adds 10 - 5 (the allowance): 50 is reached on the tenth
    assert _periods_to_flag(-10.0) == 10


def test_one_or_two_wild_readings_are_not_a_burst_three_are():
    for wild in (1, 2):
        t = BurstTest(1)
        flags = [_update(t, [-1e6])[0] for _ in range(wild)] + [_update(t, [0.0])[0] for _ in range(50)]
        assert not any(flags) and not t.flagged[0]
    assert _periods_to_flag(-1e6) == 3  # 20 (the step cap) a period: 60 >= 50 on the third


def test_readings_within_the_allowance_never_add():
    assert _periods_to_flag(-5.0) is None
    t = BurstTest(3)
    for _ in range(100):
        _update(t, [-5.0, 0.0, 40.0])
    assert np.all(t.g == 0.0) and np.all(t.peak == 0.0)


def test_a_reading_not_used_counts_as_no_fall_and_lets_the_sum_decay():
    t = BurstTest(2)
    _update(t, [-25.0, -25.0])  # 20 each
    _update(t, [np.nan, 0.0])
    assert t.g == pytest.approx([15.0, 15.0])
    _update(t, [-np.inf, np.inf])  # -inf is a fall at the cap, +inf empties the sum
    assert t.g == pytest.approx([35.0, 0.0])


def test_the_flag_is_kept_until_a_reset_and_reported_once():
    t = BurstTest(2)
    new = [_update(t, [-30.0, 0.0]) for _ in range(5)]
    assert [bool(n[0]) for n in new] == [False, False, True, False, False]
    assert t.flagged.tolist() == [True, False]
    t.reset(np.array([True, False]))
    assert t.flagged.tolist() == [False, False] and t.g[0] == 0.0
    assert t.peak[0] == pytest.approx(100.0)  # the margin seen is kept for tuning


@pytest.mark.slow
@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(min_value=-1e9, max_value=1e9) | st.sampled_from([np.nan, np.inf, -np.inf]), min_size=1, max_size=200))
def test_the_sum_is_never_negative_never_grows_by_more_than_the_cap_and_flags_only_at_the_threshold(rs):
    t = BurstTest(1)
    s = t.settings
    g_prev = 0.0
    for r in rs:
        new = _update(t, [r])[0]
        g = float(t.g[0])
        assert 0.0 <= g <= g_prev + s.step_cap + 1e-9
        if new:
            assert g >= s.threshold
        g_prev = g
    assert t.flagged[0] == (t.peak[0] >= s.threshold)


def test_a_chamber_lost_three_times_within_the_window_is_flagged_and_not_one_lost_slower():
    t = BurstTest(2)
    one = np.array([True, False])
    assert not _lost(t, 1.0, one).any() and not _lost(t, 1.5, one).any()
    assert not _lost(t, 3.2, one).any()  # 1.0 has left the 2 s window: two episodes in it
    assert _lost(t, 3.4, one).tolist() == [True, False]  # 1.5, 3.2, 3.4
    assert t.flagged.tolist() == [True, False]
    assert t.why[0].startswith("its estimate was lost 3 times within 1.90 s")
    assert not _lost(t, 3.5, one).any()  # reported once
    # spaced wider than the window, never
    t2 = BurstTest(1)
    assert not any(_lost(t2, 2.5 * k, [True])[0] for k in range(20))
    t.reset()
    assert not t.flagged.any() and t.why == ["", ""] and not _lost(t, 3.6, one).any()


def test_a_fall_flag_says_how_far_the_readings_fell():
    t = BurstTest(1)
    for _ in range(3):
        _update(t, [-30.0])
    assert t.why[0] == "its readings fell 60 sigma below its filter's prediction over the last periods"


@pytest.mark.parametrize("field, value, text", [
    ("threshold", 0.0, r"burst.threshold = 0.0 is out of range \(0.0, 10000.0\] sigma"),
    ("allowance", -1.0, r"burst.allowance = -1.0 is out of range \[0.0, 100.0\] sigma"),
    ("step_cap", 60.0, r"burst.step_cap = 60.0 is out of range \(0.0, 50.0\] sigma"),
    ("relapses", 1, r"burst.relapses = 1 must be an integer in \[2, 1000\]"),
    ("relapse_window", 0.0, r"burst.relapse_window = 0.0 is out of range \(0.0, 3600.0\] s"),
])
def test_settings_out_of_range_are_one_error_naming_the_field_and_range(field, value, text):
    with pytest.raises(ValueError, match=text):
        BurstTestSettings(**{field: value}).validate()


def test_supervisor_vents_a_burst_chamber_until_reset_and_logs_it_once():
    sup = Supervisor(SupervisorSettings(p_max=45e3, vent_margin=None), n=3)
    cmd = np.array([[0.7, 0.0], [0.5, 0.0], [0.0, 0.2]])
    p = np.full(3, 20e3)
    out = sup.apply(0.0, cmd, p, burst=np.array([False, True, False]))
    assert out.tolist() == [[0.7, 0.0], [0.0, 1.0], [0.0, 0.2]]
    # the flag is latched: later steps without it keep the chamber on the safe command
    for k in range(1, 4):
        out = sup.apply(0.01 * k, cmd, p)
        assert out[1].tolist() == [0.0, 1.0] and out[0].tolist() == [0.7, 0.0]
    assert sup.counts["burst"] == 4
    assert [(e.chamber, e.cause) for e in sup.events] == [(1, "burst")]
    sup.reset()
    assert sup.apply(1.0, cmd, p)[1].tolist() == [0.5, 0.0]


def test_robot_settings_burst_sigma_sets_the_threshold_and_zero_turns_the_test_off():
    assert RobotSettings().burst.threshold == BurstTestSettings().threshold
    assert RobotSettings(burst_sigma=80.0).validate().burst.threshold == 80.0
    low = RobotSettings(burst_sigma=10.0).validate().burst
    assert low.threshold == 10.0 and low.step_cap == pytest.approx(4.0)  # two readings at the cap cannot flag
    assert _periods_to_flag(-1e6, s=low) == 3
    assert RobotSettings(burst_sigma=0.0).validate().burst is None
    with pytest.raises(ValueError, match=r"robot.burst_sigma = -1.0 is out of range \[0.0, 10000.0\] sigma"):
        RobotSettings(burst_sigma=-1.0).validate()


def test_robot_table_burst_sigma_out_of_range_is_one_error_naming_the_key_in_sigma():
    from hbma_ctrl.app.schema import parse_role

    with pytest.raises(ValueError, match=r"burst_sigma.*-3.*\[0, 10000\] sigma"):
        parse_role("robot", {"burst_sigma": -3})
    assert parse_role("robot", {"burst_sigma": 0}).burst is None
    assert parse_role("robot", {}).burst_sigma == BurstTestSettings().threshold
