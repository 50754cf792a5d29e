"""The innovation test for model-form error (estimators/innovation.py): its statistic on synthetic white
and correlated sequences against closed-form bounds, and its flag on short rig runs (cap EKF on the cap rig:
not flagged; on the exact membrane: flagged; the exact EKF there: not flagged)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from hbma_ctrl.estimators.common import FilterSettings
from hbma_ctrl.estimators.innovation import (
    InnovationTestSettings,
    innovation_test,
    window_mean_bound,
    window_mean_stat,
    windowed_nis,
    windowed_nis_bounds,
)
from hbma_ctrl.app.scenes.evaluate import evaluate_trials
from hbma_ctrl.core.params import Platform
from hbma_ctrl.models.defaults import CAP_CHAMBER
from hbma_ctrl.sim.batch import protocol_trials
from hbma_ctrl.sim.rig import CAP_RIG, RigSettings

N_WIN = 100


def _blocks(T: np.ndarray, n: int) -> np.ndarray:
    """The sliding-window statistic at non-overlapping windows (independent for a white sequence)."""
    return T[::n]


def _ar1(rng, rho: float, size: int) -> np.ndarray:
    e = rng.standard_normal(size)
    x = np.empty(size)
    x[0] = e[0] / np.sqrt(1 - rho**2)
    for k in range(1, size):
        x[k] = rho * x[k - 1] + e[k]
    return x


def test_window_mean_bound_is_the_beta_quantile_and_tends_to_chi_square_one():
    # T / n ~ Beta(1/2, (n-1)/2); n Beta -> chi2(1) as n grows (independent closed form)
    assert window_mean_bound(N_WIN, 0.01) == pytest.approx(N_WIN * stats.beta.ppf(0.99, 0.5, 49.5), rel=1e-12)
    assert window_mean_bound(5000, 0.01) == pytest.approx(stats.chi2.ppf(0.99, 1), rel=5e-3)
    assert window_mean_bound(N_WIN, 0.001) > window_mean_bound(N_WIN, 0.01)


def test_white_sequence_stays_within_the_closed_form_bounds():
    rng = np.random.default_rng(1)
    r = 0.6 * rng.standard_normal(400 * N_WIN)  # any scale: the statistic is self-normalised
    T = _blocks(window_mean_stat(r, N_WIN), N_WIN)
    # mean of n Beta(1/2, (n-1)/2) is exactly 1
    assert np.mean(T) == pytest.approx(1.0, abs=0.15)
    # share of windows above the 5 % quantile: binomial(400, 0.05), mean 20, sd 4.4
    assert 6 <= np.sum(T > window_mean_bound(N_WIN, 0.05)) <= 36
    # windowed NIS of unit white noise: chi2(n)/n bounds, same binomial count
    nis = _blocks(windowed_nis(r / 0.6, N_WIN), N_WIN)
    lo, hi = windowed_nis_bounds(N_WIN, 0.05)
    assert lo == pytest.approx(stats.chi2.ppf(0.025, N_WIN) / N_WIN)
    assert 6 <= np.sum((nis < lo) | (nis > hi)) <= 36


def test_statistic_is_scale_free_and_skips_missing_samples():
    rng = np.random.default_rng(2)
    r = rng.standard_normal(3 * N_WIN)
    np.testing.assert_allclose(window_mean_stat(5.0 * r, N_WIN), window_mean_stat(r, N_WIN), rtol=1e-12)
    r2 = r.copy()
    r2[10] = np.nan
    T, T2 = window_mean_stat(r, N_WIN), window_mean_stat(r2, N_WIN)
    keep = np.delete(r, 10)[:N_WIN - 1]
    assert T2[0] == pytest.approx(keep.sum() ** 2 / (keep @ keep))
    assert T2[11] == pytest.approx(T[11])  # windows past the gap are unchanged
    r3 = r.copy()
    r3[:50] = np.nan  # half a window without updates: not scored
    assert np.isnan(window_mean_stat(r3, N_WIN, min_fill=0.8)[0])
    # a run shorter than a window has no statistic and no verdict
    assert window_mean_stat(r[:90], N_WIN).size == 0
    short = innovation_test(r[:90])
    assert np.isnan(short["stat"]) and not short["flag"]


def test_correlated_sequence_is_flagged_and_its_statistic_matches_the_ar1_variance():
    rng = np.random.default_rng(3)
    rho = 0.9
    r = _ar1(rng, rho, 400 * N_WIN)
    T = _blocks(window_mean_stat(r, N_WIN), N_WIN)
    # E[(sum r)^2] / E[sum r^2] for AR(1): (1+rho)/(1-rho) - 2 rho (1 - rho^n) / (n (1-rho)^2)
    expect = (1 + rho) / (1 - rho) - 2 * rho * (1 - rho**N_WIN) / (N_WIN * (1 - rho) ** 2)
    assert np.mean(T) == pytest.approx(expect, rel=0.15)
    assert np.mean(T > window_mean_bound(N_WIN, 0.05)) > 0.5
    # the windowed NIS of the same (unit-variance-scaled) sequence does not see it: same variance
    nis = _blocks(windowed_nis(r * np.sqrt(1 - rho**2), N_WIN), N_WIN)
    assert np.median(nis) == pytest.approx(1.0, abs=0.3)
    # a persistent bias that the NIS hides (variance < 1) is flagged by the mean statistic
    biased = 0.25 + 0.2 * rng.standard_normal(2000)
    out = innovation_test(biased)
    assert out["flag"] and out["nis_window_max"] < windowed_nis_bounds(N_WIN, 1e-3)[1]
    assert not innovation_test(rng.standard_normal(2000))["flag"]


@pytest.mark.parametrize("kw, msg", [({"window": 5}, "innovation.window = 5"),
                                     ({"threshold": 0.0}, "innovation.threshold = 0.0"),
                                     ({"min_fill": 1.5}, "innovation.min_fill = 1.5"),
                                     ({"alpha": 0.7}, "innovation.alpha = 0.7")])
def test_bad_settings_are_one_clear_error(kw, msg):
    with pytest.raises(ValueError, match=msg.replace(".", r"\.")):
        InnovationTestSettings(**kw).validate()


@pytest.mark.slow
def test_flag_on_rig_runs_tells_a_wrong_membrane_law_from_a_right_one():
    """One loaded protocol trial (3 mm, r1 10 mm, 600 g, 40 %): the cap EKF on its own cap rig and the
    exact EKF on the exact rig are not flagged; the cap EKF on the exact rig is (while its mean NIS stays
    below 1). The membrane law is the only difference: no structural mismatches, no delays."""
    trials = protocol_trials("nh", loads_g=[600], speeds_pct=[40], t0_mm=[3], r1_mm=[10], t_inflate_s=3.0,
                             duration_s=6.0, platform=Platform(own_mass=0.02, damping=20.0))
    cap_rig, exact_rig = RigSettings(**CAP_RIG), RigSettings(**{**CAP_RIG, "membrane": "exact"})
    fs = {m: FilterSettings(**{**CAP_CHAMBER, "membrane": m, "load_prior": "nominal"}) for m in ("cap", "exact")}
    cc = evaluate_trials(trials, "ekf", cap_rig, fs["cap"])[0].scores
    ec = evaluate_trials(trials, "ekf", exact_rig, fs["cap"])[0].scores
    ee = evaluate_trials(trials, "ekf", exact_rig, fs["exact"])[0].scores
    assert cc["innovation_flag"] == 0.0 and ee["innovation_flag"] == 0.0
    assert ec["innovation_flag"] == 1.0
    assert ec["nis_mean"] < 1.0  # what the mean NIS does not show
    assert ec["innovation_stat"] > 2 * max(cc["innovation_stat"], ee["innovation_stat"])
