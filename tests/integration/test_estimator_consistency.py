"""NEES/NIS consistency of the EKF on Monte-Carlo runs against the mismatched rig (chi-square bounds).

Each run (one noise seed) gives a time-averaged NEES of (h, F) and NIS of the pressure; the mean of
the M run values must lie inside the two-sided 95 % chi-square bounds chi2(M n) / M (n = 2 for the
NEES, 1 for the NIS). Scenes: the fig. 7 rig (r1 12.5 mm, t0 3 mm) carrying 400 g and 600 g, and a
small free chamber (r1 7.5 mm, no load, which the filter must see lift at once although it does
not know the load), at 60 % pump speed. The rig is the default truth (the exact membrane, valve
timing, pump shape, sensor lag) and the filter its default (the exact law, the datasheet delays).
With the reported heights' model-form error at 4 % (``output_rel_std``, the default until the
filter took the exact law) 600 g was under-confident, NEES 0.56-0.61 against the bound 0.73: its
height errors were 0.1 mm for a reported sigma of 0.24 mm. At 2 % the three scenes read 1.29, 1.00
and 2.74 when measured. (Not consistent yet: free inflation of the large chamber is under-confident
and fast lift-offs of small loaded chambers over-confident: see estimators/ekf.py.)
"""

import numpy as np
import pytest
from scipy.stats import chi2

from checkout import ROOT
from hbma_ctrl.estimators.common import FilterSettings
from hbma_ctrl.app.scenes.evaluate import run_filter
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.sim.rig import RigSettings, simulate_rig
from hbma_ctrl.sim.trial import InputSchedule, Trial

pytestmark = pytest.mark.slow

M = 6


@pytest.mark.parametrize("load,r1", [
    (0.4, 12.5e-3),
    (0.6, 12.5e-3),
    (0.0, 7.5e-3)])
def test_nees_and_nis_inside_chi_square_bounds(load, r1):
    tr = Trial(Actuator(r1=r1), Pneumatics(), Platform(load=load, own_mass=0.02 if load else 0.0),
               InputSchedule.inflate_deflate(0.6, 3.0), 5.0, "mc")
    nees, nis = [], []
    for seed in range(M):
        (rec,) = simulate_rig([tr], RigSettings(seed=100 + seed))
        r = run_filter("ekf", tr, rec, FilterSettings())
        nees.append(np.nanmean(r.nees))
        nis.append(np.nanmean(r.nis))
    lo, hi = chi2.ppf([0.025, 0.975], 2 * M) / M
    assert lo < np.mean(nees) < hi
    lo, hi = chi2.ppf([0.025, 0.975], M) / M
    assert lo < np.mean(nis) < hi


def test_full_protocol_requirements(tmp_path):
    """The estimator's requirements (height NRMSD <= 0.05, at most half the open loop in every scenario,
    steady force error <= 10 %) over the 150-trial protocol on the mismatched rig (about 20 s on 2
    workers)."""

    from hbma_ctrl.app.scenes.runner import run_scenario
    from hbma_ctrl.app.scenario import load_scenario

    path = ROOT / "scenarios" / "ekf_protocol.toml"
    est = run_scenario(load_scenario(path), tmp_path)["estimator"]
    assert est["n_trials"] == 150
    assert est["height_nrmsd"] <= 0.05
    # "at most half the open loop in every scenario" (t0 x r1 x load, mean over speeds)
    assert est["n_scenarios"] == 30
    assert est["scenarios_at_half_open_loop"] == 30
    assert est["scenario_ratio_to_open_loop_max"] <= 0.5
    assert est["force_steady_rel_err_mean"] <= 0.10


def _calibrated(tmp_path, name: str) -> dict:
    from hbma_ctrl.app.scenes.runner import run_scenario
    from hbma_ctrl.app.scenario import load_scenario

    path = ROOT / "scenarios" / name
    est = run_scenario(load_scenario(path), tmp_path)["estimator"]
    assert est["n_trials"] == 150 and est["n_scenarios"] == 30
    return est


# the calibrated protocols each take as long as the nominal one: they run with the sweeps (`pytest -m
# sweep`), as the golden metrics of every scenario do, and CI keeps the nominal protocol's requirements
@pytest.mark.sweep
def test_calibrated_protocol_meets_the_exact_membrane_goal(tmp_path):
    """The EKF's goal on the exact membrane (height NRMSD <= 0.02, at most half the open loop in every
    scenario) on the default rig, with the filter's factor prior from `hbma-ctrl fit` of another
    recording of that rig (scenarios/ekf_protocol_calibrated.toml; 0.031 with the nominal prior,
    ekf_protocol.toml)."""
    est = _calibrated(tmp_path, "ekf_protocol_calibrated.toml")
    assert est["height_nrmsd"] <= 0.02
    assert est["scenarios_at_half_open_loop"] == 30 and est["scenario_ratio_to_open_loop_max"] <= 0.5
    assert est["force_steady_rel_err_mean"] <= 0.05


@pytest.mark.sweep
def test_calibrated_soft_protocol_nrmsd_within_the_goal(tmp_path):
    """The soft rig (modulus x0.85), calibrated the same way: NRMSD <= 0.02 (0.029 with the nominal
    prior); its open loop's errors cancel, and one scenario of 30 stays above half of it (ratio 0.63)."""
    est = _calibrated(tmp_path, "ekf_protocol_soft_calibrated.toml")
    assert est["height_nrmsd"] <= 0.02
    assert est["scenarios_at_half_open_loop"] >= 29
