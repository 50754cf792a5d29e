"""Minimum on-time shaping of the valve duties (hbma_ctrl.runtime.pwm) and its place in the chamber
loop: every duty sent is 0 or at least the minimum, small duties pass on average, a shut valve
stays shut, and a minimum longer than the period is refused naming the key in ms."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hbma_ctrl.core.interfaces import Command
from hbma_ctrl.runtime.pwm import MinOnTime

T, MIN_ON = 0.01, 0.002  # 10 ms PWM period, 2 ms minimum opening: minimum duty 0.2


def test_duties_at_or_above_the_minimum_and_zero_pass_unchanged():
    pwm = MinOnTime(T, MIN_ON)
    for c in (Command(0.3, 1.0, 0.0), Command(1.0, 0.2, 0.5), Command(0.0, 0.0, 0.0)):
        assert pwm.shape(c) == c


@settings(max_examples=50, deadline=None)
@given(d_in=st.floats(1e-4, 0.1999), d_out=st.floats(1e-4, 0.1999), n=st.integers(20, 200))
def test_small_duties_are_sent_as_minimum_pulses_that_average_to_the_duty_asked(d_in, d_out, n):
    """Any duty below the minimum held for n periods: each period sends 0 or the minimum (what the
    valve can do), and the mean sent is within half a minimum pulse over n periods of the duty asked."""
    pwm = MinOnTime(T, MIN_ON)
    sent = np.array([pwm.shape(Command(0.7, d_in, d_out)).as_array() for _ in range(n)])
    assert np.all(sent[:, 0] == 0.7)  # the pump's speed is not a valve
    for i, d in ((1, d_in), (2, d_out)):
        assert set(np.unique(sent[:, i])) <= {0.0, 0.2}
        assert abs(sent[:, i].mean() - d) <= 0.5 * 0.2 / n + 1e-12


def test_a_shut_command_clears_the_carry_so_no_pulse_follows():
    pwm = MinOnTime(T, MIN_ON)
    pwm.shape(Command(1.0, 0.09, 0.0))  # 0.09 < 0.1: nothing sent yet, 0.09 owed
    assert pwm.shape(Command(0.0, 0.0, 1.0)).inlet == 0.0  # the vent
    assert pwm.shape(Command(1.0, 0.09, 0.0)).inlet == 0.0  # the old debt is gone


def test_no_minimum_is_inactive():
    assert not MinOnTime(T, 0.0).active


def test_minimum_longer_than_the_period_is_refused():
    with pytest.raises(ValueError, match="valve_min_on"):
        MinOnTime(T, 0.02)


def test_scene_refuses_a_minimum_longer_than_the_rig_period_naming_the_key_in_ms():
    from hbma_ctrl.system.roles import make_pwm
    from hbma_ctrl.app.schema import parse_role

    sec = parse_role("controller", {"targets_mm": [[0.0, 2.0]], "valve_min_on_ms": 15.0})
    with pytest.raises(ValueError, match=r"valve_min_on_ms = 15 is out of range \[0, 10\] ms"):
        make_pwm(sec, T)
    assert make_pwm(parse_role("controller", {"targets_mm": [[0.0, 2.0]], "valve_min_on_ms": 0.0}), T) is None
    assert make_pwm(parse_role("controller", {"targets_mm": [[0.0, 2.0]]}), T).min_duty == pytest.approx(0.002 / T)  # the default, 2 ms


def test_schema_refuses_a_negative_minimum_naming_the_key():
    from hbma_ctrl.app.schema import parse_role

    with pytest.raises(ValueError, match="valve_min_on_ms"):
        parse_role("controller", {"targets_mm": [[0.0, 2.0]], "valve_min_on_ms": -1.0})


def test_chamber_loop_sends_and_estimates_with_the_shaped_duties_every_tick():
    """Controller every 2 ticks asking a 5 % inlet duty: every tick's command is shaped (0 or 0.2),
    the controller sees what it asked, and the estimator is handed what was sent."""
    from hbma_ctrl.core.interfaces import ControllerBase, Estimate, EstimatorBase
    from hbma_ctrl.runtime.chamber import ChamberLoop, chamber_supervisor

    class Ctrl(ControllerBase):
        def step(self, t, est, ref):
            return Command(0.5, 0.05, 0.0)

    class Est(EstimatorBase):
        def __init__(self):
            self.held = []

        def step(self, t, z, cmd):
            self.held.append(cmd)
            return Estimate(t=t, h1=0.0, h2=0.0, h=0.0, F=0.0, p=z)

    from hbma_ctrl.controllers.mpc_settings import MPCSettings

    est = Est()
    loop = ChamberLoop(est, Ctrl(), chamber_supervisor(MPCSettings()), every=2, pwm=MinOnTime(T, MIN_ON))
    sent = [loop.tick(k * T, 1000.0) for k in range(40)]
    inlets = np.array([c.inlet for c in sent])
    assert set(np.unique(inlets)) == {0.0, 0.2}
    assert abs(inlets.mean() - 0.05) <= 0.1 / 40 + 1e-12
    assert loop.wanted.inlet == pytest.approx(0.05)
    assert [c.inlet for c in est.held[1:]] == list(inlets[:-1])


def test_n_chambers_at_once_shape_as_one_shaper_per_chamber():
    rng = np.random.default_rng(7)
    n = 5
    many = MinOnTime(0.01, 0.002)
    ones = [MinOnTime(0.01, 0.002) for _ in range(n)]
    for _ in range(200):
        U = rng.uniform(0, 1, (3, n)) * (rng.random((3, n)) < 0.7) * rng.choice([1.0, 0.15], (3, n))
        got = many.shape_inputs(U)
        for i, one in enumerate(ones):
            c = one.shape(Command(*U[:, i]))
            assert np.array_equal(got[:, i], [c.speed, c.inlet, c.outlet])
        assert np.array_equal(got[0], U[0])  # the pump's speed is not a valve


def test_one_chambers_shaping_follows_the_numpy_oracle_bit_for_bit():
    """MinOnTime.shape (its Function, the one a generated chamber loop runs) over 400 periods of random
    commands, duties at 0, at the minimum and at half of it among them: the same commands and carries
    as the numpy oracle, duties under the minimum shaped, not only passed through."""
    from oracles.pwm import MinOnTimeOracle

    pwm, oracle = MinOnTime(T, MIN_ON), MinOnTimeOracle(T, MIN_ON)
    m = pwm.min_duty
    rng = np.random.default_rng(5)
    small = 0
    for k in range(400):
        u = rng.random(3) * (rng.random(3) < 0.6) * np.where(rng.random(3) < 0.5, 0.3, 1.0)
        if k % 5 == 0:
            u[rng.integers(1, 3)] = rng.choice([0.0, m, 0.5 * m])
        small += int(0 < u[1] < m)
        assert pwm.shape(Command(*u)) == oracle.shape(Command(*u)), k
        assert np.array_equal(pwm.carry, oracle.carry), k
    assert small > 5
