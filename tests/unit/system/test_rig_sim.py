"""The ``sim`` rig backend: lockstep time, deterministic readings, the RigIO contract, chamber and robot."""

from __future__ import annotations

import numpy as np
import pytest

from hbma_ctrl.system.sim_rig import SimRig
from hbma_ctrl.system.rigio import RigIO, safe_u
from hbma_ctrl.system.sections import RobotSettings
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.robot.design import RobotDesign, RobotPneumatics
from hbma_ctrl.robot.rig import RobotRigSettings
from hbma_ctrl.sim.rig import RigSettings

ACT, PN = Actuator(), Pneumatics()
INFLATE = np.array([[1.0], [1.0], [0.0]])


def chamber(seed=1, load=0.4, **kw):
    return SimRig.chamber(ACT, PN, Platform(load=load), RigSettings(seed=seed), **kw)


def run(rig, steps, u):
    out = []
    for _ in range(steps):
        r = rig.read()
        out.append((r.t, r.seq, r.p.copy()))
        rig.write(u)
    return out


def test_chamber_is_a_rigio_with_one_chamber():
    rig = chamber()
    assert isinstance(rig, RigIO)
    assert rig.n == 1 and rig.sample_period == pytest.approx(0.01) and rig.sensor_range == pytest.approx(35e3)


def test_same_seed_same_readings_other_seed_other_readings():
    a, b, c = run(chamber(1), 60, INFLATE), run(chamber(1), 60, INFLATE), run(chamber(2), 60, INFLATE)
    pa, pb, pc = (np.array([x[2][0] for x in r]) for r in (a, b, c))
    assert np.array_equal(pa, pb)
    assert [x[:2] for x in a] == [x[:2] for x in b]
    assert not np.array_equal(pa, pc)


def test_each_write_advances_exactly_one_period():
    rig = chamber()
    rows = run(rig, 25, INFLATE)
    assert [r[0] for r in rows] == [k * 0.01 for k in range(25)]  # exact, no accumulated rounding
    assert [r[1] for r in rows] == list(range(25))
    assert rig.t == 25 * 0.01 and rig.truth()["t"] == pytest.approx(0.25, abs=1e-12)
    assert rig.truth()["p"] > 5e3  # the pump did inflate it


def test_a_second_read_in_the_same_period_repeats_the_packet_as_not_fresh():
    rig = chamber()
    first, again = rig.read(), rig.read()
    assert first.fresh.tolist() == [True] and again.fresh.tolist() == [False]
    assert again.seq == first.seq and np.array_equal(again.p, first.p)
    rig.write(INFLATE)
    assert rig.read().fresh.tolist() == [True]


@pytest.mark.parametrize("u", [np.zeros((3, 2)), np.array([[1.5], [0.0], [0.0]]), np.array([[np.nan], [0], [0]])])
def test_bad_commands_are_refused(u):
    with pytest.raises(ValueError, match="rig command"):
        chamber().write(u)


def test_load_steps_land_at_their_rig_time():
    rig = chamber(load=0.4, load_steps=((0.05, 0.6),))
    run(rig, 5, INFLATE)
    assert rig.rig.platform.load == pytest.approx(0.6)
    rig2 = chamber(load=0.4, load_steps=((0.05, 0.6),))
    run(rig2, 4, INFLATE)
    assert rig2.rig.platform.load == pytest.approx(0.4)


def test_safe_holds_the_safe_command_and_close_ends_the_run():
    rig = chamber()
    rig.write(INFLATE)
    rig.safe()
    assert np.array_equal(rig.held, safe_u(1))
    rig.close()
    with pytest.raises(RuntimeError):
        rig.read()


def robot_rig(seed=0):
    s = RobotSettings(design=RobotDesign(n_layers=1), pneumatics=RobotPneumatics()).validate()
    return SimRig.robot(s, RobotRigSettings(seed=seed))


def test_robot_rig_every_chamber_deterministic():
    u = np.zeros((3, 3))
    u[0], u[1, 0], u[2, 1:] = 1.0, 1.0, 0.0  # pump chamber 0 only
    a, b = robot_rig(), robot_rig()
    assert a.n == 3 and isinstance(a, RigIO)
    ra, rb = run(a, 20, u), run(b, 20, u)
    pa = np.array([x[2] for x in ra])
    assert np.array_equal(pa, np.array([x[2] for x in rb]))
    assert pa.shape == (20, 3)
    assert a.t == pytest.approx(0.2, abs=1e-12) and a.truth()["t"] == pytest.approx(0.2, abs=1e-9)
    tr = a.truth()["p"]
    assert tr[0] > 2e3 and abs(tr[1]) < 1e3  # only the pumped chamber is inflated
