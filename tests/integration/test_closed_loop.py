"""Closed loop on the mismatched rig: rig -> EKF -> controller -> rig (and an oracle estimate to
separate the controller's share of the error from the estimator's).

The rig is the default truth (the exact membrane, valve timing, a pump map of another shape, a
sensor lag: :data:`hbma_ctrl.sim.rig.STRUCTURED_RIG`) and the roles their defaults (the exact law,
the datasheet delays and minimum opening), as the scenes run them; where a test is about the cap rig
it says so.

Each CI test simulates a few seconds with the fast (RTI) variant, on one rig noise seed or a few
(seeds 0..k, not chosen); the 0 g claim's pass rate over 20 seeds is a ``slow`` test, how often the
other cases hold over seeds is ``hbma-ctrl bench loop``. Every loop starts with the start-up
calibration (the [controller] default). No test asserts a timing.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hbma_ctrl.estimators.ekf import EKF, EKFSettings
from hbma_ctrl.app.scenes.controller import (
    closed_loop,
    loop_metrics,
    settle_results,
)
from hbma_ctrl.app.schema import parse_role
from hbma_ctrl.core.interfaces import Estimate, EstimatorBase
from hbma_ctrl.core.params import Actuator, Platform, Pneumatics
from hbma_ctrl.models.tables import PredictionModel
from hbma_ctrl.models.defaults import CAP_CHAMBER
from hbma_ctrl.sim.rig import CAP_RIG, RigSettings

ACT, PN = Actuator(), Pneumatics()


@pytest.fixture(scope="module")
def model(prediction_model):
    return prediction_model  # PredictionModel(ACT, PN): the default law, the exact membrane's


class OracleFromRig(EstimatorBase):
    """Estimate = the rig's true state (tests only): isolates the controller from the estimator."""

    def attach(self, rig):
        self.rig = rig

    def step(self, t, measurement, applied):
        tr = self.rig.truth()
        return Estimate(t=t, h1=tr["h1"], h2=tr["h2"], h=tr["h"], F=tr["F"], p=tr["p"])


def run(section_raw, load_kg, duration, model, rig=None, oracle=False, calibrate=None):
    sec = parse_role("controller", section_raw)
    log = closed_loop(ACT, PN, Platform(load=load_kg), sec, duration, rig or RigSettings(seed=3),
                      estimator=OracleFromRig() if oracle else None, model=model, calibrate=calibrate)
    return sec, log, loop_metrics(log, sec)


STEPS = [[0.0, 2.0], [2.0, 8.0], [4.5, 5.0]]


@pytest.mark.slow
@pytest.mark.parametrize("load", [0.0, 0.4])
def test_rti_with_true_state_settles_steps_within_0p3mm(model, load):
    """The controller's own share: with the true state it settles 2 -> 8 -> 5 mm on the mismatched
    rig within 0.3 mm, never above p_max."""
    sec, log, m = run({"targets_mm": STEPS, "budget_ms": 1000.0}, load, 7.0, model, oracle=True)
    assert m["steps_settled"] == 3, m["settle"]
    assert m["max_pressure_kpa"] <= 35.0 and m["fallbacks"] == 0


@pytest.mark.slow
def test_ekf_loop_400g_tracks_the_estimate_and_respects_p_max(model):
    """Full chain rig -> EKF -> RTI -> rig, 400 g: the estimate settles within 0.3 mm of each
    target (the truth's own criterion: test_ekf_loop_truth_settles_within_0p3mm)."""
    sec, log, m = run({"targets_mm": STEPS}, 0.4, 7.0, model)
    assert m["steps_settled_estimate"] == 3, m["settle_estimate"]
    assert m["max_pressure_kpa"] <= 35.0
    assert m["height_est_rmse_mm"] < 2.0


