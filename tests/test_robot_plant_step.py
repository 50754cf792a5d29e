"""The robot rig's period as one casadi Function (hbma_ctrl.robot.plant_step) against RobotRig itself,
and the load sharing Function against hbma_ctrl.robot.statics.load_sharing."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from hbma_ctrl.core.params import Pneumatics
from hbma_ctrl.robot.design import RobotDesign
from hbma_ctrl.robot.plant_step import load_sharing_function, robot_rig_step_function
from hbma_ctrl.robot.rig import RobotRig, RobotRigSettings
from hbma_ctrl.robot.statics import load_sharing
from hbma_ctrl.sim.rig import IDEAL_STRUCTURE

DESIGN = RobotDesign(n_layers=2).validate()


def test_load_sharing_function_equals_the_numpy_statics_over_poses_and_tip_loads():
    """Level layers (the bend's direction undefined), one chamber up, random poses up to 17 mm, with
    and without a tip force and moment: the same forces (and tip) to rounding."""
    f = load_sharing_function(DESIGN)
    rng = np.random.default_rng(0)
    poses = [np.zeros(6), np.full(6, 4e-3), np.array([17e-3, 0, 0, 0, 0, 0]), np.array([0, 0, 0, 0, 17e-3, 17e-3])]
    poses += [rng.uniform(0.0, 17e-3, 6) for _ in range(30)]
    for i, h in enumerate(poses):
        ft = np.zeros(3) if i % 2 == 0 else rng.normal(0.0, 0.1, 3)
        mt = np.zeros(3) if i % 3 == 0 else rng.normal(0.0, 2e-3, 3)
        ref = load_sharing(DESIGN, h.reshape(2, 3), ft, mt)
        F, tip = (np.asarray(v).ravel() for v in f(h, ft, mt))
        np.testing.assert_allclose(F, ref.forces.ravel(), rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(tip, ref.pose.tip_position, rtol=1e-12, atol=1e-15)


def _run(rig: RobotRig, periods: int, seed: int):
    """The Function and the rig side by side on the same commands: the largest relative differences
    of the states, modes, lagged readings, parameters (loads, moving masses) and shared forces, and the
    modes seen and the largest height, m."""
    fn = robot_rig_step_function(rig)
    n = rig.n
    X, mode, th = rig.plant.X.copy(), rig.plant.mode[None, :].copy(), rig.plant.thetas.copy()
    hist = np.zeros((fn.size1_in(3), n))
    ps, pp = rig._p_sensed[None, :].copy(), rig._p_prev[None, :].copy()
    rng = np.random.default_rng(seed)
    worst, modes, h_max = {}, set(), 0.0
    for k in range(periods):
        # pump hard (the chambers lift, the layers tilt), then vent (back to rest), with noise in both
        pump = k < 2 * periods // 3
        U = np.vstack([rng.uniform(0.6, 1.0, n), rng.uniform(0.6, 1.0, n) * pump,
                       rng.uniform(0.5, 1.0, n) * (not pump)])
        X, mode, y, hist, th, ps, pp, F = (np.asarray(o) for o in fn(X, mode, U, hist, th, ps, pp, np.zeros(3)))
        rig.apply(U)
        modes |= set(rig.plant.mode.tolist())
        h_max = max(h_max, float(rig.plant.output("h").max()))
        for key, a, b in (("X", X, rig.plant.X), ("mode", mode.ravel(), rig.plant.mode),
                          ("p_sensed", ps.ravel(), rig._p_sensed), ("theta", th, rig.plant.thetas),
                          ("F", F.ravel(), rig.loads)):
            scale = np.abs(b).max(axis=-1, keepdims=True) + 1e-300
            worst[key] = max(worst.get(key, 0.0), float(np.max(np.abs(a - b) / scale)))
    return worst, modes, h_max


@pytest.mark.parametrize("topology", ["per_chamber", "shared"])
def test_robot_rig_step_follows_the_rig_through_lift_off_and_touch_down(topology):
    """The default robot rig (platform chambers, valve delay and minimum opening, tilted pump, sensor
    lag): 120 periods of the Function and of RobotRig.apply on the same commands agree to 1e-9 of each
    quantity's scale, through lift-offs and touch-downs; a shared pump's manifold included."""
    rig = RobotRig(DESIGN, Pneumatics(), 50e3, topology, RobotRigSettings(noise_std=0.0))
    worst, modes, h_max = _run(rig, 120, 1)
    assert modes == {0.0, 1.0} and h_max > 1.5e-3  # the run lifted and came back to rest
    assert all(v < 1e-9 for v in worst.values()), worst


def test_robot_rig_step_without_valve_timing_and_refused_for_the_quasi_static_rig():
    rig = RobotRig(DESIGN, Pneumatics(), 50e3, "per_chamber", RobotRigSettings(noise_std=0.0, **IDEAL_STRUCTURE))
    worst, _, _ = _run(rig, 30, 2)
    assert all(v < 1e-9 for v in worst.values()), worst
    fn = robot_rig_step_function(rig)
    cg = ca.CodeGenerator("robot_rig_step_check.c")
    cg.add(fn)  # one generable Function (no Python callbacks)
    assert "robot_rig_step" in cg.dump()
    qs = RobotRig(DESIGN, Pneumatics(), 50e3, "per_chamber", RobotRigSettings(fidelity="quasi_static"))
    with pytest.raises(ValueError, match=r"\[rig\] fidelity = 'quasi_static'"):
        robot_rig_step_function(qs)
