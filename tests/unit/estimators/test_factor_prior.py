"""The filter's prior on its pump-flow, modulus and dead-volume factors ([estimator] *_init, *_init_std):
where the filter starts, what the start-up calibration starts from, and the keys' errors."""

from __future__ import annotations

import numpy as np
import pytest

from hbma_ctrl.estimators.common import FACTOR_RANGE, FilterSettings
from hbma_ctrl.estimators.ekf import EKF
from hbma_ctrl.app.schema.document import parse_role
from hbma_ctrl.core.interfaces import Command
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.runtime.calibrate import CalibrationSettings


def test_ekf_starts_at_the_prior_factors_with_their_spreads():
    s = FilterSettings(flow_factor_init=0.9, modulus_init=1.2, dead_volume_init=1.1, flow_factor_init_std=0.05,
                       modulus_init_std=0.04, dead_volume_init_std=0.03).validate()
    f = EKF(Actuator(), Pneumatics(), s)
    f.step(0.0, 0.0, Command(0.0, 0.0, 0.0))  # the first reading: the prior, then its update at rest
    names = list(f.state_names)
    idx = [names.index(n) for n in ("b", "k", "c")]
    # a vented, resting chamber's reading says nothing about k and only b / c while pumping: the
    # factors stay where the prior put them
    np.testing.assert_allclose(f.x[idx], [0.9, 1.2, 1.1], atol=1e-6)
    np.testing.assert_allclose(np.sqrt(np.diag(f.P)[idx]), [0.05, 0.04, 0.03], rtol=1e-3)


def test_the_gas_mass_prior_does_not_depend_on_the_dead_volume_factor():
    # the state's gas mass is referred to the nominal dead volume (hbma_ctrl.models.chamber): the
    # same reading gives the same m whatever c the prior holds
    ms = []
    for c in (1.0, 1.3):
        f = EKF(Actuator(), Pneumatics(), FilterSettings(dead_volume_init=c).validate())
        f.step(0.0, 2000.0, Command(0.0, 0.0, 0.0))
        ms.append(f.x[0])
    assert ms[0] == pytest.approx(ms[1], rel=1e-9)


@pytest.mark.parametrize("key,value", [("modulus_init", 3.0), ("flow_factor_init", 0.2), ("dead_volume_init_std", -1.0)])
def test_prior_keys_out_of_range_are_one_error(key, value):
    with pytest.raises(ValueError) as exc:
        parse_role("estimator", {key: value})
    msg = str(exc.value)
    assert f"[estimator] {key} = " in msg and ("[0.5, 2]" in msg or "[0, 10]" in msg), msg


def test_prior_keys_reach_the_filter_settings():
    sec = parse_role("estimator", {"modulus_init": 1.15, "dead_volume_init": 1.2, "flow_factor_init_std": 0.05})
    assert sec.tuning == {"modulus_init": 1.15, "dead_volume_init": 1.2, "flow_factor_init_std": 0.05}
    assert FACTOR_RANGE == (0.5, 2.0)


def test_startup_calibration_starts_from_the_estimators_prior():
    from hbma_ctrl.app.bench.mpc import default_section
    from hbma_ctrl.system.roles import make_calibration
    from hbma_ctrl.sim.rig import RigSettings

    s = FilterSettings(flow_factor_init=0.9, modulus_init=1.15, dead_volume_init=1.2, modulus_init_std=0.05).validate()
    est = EKF(Actuator(), Pneumatics(), s)
    cal = make_calibration(Actuator(), Pneumatics(), Platform(), default_section(), RigSettings(), est)
    assert cal.settings.prior_mean == (0.9, 1.15, 1.2)
    assert cal.settings.prior_std == (s.flow_factor_init_std, 0.05, s.dead_volume_init_std)
    with pytest.raises(ValueError, match=r"prior_mean\[1\]"):
        CalibrationSettings(prior_mean=(1.0, 2.5, 1.0)).validate()