@pytest.mark.slow
def test_load_added_mid_run_is_rejected(model):
    """400 g holding 5 mm, +200 g at 2 s (true state fed back: the controller's share): the height
    dips and comes back within 0.3 mm."""
    sec, log, m = run({"targets_mm": [[0.0, 5.0]], "load_steps_g": [[2.0, 600.0]], "budget_ms": 1000.0}, 0.4,
                      4.0, model, oracle=True)
    before = log.h_true[np.searchsorted(log.t, 1.99)]
    assert abs(before - 5e-3) < 0.3e-3
    dip = np.min(log.h_true[log.t >= 2.0])
    assert dip < before - 0.3e-3  # the load did push it down
    tail = log.t >= 3.5
    assert np.all(np.abs(log.h_true[tail] - 5e-3) < 0.3e-3)
    assert m["max_pressure_kpa"] <= 35.0


@pytest.mark.slow
def test_load_added_mid_run_through_ekf(model):
    """The same through the EKF: the true height is back within 0.3 mm of 5 mm over the last
    second (it ended 0.5 mm low before the filter carried the dead volume)."""
    sec, log, m = run({"targets_mm": [[0.0, 5.0]], "load_steps_g": [[2.0, 600.0]]}, 0.4, 6.0, model)
    tail = log.t >= 5.0
    assert np.all(np.abs(log.h_true[tail] - 5e-3) < 0.3e-3)
    assert m["max_pressure_kpa"] <= 35.0


@pytest.mark.slow
def test_pressure_limit_with_dropouts_and_infeasible_target(model):
    """p_max = 20 kPa is below what 8 mm under 400 g needs on the rig: the target is clipped and
    reported, and with 20 % sensor dropouts the true pressure still never exceeds 20 kPa."""
    rig = RigSettings(seed=5, dropout_prob=0.2)
    sec, log, m = run({"targets_mm": [[0.0, 8.0]], "p_max_kpa": 20.0}, 0.4, 4.0, model, rig=rig)
    assert np.isnan(log.p_meas).sum() > 20
    assert m["max_pressure_kpa"] <= 20.0
    assert m["target_clipped_steps"] > 0
    assert np.max(log.h_true) < 8e-3


@pytest.mark.slow
def test_forced_solver_failure_stays_safe(model):
    """Every solve fails from 0.5 s to 1.3 s during the inflation: the loop first runs on the
    shifted plan, then the safe command (vents), never above p_max; it recovers afterwards (from
    the vented 0 mm back above 5 mm: on the exact membrane 400 g at 8 mm needs more than the 25 kPa
    allowed, so it climbs to the pressure limit, 5.7 mm)."""
    sec, log, m = run({"targets_mm": [[0.0, 8.0]], "fail_window_s": [0.5, 1.3], "p_max_kpa": 25.0,
                       "budget_ms": 1000.0}, 0.4, 3.5,
                      model)
    d = m["fallback_detail"]
    assert d["solver_failed"] >= 35 and d["shifted_plan"] >= 1 and d["safe_command"] >= 1
    assert m["fallbacks"] == d["shifted_plan"] + d["safe_command"]
    win = (log.t > 1.0) & (log.t < 1.3)
    assert np.all(log.u[win, 0] == 0.0) and np.all(log.u[win, 2] == 1.0)  # safe: pump off, vent
    assert m["max_pressure_kpa"] <= 25.0
    assert log.h_est[np.searchsorted(log.t, 1.3)] < 1e-3 and log.h_est[-1] > 5e-3  # back to tracking


CRITERION = {"targets_mm": [[0.0, 2.0], [3.0, 8.0], [6.0, 5.0]]}


