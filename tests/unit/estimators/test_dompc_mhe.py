"""do-mpc's MHE beside the package's on the same samples (the `bench` extra; skipped without do-mpc)."""

import numpy as np
import pytest

from hbma_ctrl.core import interrupt
from hbma_ctrl.core.params import Platform
from hbma_ctrl.estimators.common import FilterSettings
from hbma_ctrl.estimators.mhe import MHESettings
from hbma_ctrl.sim.batch import protocol_trials
from hbma_ctrl.sim.rig import RigSettings, simulate_rig

pytest.importorskip("do_mpc")


@pytest.mark.slow
def test_compare_dompc_reports_both_step_times_their_ratio_and_a_pressure_difference_and_checks_each_step():
    from hbma_ctrl.estimators.dompc_mhe import compare_dompc

    trials = protocol_trials("nh", platform=Platform(own_mass=0.02), loads_g=(0.0,), speeds_pct=(100.0,),
                             r1_mm=(12.5,))
    rig = RigSettings(seed=0)
    fs = FilterSettings(sample_period=rig.sample_period, sensor_range=rig.sensor_range, noise_std=rig.noise_std)
    s = MHESettings(**{f: getattr(fs, f) for f in fs.__dataclass_fields__}, horizon=5).validate()
    rec = simulate_rig(trials[:1], rig)[0]
    checks = []
    interrupt.set_check(lambda: checks.append(1))
    try:
        out = compare_dompc(trials[0], rec, s, steps=3)
    finally:
        interrupt.set_check(None)
    assert out["dompc_steps"] == 3 and len(checks) >= 3  # a signal may end it between do-mpc's steps
    assert out["dompc_mhe_step_us_median"] > 0 and out["dompc_compare_mhe_step_us_median"] > 0
    assert out["dompc_mhe_over_mhe_speed"] == pytest.approx(
        out["dompc_mhe_step_us_median"] / out["dompc_compare_mhe_step_us_median"])
    assert np.isfinite(out["dompc_vs_mhe_pressure_rms_pa"])
