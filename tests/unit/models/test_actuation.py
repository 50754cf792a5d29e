"""Valve and sensor delays as dead times on the commands (hbma_ctrl.models.actuation): the averaged
acting command against a brute-force integral of the held commands, its bounds, and the split
between the pump's speed (sensor delay only) and the valves (both)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hbma_ctrl.models.actuation import CommandTiming, acting_average

T = 0.01


def brute(history: list, u_new: np.ndarray, k: int, delay: float, n: int = 20000) -> np.ndarray:
    """Midpoint integral over the window of the held-command function, divided by its length."""
    span = k * T
    tau = -span - delay + (np.arange(n) + 0.5) * span / n  # times at which the command was sent
    out = np.zeros((n, len(u_new)))
    for i, s in enumerate(tau):
        if s > -span:
            out[i] = u_new
        else:
            j = int(np.ceil((-span - s) / T - 1e-12))  # 1: the last history period
            out[i] = history[-min(j, len(history))] if history else u_new
    return out.mean(axis=0)


def test_no_delay_is_the_command_itself():
    u = np.array([0.3, 1.0, 0.0])
    assert np.array_equal(acting_average([np.ones(3)], u, 1, T, 0.0), u)


def test_delay_of_one_period_is_the_previous_command():
    prev, u = np.array([1.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])
    assert np.allclose(acting_average([prev], u, 1, T, T), prev)


def test_delay_of_0p8_period_mixes_80_percent_of_the_previous_command():
    prev, u = np.array([0.0, 0.0, 1.0]), np.array([1.0, 1.0, 0.0])
    assert np.allclose(acting_average([prev], u, 1, T, 0.8 * T), 0.8 * prev + 0.2 * u)


def test_delay_over_two_periods_reaches_the_older_commands():
    """17 ms at 10 ms periods: the window [-27, -17] ms covers 7 ms of the older command (held up
    to -20 ms) and 3 ms of the last one (-20 to -10 ms)."""
    old, last, u = np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0])
    got = acting_average([old, last], u, 1, T, 0.017)
    assert np.allclose(got, 0.7 * old + 0.3 * last)


@pytest.mark.slow
@settings(max_examples=60, deadline=None)
@given(hist=st.lists(st.lists(st.floats(0.0, 1.0), min_size=3, max_size=3), min_size=0, max_size=12),
       u=st.lists(st.floats(0.0, 1.0), min_size=3, max_size=3),
       k=st.integers(1, 5), delay=st.floats(0.0, 0.1))
def test_average_matches_the_integral_of_the_held_commands_and_stays_in_range(hist, u, k, delay):
    """Any history, any k, any delay in [0, 100] ms: the average equals the integral of the held
    commands over the window (to the brute force's resolution) and never leaves [min, max] of the
    commands (a plant refuses a command past 1)."""
    hist = [np.array(h) for h in hist]
    u = np.array(u)
    got = acting_average(hist, u, k, T, delay)
    assert np.allclose(got, brute(hist, u, k, delay), atol=2e-4)
    allv = np.vstack(hist + [u])
    assert np.all(got >= allv.min(axis=0)) and np.all(got <= allv.max(axis=0))


def test_timing_delays_the_valves_by_both_and_the_speed_by_the_sensor_only():
    """valve 5 ms + sensor 3 ms: the valves lag 8 ms (80 % of the period still the old command),
    the pump's speed 3 ms (30 %)."""
    tm = CommandTiming(T, valve_delay=0.005, sensor_delay=0.003)
    tm.acting(np.array([0.0, 0.0, 1.0]), 0)  # the vent held before
    got = tm.acting(np.array([1.0, 1.0, 0.0]), 1)
    assert np.allclose(got, [0.7, 0.2, 0.8])
    assert np.allclose(tm.acting(np.array([1.0, 1.0, 0.0]), 1), [1.0, 1.0, 0.0])


def test_timing_without_delays_is_inactive_and_returns_the_command():
    tm = CommandTiming(T)
    assert not tm.active
    assert np.array_equal(tm.acting(np.array([0.5, 1.0, 0.0]), 1), [0.5, 1.0, 0.0])


@pytest.mark.parametrize("kw, key", [({"valve_delay": 0.2}, "valve_delay"), ({"sensor_delay": -1e-3}, "sensor_delay")])
def test_bad_delays_name_the_key(kw, key):
    with pytest.raises(ValueError, match=key):
        CommandTiming(T, **kw)


def test_ekf_with_delays_is_the_ekf_fed_the_acting_commands():
    """The filter's delays enter through its commands only: an EKF with 5 + 3 ms gives, step for
    step, what an EKF without them gives when fed the acting commands."""
    from hbma_ctrl.estimators.ekf import EKF, EKFSettings
    from hbma_ctrl.core.interfaces import Command
    from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
    from hbma_ctrl.sim.rig import Rig, RigSettings

    act, pn = Actuator(), Pneumatics()
    rig = Rig(act, pn, Platform(), RigSettings(seed=4, valve_delay=0.005, sensor_tau=0.003))
    timed = EKF(act, pn, EKFSettings(valve_delay=0.005, sensor_delay=0.003))
    plain = EKF(act, pn, EKFSettings(valve_delay=0.0, sensor_delay=0.0))
    tm = CommandTiming(T, 0.005, 0.003)
    cmd = Command(0.0, 0.0, 1.0)
    for k in range(50):
        z = rig.measure()
        a = timed.step(k * T, z, cmd)
        b = plain.step(k * T, z, Command(*tm.acting(cmd.as_array(), 1 if k else 0)))
        assert (a.h, a.p, a.F) == (b.h, b.p, b.F)
        cmd = Command(0.8, 1.0, 0.0) if 5 <= k < 30 else Command(0.0, 0.0, 0.3 if k > 40 else 0.0)
        rig.apply(cmd)
    assert a.h > 1e-3  # the membrane did inflate


@settings(max_examples=40, deadline=None)
@given(st.floats(0.0, 0.1), st.floats(0.0, 0.1), st.lists(st.lists(st.floats(0.0, 1.0), min_size=3, max_size=3),
                                                         min_size=1, max_size=30))
def test_timing_with_a_full_history_gives_acting_averages_value(valve_delay, sensor_delay, commands):
    """The one-period step on a full history (precomputed weights) gives what acting_average gives for
    the same commands, over the whole delay range, within rounding; the result stays within [0, 1]."""
    tm = CommandTiming(T, valve_delay, sensor_delay)
    hist: list = []
    for k, c in enumerate(commands):
        u = np.array(c)
        got = tm.acting(u, 1 if k else 0)
        want = u.copy()
        if k and tm.active:
            want[0] = acting_average([h[:1] for h in hist], u[:1], 1, T, sensor_delay)[0]
            want[1:] = acting_average([h[1:] for h in hist], u[1:], 1, T, valve_delay + sensor_delay)
        hist = (hist + [u])[-tm._keep:]
        assert np.allclose(got, want, rtol=0, atol=1e-12) and np.all((got >= 0) & (got <= 1))


def test_n_chambers_at_once_act_as_one_timing_per_chamber():
    """A 3 x n command (the robot's bank) is timed column by column as n single-chamber timings."""
    rng = np.random.default_rng(3)
    n = 4
    many = CommandTiming(0.01, 0.005, 0.003)
    ones = [CommandTiming(0.01, 0.005, 0.003) for _ in range(n)]
    for k in [0, 1, 1, 2, 1, 1, 3, 1, 1, 1, 5, 1]:
        U = rng.uniform(0, 1, (3, n))
        got = many.acting(U, k)
        assert got.shape == (3, n)
        for i, one in enumerate(ones):
            assert np.allclose(got[:, i], one.acting(U[:, i], k), rtol=0, atol=1e-12)