@pytest.mark.slow
def test_ekf_loop_400g_truth_settles_within_0p3mm(model):
    """The closed-loop criterion on the truth through the EKF: 2 -> 8 -> 5 mm with 400 g on the
    mismatched rig settle within 0.3 mm, never above p_max, the calibration included."""
    sec, log, m = run(CRITERION, 0.4, 9.0, model)
    assert m["max_pressure_kpa"] <= 35.0 and m["calibration"]["status"] == "ok"
    assert m["steps_settled"] == 3, m["settle"]


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(4))
def test_ekf_loop_0g_truth_settles_within_0p3mm_on_seeds_0_to_3(model, seed):
    """The same with 0 g (the free cap) on rig seeds 0..3 (seed 0 missed the 8 mm step by 0.32 mm
    without the start-up calibration: the EKF's modulus factor settled at 1.10 for the rig's 1.15)."""
    sec, log, m = run(CRITERION, 0.0, 9.0, model, rig=RigSettings(seed=seed))
    assert m["max_pressure_kpa"] <= 35.0
    assert m["steps_settled"] == 3, (m["settle"], m["calibration"])


@pytest.mark.slow
def test_calibration_learns_the_factors_the_ekf_alone_misses(model):
    """Seeds 0-2, 0 g on the cap rig with the cap models (identification needs the model's form to be
    the rig's): with the calibration the EKF ends every run with its modulus factor within 0.03 of the
    rig's 1.15, its dead-volume factor within 0.12 of the rig's 1.2 and every step settled; without
    it, at least two runs end with one of them further off (measured: every run, k 1.185 / 1.184 /
    1.081 and c 1.53 / 1.47 / 0.86: a free inflation trades the factors along their ridge)."""
    cap_model = PredictionModel(ACT, PN, membrane="cap")
    rows = {False: [], True: []}
    for seed in range(3):
        for cal in (False, True):
            sec = replace(parse_role("controller", CRITERION), valve_min_on=0.0)
            est = EKF(ACT, PN, EKFSettings(sample_period=0.01, noise_std=200.0, sensor_range=35e3, **CAP_CHAMBER))
            log = closed_loop(ACT, PN, Platform(load=0.0), sec, 9.0, RigSettings(seed=seed, **CAP_RIG),
                              estimator=est, model=cap_model, calibrate=cal)
            rows[cal].append((float(est.x[3]), float(est.x[4]), loop_metrics(log, sec)["steps_settled"]))
    assert all(abs(k - 1.15) < 0.03 and abs(c - 1.2) < 0.12 and settled == 3 for k, c, settled in rows[True]), \
        rows[True]
    assert sum(abs(k - 1.15) > 0.03 or abs(c - 1.2) > 0.2 for k, c, _ in rows[False]) >= 2, rows[False]


@pytest.mark.sweep
def test_ekf_loop_0g_settles_on_19_of_20_seeds(model):
    """The README's 0 g claim as a pass rate: 2 -> 8 -> 5 mm through the EKF with the start-up
    calibration settles within 0.3 mm on at least 19 of rig seeds 0..19 (11 of 20 without it;
    the one miss is seed 9's 2 mm step, 0.30 mm high on a 0.03 N phantom load)."""
    passed = []
    for seed in range(20):
        sec, log, m = run(CRITERION, 0.0, 9.0, model, rig=RigSettings(seed=seed))
        assert m["max_pressure_kpa"] <= 35.0
        passed.append(m["steps_settled"] == 3)
    assert sum(passed) >= 19, [i for i, ok in enumerate(passed) if not ok]


def test_settle_results_detects_unsettled():
    class L:
        t = np.linspace(0, 2, 201)
        h_true = np.where(t < 1, 2e-3, 2.5e-3)
        h_est = h_true

    sec = parse_role("controller", {"targets_mm": [[0.0, 2.0], [1.0, 3.0]]})
    res = settle_results(L, sec.reference, 0.3e-3)
    assert res[0]["settled"] and res[0]["settle_time_s"] == 0.0
    assert not res[1]["settled"] and res[1]["final_error_mm"] == pytest.approx(-0.5)


