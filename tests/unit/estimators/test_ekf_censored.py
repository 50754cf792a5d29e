"""The lift-off detector and the sensor's range: readings just under the range are a sample biased
low (the clipped ones are taken out as saturated), and must not be read as a membrane lifting."""

from __future__ import annotations

import numpy as np
import pytest

from hbma_ctrl.app.scenes.evaluate import run_filter, score
from checkout import ROOT
from hbma_ctrl.app.scenario import load_scenario
from hbma_ctrl.system.sections import filter_settings_for
from hbma_ctrl.sim.rig import simulate_rig

pytestmark = pytest.mark.slow


def test_readings_under_the_range_do_not_fire_a_lift_off_below_it(tmp_path):
    """800 g on the 7.5 mm, 2 mm chamber at full speed (protocol trial t2_r7.5_m800_s100, its own
    noise stream): the platform lifts at 45 kPa, above the 35 kPa range. The filter stays resting
    until the readings saturate, its load keeps the nominal 8.04 N, and its height error stays
    within 0.5 mm (it once declared a lift-off at 34 kPa, a load of 6 N and a 2 mm height)."""
    scn = load_scenario(ROOT / "scenarios" / "ekf_protocol.toml")
    rig = scn.role("rig")
    fs = filter_settings_for(scn.role("estimator"), rig)
    trials = scn.trials()
    i = [t.name for t in trials].index("t2_r7.5_m800_s100")
    (rec,) = simulate_rig([trials[i]], rig, [i])
    r = run_filter("ekf", trials[i], rec, fs)
    near = rec.meas > fs.sensor_range - 3.0 * fs.noise_std
    assert np.any(near & (rec.meas < fs.sensor_range))  # the case: unclipped readings near the range
    lifted = np.array(["lift_off" in f for f in r.flags])
    assert not np.any(lifted & (rec.meas < fs.sensor_range))
    assert np.nanmax(np.abs(r.est["W"] - r.est["W"][0])) < 0.5
    assert np.nanmax(np.abs(r.est["h"] - rec.truth["h"])) < 0.5e-3
    assert score(r, trials[i])["height_rmse_mm"] < 0.05