@pytest.mark.slow
def test_scenario_run_writes_controller_metrics(tmp_path):
    """A scenario with [rig], [estimator] (UKF) and [controller] through the runner: metrics.json
    has the contract's controller keys; the CSV and the plot are written."""
    import json

    from hbma_ctrl.app.scenes.runner import run_scenario
    from hbma_ctrl.app.scenario import parse_scenario

    data = {"scenario": {"name": "cl", "duration_s": 3.5}, "load": {"mass_g": 400.0},
            "rig": {"seed": 7}, "estimator": {"filter": "ukf"},
            "controller": {"targets_mm": [[0.0, 3.0]], "p_max_kpa": 30.0}}
    scn = parse_scenario(data)
    run_scenario(scn, tmp_path)
    doc = json.loads((tmp_path / "metrics.json").read_text())
    est = doc["estimator"]  # the UKF ran in the loop: its accuracy is reported beside the controller's
    assert est["filter"] == "UKF"
    for key in ("height_nrmsd", "height_nrmsd_open_loop", "pressure_nrmsd", "force_rmse_n", "nees_mean",
                "nis_mean", "step_us_median"):
        assert key in est
    assert 0 <= est["height_nrmsd"] < est["height_nrmsd_open_loop"]
    m = doc["controller"]
    for key in ("height_rmse_mm", "max_pressure_kpa", "pressure_limit_kpa", "solve_ms_median", "solve_ms_p99",
                "solve_ms_max", "fallbacks"):
        assert key in m
    assert m["pressure_limit_kpa"] == pytest.approx(30.0) and m["max_pressure_kpa"] <= 30.0
    assert m["steps_settled_estimate"] == 1
    assert (tmp_path / "closed_loop.csv").stat().st_size > 1000 and (tmp_path / "closed_loop.png").is_file()


@pytest.mark.slow
def test_structured_rig_400g_settles_with_the_timing_modelled_and_never_lifts_without():
    """The truth that differs in structure (exact membrane with plate contact, 5 ms valve delay, 2 ms
    minimum opening, tilted pump map, 3 ms sensor lag), 400 g, 2 -> 8 -> 5 mm, exact-law EKF,
    calibration and MPC. Taking the commands as acting at once, the filter reads the late pressure
    rise as a lift-off at zero load and the true platform never leaves the plate while the estimate
    sits on the targets; with the valve and sensor delays modelled (5 and 3 ms) every step settles
    within 0.3 mm (rig seed 0; ``bench loop --rig structured`` gives the rate over seeds)."""
    from hbma_ctrl.app.bench.loop import loop_setup, run_case

    timed = run_case("steps_400g", 0, loop_setup("structured"))
    naive = run_case("steps_400g", 0, loop_setup("structured", valve_delay_ms=0.0, sensor_delay_ms=0.0))
    assert timed["passed"] and timed["calibration"]["status"] == "ok", timed
    assert not naive["passed"] and naive["final_error_mm"] > 4.0, naive
    assert max(timed["max_pressure_kpa"], naive["max_pressure_kpa"]) <= 35.0


@pytest.mark.parametrize("prior,prior_std,needle", [
    ("1,1", None, "--prior = '1,1': three factors b,k,c, each in [0.5, 2]"),
    ("0.3,1,1", None, "--prior = '0.3,1,1': three factors"),
    ("a,1,1", None, "--prior = 'a,1,1': three numbers b,k,c"),
    (None, 0.0, "--prior-std = 0 is out of range (0, 10]"),
])
def test_bench_loop_prior_flags_are_one_error(prior, prior_std, needle):
    from hbma_ctrl.app.bench.loop import loop_setup

    with pytest.raises(ValueError) as exc:
        loop_setup(prior=prior, prior_std=prior_std)
    assert needle in str(exc.value)


def test_bench_loop_prior_reaches_the_filter_settings():
    from hbma_ctrl.app.bench.loop import _prior_settings, loop_setup

    setup = loop_setup(prior="0.92,1.15,1.13", prior_std=0.05)
    kw = _prior_settings(setup)
    assert kw == {"flow_factor_init": 0.92, "modulus_init": 1.15, "dead_volume_init": 1.13,
                  "flow_factor_init_std": 0.05, "modulus_init_std": 0.05, "dead_volume_init_std": 0.05}
    assert _prior_settings(loop_setup()) == {}  # no prior: the filter's own defaults
